"""Many small messages into one MCAP file, serialised in bulk.

mcap's ``Writer`` builds every message record in Python (~10 us each: 1.1 s for the 99k poses of
``paper --size 12``'s aligned.mcap). :func:`write_bulk` writes the same file — byte for byte what
``Writer(fh, compression=ZSTD, enable_data_crcs=True)`` writes for one schema, its channels
registered first, then the messages in the given order (``tests/test_io.py`` compares the bytes) —
with the message records and their indexes packed by numpy. Only the few per-chunk and summary
records go through mcap's record classes.
"""

from __future__ import annotations

import zlib
from typing import BinaryIO, Sequence

import numpy as np
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Schema, Statistics, SummaryOffset
from mcap.writer import MCAP0_MAGIC
from numpy.typing import NDArray

CHUNK_SIZE = 1024 * 1024  # mcap Writer's default: a chunk is closed after the record that passes it
# A message record's fixed part: opcode, record length, channel id, sequence, log and publish time.
_MESSAGE_HEAD = np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"), ("log", "<u8"), ("pub", "<u8")])


def write_bulk(
    fh: BinaryIO,
    schema: Schema,
    channels: Sequence[Channel],
    channel_ids: NDArray[np.integer],
    log_times: NDArray[np.integer],
    data: Sequence[bytes],
    *,
    library: str,
    chunk_size: int = CHUNK_SIZE,
) -> None:
    """Write the file: ``channels`` (ids 1..n, all of ``schema``), message k on channel
    ``channel_ids[k]`` at ``log_times[k]`` ns (log time = publish time, sequence 0), in this order."""
    out = _Out(fh)
    out.write(MCAP0_MAGIC)
    out.record(Header(profile="", library=library))
    prefix_builder = RecordBuilder()
    schema.write(prefix_builder)
    for c in channels:
        c.write(prefix_builder)
    prefix = prefix_builder.end()  # the first chunk opens with the schema and channels

    n = len(data)
    if n and (np.min(log_times) < 0 or np.max(channel_ids) > 0xFFFF or np.min(channel_ids) < 1):
        raise ValueError("MCAP messages need log times >= 0 and channel ids 1..65535")  # the Writer's struct packing
    ch = np.asarray(channel_ids, np.uint16)
    t = np.asarray(log_times, np.uint64)
    size = np.fromiter(map(len, data), np.int64, n)
    head = np.zeros(n, _MESSAGE_HEAD)
    head["op"], head["len"], head["ch"], head["log"], head["pub"] = int(Opcode.MESSAGE), 22 + size, ch, t, t
    head_bytes = head.tobytes()
    record_end = np.cumsum(_MESSAGE_HEAD.itemsize + size)  # bytes of messages 0..k

    chunk_indexes: list[ChunkIndex] = []
    start = 0
    while start < n:
        lead = len(prefix) if start == 0 else 0
        before = int(record_end[start - 1]) if start else 0
        # the first message after which the chunk holds more than chunk_size bytes closes it
        end = min(int(np.searchsorted(record_end, chunk_size - lead + before, side="right")), n - 1) + 1
        parts: list[bytes] = [prefix] if start == 0 else []
        w = _MESSAGE_HEAD.itemsize
        for k in range(start, end):
            parts.append(head_bytes[k * w : (k + 1) * w])
            parts.append(data[k])
        chunk_indexes.append(_write_chunk(out, b"".join(parts), ch[start:end], t[start:end],
                                          lead + record_end[start:end] - before - (w + size[start:end])))
        start = end

    out.record(DataEnd(data_section_crc=out.crc))
    summary_start = out.pos
    summary, offsets = RecordBuilder(), []

    def group(opcode: Opcode, records: Sequence[object]) -> None:
        begin = summary.count
        for r in records:
            r.write(summary)  # type: ignore[attr-defined]
        offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + begin,
                                     group_length=summary.count - begin))

    first = {int(c): None for c in ch.tolist()}  # channels in order of their first message
    counts = np.bincount(ch, minlength=len(channels) + 1) if n else np.zeros(len(channels) + 1, np.int64)
    stats = Statistics(
        message_count=n, schema_count=1, channel_count=len(channels), attachment_count=0, metadata_count=0,
        chunk_count=len(chunk_indexes), message_start_time=int(t.min()) if n else 0,
        message_end_time=int(t.max()) if n else 0, channel_message_counts={c: int(counts[c]) for c in first},
    )
    group(Opcode.SCHEMA, [schema])
    group(Opcode.CHANNEL, list(channels))
    group(Opcode.STATISTICS, [stats])
    group(Opcode.CHUNK_INDEX, chunk_indexes)
    group(Opcode.ATTACHMENT_INDEX, [])
    group(Opcode.METADATA_INDEX, [])
    summary_offset_start = summary_start + summary.count
    for o in offsets:
        o.write(summary)
    body = summary.end()
    footer_head = np.zeros(1, [("op", "u1"), ("len", "<u8"), ("s", "<u8"), ("o", "<u8")])
    footer_head[0] = (int(Opcode.FOOTER), 20, summary_start, summary_offset_start)
    summary_crc = zlib.crc32(footer_head.tobytes(), zlib.crc32(body))
    out.write(body)
    out.record(Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=summary_crc))
    out.fh.write(MCAP0_MAGIC)


def _write_chunk(out: "_Out", chunk_data: bytes, ch: NDArray, t: NDArray, offsets: NDArray) -> ChunkIndex:
    """One chunk record and its message indexes (as the Writer does when a chunk is finalised)."""
    compressed = zstandard.compress(chunk_data)
    chunk = Chunk(compression="zstd", data=compressed, message_start_time=int(t.min()), message_end_time=int(t.max()),
                  uncompressed_crc=zlib.crc32(chunk_data), uncompressed_size=len(chunk_data))
    chunk_start = out.pos
    out.record(chunk)
    index = ChunkIndex(
        message_start_time=chunk.message_start_time, message_end_time=chunk.message_end_time,
        chunk_start_offset=chunk_start, chunk_length=out.pos - chunk_start, message_index_offsets={},
        message_index_length=0, compression="zstd", compressed_size=len(compressed),
        uncompressed_size=len(chunk_data),
    )
    index_start = out.pos
    _, first = np.unique(ch, return_index=True)
    parts = []
    length = 0
    for c in ch[np.sort(first)].tolist():  # channels in order of their first message in the chunk
        mine = ch == c
        pairs = np.stack([t[mine], offsets[mine].astype(np.uint64)], axis=1).astype("<u8").tobytes()
        head = np.zeros(1, [("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("n", "<u4")])
        head[0] = (int(Opcode.MESSAGE_INDEX), 6 + len(pairs), c, len(pairs))
        index.message_index_offsets[int(c)] = index_start + length
        parts += [head.tobytes(), pairs]
        length += head.itemsize + len(pairs)
    out.write(b"".join(parts))
    index.message_index_length = length
    return index


class _Out:
    """The output stream, its position, and the data-section CRC over everything written."""

    def __init__(self, fh: BinaryIO) -> None:
        self.fh, self.pos, self.crc = fh, 0, 0

    def write(self, b: bytes) -> None:
        self.fh.write(b)
        self.pos += len(b)
        self.crc = zlib.crc32(b, self.crc)

    def record(self, r: object) -> None:
        rb = RecordBuilder()
        r.write(rb)  # type: ignore[attr-defined]
        self.write(rb.end())
