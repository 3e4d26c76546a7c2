"""Batched SocketCAN receive and send: one system call per event-loop wake-up and per cycle's commands.

python-can's socketcan bus costs, per received frame, a ``select``, a ``recvmsg``, an ``ioctl``
(CPython resolves the interface name of every ``recvmsg`` source address) and two clock reads,
and per sent frame a ``select``, a ``send`` and two clock reads. That is cheap on a native
kernel (clock reads are vDSO calls there) but not where every system call traps into another
kernel: in user-mode Linux (the vcan test suite, CI's VM) those calls were most of the CAN
host's CPU time per control cycle. :class:`FrameReader` drains every frame the socket holds with
one ``recvmmsg(MSG_DONTWAIT)`` (libc through ctypes, no source address, the kernel's
``SO_TIMESTAMPNS`` receive time from the control message), and :class:`FrameWriter`
sends a cycle's command frames with one non-blocking ``sendmmsg``. Both work on the socket
of an open ``can.interfaces.socketcan`` bus, whose filters and options (``SO_TIMESTAMPNS``,
``receive_own_messages``) stay in force. :func:`frame_reader` and :func:`frame_writer` return
None where this does not apply (not Linux, no libc ``recvmmsg``/``sendmmsg``, a bus without a
raw socket): the backend then receives and sends through python-can.
"""

from __future__ import annotations

import ctypes
import errno
import socket
import struct
import sys
from collections.abc import Callable
from typing import Any

__all__ = ["FrameReader", "FrameWriter", "frame_reader", "frame_writer"]

#: struct can_frame / canfd_frame header: can_id (with the EFF/RTR/ERR flags), length, flags, 2 reserved
_HEADER = struct.Struct("=IBB2x")
#: the largest frame the socket can deliver (CANFD_MTU)
_MTU = 72
#: frames taken per ``recvmmsg``; more stay queued and wake the loop again (a flood cannot hold it)
BATCH = 16
_SOL_SOCKET = socket.SOL_SOCKET
_SCM_TIMESTAMPNS = 35  # SO_TIMESTAMPNS, the control message python-can's bus asks the kernel for
_MSG_DONTWAIT = getattr(socket, "MSG_DONTWAIT", 0x40)


class _IOVec(ctypes.Structure):
    _fields_ = [("iov_base", ctypes.c_void_p), ("iov_len", ctypes.c_size_t)]


class _MsgHdr(ctypes.Structure):
    _fields_ = [
        ("msg_name", ctypes.c_void_p),
        ("msg_namelen", ctypes.c_uint32),
        ("msg_iov", ctypes.POINTER(_IOVec)),
        ("msg_iovlen", ctypes.c_size_t),
        ("msg_control", ctypes.c_void_p),
        ("msg_controllen", ctypes.c_size_t),
        ("msg_flags", ctypes.c_int),
    ]


class _MMsgHdr(ctypes.Structure):
    _fields_ = [("msg_hdr", _MsgHdr), ("msg_len", ctypes.c_uint)]


class _CMsgHdr(ctypes.Structure):
    _fields_ = [("cmsg_len", ctypes.c_size_t), ("cmsg_level", ctypes.c_int), ("cmsg_type", ctypes.c_int)]


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


_CMSG_HDR = ctypes.sizeof(_CMsgHdr)  # already aligned to size_t on Linux
_CONTROL = _CMSG_HDR + ctypes.sizeof(_Timespec)  # CMSG_SPACE(sizeof(struct timespec))
_TIMESPEC = struct.Struct("@ll")
_CMSG = struct.Struct("@Nii")

_LIBC: dict[str, Any] = {}


def _libc_fn(name: str) -> Any:
    """The C library's ``recvmmsg``/``sendmmsg`` (bound once), or False where there is none."""
    fn = _LIBC.get(name)
    if fn is None:
        fn = False
        if sys.platform.startswith("linux"):
            try:
                fn = getattr(ctypes.CDLL(None, use_errno=True), name)
                args = [ctypes.c_int, ctypes.POINTER(_MMsgHdr), ctypes.c_uint, ctypes.c_int]
                fn.argtypes = [*args, ctypes.c_void_p] if name == "recvmmsg" else args
                fn.restype = ctypes.c_int
            except (OSError, AttributeError):
                fn = False
        _LIBC[name] = fn
    return fn


#: handler(can_id with its EFF/RTR/ERR flag bits, data, kernel receive time on the wall clock or 0.0)
FrameHandler = Callable[[int, bytes, float], None]


