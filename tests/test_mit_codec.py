"""MIT mini-cheetah codec: golden vector, round trips, DLCs, error codes, limit policies."""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agentsdk.backends.can.mit import (
    CLEAR_ERROR,
    DISABLE,
    ENABLE,
    MODEL_RANGES,
    PROFILES,
    ZERO,
    MotorRanges,
    decode_command,
    decode_reply,
    encode_command,
    encode_reply,
    float_to_uint,
    is_special,
    profile_for,
    ranges_for,
    uint_to_float,
)
from agentsdk.errors import ConfigurationError, InvalidValueError, LimitViolation

PROPS = settings(database=None, deadline=None, max_examples=300, suppress_health_check=[HealthCheck.too_slow])

FIELDS = ("p", "v", "kp", "kd", "t")
NAMES = {"p": "position", "v": "velocity", "kp": "kp", "kd": "kd", "t": "torque"}
BITS = {"p": 16, "v": 12, "kp": 12, "kd": 12, "t": 12}
SHIFT = {"p": 48, "v": 36, "kp": 24, "kd": 12, "t": 0}
MODELS = sorted(MODEL_RANGES)


def bounds(r: MotorRanges, f: str) -> tuple[float, float]:
    return getattr(r, f"{f}_min"), getattr(r, f"{f}_max")


def codes(frame: bytes) -> dict[str, int]:
    w = int.from_bytes(frame, "big")
    return {f: (w >> SHIFT[f]) & ((1 << BITS[f]) - 1) for f in FIELDS}


def within_lsb(decoded: float, x: float, r: MotorRanges, f: str, lsbs: int = 1) -> bool:
    return abs(decoded - x) <= lsbs * r.lsb(f) * (1 + 1e-9)


def special_avoided(frame: bytes) -> bool:
    """True when encode_command lowered kd by one LSB to keep the frame from reading as special."""
    c = codes(frame)
    return c["p"] == 0xFFFF and c["v"] == c["kp"] == 0xFFF and c["kd"] == 0xFFE and 0xFFB <= c["t"] <= 0xFFE


def assert_round_trip(values: tuple[float, ...], r: MotorRanges) -> None:
    frame = encode_command(*values, r)
    assert len(frame) == 8
    assert is_special(frame) is None
    decoded = decode_command(frame, r)
    for f, x, d in zip(FIELDS, values, decoded, strict=True):
        lsbs = 2 if f == "kd" and special_avoided(frame) else 1
        assert within_lsb(d, x, r, f, lsbs), (f, x, d)


def values_in(r: MotorRanges) -> st.SearchStrategy[tuple[float, ...]]:
    return st.tuples(*(st.floats(*bounds(r, f), allow_nan=False) for f in FIELDS))


def model_and_values() -> st.SearchStrategy[tuple[str, tuple[float, ...]]]:
    return st.sampled_from(MODELS).flatmap(lambda m: st.tuples(st.just(m), values_in(MODEL_RANGES[m])))


@st.composite
def custom_ranges(draw: st.DrawFn) -> MotorRanges:
    """User overrides: arbitrary finite ranges, including odd spans."""
    kw = {}
    for f in FIELDS:
        lo = draw(st.floats(-1e4, 1e4, allow_nan=False))
        span = draw(st.floats(1e-3, 1e4, allow_nan=False))
        kw[f"{f}_min"], kw[f"{f}_max"] = lo, lo + span
    return MotorRanges(**kw)


# ---------------------------------------------------------------- golden vector and firmware maps


def test_golden_vector_ak80_9_all_zero() -> None:
    frame = encode_command(0.0, 0.0, 0.0, 0.0, 0.0, ranges_for("AK80-9"))
    assert frame == bytes.fromhex("7F FF 7F F0 00 00 07 FF")


