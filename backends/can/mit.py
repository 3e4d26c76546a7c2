"""Codec for the MIT mini-cheetah CAN protocol (CubeMars/T-Motor AK series, Damiao in MIT mode).

One 8-byte command frame (host -> motor, arbitration id = motor id) carries a position
target ``p``, a velocity target ``v``, the gains ``kp``/``kd`` and a feed-forward torque
``t``, bit-packed big-endian as 16+12+12+12+12 bits; the motor answers every frame with
one reply frame on the master id (position, velocity, torque and, depending on the
vendor, temperature and an error/status code). Each field is a linear map of a
per-model range onto ``0 .. 2**bits - 1``.

The firmware does not clamp: an out-of-range value spills into the neighbouring bit
field. :func:`encode_command` therefore rejects NaN/inf always, and rejects or clamps
out-of-range values (``policy``), so that a code never leaves its field.

Everything here runs in the control hot path (one encode and one decode per motor per
cycle): plain ``int``/``float`` arithmetic with scale factors precomputed in
:class:`MotorRanges`, no numpy, no allocation beyond the result.

Example::

    >>> r = ranges_for("AK80-9")
    >>> encode_command(0.0, 0.0, 0.0, 0.0, 0.0, r).hex(" ")
    '7f ff 7f f0 00 00 07 ff'
"""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Final, Literal

from agentsdk.errors import ConfigurationError, InvalidValueError, LimitViolation

__all__ = [
    "CLEAR_ERROR",
    "DISABLE",
    "ENABLE",
    "KD_BITS",
    "KP_BITS",
    "MODEL_RANGES",
    "PROFILES",
    "P_BITS",
    "SPECIAL_FRAMES",
    "T_BITS",
    "V_BITS",
    "ZERO",
    "LimitPolicy",
    "MotorRanges",
    "MotorReply",
    "SpecialFrame",
    "VendorProfile",
    "decode_command",
    "decode_reply",
    "encode_command",
    "encode_command_into",
    "encode_reply",
    "float_to_uint",
    "is_special",
    "profile_for",
    "ranges_for",
    "reply_error_code",
    "reply_state",
    "reply_temperature",
    "uint_to_float",
]

P_BITS: Final = 16
V_BITS: Final = 12
KP_BITS: Final = 12
KD_BITS: Final = 12
T_BITS: Final = 12

_MAX16: Final = (1 << 16) - 1
_MAX12: Final = (1 << 12) - 1

#: Codes are truncated like the firmware, but a value whose code lies within this many
#: LSB below the next integer is rounded up: it absorbs float noise, so that ``x_max``
#: encodes to ``2**bits - 1`` and decode -> encode is the identity on codes.
_GUARD: Final = 1e-6

#: the command word, big-endian
_WORD: Final = struct.Struct(">Q")

LimitPolicy = Literal["reject", "clamp"]
_POLICIES: Final = frozenset({"reject", "clamp"})

SpecialFrame = Literal["enable", "disable", "zero", "clear_error"]


# ----------------------------------------------------------------------------- ranges


