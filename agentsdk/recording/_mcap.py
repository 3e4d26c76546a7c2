"""A block-at-a-time MCAP writer: whole chunks of fixed-size messages built with numpy.

``mcap.writer.Writer`` costs about 8 µs of Python per message (a record
object, statistics, a message-index entry), which at one message per control
tick is most of the recorder's cost, paid in the GIL the control loop needs.
Here a chunk's message records are laid out in one ``uint8`` array: every
message of a channel has the same size (:mod:`._cdr`), so each channel's
records are a ``(k, 31 + size)`` array filled column by column and scattered
into log-time order.  The other records (header, schemas, channels, metadata,
chunk, indexes, summary, footer) are written with the ``mcap`` package's own
record classes, so the file is standard MCAP read by every MCAP reader.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from typing import IO

import numpy as np
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

__all__ = ["McapFile", "Part"]

MAGIC = b"\x89MCAP0\r\n"
_MESSAGE_HEAD = 31  # opcode u8, length u64, channel u16, sequence u32, log time u64, publish time u64

#: one channel's messages of a chunk: (channel id, log times (k,), payloads: (k, size) uint8 or k bytes)
Part = tuple[int, np.ndarray, "np.ndarray | Sequence[bytes]"]


class McapFile:
    """An MCAP file written chunk by chunk; ``message_index=True`` adds chunk and message indexes."""

    def __init__(self, stream: IO[bytes], *, profile: str, library: str, message_index: bool) -> None:
        self.stream = stream
        self.message_index = message_index
        self._zstd = zstandard.ZstdCompressor(level=3)
        self._rb = RecordBuilder()
        self.schemas: list[Schema] = []
        self.channels: list[Channel] = []
        self.stats = Statistics(
            attachment_count=0, channel_count=0, channel_message_counts={}, chunk_count=0, message_count=0,
            message_end_time=0, message_start_time=0, metadata_count=0, schema_count=0,
        )
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._offset = 0
        self._write(MAGIC)
        Header(profile=profile, library=library).write(self._rb)
        self._emit()

    # -------------------------------------------------------------- plumbing
    def _write(self, data: bytes) -> None:
        self.stream.write(data)
        self._offset += len(data)

    def _emit(self) -> int:
        """Write the records built so far; returns their length."""
        data: bytes = self._rb.end()  # type: ignore[no-untyped-call]  # mcap has no annotations here
        self._write(data)
        return len(data)

    # -------------------------------------------------------------- definitions
    def schema(self, name: str, encoding: str, data: bytes) -> int:
        s = Schema(id=len(self.schemas) + 1, data=data, encoding=encoding, name=name)
        self.schemas.append(s)
        self.stats.schema_count += 1
        s.write(self._rb)
        self._emit()
        return s.id

    def channel(self, topic: str, encoding: str, schema_id: int, metadata: dict[str, str]) -> int:
        c = Channel(id=len(self.channels) + 1, topic=topic, message_encoding=encoding, metadata=metadata,
                    schema_id=schema_id)
        self.channels.append(c)
        self.stats.channel_count += 1
        self.stats.channel_message_counts[c.id] = 0
        c.write(self._rb)
        self._emit()
        return c.id

    def metadata(self, name: str, values: dict[str, str]) -> None:
        offset = self._offset
        Metadata(name=name, metadata=values).write(self._rb)
        length = self._emit()
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))
        self.stats.metadata_count += 1

    # -------------------------------------------------------------- messages
    def chunk(self, parts: Sequence[Part]) -> None:
        """One compressed chunk of the parts' messages in log-time order (ties: in part order)."""
        parts = [p for p in parts if len(p[1])]
        if not parts:
            return
        stamps = np.concatenate([p[1] for p in parts]).astype(np.int64)
        kinds = np.concatenate([np.full(len(p[1]), k, dtype=np.int64) for k, p in enumerate(parts)])
        local = np.concatenate([np.arange(len(p[1])) for p in parts])
        order = np.lexsort((kinds, stamps))
        records: list[np.ndarray | list[bytes]] = []
        sizes = np.empty(len(parts), dtype=np.int64)
        index: dict[int, list[tuple[int, int]]] = {}
        for k, (cid, ns, payload) in enumerate(parts):
            seq0 = self.stats.channel_message_counts[cid]
            if isinstance(payload, np.ndarray):
                records.append(_records(cid, seq0, ns, payload))
                sizes[k] = payload.shape[1] + _MESSAGE_HEAD
            else:
                records.append([_record(cid, seq0 + i, int(ns[i]), d) for i, d in enumerate(payload)])
                sizes[k] = -1
            self.stats.channel_message_counts[cid] = seq0 + len(ns)
        # copy runs of consecutive messages of one part (the streams interleave in log-time order)
        ks, ls = kinds[order], local[order]
        cuts = np.flatnonzero(np.diff(ks)) + 1
        chunks: list[bytes | memoryview] = []
        offset = 0
        offsets = np.empty(len(order), dtype=np.int64)
        for a, b in zip(np.concatenate(([0], cuts)).tolist(), np.concatenate((cuts, [len(order)])).tolist(),
                        strict=True):
            k, i0, n = int(ks[a]), int(ls[a]), b - a
            rec = records[k]
            if isinstance(rec, np.ndarray):
                size = int(sizes[k])
                if self.message_index:
                    offsets[a:b] = offset + size * np.arange(n)
                chunks.append(rec[i0 : i0 + n].data.cast("B"))
                offset += size * n
            else:
                for j in range(n):
                    offsets[a + j] = offset
                    chunks.append(rec[i0 + j])
                    offset += len(rec[i0 + j])
        if self.message_index:
            pos = np.empty(len(order), dtype=np.int64)
            pos[order] = offsets
            first = 0
            for cid, ns, _payload in parts:
                k = len(ns)
                index.setdefault(cid, []).extend(zip(ns.tolist(), pos[first : first + k].tolist(), strict=True))
                first += k
        raw = b"".join(chunks)
        start, end = int(stamps.min()), int(stamps.max())
        st = self.stats
        st.message_start_time = start if st.message_count == 0 else min(st.message_start_time, start)
        st.message_end_time = max(st.message_end_time, end)
        st.message_count += len(order)
        st.chunk_count += 1
        data = self._zstd.compress(raw)
        chunk_start = self._offset
        Chunk(compression="zstd", data=data, message_end_time=end, message_start_time=start,
              uncompressed_crc=zlib.crc32(raw), uncompressed_size=len(raw)).write(self._rb)
        length = self._emit()
        index_offsets: dict[int, int] = {}
        if self.message_index:
            for cid in sorted(index):
                index_offsets[cid] = self._offset
                MessageIndex(channel_id=cid, records=sorted(index[cid])).write(self._rb)
                self._emit()
            self._chunk_indexes.append(ChunkIndex(
                chunk_length=length, chunk_start_offset=chunk_start, compression="zstd", compressed_size=len(data),
                message_end_time=end, message_index_length=self._offset - chunk_start - length,
                message_index_offsets=index_offsets, message_start_time=start, uncompressed_size=len(raw),
            ))

    def flush(self) -> None:
        self.stream.flush()

    # -------------------------------------------------------------- summary
    def finish(self) -> None:
        """Data end, summary (schemas, channels, statistics, indexes), summary offsets, footer."""
        DataEnd(data_section_crc=0).write(self._rb)
        self._emit()
        summary_start = self._offset
        groups: list[tuple[int, Sequence[Schema | Channel | Statistics | ChunkIndex | MetadataIndex]]] = [
            (Opcode.SCHEMA, self.schemas),
            (Opcode.CHANNEL, self.channels),
            (Opcode.STATISTICS, [self.stats]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes if self.message_index else []),
            (Opcode.METADATA_INDEX, self._metadata_indexes),
        ]
        rb = RecordBuilder()
        offsets = []
        for opcode, records in groups:
            if not records:
                continue
            begin = rb.count
            for r in records:
                r.write(rb)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + begin,
                                         group_length=rb.count - begin))
        offset_start = summary_start + rb.count
        for o in offsets:
            o.write(rb)
        summary: bytes = rb.end()  # type: ignore[no-untyped-call]
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), crc)
        self._write(summary)
        Footer(summary_start=summary_start, summary_offset_start=offset_start, summary_crc=crc).write(self._rb)
        self._emit()
        self._write(MAGIC)
        self.stream.flush()


