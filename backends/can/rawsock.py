"""Batched SocketCAN receive and plain sends: one system call per event-loop wake-up, not six per frame.

python-can's socketcan bus costs, per received frame, a ``select``, a ``recvmsg``, an ``ioctl``
(CPython resolves the interface name of every ``recvmsg`` source address) and two clock reads,
and per sent frame a ``select``, a ``send`` and two clock reads. That is cheap on a native
kernel (clock reads are vDSO calls there) but not where every system call traps into another
kernel: in user-mode Linux (the vcan test suite, CI's VM) those calls were most of the CAN
host's CPU time per control cycle. :class:`FrameReader` drains every frame the socket holds with
one ``recvmmsg(MSG_DONTWAIT)`` (libc through ctypes, no source address, the kernel's
``SO_TIMESTAMPNS`` receive time from the control message), and :func:`send_frame` is one
non-blocking ``send``. Both work on the socket of an open ``can.interfaces.socketcan`` bus, whose
filters and options (``SO_TIMESTAMPNS``, ``receive_own_messages``) stay in force.
:func:`frame_reader` returns None where this does not apply (not Linux, no libc ``recvmmsg``,
a bus without a raw socket): the backend then uses python-can's own receive path.
"""

from __future__ import annotations

import ctypes
import errno
import socket
import struct
import sys
from collections.abc import Callable
from typing import Any

__all__ = ["FrameReader", "build_frame", "frame_reader", "send_frame"]

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

_RECVMMSG: Any = None


def _recvmmsg() -> Any:
    """The C library's ``recvmmsg`` (bound once), or False where there is none."""
    global _RECVMMSG
    if _RECVMMSG is None:
        _RECVMMSG = False
        if sys.platform.startswith("linux"):
            try:
                fn = ctypes.CDLL(None, use_errno=True).recvmmsg
                fn.argtypes = [ctypes.c_int, ctypes.POINTER(_MMsgHdr), ctypes.c_uint, ctypes.c_int, ctypes.c_void_p]
                fn.restype = ctypes.c_int
                _RECVMMSG = fn
            except (OSError, AttributeError):
                pass
    return _RECVMMSG


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


def frame_reader(bus: Any, handler: FrameHandler) -> FrameReader | None:
    """A :class:`FrameReader` on a python-can socketcan bus's raw socket, or None where it does not apply."""
    sock = getattr(bus, "socket", None)
    fn = _recvmmsg()
    if not fn or not isinstance(sock, socket.socket) or sock.family != getattr(socket, "AF_CAN", -1):
        return None
    if sock.type != socket.SOCK_RAW:
        return None
    return FrameReader(sock.fileno(), handler, fn)


def build_frame(can_id: int, data: bytes | bytearray) -> bytearray:
    """A classic ``struct can_frame`` (16 bytes) for ``can_id`` (11-bit) and up to 8 data bytes."""
    frame = bytearray(16)
    _HEADER.pack_into(frame, 0, can_id, len(data), 0)
    frame[8:8 + len(data)] = data
    return frame


def send_frame(sock: socket.socket, frame: bytearray) -> None:
    """Send one frame without blocking: one system call. Raises ``OSError`` (``ENOBUFS``/``EAGAIN``: TX queue full)."""
    if sock.send(frame, _MSG_DONTWAIT) != len(frame):
        raise OSError(errno.EIO, "CAN frame only partly sent")