@dataclass(frozen=True, slots=True)
class MotorRanges:
    """Physical range of each MIT field: position [rad], velocity [rad/s], gains, torque [N·m].

    Raises :class:`~agentsdk.errors.ConfigurationError` when a bound is not finite or a
    ``min`` is not below its ``max``.
    """

    p_min: float = -12.5
    p_max: float = 12.5
    v_min: float = -50.0
    v_max: float = 50.0
    kp_min: float = 0.0
    kp_max: float = 500.0
    kd_min: float = 0.0
    kd_max: float = 5.0
    t_min: float = -18.0
    t_max: float = 18.0
    # precomputed in __post_init__: span and code-per-unit scale of each field
    _p_span: float = field(init=False, repr=False, compare=False)
    _v_span: float = field(init=False, repr=False, compare=False)
    _kp_span: float = field(init=False, repr=False, compare=False)
    _kd_span: float = field(init=False, repr=False, compare=False)
    _t_span: float = field(init=False, repr=False, compare=False)
    _p_scale: float = field(init=False, repr=False, compare=False)
    _v_scale: float = field(init=False, repr=False, compare=False)
    _kp_scale: float = field(init=False, repr=False, compare=False)
    _kd_scale: float = field(init=False, repr=False, compare=False)
    _t_scale: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name, bits in (("p", P_BITS), ("v", V_BITS), ("kp", KP_BITS), ("kd", KD_BITS), ("t", T_BITS)):
            lo = getattr(self, f"{name}_min")
            hi = getattr(self, f"{name}_max")
            try:
                lo, hi = float(lo), float(hi)
            except (TypeError, ValueError) as exc:
                raise ConfigurationError(
                    f"MotorRanges.{name}_min/{name}_max must be numbers, got {lo!r}, {hi!r}"
                ) from exc
            if not (math.isfinite(lo) and math.isfinite(hi)) or not lo < hi:
                raise ConfigurationError(
                    f"MotorRanges: need finite {name}_min < {name}_max, got {name}_min={lo!r}, {name}_max={hi!r}"
                )
            object.__setattr__(self, f"{name}_min", lo)
            object.__setattr__(self, f"{name}_max", hi)
            span = hi - lo
            object.__setattr__(self, f"_{name}_span", span)
            object.__setattr__(self, f"_{name}_scale", ((1 << bits) - 1) / span)

    def lsb(self, name: str) -> float:
        """Resolution of field ``name`` (``"p"``, ``"v"``, ``"kp"``, ``"kd"``, ``"t"``) in physical units."""
        bits = P_BITS if name == "p" else V_BITS
        try:
            span: float = getattr(self, f"_{name}_span")
        except AttributeError:
            raise KeyError(f"unknown MIT field {name!r} (p, v, kp, kd, t)") from None
        return span / ((1 << bits) - 1)


def _symmetric(p: float, v: float, t: float) -> MotorRanges:
    return MotorRanges(-p, p, -v, v, 0.0, 500.0, 0.0, 5.0, -t, t)


#: Default ranges per motor model (firmware defaults; other firmware versions differ,
#: override with :func:`ranges_for`). CubeMars AK series from the vendor datasheets;
#: Damiao models from the vendor's ``DM_CAN`` defaults (PMAX/VMAX/TMAX are configurable
#: on the motor, so check yours).
MODEL_RANGES: Final[Mapping[str, MotorRanges]] = MappingProxyType(
    {
        "AK80-9": _symmetric(12.5, 50.0, 18.0),
        "AK10-9": _symmetric(12.5, 50.0, 65.0),
        "AK60-6": _symmetric(12.5, 50.0, 15.0),
        "AK70-10": _symmetric(12.5, 50.0, 25.0),
        "AK80-6": _symmetric(12.5, 76.0, 12.0),
        "AK80-64": _symmetric(12.5, 8.0, 144.0),
        "DM4310": _symmetric(12.5, 30.0, 10.0),
        "DM4310-48V": _symmetric(12.5, 50.0, 10.0),
        "DM4340": _symmetric(12.5, 8.0, 28.0),
        "DM4340-48V": _symmetric(12.5, 10.0, 28.0),
        "DM6006": _symmetric(12.5, 45.0, 20.0),
        "DM8006": _symmetric(12.5, 45.0, 40.0),
        "DM8009": _symmetric(12.5, 45.0, 54.0),
        "DM10010L": _symmetric(12.5, 25.0, 200.0),
        "DM10010": _symmetric(12.5, 20.0, 200.0),
    }
)

_RANGE_FIELD_NAMES: Final = tuple(f.name for f in dataclasses.fields(MotorRanges) if f.init)
_MODEL_KEYS: Final = {name.upper(): name for name in MODEL_RANGES}


