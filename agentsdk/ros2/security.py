"""Who may see and command a served robot: a keystore of roles, and serving with it.

**DDS Security is not available to the face.** SROS2 uses the OMG DDS Security plugins
(authentication with a CA-signed identity, access control with signed governance and
permissions, encryption). The ``cyclonedds`` Python wheel the face runs on (11.0.1) is built
without them: a configuration with a ``<Security>`` section fails with ``Security: unknown
element``, and the wheel ships no ``libdds_security_*`` plugin. Debian's Cyclone DDS C library
(0.10.2, ``libddsc0debian``) does ship the plugins, but the Python binding cannot use that
library (another major version), so a served robot cannot be an SROS2 participant here.

**What is used instead: Cyclone DDS domain tags, one per role.** A participant only discovers
participants whose domain tag (``<Discovery><Tag>``) equals its own; without discovery it
learns no topic, matches no reader or writer and sends nothing anyone receives. A keystore
(:func:`create_keystore`, ``agentsdk security create DIR``) holds a random 256-bit tag for each
role:

* ``operator``: the full face (state, services, the JTC topic and action, the lease) on the
  robot's domain, under the operator tag;
* ``viewer``: a read-only face (``joint_states``, ``tf``, ``robot_description``, diagnostics,
  controller state, action status; no command topic, no service, no action server) on the
  viewer domain (by default the next domain id), under the viewer tag.

Each role also gets an identity file (``operator.json``, ``viewer.json``) holding only its own
domain and tag: give a viewer ``viewer.json`` and it can read but has nothing that could
command. :func:`identity_config` (``agentsdk security config``) turns an identity into the
``CYCLONEDDS_URI`` configuration for a client -- agentsdk's or any Cyclone DDS based ROS 2
node (``RMW_IMPLEMENTATION=rmw_cyclonedds_cpp``, ``ROS_DOMAIN_ID`` = the identity's domain).

**Guarantees and limits** (measured by ``tests/test_ros2_security.py``): a participant without
a role's tag sees no topic of the robot and its commands reach nothing; a viewer reads
``joint_states`` and its goals and trajectories reach no reader; an operator commands.
Unlike DDS Security the tags are shared secrets that travel **in clear text** in discovery
packets and the data is not encrypted or signed: whoever can capture traffic on the link
learns the tags and can read or forge data. Use it on a trusted link (a dedicated network,
a VPN such as WireGuard), and treat identity files like passwords (they are written 0600).
"""

from __future__ import annotations

import json
import os
import secrets
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

from ..errors import ConfigurationError, InvalidValueError
from .dds import network_config, resolve_domain_id

if TYPE_CHECKING:
    from ..robot import Robot
    from .server import RosFace

__all__ = ["ROLES", "Identity", "SecuredFace", "create_keystore", "expose_secured", "identity_config",
           "load_identity", "load_keystore"]

#: the roles a keystore holds
ROLES = ("operator", "viewer")
_FORMAT = "agentsdk-keystore/1"
_MECHANISM = "cyclonedds-domain-tag"


@dataclass(frozen=True)
class Identity:
    """One role's credentials: its domain id and domain tag."""

    role: str
    domain_id: int
    tag: str


def create_keystore(path: str | os.PathLike[str], *, domain_id: int | None = None,
                    viewer_domain_id: int | None = None, overwrite: bool = False) -> dict[str, Identity]:
    """Create a keystore in directory ``path``: ``keystore.json`` (every role) and ``<role>.json`` each.

    ``domain_id``: the operators' domain (default ``ROS_DOMAIN_ID``, else 0);
    ``viewer_domain_id``: the viewers' (default the next id). Files are written 0600 in a
    0700 directory; an existing keystore is kept unless ``overwrite``.
    """
    root = Path(path)
    operator_domain = resolve_domain_id(domain_id)
    viewer_domain = resolve_domain_id((operator_domain + 1) % 233 if viewer_domain_id is None else viewer_domain_id)
    if viewer_domain == operator_domain:
        raise InvalidValueError(f"the viewer domain must differ from the operator domain ({operator_domain}): "
                                "one process serves each domain with one configuration")
    if (root / "keystore.json").exists() and not overwrite:
        raise ConfigurationError(f"{root / 'keystore.json'} exists: pass overwrite (--force) to replace its secrets")
    root.mkdir(parents=True, exist_ok=True)
    os.chmod(root, 0o700)
    ids = {
        "operator": Identity("operator", operator_domain, secrets.token_hex(32)),
        "viewer": Identity("viewer", viewer_domain, secrets.token_hex(32)),
    }
    _write(root / "keystore.json", {"format": _FORMAT, "mechanism": _MECHANISM,
                                    "roles": {r: _as_json(i) for r, i in ids.items()}})
    for role, ident in ids.items():
        _write(root / f"{role}.json", {"format": _FORMAT, "mechanism": _MECHANISM, **_as_json(ident)})
    return ids