def test_firmware_scalar_maps_truncate() -> None:
    assert float_to_uint(0.0, -12.5, 12.5, 16) == 0x7FFF  # 32767.5 truncated
    assert float_to_uint(0.0, -50.0, 50.0, 12) == 0x7FF
    assert float_to_uint(12.5, -12.5, 12.5, 16) == 0xFFFF
    assert float_to_uint(-12.5, -12.5, 12.5, 16) == 0
    assert uint_to_float(0, -12.5, 12.5, 16) == -12.5
    assert uint_to_float(0xFFFF, -12.5, 12.5, 16) == 12.5
    # the firmware does not clamp: out of range leaves the field (what encode_command prevents)
    assert float_to_uint(60.0, -50.0, 50.0, 12) > 0xFFF
    assert float_to_uint(-60.0, -50.0, 50.0, 12) < 0


def test_zero_is_not_representable_in_symmetric_ranges() -> None:
    """Code 2**(bits-1)-1 decodes to -LSB/2: a commanded 0 reads back slightly negative."""
    r = ranges_for("AK80-9")
    p, v, _kp, _kd, t = decode_command(encode_command(0.0, 0.0, 0.0, 0.0, 0.0, r), r)
    assert -r.lsb("p") < p < 0 and -r.lsb("v") < v < 0 and -r.lsb("t") < t < 0


# ---------------------------------------------------------------- command round trips


@pytest.mark.parametrize("model", MODELS)
def test_boundary_values_give_boundary_codes_and_back(model: str) -> None:
    r = ranges_for(model)
    lo = encode_command(r.p_min, r.v_min, r.kp_min, r.kd_min, r.t_min, r)
    hi = encode_command(r.p_max, r.v_max, r.kp_max, r.kd_max, r.t_max, r)
    assert lo == bytes(8)
    assert hi == b"\xff" * 8
    assert decode_command(lo, r) == (r.p_min, r.v_min, r.kp_min, r.kd_min, r.t_min)
    assert decode_command(hi, r) == (r.p_max, r.v_max, r.kp_max, r.kd_max, r.t_max)


@PROPS
@given(model_and_values())
def test_command_round_trip_within_one_lsb_every_model(mv: tuple[str, tuple[float, ...]]) -> None:
    model, values = mv
    assert_round_trip(values, MODEL_RANGES[model])


@PROPS
@given(custom_ranges(), st.data())
def test_command_round_trip_custom_ranges(r: MotorRanges, data: st.DataObject) -> None:
    assert_round_trip(data.draw(values_in(r)), r)
    assert codes(encode_command(*(bounds(r, f)[1] for f in FIELDS), r)) == {f: (1 << BITS[f]) - 1 for f in FIELDS}
    assert codes(encode_command(*(bounds(r, f)[0] for f in FIELDS), r)) == dict.fromkeys(FIELDS, 0)


@PROPS
@given(st.sampled_from(MODELS), st.binary(min_size=8, max_size=8))
def test_decode_then_encode_command_is_identity_on_codes(model: str, frame: bytes) -> None:
    r = MODEL_RANGES[model]
    if is_special(frame) is not None:
        return
    assert encode_command(*decode_command(frame, r), r) == frame


def test_decode_command_rejects_wrong_length() -> None:
    with pytest.raises(InvalidValueError, match="8 data bytes"):
        decode_command(b"\x00" * 7, ranges_for("AK80-9"))


# ---------------------------------------------------------------- special frames


def test_special_frames() -> None:
    assert ENABLE == bytes.fromhex("FFFFFFFFFFFFFFFC")
    assert DISABLE == bytes.fromhex("FFFFFFFFFFFFFFFD")
    assert ZERO == bytes.fromhex("FFFFFFFFFFFFFFFE")
    assert CLEAR_ERROR == bytes.fromhex("FFFFFFFFFFFFFFFB")
    assert is_special(ENABLE) == "enable"
    assert is_special(bytearray(DISABLE)) == "disable"
    assert is_special(memoryview(ZERO)) == "zero"
    assert is_special(CLEAR_ERROR) == "clear_error"
    assert is_special(b"\xff" * 8) is None
    assert is_special(ENABLE[:7]) is None
    assert is_special(bytes.fromhex("FFFFFFFFFFFFFEFC")) is None