def ranges_for(model: str, overrides: Mapping[str, float] | None = None) -> MotorRanges:
    """Ranges of ``model`` (case-insensitive), with any field replaced from ``overrides``.

    ``overrides`` keys are :class:`MotorRanges` field names (``p_min``, ``t_max`` ...), e.g.
    for a firmware whose torque range differs from the table::

        ranges_for("AK80-9", {"t_min": -25.0, "t_max": 25.0})

    Raises :class:`~agentsdk.errors.ConfigurationError` for an unknown model (listing the
    known ones), an unknown field or an invalid range.
    """
    key = _MODEL_KEYS.get(str(model).strip().upper())
    if key is None:
        raise ConfigurationError(f"unknown motor model {model!r}; known models: {', '.join(MODEL_RANGES)}")
    base = MODEL_RANGES[key]
    if not overrides:
        return base
    unknown = sorted(set(overrides) - set(_RANGE_FIELD_NAMES))
    if unknown:
        raise ConfigurationError(
            f"unknown range field(s) {', '.join(map(repr, unknown))} for {key}; valid: {', '.join(_RANGE_FIELD_NAMES)}"
        )
    return dataclasses.replace(base, **dict(overrides))


# ----------------------------------------------------------------------------- vendor profiles

#: CubeMars AK error codes (reply byte 7).
CUBEMARS_ERRORS: Final[Mapping[int, str]] = MappingProxyType(
    {
        0: "none",
        1: "over-temperature",
        2: "over-current",
        3: "over-voltage",
        4: "under-voltage",
        5: "encoder fault",
        6: "phase imbalance",
    }
)

#: Damiao status (high nibble of reply byte 0).
DAMIAO_STATUS: Final[Mapping[int, str]] = MappingProxyType(
    {
        0x0: "disabled",
        0x1: "enabled",
        0x8: "over-voltage",
        0x9: "under-voltage",
        0xA: "over-current",
        0xB: "MOSFET over-temperature",
        0xC: "rotor over-temperature",
        0xD: "lost communication",
        0xE: "overload",
    }
)


@dataclass(frozen=True, slots=True)
class VendorProfile:
    """How one firmware lays out the MIT reply frame.

    - ``reply_dlc``: the DLC this firmware sends; ``accepted_dlcs``: what the decoder takes.
    - ``id_byte``: byte 0 is the motor id (``"id"``) or ``status << 4 | id`` (``"status_id"``, Damiao).
    - ``byte6`` / ``byte7``: meaning of the optional trailing bytes.
    - ``temperature_offset``: degrees C = raw byte + offset.
    - ``error_codes``: byte-7 error codes (``byte7 == "error_code"``).
    - ``status_codes`` / ``ok_statuses``: the status nibble (``id_byte == "status_id"``) and
      the statuses that are not faults.
    """

    name: str
    reply_dlc: int
    id_byte: Literal["id", "status_id"] = "id"
    byte6: Literal["temperature", "mosfet_temperature", "none"] = "temperature"
    byte7: Literal["error_code", "rotor_temperature", "none"] = "error_code"
    temperature_offset: float = 0.0
    accepted_dlcs: frozenset[int] = frozenset({6, 7, 8})
    error_codes: Mapping[int, str] = field(default_factory=lambda: CUBEMARS_ERRORS)
    status_codes: Mapping[int, str] = field(default_factory=lambda: MappingProxyType({}))
    ok_statuses: frozenset[int] = frozenset()

    def __post_init__(self) -> None:
        if not self.accepted_dlcs or not self.accepted_dlcs <= {6, 7, 8}:
            raise ConfigurationError(f"profile {self.name}: accepted_dlcs must be a subset of {{6, 7, 8}}")
        if self.reply_dlc not in self.accepted_dlcs:
            raise ConfigurationError(f"profile {self.name}: reply_dlc {self.reply_dlc} not in accepted_dlcs")

    @property
    def id_mask(self) -> int:
        """Bits of the motor id that reply byte 0 carries (0xFF, or 0x0F for ``status_id``)."""
        return 0x0F if self.id_byte == "status_id" else 0xFF

    def error_name(self, code: int) -> str | None:
        """Name of a fault code (``None`` for 0 = no fault)."""
        if code == 0:
            return None
        table = self.status_codes if self.id_byte == "status_id" else self.error_codes
        return table.get(code, f"unknown error code {code:#x}")