def _as_json(ident: Identity) -> dict[str, Any]:
    return {"role": ident.role, "domain_id": ident.domain_id, "tag": ident.tag}


def _write(path: Path, data: dict[str, Any]) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=2)
        f.write("\n")
    os.chmod(path, 0o600)


def _read(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigurationError(f"{path}: no such keystore file (create one: agentsdk security create DIR)") from None
    except (OSError, ValueError) as exc:
        raise ConfigurationError(f"{path}: not a readable agentsdk keystore file: {exc}") from exc
    if not isinstance(data, dict) or data.get("format") != _FORMAT or data.get("mechanism") != _MECHANISM:
        raise ConfigurationError(f"{path}: not an agentsdk keystore file (format {_FORMAT!r})")
    return data


def _identity(data: Any, where: Path) -> Identity:
    try:
        role, domain, tag = data["role"], data["domain_id"], data["tag"]
    except (KeyError, TypeError):
        raise ConfigurationError(f"{where}: an identity needs role, domain_id and tag") from None
    if role not in ROLES or not isinstance(tag, str) or len(tag) < 32 or not all(c in "0123456789abcdef" for c in tag):
        raise ConfigurationError(f"{where}: invalid identity (role one of {ROLES}, tag of at least 32 hex digits)")
    return Identity(role, resolve_domain_id(domain), tag)


def load_keystore(path: str | os.PathLike[str]) -> dict[str, Identity]:
    """Every role's identity from the keystore directory ``path``."""
    file = Path(path) / "keystore.json"
    roles = _read(file).get("roles")
    if not isinstance(roles, dict) or set(roles) != set(ROLES):
        raise ConfigurationError(f"{file}: the keystore must hold the roles {ROLES}")
    return {role: _identity(roles[role], file) for role in ROLES}


def load_identity(path: str | os.PathLike[str]) -> Identity:
    """One role's identity from its file (``viewer.json``...)."""
    file = Path(path)
    return _identity(_read(file), file)


def identity_config(identity: Identity, interface: str = "127.0.0.1", peers: Sequence[str] = ()) -> str:
    """The Cyclone DDS configuration (for ``CYCLONEDDS_URI``) of a participant with ``identity``."""
    return network_config(identity.domain_id, interface, tuple(peers), tag=identity.tag)


class SecuredFace:
    """A robot served per role (what :func:`expose_secured` returns); an async context manager."""

    def __init__(self, robot: Robot, keystore: str | os.PathLike[str], namespace: str = "", *,
                 interface: str = "127.0.0.1", peers: Sequence[str] = (), **options: Any) -> None:
        from .server import RosFace

        ids = load_keystore(keystore)
        for bad in ("domain_id", "dds_config", "read_only"):
            if bad in options:
                raise InvalidValueError(f"{bad} comes from the keystore when serving with one")
        self.identities = ids
        op, viewer = ids["operator"], ids["viewer"]
        #: the operators' face: everything, on the operator domain and tag
        self.operator = RosFace(robot, namespace=namespace, domain_id=op.domain_id,
                                dds_config=identity_config(op, interface, peers), **options)
        viewer_options = {k: v for k, v in options.items() if k not in ("lease", "lease_category", "require_lease")}
        #: the viewers' face: state only, on the viewer domain and tag
        self.viewer = RosFace(robot, namespace=namespace, domain_id=viewer.domain_id, read_only=True, lease=None,
                              dds_config=identity_config(viewer, interface, peers), **viewer_options)

    @property
    def faces(self) -> tuple[RosFace, RosFace]:
        """(operator face, viewer face)."""
        return self.operator, self.viewer

    async def start(self) -> None:
        """Start both faces (neither runs when one fails)."""
        await self.operator.start()
        try:
            await self.viewer.start()
        except BaseException:
            await self.operator.aclose()
            raise

    async def aclose(self) -> None:
        """Stop serving both faces (idempotent)."""
        try:
            await self.viewer.aclose()
        finally:
            await self.operator.aclose()

    async def __aenter__(self) -> SecuredFace:
        await self.start()
        return self

    async def __aexit__(self, et: type[BaseException] | None, e: BaseException | None,
                        tb: TracebackType | None) -> None:
        await self.aclose()


def expose_secured(robot: Robot, keystore: str | os.PathLike[str], namespace: str = "", *,
                   interface: str = "127.0.0.1", peers: Sequence[str] = (), **options: Any) -> SecuredFace:
    """Serve ``robot`` to the roles of ``keystore`` only (see the module documentation).

    ``interface``/``peers`` choose the network (default loopback); ``options`` are
    :func:`agentsdk.ros2.expose`'s (``rate``, ``lease``...; the domains come from the keystore).
    """
    return SecuredFace(robot, keystore, namespace, interface=interface, peers=peers, **options)