@pytest.mark.parametrize("t_code", [0xFFB, 0xFFC, 0xFFD, 0xFFE])
def test_a_command_never_encodes_as_a_special_frame(t_code: int) -> None:
    r = ranges_for("AK80-9")
    t = uint_to_float(t_code, r.t_min, r.t_max, 12)
    frame = encode_command(r.p_max, r.v_max, r.kp_max, r.kd_max, t, r)
    assert is_special(frame) is None
    c = codes(frame)
    assert c == {"p": 0xFFFF, "v": 0xFFF, "kp": 0xFFF, "kd": 0xFFE, "t": t_code}  # kd lowered by one LSB


# ---------------------------------------------------------------- NaN/inf and limits


@pytest.mark.parametrize("policy", ["reject", "clamp"])
@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_always_rejected(policy: str, field: str, bad: float) -> None:
    args = dict.fromkeys(FIELDS, 0.0)
    args[field] = bad
    with pytest.raises(InvalidValueError, match=NAMES[field]):
        encode_command(*args.values(), ranges_for("AK80-9"), policy=policy)  # type: ignore[arg-type]


@pytest.mark.parametrize("field", FIELDS)
def test_out_of_range_rejected_with_field_value_and_range(field: str) -> None:
    r = ranges_for("AK80-9")
    lo, hi = bounds(r, field)
    args = dict.fromkeys(FIELDS, 0.0)
    args[field] = hi + 1.0
    with pytest.raises(LimitViolation) as info:
        encode_command(*args.values(), r)
    msg = str(info.value)
    assert NAMES[field] in msg and repr(hi + 1.0) in msg and str(lo) in msg and str(hi) in msg


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("field", FIELDS)
@pytest.mark.parametrize("side", ["low", "high"])
@pytest.mark.parametrize("excess", [1e-9, 1e-3, 1.0, 1e9])
def test_clamp_never_disturbs_neighbouring_fields(model: str, field: str, side: str, excess: float) -> None:
    r = ranges_for(model)
    lo, hi = bounds(r, field)
    # neighbours at mid-range values with non-trivial bit patterns
    base = {f: bounds(r, f)[0] + 0.37 * (bounds(r, f)[1] - bounds(r, f)[0]) for f in FIELDS}
    over = dict(base)
    over[field] = lo - excess if side == "low" else hi + excess
    at_bound = dict(base)
    at_bound[field] = lo if side == "low" else hi
    clamped = encode_command(*over.values(), r, policy="clamp")
    assert clamped == encode_command(*at_bound.values(), r)
    c, ref = codes(clamped), codes(encode_command(*base.values(), r))
    for f in FIELDS:
        if f != field:
            assert c[f] == ref[f], f
    assert c[field] == (0 if side == "low" else (1 << BITS[field]) - 1)
    with pytest.raises(LimitViolation):
        encode_command(*over.values(), r, policy="reject")


def test_unknown_policy() -> None:
    with pytest.raises(ConfigurationError, match="policy"):
        encode_command(0, 0, 0, 0, 0, ranges_for("AK80-9"), policy="saturate")  # type: ignore[arg-type]


# ---------------------------------------------------------------- replies


@PROPS
@given(st.sampled_from(MODELS), st.sampled_from(sorted(PROFILES)), st.data())
def test_reply_round_trip_within_one_lsb(model: str, profile_name: str, data: st.DataObject) -> None:
    r, prof = MODEL_RANGES[model], PROFILES[profile_name]
    p = data.draw(st.floats(r.p_min, r.p_max))
    v = data.draw(st.floats(r.v_min, r.v_max))
    t = data.draw(st.floats(r.t_min, r.t_max))
    mid = data.draw(st.integers(1, 15))
    temp = data.draw(st.integers(0, 120))
    frame = encode_reply(mid, p, v, t, r, prof, temperature=temp, rotor_temperature=temp + 1, status=1)
    assert len(frame) == prof.reply_dlc
    reply = decode_reply(frame, r, prof)
    assert reply.motor_id == mid and reply.dlc == prof.reply_dlc and reply.raw == frame
    assert within_lsb(reply.position, p, r, "p")
    assert within_lsb(reply.velocity, v, r, "v")
    assert within_lsb(reply.torque, t, r, "t")
    if prof.byte6 != "none":
        assert reply.temperature == temp
    if prof.byte7 == "rotor_temperature":
        assert reply.rotor_temperature == temp + 1
    assert reply.ok and reply.error is None