def _sizes(payload: np.ndarray | Sequence[bytes]) -> np.ndarray:
    if isinstance(payload, np.ndarray):
        return np.full(len(payload), payload.shape[1], dtype=np.int64)
    return np.array([len(d) for d in payload], dtype=np.int64)


def _record(cid: int, seq: int, ns: int, data: bytes) -> bytes:
    return struct.pack("<BQHIQQ", Opcode.MESSAGE, 22 + len(data), cid, seq & 0xFFFFFFFF, ns, ns) + data


def _records(cid: int, seq0: int, ns: np.ndarray, payload: np.ndarray) -> np.ndarray:
    """Message records of one channel (fixed payload size) as a ``(k, 31 + size)`` array."""
    k, size = payload.shape
    rec = np.empty((k, _MESSAGE_HEAD + size), dtype=np.uint8)
    rec[:, 0] = Opcode.MESSAGE
    rec[:, 1:9].view("<u8")[:, 0] = 22 + size
    rec[:, 9:11].view("<u2")[:, 0] = cid
    rec[:, 11:15].view("<u4")[:, 0] = (seq0 + np.arange(k)) & 0xFFFFFFFF
    rec[:, 15:23].view("<i8")[:, 0] = ns
    rec[:, 23:31].view("<i8")[:, 0] = ns
    rec[:, 31:] = payload
    return rec