class FrameReader:
    """Drains a SocketCAN socket in batches; call :meth:`drain` when it is readable (event loop reader)."""

    def __init__(self, fd: int, handler: FrameHandler, recvmmsg: Any) -> None:
        self.fd = fd
        self._handler = handler
        self._recvmmsg = recvmmsg
        self._frames = ctypes.create_string_buffer(BATCH * _MTU)
        self._control = ctypes.create_string_buffer(BATCH * _CONTROL)
        self._iov = (_IOVec * BATCH)()
        self._vec = (_MMsgHdr * BATCH)()
        base_f, base_c = ctypes.addressof(self._frames), ctypes.addressof(self._control)
        for i in range(BATCH):
            self._iov[i].iov_base = base_f + i * _MTU
            self._iov[i].iov_len = _MTU
            hdr = self._vec[i].msg_hdr
            hdr.msg_name = None
            hdr.msg_namelen = 0
            hdr.msg_iov = ctypes.pointer(self._iov[i])
            hdr.msg_iovlen = 1
            hdr.msg_control = base_c + i * _CONTROL
            hdr.msg_controllen = _CONTROL
        #: frames received per :meth:`drain` call (statistics)
        self.frames = 0
        self.calls = 0

    def drain(self, more: Callable[[], bool] | None = None) -> None:
        """Take what the socket holds, up to :data:`BATCH` frames per call, and hand each to the handler.

        ``more()`` false after a batch ends the drain early (the rest wakes the loop again).
        Raises ``OSError`` for a receive error other than "nothing queued".
        """
        vec, fn, fd = self._vec, self._recvmmsg, self.fd
        frames, control, handler = self._frames, self._control, self._handler
        while True:
            n = fn(fd, vec, BATCH, _MSG_DONTWAIT, None)
            self.calls += 1
            if n < 0:
                err = ctypes.get_errno()
                if err in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EINTR):
                    return
                raise OSError(err, f"CAN receive failed: {errno.errorcode.get(err, err)}")
            raw = frames.raw if n else b""
            ctl = control.raw if n else b""
            for i in range(n):
                m = vec[i]
                size = m.msg_len
                if size < 16:
                    continue
                off = i * _MTU
                can_id, length, _flags = _HEADER.unpack_from(raw, off)
                if length > size - 8:
                    continue
                ts = 0.0
                hdr = m.msg_hdr
                if hdr.msg_controllen >= _CONTROL:
                    coff = i * _CONTROL
                    _len, level, kind = _CMSG.unpack_from(ctl, coff)
                    if level == _SOL_SOCKET and kind == _SCM_TIMESTAMPNS:
                        sec, nsec = _TIMESPEC.unpack_from(ctl, coff + _CMSG_HDR)
                        ts = sec + nsec * 1e-9
                hdr.msg_controllen = _CONTROL  # the kernel wrote back the length it used
                handler(can_id, raw[off + 8:off + 8 + length], ts)
            self.frames += n
            if n < BATCH or (more is not None and not more()):
                return


class FrameWriter:
    """The command frames of one cycle (one classic 8-byte frame per CAN id), sent with one ``sendmmsg``."""

    def __init__(self, fd: int, can_ids: list[int], sendmmsg: Any) -> None:
        self.fd = fd
        self._sendmmsg = sendmmsg
        n = len(can_ids)
        self.count = n
        self._buf = (ctypes.c_ubyte * (16 * n))()
        self._view = memoryview(self._buf).cast("B")
        self._iov = (_IOVec * n)()
        self._vec = (_MMsgHdr * n)()
        base = ctypes.addressof(self._buf)
        for k, can_id in enumerate(can_ids):
            _HEADER.pack_into(self._view, 16 * k, can_id, 8, 0)
            self._iov[k].iov_base = base + 16 * k
            self._iov[k].iov_len = 16
            hdr = self._vec[k].msg_hdr
            hdr.msg_iov = ctypes.pointer(self._iov[k])
            hdr.msg_iovlen = 1

    def set_data(self, k: int, data: bytes | bytearray) -> None:
        """The 8 data bytes of frame ``k`` (a copy into the frame buffer, no allocation)."""
        self._view[16 * k + 8:16 * k + 16] = data

    def send(self) -> tuple[int, int]:
        """Send every frame without blocking, in order: (frames sent, errno of the first one not sent or 0)."""
        sent = self._sendmmsg(self.fd, self._vec, self.count, _MSG_DONTWAIT)
        if sent < 0:
            return 0, ctypes.get_errno()
        if sent < self.count:  # the kernel stops at the first frame it could not queue: ask why
            more = self._sendmmsg(self.fd, ctypes.byref(self._vec[sent]), 1, _MSG_DONTWAIT)
            return sent + max(more, 0), (ctypes.get_errno() if more < 0 else 0)
        return sent, 0


def _raw_can_socket(bus: Any) -> socket.socket | None:
    sock = getattr(bus, "socket", None)
    if not isinstance(sock, socket.socket) or sock.family != getattr(socket, "AF_CAN", -1):
        return None
    return sock if sock.type == socket.SOCK_RAW else None


def frame_reader(bus: Any, handler: FrameHandler) -> FrameReader | None:
    """A :class:`FrameReader` on a python-can socketcan bus's raw socket, or None where it does not apply."""
    sock, fn = _raw_can_socket(bus), _libc_fn("recvmmsg")
    return FrameReader(sock.fileno(), handler, fn) if sock is not None and fn else None


def frame_writer(bus: Any, can_ids: list[int]) -> FrameWriter | None:
    """A :class:`FrameWriter` for ``can_ids`` (11-bit) on a socketcan bus's raw socket, or None where not applicable."""
    sock, fn = _raw_can_socket(bus), _libc_fn("sendmmsg")
    return FrameWriter(sock.fileno(), can_ids, fn) if sock is not None and fn else None