@pytest.mark.parametrize("model", MODELS)
def test_reply_boundaries_exact(model: str) -> None:
    r, prof = ranges_for(model), PROFILES["cubemars"]
    lo = decode_reply(encode_reply(1, r.p_min, r.v_min, r.t_min, r, prof), r, prof)
    hi = decode_reply(encode_reply(1, r.p_max, r.v_max, r.t_max, r, prof), r, prof)
    assert (lo.position, lo.velocity, lo.torque) == (r.p_min, r.v_min, r.t_min)
    assert (hi.position, hi.velocity, hi.torque) == (r.p_max, r.v_max, r.t_max)


@PROPS
@given(st.sampled_from(MODELS), st.binary(min_size=8, max_size=8))
def test_decode_then_encode_reply_is_identity(model: str, frame: bytes) -> None:
    r = MODEL_RANGES[model]
    for name in ("cubemars", "damiao"):
        prof = PROFILES[name]
        rep = decode_reply(frame, r, prof)
        again = encode_reply(
            rep.motor_id,
            rep.position,
            rep.velocity,
            rep.torque,
            r,
            prof,
            temperature=rep.temperature,
            error_code=rep.error_code,
            status=rep.status,
            rotor_temperature=rep.rotor_temperature,
        )
        assert again == frame


def test_reply_position_wraps_like_the_firmware_unless_asked_to_saturate() -> None:
    r, prof = ranges_for("AK80-9"), PROFILES["cubemars"]
    beyond = r.p_max + 10 * r.lsb("p")
    wrapped = decode_reply(encode_reply(1, beyond, 0.0, 0.0, r, prof), r, prof)
    assert wrapped.position < r.p_min + 10 * r.lsb("p")
    saturated = decode_reply(encode_reply(1, beyond, 0.0, 0.0, r, prof, wrap_position=False), r, prof)
    assert saturated.position == r.p_max
    # velocity and torque saturate
    rep = decode_reply(encode_reply(1, 0.0, 1e6, -1e6, r, prof), r, prof)
    assert (rep.velocity, rep.torque) == (r.v_max, r.t_min)
    with pytest.raises(InvalidValueError, match="velocity"):
        encode_reply(1, 0.0, math.nan, 0.0, r, prof)


@pytest.mark.parametrize("dlc", [6, 7, 8])
def test_cubemars_decodes_each_dlc(dlc: int) -> None:
    r, prof = ranges_for("AK80-9"), PROFILES["cubemars"]
    full = encode_reply(5, 1.0, -2.0, 3.0, r, prof, temperature=45.0, error_code=2)
    rep = decode_reply(full[:dlc], r, prof)
    assert rep.motor_id == 5 and rep.dlc == dlc
    assert within_lsb(rep.position, 1.0, r, "p")
    assert within_lsb(rep.velocity, -2.0, r, "v")
    assert within_lsb(rep.torque, 3.0, r, "t")
    assert rep.temperature == (45.0 if dlc >= 7 else None)
    assert full[6] == 45 + 40  # manual v1.0.15: byte 6 = degrees C + 40
    assert rep.error_code == (2 if dlc == 8 else 0)
    assert rep.error == ("over-current" if dlc == 8 else None)
    assert rep.status is None


def test_katz_profile_is_six_bytes() -> None:
    r, prof = ranges_for("AK80-9"), PROFILES["katz"]
    frame = encode_reply(2, 0.5, 0.0, 0.0, r, prof)
    assert len(frame) == 6
    rep = decode_reply(frame, r, prof)
    assert rep.temperature is None and rep.error_code == 0 and rep.motor_id == 2


@pytest.mark.parametrize("bad_len", [0, 5, 9])
@pytest.mark.parametrize("name", sorted(PROFILES))
def test_malformed_reply_length(name: str, bad_len: int) -> None:
    with pytest.raises(InvalidValueError, match="data bytes"):
        decode_reply(bytes(bad_len), ranges_for("AK80-9"), PROFILES[name])


@pytest.mark.parametrize("dlc", [6, 7])
def test_damiao_needs_eight_bytes(dlc: int) -> None:
    with pytest.raises(InvalidValueError):
        decode_reply(bytes(dlc), ranges_for("DM4310"), PROFILES["damiao"])