#: Reply layouts. ``cubemars``: CubeMars AK manual v1.0.15 (DLC 8, byte 6 = temperature + 40,
#: byte 7 = error code); ``katz``: the original mini-cheetah firmware (DLC 6, no
#: temperature/error); ``damiao``: Damiao MIT mode (DLC 8, byte 0 = status << 4 | id,
#: byte 6 = MOSFET temperature, byte 7 = rotor temperature, both plain degrees C).
PROFILES: Final[Mapping[str, VendorProfile]] = MappingProxyType(
    {
        "cubemars": VendorProfile(name="cubemars", reply_dlc=8, temperature_offset=-40.0),
        "katz": VendorProfile(name="katz", reply_dlc=6, byte6="none", byte7="none"),
        "damiao": VendorProfile(
            name="damiao",
            reply_dlc=8,
            id_byte="status_id",
            byte6="mosfet_temperature",
            byte7="rotor_temperature",
            accepted_dlcs=frozenset({8}),
            error_codes=MappingProxyType({}),
            status_codes=DAMIAO_STATUS,
            ok_statuses=frozenset({0x0, 0x1}),
        ),
    }
)


def profile_for(name: str | VendorProfile) -> VendorProfile:
    """The :data:`PROFILES` entry ``name`` (a profile passes through); unknown -> ConfigurationError."""
    if isinstance(name, VendorProfile):
        return name
    try:
        return PROFILES[str(name).strip().lower()]
    except KeyError:
        raise ConfigurationError(f"unknown MIT vendor profile {name!r}; known: {', '.join(PROFILES)}") from None


# ----------------------------------------------------------------------------- scalar maps


def float_to_uint(x: float, lo: float, hi: float, bits: int) -> int:
    """Firmware ``float_to_uint``: ``int((x - lo) * (2**bits - 1) / (hi - lo))``, truncated.

    Like the firmware it neither clamps nor checks: outside ``[lo, hi]`` the result leaves
    ``0 .. 2**bits - 1``. Use :func:`encode_command` to build frames.
    """
    return int((x - lo) * ((1 << bits) - 1) / (hi - lo))


def uint_to_float(u: int, lo: float, hi: float, bits: int) -> float:
    """Firmware ``uint_to_float``: ``u * (hi - lo) / (2**bits - 1) + lo``."""
    return u * (hi - lo) / ((1 << bits) - 1) + lo


# ----------------------------------------------------------------------------- special frames

ENABLE: Final = b"\xff\xff\xff\xff\xff\xff\xff\xfc"
DISABLE: Final = b"\xff\xff\xff\xff\xff\xff\xff\xfd"
ZERO: Final = b"\xff\xff\xff\xff\xff\xff\xff\xfe"
CLEAR_ERROR: Final = b"\xff\xff\xff\xff\xff\xff\xff\xfb"

SPECIAL_FRAMES: Final[Mapping[SpecialFrame, bytes]] = MappingProxyType(
    {"enable": ENABLE, "disable": DISABLE, "zero": ZERO, "clear_error": CLEAR_ERROR}
)
_SPECIAL_BY_LAST: Final[Mapping[int, SpecialFrame]] = MappingProxyType(
    {0xFC: "enable", 0xFD: "disable", 0xFE: "zero", 0xFB: "clear_error"}
)
_SPECIAL_PREFIX: Final = b"\xff" * 7
_SPECIAL_LOW: Final = int.from_bytes(CLEAR_ERROR, "big")  # ...FB
_SPECIAL_HIGH: Final = int.from_bytes(ZERO, "big")  # ...FE


def is_special(data: bytes | bytearray | memoryview) -> SpecialFrame | None:
    """Which special frame ``data`` is (``"enable"``, ``"disable"``, ``"zero"``, ``"clear_error"``), else None."""
    if len(data) != 8 or data[:7] != _SPECIAL_PREFIX:
        return None
    return _SPECIAL_BY_LAST.get(data[7])


# ----------------------------------------------------------------------------- command frame


