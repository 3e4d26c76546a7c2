"""DDS plumbing for the ROS 2 face: names, QoS, the loopback config, services, the reader thread.

Everything here follows what ROS 2's ``rmw_cyclonedds`` puts on the wire:

* topic ``/ns/name`` is the DDS topic ``rt/ns/name``; service ``/ns/srv`` is the request topic
  ``rq/ns/srvRequest`` and the reply topic ``rr/ns/srvReply``;
* a service request or reply sample is the ``rmw_cyclonedds`` request header (client writer
  id as uint64, int64 sequence number) followed by the message's fields in one CDR stream:
  :func:`service_wire_type` builds that type from the message type;
* ``ROS_DOMAIN_ID`` picks the domain; without ``CYCLONEDDS_URI`` the participant talks on
  loopback only (:func:`loopback_config`).

DDS reads never block the event loop: one thread per participant waits on a DDS waitset and
hands the samples to the event loop with ``call_soon_threadsafe``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import re
import threading
import typing
from collections.abc import Callable, Iterator
from typing import Any

from cyclonedds.core import GuardCondition, InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.idl import IdlStruct, make_idl_struct
from cyclonedds.internal import InvalidSample
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from ..errors import ConfigurationError, InvalidValueError
from ._fast import RawDataWriter
from .msgs import Gid, NodeEntitiesInfo, ParticipantEntitiesInfo, RequestHeader

__all__ = [
    "QOS_DEFAULT", "QOS_LATCHED", "QOS_SENSOR", "DdsNode", "loopback_config", "network_config", "normalize_namespace",
    "participant",
    "resolve_domain_id", "service_wire_type",
]

log = logging.getLogger(__name__)

_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def normalize_namespace(namespace: str) -> str:
    """``"arm1"``, ``"/arm1/"`` -> ``"/arm1"``; ``""``/``"/"`` -> ``""``. Invalid names raise."""
    if not isinstance(namespace, str):
        raise InvalidValueError(f"namespace must be a string like '/arm1', got {namespace!r}")
    parts = [p for p in namespace.strip().split("/") if p]
    for p in parts:
        if not _TOKEN.match(p):
            raise InvalidValueError(
                f"invalid ROS 2 namespace {namespace!r}: {p!r} must be letters, digits and '_', "
                "not starting with a digit"
            )
    return "".join("/" + p for p in parts)


def resolve_domain_id(domain_id: int | None) -> int:
    """``domain_id``, else ``ROS_DOMAIN_ID`` from the environment, else 0 (ROS 2's rule)."""
    if domain_id is None:
        env = os.environ.get("ROS_DOMAIN_ID", "").strip()
        if not env:
            return 0
        try:
            domain_id = int(env)
        except ValueError:
            raise ConfigurationError(f"ROS_DOMAIN_ID must be an integer, got {env!r}") from None
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or not 0 <= domain_id <= 232:
        raise InvalidValueError(f"ROS 2 domain id must be an integer in [0, 232], got {domain_id!r}")
    return domain_id


def loopback_config(domain_id: int) -> str:
    """Cyclone DDS configuration that keeps all traffic on 127.0.0.1 (unicast discovery, no multicast)."""
    return (
        f'<CycloneDDS><Domain id="{domain_id}"><General><Interfaces>'
        '<NetworkInterface address="127.0.0.1"/></Interfaces>'
        "<AllowMulticast>false</AllowMulticast></General>"
        "<Discovery><ParticipantIndex>auto</ParticipantIndex>"
        "<MaxAutoParticipantIndex>50</MaxAutoParticipantIndex>"
        '<Peers><Peer Address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>'
    )


def network_config(domain_id: int, interface: str, peers: list[str] | tuple[str, ...] = (),
                   tag: str | None = None) -> str:
    """Cyclone DDS configuration on one network ``interface`` (an address or a name) with unicast ``peers``.

    Discovery is unicast to ``peers`` (addresses or host names; none: multicast discovery on
    that interface). ``interface="127.0.0.1"`` without peers or tag is :func:`loopback_config`.
    ``tag``: Cyclone DDS's domain tag -- only participants with the same tag discover each
    other (:mod:`agentsdk.ros2.security`).
    """
    token = re.compile(r"^[A-Za-z0-9_.:%-]+$")
    for what, value in [("interface", interface), *(("peer", p) for p in peers)]:
        if not isinstance(value, str) or not token.match(value):
            raise InvalidValueError(f"{what} must be an address or a name like 10.0.0.2 or eth0, got {value!r}")
    if tag is not None and not re.match(r"^[A-Za-z0-9_-]{1,256}$", tag):
        raise InvalidValueError("a domain tag must be 1 to 256 letters, digits, '_' or '-'")
    if interface == "127.0.0.1" and not peers and tag is None:
        return loopback_config(domain_id)
    is_address = re.match(r"^[0-9.]+$|:", interface) is not None
    nic = f'<NetworkInterface address="{interface}"/>' if is_address else f'<NetworkInterface name="{interface}"/>'
    if interface == "127.0.0.1" and not peers:
        peers = ("127.0.0.1",)
    multicast = "false" if peers else "true"
    peer_xml = "".join(f'<Peer Address="{p}"/>' for p in peers)
    tag_xml = "" if tag is None else f"<Tag>{tag}</Tag>"
    return (
        f'<CycloneDDS><Domain id="{domain_id}"><General><Interfaces>{nic}</Interfaces>'
        f"<AllowMulticast>{multicast}</AllowMulticast></General>"
        # announce every second (Cyclone's default: 30 s): a lost first exchange on a lossy link costs 1 s, not 30
        f"<Discovery>{tag_xml}<SPDPInterval>1 s</SPDPInterval><ParticipantIndex>auto</ParticipantIndex>"
        "<MaxAutoParticipantIndex>50</MaxAutoParticipantIndex>"
        f"<Peers>{peer_xml}</Peers></Discovery></Domain></CycloneDDS>"
    )


def _reliable(depth: int, transient_local: bool = False, user_data: bytes | None = None) -> Qos:
    policies: list[Any] = [
        Policy.Reliability.Reliable(duration(milliseconds=100)),
        Policy.Durability.TransientLocal if transient_local else Policy.Durability.Volatile,
        Policy.History.KeepLast(depth),
    ]
    if user_data is not None:
        policies.append(Policy.Userdata(user_data))
    return Qos(*policies)


#: ROS 2's default QoS: reliable, volatile, keep last 10
QOS_DEFAULT = _reliable(10)
#: ``robot_description``, ``tf_static``, action status: reliable, transient local, keep last 1
QOS_LATCHED = _reliable(1, transient_local=True)
#: ROS 2's ``SensorDataQoS``: best effort, volatile, keep last 5
QOS_SENSOR = Qos(Policy.Reliability.BestEffort, Policy.Durability.Volatile, Policy.History.KeepLast(5))
#: services: reliable, volatile, keep last (rmw_cyclonedds' services use keep all; 100 is plenty)
QOS_SERVICE = _reliable(100)

_WIRE_TYPES: dict[type[Any], type[Any]] = {}


def service_wire_type(message: type[Any]) -> type[Any]:
    """The ``rmw_cyclonedds`` wire type of a service message: a ``request_header`` then its fields.

    Same DDS type name as ``message`` (so a ROS 2 client matches it); the CDR bytes are the
    header's 16 bytes followed by the message's own fields in one stream.
    """
    wire = _WIRE_TYPES.get(message)
    if wire is None:
        fields: dict[str, Any] = {"request_header": RequestHeader}
        hints = typing.get_type_hints(message, include_extras=True)
        for f in dataclasses.fields(message):
            fields[f.name] = hints[f.name]
        typename = message.__idl_typename__
        wire = make_idl_struct(f"{message.__name__}_Wire", typename, fields)
        wire.__idl_annotations__["extensibility"] = "final"
        _WIRE_TYPES[message] = wire
    return wire


def unwrap(message: type[Any], sample: Any) -> tuple[RequestHeader, Any]:
    """``(request header, message)`` of a wire sample."""
    body = message(**{f.name: getattr(sample, f.name) for f in dataclasses.fields(message)})
    return sample.request_header, body


def wrap(message: type[Any], header: RequestHeader, body: Any) -> Any:
    """The wire sample of ``body`` with ``header`` (a reply repeats the request's header)."""
    wire = service_wire_type(message)
    return wire(request_header=header, **{f.name: getattr(body, f.name) for f in dataclasses.fields(message)})


# ------------------------------------------------------------------ domains shared per process
_domains: dict[int, tuple[Domain | None, int, str | None]] = {}
_domains_lock = threading.Lock()


def _acquire_domain(domain_id: int, config: str | None = None) -> None:
    with _domains_lock:
        dom, n, current = _domains.get(domain_id, (None, 0, None))
        if n == 0:
            if config is not None:
                dom, current = Domain(domain_id, config), config
            elif not os.environ.get("CYCLONEDDS_URI"):
                dom = Domain(domain_id, loopback_config(domain_id))
        elif config is not None and config != current:
            raise ConfigurationError(
                f"DDS domain {domain_id} is already open in this process with another configuration "
                "(one configuration per domain and process: use another domain id)")
        _domains[domain_id] = (dom, n + 1, current)


@contextlib.contextmanager
def participant(domain_id: int) -> Iterator[DomainParticipant]:
    """A bare participant on ``domain_id`` (the process's shared domain: loopback unless ``CYCLONEDDS_URI``).

    For short blocking look-ups off the event loop (discovery, a latched topic); deleted on exit.
    """
    _acquire_domain(domain_id)
    try:
        dp = DomainParticipant(domain_id)
        try:
            yield dp
        finally:
            dp.__del__()  # frees it now, not at GC (idempotent)
    finally:
        _release_domain(domain_id)


def _release_domain(domain_id: int) -> None:
    with _domains_lock:
        dom, n, config = _domains[domain_id]
        if n <= 1:
            del _domains[domain_id]
            if dom is not None:
                dom.__del__()  # frees the domain's sockets now, not at GC (idempotent)
        else:
            _domains[domain_id] = (dom, n - 1, config)


class DdsNode:
    """One DDS participant with ROS-named topics and a reader thread feeding the event loop.

    ``subscribe`` callbacks run on the event loop with one sample each. :meth:`close`
    stops the thread and deletes the participant (idempotent). ``config``: the Cyclone DDS
    configuration of the domain (default: ``CYCLONEDDS_URI``, else :func:`loopback_config`).
    """

    def __init__(self, domain_id: int, namespace: str, loop: asyncio.AbstractEventLoop,
                 config: str | None = None) -> None:
        self.domain_id = domain_id
        self.namespace = namespace
        self._loop = loop
        _acquire_domain(domain_id, config)
        try:
            self.participant = DomainParticipant(domain_id)
        except Exception:
            _release_domain(domain_id)
            raise
        self._waitset = WaitSet(self.participant)
        self._guard = GuardCondition(self.participant)
        self._waitset.attach(self._guard)
        self._topics: dict[str, Topic[Any]] = {}
        self._readers: list[tuple[ReadCondition, DataReader[Any], Callable[[Any], None]]] = []
        self._entities: list[Any] = []
        #: DDS GUIDs (16 bytes) of this node's readers and writers, for ros_discovery_info
        self.reader_guids: list[bytes] = []
        self.writer_guids: list[bytes] = []
        self._lock = threading.Lock()
        self._closed = False
        self._thread: threading.Thread | None = None

    def name(self, name: str) -> str:
        """The ROS name ``name`` under this node's namespace, without the leading slash."""
        return f"{self.namespace}/{name}".lstrip("/")

    def _topic(self, dds_name: str, data_type: type[IdlStruct]) -> Topic[Any]:
        topic = self._topics.get(dds_name)
        if topic is None:
            topic = Topic(self.participant, dds_name, data_type)
            self._topics[dds_name] = topic
        return topic

    def writer(self, name: str, data_type: type[IdlStruct], qos: Qos = QOS_DEFAULT, *,
               prefix: str = "rt/") -> DataWriter[Any]:
        """A writer of the ROS topic ``name`` (relative to the namespace)."""
        w: DataWriter[Any] = RawDataWriter(self.participant, self._topic(prefix + self.name(name), data_type), qos=qos)
        self._entities.append(w)
        self.writer_guids.append(w.guid.bytes)
        return w

    def subscribe(self, name: str, data_type: type[IdlStruct], callback: Callable[[Any], None],
                  qos: Qos = QOS_DEFAULT, *, prefix: str = "rt/") -> DataReader[Any]:
        """Call ``callback(sample)`` on the event loop for every sample of the ROS topic ``name``."""
        r: DataReader[Any] = DataReader(self.participant, self._topic(prefix + self.name(name), data_type), qos=qos)
        cond = ReadCondition(r, SampleState.Any | ViewState.Any | InstanceState.Any)
        with self._lock:
            self._readers.append((cond, r, callback))
            self._waitset.attach(cond)
        self._entities.append(r)
        self.reader_guids.append(r.guid.bytes)
        return r

    def service(self, name: str, request: type[IdlStruct], response: type[IdlStruct],
                handler: Callable[[RequestHeader, Any, Callable[[Any], None]], None]) -> None:
        """Serve the ROS service ``name``: ``handler(header, request, reply)``; ``reply(response)`` answers."""
        sid = f"serviceid={self.participant.guid}:{len(self._topics)};".encode()
        full = self.name(name)
        writer: DataWriter[Any] = DataWriter(
            self.participant, self._topic(f"rr/{full}Reply", service_wire_type(response)),
            qos=_reliable(100, user_data=sid))
        self._entities.append(writer)
        self.writer_guids.append(writer.guid.bytes)

        def on_request(sample: Any) -> None:
            header, body = unwrap(request, sample)

            def reply(resp: Any) -> None:
                writer.write(wrap(response, header, resp))

            handler(header, body, reply)

        r: DataReader[Any] = DataReader(
            self.participant, self._topic(f"rq/{full}Request", service_wire_type(request)),
            qos=_reliable(100, user_data=sid))
        cond = ReadCondition(r, SampleState.Any | ViewState.Any | InstanceState.Any)
        with self._lock:
            self._readers.append((cond, r, on_request))
            self._waitset.attach(cond)
        self._entities.append(r)
        self.reader_guids.append(r.guid.bytes)

    def announce(self, node_name: str) -> None:
        """Publish ``ros_discovery_info`` so ``ros2 node list`` / ``ros2 node info`` show this node.

        rmw_dds_common's graph message (Humble layout), on the un-prefixed DDS topic
        ``ros_discovery_info``, reliable + transient local, keep last 1.
        """
        w: DataWriter[Any] = DataWriter(self.participant, self._topic("ros_discovery_info", ParticipantEntitiesInfo),
                                        qos=QOS_LATCHED)
        self._entities.append(w)

        def gid(guid: bytes) -> Gid:
            return Gid(guid + bytes(24 - len(guid)))

        w.write(ParticipantEntitiesInfo(gid(self.participant.guid.bytes), [NodeEntitiesInfo(
            self.namespace or "/", node_name,
            [gid(g) for g in self.reader_guids], [gid(g) for g in self.writer_guids])]))

    def start(self) -> None:
        """Start the reader thread (after every subscription is made)."""
        self._thread = threading.Thread(target=self._run, name=f"agentsdk-ros2{self.namespace or '/'}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        loop = self._loop
        while not self._closed:
            try:
                self._waitset.wait(duration(seconds=1))
            except Exception:  # the participant was deleted under us: closing
                if self._closed:
                    return
                raise
            if self._closed:
                return
            with self._lock:
                readers = list(self._readers)
            for _cond, reader, callback in readers:
                try:
                    samples = reader.take(N=64)
                except Exception:
                    if self._closed:
                        return
                    raise
                for s in samples:
                    if not isinstance(s, InvalidSample):  # disposes / unregisters carry no data
                        try:
                            loop.call_soon_threadsafe(callback, s)
                        except RuntimeError:  # the event loop closed
                            return

    def close(self) -> None:
        """Stop the reader thread and delete the participant (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._guard.set(True)
            if self._thread is not None:
                self._thread.join(timeout=5.0)
        finally:
            try:
                self.participant.__del__()  # deletes every entity below it now (idempotent)
            finally:
                _release_domain(self.domain_id)