@pytest.mark.parametrize(
    ("code", "name"),
    [
        (0, None),
        (1, "over-temperature"),
        (2, "over-current"),
        (3, "over-voltage"),
        (4, "under-voltage"),
        (5, "encoder fault"),
        (6, "phase imbalance"),
        (7, "unknown error code 0x7"),
    ],
)
def test_cubemars_error_codes(code: int, name: str | None) -> None:
    r, prof = ranges_for("AK80-9"), PROFILES["cubemars"]
    rep = decode_reply(encode_reply(1, 0.0, 0.0, 0.0, r, prof, error_code=code), r, prof)
    assert rep.error_code == code and rep.error == name and rep.ok is (code == 0)


@pytest.mark.parametrize(
    ("status", "error_code", "name"),
    [
        (0x0, 0, None),  # disabled
        (0x1, 0, None),  # enabled
        (0x8, 0x8, "over-voltage"),
        (0x9, 0x9, "under-voltage"),
        (0xA, 0xA, "over-current"),
        (0xB, 0xB, "MOSFET over-temperature"),
        (0xC, 0xC, "rotor over-temperature"),
        (0xD, 0xD, "lost communication"),
        (0xE, 0xE, "overload"),
        (0x5, 0x5, "unknown error code 0x5"),
    ],
)
def test_damiao_status(status: int, error_code: int, name: str | None) -> None:
    r, prof = ranges_for("DM4310"), PROFILES["damiao"]
    frame = encode_reply(7, 0.0, 0.0, 0.0, r, prof, status=status, temperature=41.0, rotor_temperature=52.0)
    assert frame[0] == (status << 4) | 7
    rep = decode_reply(frame, r, prof)
    assert rep.motor_id == 7 and rep.status == status
    assert rep.error_code == error_code and rep.error == name
    assert rep.temperature == 41.0 and rep.rotor_temperature == 52.0


# ---------------------------------------------------------------- ranges and profiles


def test_model_table() -> None:
    for model in ("AK80-9", "AK10-9", "AK60-6", "AK70-10", "AK80-6", "AK80-64"):
        r = ranges_for(model)
        assert (r.kp_min, r.kp_max, r.kd_min, r.kd_max) == (0.0, 500.0, 0.0, 5.0)
        assert (r.p_min, r.p_max) == (-12.5, 12.5)
    assert (ranges_for("AK80-6").v_max, ranges_for("AK80-6").t_max) == (76.0, 12.0)
    assert (ranges_for("AK80-64").v_max, ranges_for("AK80-64").t_max) == (8.0, 144.0)
    assert ranges_for("ak10-9") is MODEL_RANGES["AK10-9"]


def test_ranges_overrides() -> None:
    r = ranges_for("AK80-9", {"t_min": -25, "t_max": 25.0})
    assert (r.t_min, r.t_max, r.v_max) == (-25.0, 25.0, 50.0)
    assert isinstance(r.t_min, float)
    assert encode_command(0, 0, 0, 0, 24.0, r)  # inside the overridden range
    with pytest.raises(ConfigurationError, match="t_mx"):
        ranges_for("AK80-9", {"t_mx": 3.0})
    with pytest.raises(ConfigurationError, match="t_min < t_max"):
        ranges_for("AK80-9", {"t_min": 30.0})
    with pytest.raises(ConfigurationError, match="finite"):
        MotorRanges(p_max=math.inf)


def test_unknown_model_lists_known_ones() -> None:
    with pytest.raises(ConfigurationError) as info:
        ranges_for("AK99-1")
    for model in ("AK80-9", "AK10-9", "AK60-6", "AK70-10", "AK80-6", "AK80-64"):
        assert model in str(info.value)


def test_profiles() -> None:
    assert profile_for("CubeMars") is PROFILES["cubemars"]
    assert PROFILES["damiao"].reply_dlc == 8 and PROFILES["damiao"].id_mask == 0x0F
    assert PROFILES["cubemars"].id_mask == 0xFF
    with pytest.raises(ConfigurationError, match="cubemars"):
        profile_for("odrive")