def _limit(name: str, x: float, lo: float, hi: float, policy: str) -> float:
    """Slow path of :func:`encode_command`: ``x`` failed ``lo <= x <= hi``."""
    try:
        finite = math.isfinite(x)
    except TypeError:
        raise InvalidValueError(f"{name} must be a real number, got {x!r}") from None
    if not finite:
        raise InvalidValueError(f"{name} must be finite, got {x!r}")
    if policy == "clamp":
        return lo if x < lo else hi
    raise LimitViolation(f"{name}={x!r} outside the motor range [{lo}, {hi}]")


def _command_word(p: float, v: float, kp: float, kd: float, t: float, r: MotorRanges, policy: str) -> int:
    """The 64-bit MIT command word (see :func:`encode_command`)."""
    if policy not in _POLICIES:
        raise ConfigurationError(f"unknown limit policy {policy!r}; use 'reject' or 'clamp'")
    # Comparisons are False for NaN, so one chained test per field is the whole fast path.
    if not r.p_min <= p <= r.p_max:
        p = _limit("position", p, r.p_min, r.p_max, policy)
    if not r.v_min <= v <= r.v_max:
        v = _limit("velocity", v, r.v_min, r.v_max, policy)
    if not r.kp_min <= kp <= r.kp_max:
        kp = _limit("kp", kp, r.kp_min, r.kp_max, policy)
    if not r.kd_min <= kd <= r.kd_max:
        kd = _limit("kd", kd, r.kd_min, r.kd_max, policy)
    if not r.t_min <= t <= r.t_max:
        t = _limit("torque", t, r.t_min, r.t_max, policy)
    up = int((p - r.p_min) * r._p_scale + _GUARD)
    uv = int((v - r.v_min) * r._v_scale + _GUARD)
    ukp = int((kp - r.kp_min) * r._kp_scale + _GUARD)
    ukd = int((kd - r.kd_min) * r._kd_scale + _GUARD)
    ut = int((t - r.t_min) * r._t_scale + _GUARD)
    # Every code must stay inside its bit field (a negative code has all high bits set).
    if (up >> P_BITS) | (uv >> V_BITS) | (ukp >> KP_BITS) | (ukd >> KD_BITS) | (ut >> T_BITS):
        raise InvalidValueError(
            f"internal error: MIT code out of its field (p={up}, v={uv}, kp={ukp}, kd={ukd}, t={ut})"
        )
    word = (up << 48) | (uv << 36) | (ukp << 24) | (ukd << 12) | ut
    if _SPECIAL_LOW <= word <= _SPECIAL_HIGH:
        word -= 1 << 12  # kd - 1 LSB: never emit enable/disable/zero/clear by accident
    return word


def encode_command(
    p: float,
    v: float,
    kp: float,
    kd: float,
    t: float,
    ranges: MotorRanges,
    *,
    policy: LimitPolicy = "reject",
) -> bytes:
    """Pack one MIT command (position, velocity, kp, kd, feed-forward torque) into 8 bytes.

    NaN/inf always raise :class:`~agentsdk.errors.InvalidValueError` naming the field.
    Out-of-range values raise :class:`~agentsdk.errors.LimitViolation` (field, value and
    range) under ``policy="reject"`` and are clamped to the range under ``policy="clamp"``.

    Codes are truncated like the firmware's ``float_to_uint`` (plus a 1e-6 LSB guard
    against float noise). A frame that would collide with a special frame (every field
    at its maximum and ``t`` within 4 LSB of ``t_max``: ``FF..FB``-``FF..FE``) gets ``kd``
    lowered by one LSB, so a command can never be read as enable/disable/zero.
    """
    return _command_word(p, v, kp, kd, t, ranges, policy).to_bytes(8, "big")


def encode_command_into(
    buffer: bytearray | memoryview,
    p: float,
    v: float,
    kp: float,
    kd: float,
    t: float,
    ranges: MotorRanges,
    *,
    policy: LimitPolicy = "reject",
) -> None:
    """:func:`encode_command` into the first 8 bytes of a writable ``buffer`` (e.g. a reused
    ``can.Message.data``), like ``struct.pack_into``: no new bytes object per frame.
    """
    _WORD.pack_into(buffer, 0, _command_word(p, v, kp, kd, t, ranges, policy))


def decode_command(
    data: bytes | bytearray | memoryview, ranges: MotorRanges
) -> tuple[float, float, float, float, float]:
    """Unpack an 8-byte MIT command into ``(p, v, kp, kd, t)`` (the motor side; used by the emulator).

    Special frames are not commands: check :func:`is_special` first.
    """
    if len(data) != 8:
        raise InvalidValueError(f"MIT command frame must have 8 data bytes, got {len(data)}")
    r = ranges
    w = int.from_bytes(data, "big")
    return (
        (w >> 48) * r._p_span / _MAX16 + r.p_min,
        ((w >> 36) & _MAX12) * r._v_span / _MAX12 + r.v_min,
        ((w >> 24) & _MAX12) * r._kp_span / _MAX12 + r.kp_min,
        ((w >> 12) & _MAX12) * r._kd_span / _MAX12 + r.kd_min,
        (w & _MAX12) * r._t_span / _MAX12 + r.t_min,
    )


# ----------------------------------------------------------------------------- reply frame


@dataclass(frozen=True, slots=True)
class MotorReply:
    """One decoded reply frame, in the motor frame (before direction/offset/gear ratio).

    ``motor_id`` is what byte 0 carries: the low 8 bits of the CAN id (CubeMars) or the low
    4 bits (Damiao). ``error_code`` is 0 when healthy; for Damiao it is the fault status
    (``status`` keeps the raw nibble: 0 disabled, 1 enabled, 8..E faults). ``temperature`` is
    the driver/motor temperature (Damiao: MOSFET), ``None`` when the DLC doesn't carry it.
    """

    motor_id: int
    position: float
    velocity: float
    torque: float
    temperature: float | None = None
    error_code: int = 0
    error: str | None = None
    status: int | None = None
    rotor_temperature: float | None = None
    dlc: int = 8
    raw: bytes = b""

    @property
    def ok(self) -> bool:
        """True when the motor reports no fault."""
        return self.error_code == 0


def reply_state(data: bytes | bytearray | memoryview, ranges: MotorRanges) -> tuple[float, float, float]:
    """``(position, velocity, torque)`` of a reply frame (the motor frame), without building a :class:`MotorReply`.

    The hot-path part of :func:`decode_reply`; the caller checks the DLC.
    """
    r = ranges
    w = (data[1] << 32) | (data[2] << 24) | (data[3] << 16) | (data[4] << 8) | data[5]
    return (
        (w >> 24) * r._p_span / _MAX16 + r.p_min,
        ((w >> 12) & _MAX12) * r._v_span / _MAX12 + r.v_min,
        (w & _MAX12) * r._t_span / _MAX12 + r.t_min,
    )


def reply_error_code(data: bytes | bytearray | memoryview, profile: VendorProfile) -> int:
    """The fault code a reply frame carries (0 when healthy), as :attr:`MotorReply.error_code`."""
    if profile.id_byte == "status_id":
        status = data[0] >> 4
        return 0 if status in profile.ok_statuses else status
    if len(data) == 8 and profile.byte7 == "error_code":
        return data[7]
    return 0


def reply_temperature(data: bytes | bytearray | memoryview, profile: VendorProfile) -> float | None:
    """The temperature a reply frame carries (byte 6 + the profile's offset) or None, as ``MotorReply.temperature``."""
    if len(data) >= 7 and profile.byte6 != "none":
        return data[6] + profile.temperature_offset
    return None


def decode_reply(data: bytes | bytearray | memoryview, ranges: MotorRanges, profile: VendorProfile) -> MotorReply:
    """Decode a reply frame laid out per ``profile``; a DLC the profile doesn't accept -> InvalidValueError."""
    n = len(data)
    if n not in profile.accepted_dlcs:
        dlcs = "/".join(map(str, sorted(profile.accepted_dlcs)))
        raise InvalidValueError(f"{profile.name} MIT reply must have {dlcs} data bytes, got {n}")
    b0 = data[0]
    position, velocity, torque = reply_state(data, ranges)
    temperature = None
    rotor_temperature = None
    status = None
    error_code = 0
    if profile.id_byte == "status_id":
        motor_id = b0 & 0x0F
        status = b0 >> 4
        if status not in profile.ok_statuses:
            error_code = status
    else:
        motor_id = b0
    if n >= 7 and profile.byte6 != "none":
        temperature = data[6] + profile.temperature_offset
    if n == 8:
        if profile.byte7 == "error_code":
            error_code = data[7]
        elif profile.byte7 == "rotor_temperature":
            rotor_temperature = data[7] + profile.temperature_offset
    return MotorReply(
        motor_id,
        position,
        velocity,
        torque,
        temperature,
        error_code,
        profile.error_name(error_code) if error_code else None,
        status,
        rotor_temperature,
        n,
        bytes(data),
    )


def _reply_code(name: str, x: float, lo: float, scale: float, maxcode: int, wrap: bool) -> int:
    try:
        finite = math.isfinite(x)
    except TypeError:
        raise InvalidValueError(f"{name} must be a real number, got {x!r}") from None
    if not finite:
        raise InvalidValueError(f"{name} must be finite, got {x!r}")
    u = math.floor((x - lo) * scale + _GUARD)
    if wrap:
        return u & maxcode  # the firmware's uint16 truncation: the reading wraps around
    return 0 if u < 0 else maxcode if u > maxcode else u


def _temp_byte(name: str, value: float | None, offset: float) -> int:
    if value is None:
        return 0
    try:
        raw = round(value - offset)
    except (TypeError, ValueError, OverflowError):
        raise InvalidValueError(f"{name} must be a finite number, got {value!r}") from None
    return 0 if raw < 0 else 255 if raw > 255 else raw


def encode_reply(
    motor_id: int,
    position: float,
    velocity: float,
    torque: float,
    ranges: MotorRanges,
    profile: VendorProfile,
    *,
    temperature: float | None = None,
    error_code: int = 0,
    status: int | None = None,
    rotor_temperature: float | None = None,
    dlc: int | None = None,
    wrap_position: bool = True,
) -> bytes:
    """Build a reply frame (the motor side; used by the emulator); inverse of :func:`decode_reply`.

    Velocity and torque saturate at their range. Position wraps around like the firmware
    (a 16-bit truncation: ``p_max`` + 1 LSB reads as ``p_min``) unless ``wrap_position=False``
    (then it saturates). Temperatures are rounded to whole degrees and saturate at the byte.
    For a ``status_id`` profile, byte 0 is ``status << 4 | id`` with ``status`` defaulting to
    ``error_code``; otherwise ``error_code`` goes to byte 7 when the profile has it.
    """
    n = profile.reply_dlc if dlc is None else dlc
    if n not in profile.accepted_dlcs:
        raise InvalidValueError(f"{profile.name} MIT reply cannot have DLC {n}")
    r = ranges
    up = _reply_code("position", position, r.p_min, r._p_scale, _MAX16, wrap_position)
    uv = _reply_code("velocity", velocity, r.v_min, r._v_scale, _MAX12, False)
    ut = _reply_code("torque", torque, r.t_min, r._t_scale, _MAX12, False)
    if profile.id_byte == "status_id":
        st = error_code if status is None else status
        if not 0 <= st <= 0xF:
            raise InvalidValueError(f"{profile.name} status must be 0..15, got {st}")
        b0 = (st << 4) | (motor_id & 0x0F)
    else:
        b0 = motor_id & 0xFF
    out = bytearray(n)
    out[0] = b0
    out[1:6] = ((up << 24) | (uv << 12) | ut).to_bytes(5, "big")
    if n >= 7 and profile.byte6 != "none":
        out[6] = _temp_byte("temperature", temperature, profile.temperature_offset)
    if n == 8:
        if profile.byte7 == "error_code":
            if not 0 <= error_code <= 0xFF:
                raise InvalidValueError(f"error_code must be 0..255, got {error_code}")
            out[7] = error_code
        elif profile.byte7 == "rotor_temperature":
            out[7] = _temp_byte("rotor_temperature", rotor_temperature, profile.temperature_offset)
    return bytes(out)
