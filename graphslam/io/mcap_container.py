"""The MCAP container, read in one pass with every CRC the file carries checked.

Why not ``mcap.reader``: it builds a Python object per record through a byte-stream
class (about half of reading a survey), checks chunk CRCs only when asked and never the
data-section or summary CRC, and surfaces damage as ``ZstdError``, ``KeyError``,
``struct.error``, ``CRCValidationError`` (a ``ValueError``) or a record length limit.
Here the file is read into memory, records are cut with ``struct.unpack_from``, and
every problem is a ``DamagedMcap`` with the byte offset where it was found (the reader
turns it into ``InputError`` naming the file).

Format (https://mcap.dev/spec, version 0): magic, records (``opcode u8, length u64,
body``), magic. The data section ends with a DataEnd record (CRC-32 of everything
before it, 0 = not computed); the Footer (last record) holds the summary's offset and
CRC. Chunks hold Schema/Channel/Message records, compressed (``""``, ``zstd``, ``lz4``),
with the CRC-32 of their uncompressed bytes. Only the data section is decoded; the
summary (indexes, statistics) is only checked against its CRC.

What no CRC can catch: with ``data_section_crc == 0`` (the ``mcap`` writer's default;
``graphslam.io.mcap_writer`` turns it on) a changed byte *outside* chunks, e.g. in the
session metadata record, goes unnoticed.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from typing import Collection

MAGIC = b"\x89MCAP0\r\n"

OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_METADATA, OP_DATA_END = 0x0C, 0x0F

_RECORD = struct.Struct("<BQ")  # opcode, body length
_MESSAGE = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<QQQI")  # start time, end time, uncompressed size, uncompressed CRC
_FOOTER = struct.Struct("<QQI")  # summary start, summary offset start, summary CRC
_FOOTER_LEN = _RECORD.size + _FOOTER.size
# A chunk that claims more than this uncompressed is damaged, not big (real chunks: ~1 MB).
MAX_CHUNK_BYTES = 1 << 30
_PIECE = 1 << 22  # decompression output piece


class DamagedMcap(Exception):
    """The container is damaged or truncated; the message says what and at which byte."""


@dataclass(frozen=True)
class Channel:
    id: int
    topic: str
    message_encoding: str
    schema_id: int  # 0 = no schema


@dataclass(frozen=True)
class Schema:
    id: int
    name: str
    encoding: str


@dataclass
class TopicMessages:
    """One topic's messages in file order (across its channels)."""

    channels: list[Channel] = field(default_factory=list)
    log_times: list[int] = field(default_factory=list)
    data: list[bytes] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.data)


@dataclass
class McapContents:
    schemas: dict[int, Schema]
    channels: dict[int, Channel]
    metadata: dict[str, dict[str, str]]  # name -> key/value map (a name repeated: the last record)
    topics: dict[str, TopicMessages]  # only the topics asked for, only those with messages


class _Cursor:
    """Reads the fields of one record body; running past its end is damage, not an IndexError."""

    __slots__ = ("buf", "pos", "end", "what")

    def __init__(self, buf: bytes, start: int, end: int, what: str) -> None:
        self.buf, self.pos, self.end, self.what = buf, start, end, what

    def _take(self, n: int) -> int:
        p = self.pos
        if n < 0 or p + n > self.end:
            raise DamagedMcap(f"{self.what}: field runs past the end of the record")
        self.pos = p + n
        return p

    def u16(self) -> int:
        return _U16.unpack_from(self.buf, self._take(2))[0]

    def u32(self) -> int:
        return _U32.unpack_from(self.buf, self._take(4))[0]

    def u64(self) -> int:
        return _U64.unpack_from(self.buf, self._take(8))[0]

    def bytes_(self, n: int) -> bytes:
        p = self._take(n)
        return self.buf[p : p + n]

    def string(self) -> str:
        raw = self.bytes_(self.u32())
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise DamagedMcap(f"{self.what}: string is not UTF-8") from None

    def string_map(self) -> dict[str, str]:
        n = self.u32()
        start = self._take(n)
        sub = _Cursor(self.buf, start, start + n, self.what)
        out: dict[str, str] = {}
        while sub.pos < sub.end:
            k = sub.string()
            out[k] = sub.string()
        return out


def read_mcap(buf: bytes, topics: Collection[str]) -> McapContents:
    """Parse a whole MCAP file held in ``buf``; keep the messages of ``topics``.

    Raises ``DamagedMcap`` on bad magic, truncation, a record that does not parse, a CRC
    mismatch, an unknown compression, or a message on a channel never defined."""
    n = len(buf)
    if n < 2 * len(MAGIC) + _FOOTER_LEN or buf[: len(MAGIC)] != MAGIC:
        raise DamagedMcap("truncated or not MCAP (too short)" if buf[: len(MAGIC)] == MAGIC else "bad magic bytes")
    if buf[-len(MAGIC) :] != MAGIC:
        raise DamagedMcap("truncated: no MCAP magic at the end of the file")
    footer_at = n - len(MAGIC) - _FOOTER_LEN
    op, length = _RECORD.unpack_from(buf, footer_at)
    if op != OP_FOOTER or length != _FOOTER.size:
        raise DamagedMcap(f"truncated or damaged: no footer record at byte {footer_at}")
    summary_start, _, summary_crc = _FOOTER.unpack_from(buf, footer_at + _RECORD.size)

    state = _State(buf, topics)
    data_end = state.records(len(MAGIC), footer_at, top_level=True)
    if data_end is None:
        raise DamagedMcap("no DataEnd record before the footer")
    at, stored_crc = data_end
    if stored_crc and zlib.crc32(memoryview(buf)[:at]) != stored_crc:
        raise DamagedMcap("data section CRC mismatch")
    after_data = at + _RECORD.size + _RECORD.unpack_from(buf, at)[1]  # the end of the DataEnd record
    if summary_start and not after_data <= summary_start <= footer_at:
        raise DamagedMcap(f"footer: summary start {summary_start} outside the file's summary section")
    if summary_crc:
        summary = memoryview(buf)[summary_start or footer_at : footer_at]
        if zlib.crc32(buf[footer_at : footer_at + _RECORD.size + 16], zlib.crc32(summary)) != summary_crc:
            raise DamagedMcap("summary section CRC mismatch")
    return McapContents(state.schemas, state.channels, state.metadata, state.topics)


class _State:
    def __init__(self, buf: bytes, topics: Collection[str]) -> None:
        self.buf = buf
        self.wanted = frozenset(topics)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.topics: dict[str, TopicMessages] = {}
        # channel id -> its topic's lists (None: a topic not asked for); filled on first message
        self.sinks: dict[int, TopicMessages | None] = {}

    def records(self, pos: int, end: int, *, top_level: bool, buf: bytes | None = None) -> tuple[int, int] | None:
        """Walk records in ``buf[pos:end]``. Top level: stop at DataEnd, return (its offset, its CRC)."""
        buf = self.buf if buf is None else buf
        unpack_record, unpack_message = _RECORD.unpack_from, _MESSAGE.unpack_from
        sinks = self.sinks
        where = "" if top_level else " in a chunk"
        while pos < end:
            if pos + 9 > end:
                raise DamagedMcap(f"record header at byte {pos}{where} cut short")
            op, length = unpack_record(buf, pos)
            body = pos + 9
            stop = body + length
            if stop > end:
                raise DamagedMcap(f"record at byte {pos}{where} (opcode 0x{op:02x}, {length} bytes) runs past the end")
            if op == OP_MESSAGE:
                if length < _MESSAGE.size:
                    raise DamagedMcap(f"message record at byte {pos}{where} too short")
                cid, _seq, log_time, _pub = unpack_message(buf, body)
                sink = sinks.get(cid, False)
                if sink is False:
                    sink = self._sink(cid, pos, where)
                if sink is not None:
                    sink.log_times.append(log_time)
                    sink.data.append(buf[body + _MESSAGE.size : stop])
            elif op == OP_CHUNK:
                if not top_level:
                    raise DamagedMcap(f"chunk inside a chunk at byte {pos}")
                self._chunk(pos, body, stop)
            elif op == OP_SCHEMA:
                c = _Cursor(buf, body, stop, f"schema record at byte {pos}{where}")
                sid, name, enc = c.u16(), c.string(), c.string()
                c.bytes_(c.u32())
                self._define(self.schemas, Schema(sid, name, enc), pos)
            elif op == OP_CHANNEL:
                c = _Cursor(buf, body, stop, f"channel record at byte {pos}{where}")
                cid, sid = c.u16(), c.u16()
                topic, enc = c.string(), c.string()
                c.string_map()
                self._define(self.channels, Channel(cid, topic, enc, sid), pos)
            elif not top_level:
                raise DamagedMcap(f"record of opcode 0x{op:02x} inside a chunk at byte {pos}")
            elif op == OP_METADATA:
                c = _Cursor(buf, body, stop, f"metadata record at byte {pos}")
                name = c.string()
                self.metadata[name] = c.string_map()
            elif op == OP_DATA_END:
                if length < 4:
                    raise DamagedMcap(f"DataEnd record at byte {pos} too short")
                return pos, _U32.unpack_from(buf, body)[0]
            elif op == OP_FOOTER:
                raise DamagedMcap(f"footer record at byte {pos} before the end of the file")
            # Header, message/chunk indexes, attachments, private records: nothing to read.
            pos = stop
        return None

    def _define(self, table: dict, rec: Schema | Channel, pos: int) -> None:
        old = table.setdefault(rec.id, rec)
        if old != rec:
            raise DamagedMcap(f"record at byte {pos} redefines {type(rec).__name__.lower()} id {rec.id} differently")

    def _sink(self, cid: int, pos: int, where: str) -> TopicMessages | None:
        ch = self.channels.get(cid)
        if ch is None:
            raise DamagedMcap(f"message at byte {pos}{where} on channel {cid}, which is not defined before it")
        sink = None
        if ch.topic in self.wanted:
            sink = self.topics.setdefault(ch.topic, TopicMessages())
            sink.channels.append(ch)
        self.sinks[cid] = sink
        return sink

    def _chunk(self, pos: int, body: int, stop: int) -> None:
        c = _Cursor(self.buf, body, stop, f"chunk at byte {pos}")
        _, _, size, crc = _CHUNK_HEAD.unpack_from(self.buf, c._take(_CHUNK_HEAD.size))
        compression = c.string()
        packed = c.bytes_(c.u64())
        if size > MAX_CHUNK_BYTES:
            raise DamagedMcap(f"chunk at byte {pos} claims {size} bytes uncompressed")
        data = _decompress(compression, packed, size, pos)
        if len(data) != size:
            raise DamagedMcap(f"chunk at byte {pos}: {len(data)} bytes uncompressed, the record says {size}")
        if crc and zlib.crc32(data) != crc:
            raise DamagedMcap(f"chunk at byte {pos}: CRC mismatch")
        self.records(0, len(data), top_level=False, buf=data)


def _decompress(compression: str, packed: bytes, size: int, pos: int) -> bytes:
    """At most ``size + 1`` bytes, produced in pieces: a damaged size field cannot make us
    allocate more than the data really holds (plus one piece)."""
    if compression == "":
        return packed
    if compression == "zstd":
        import zstandard

        errors: tuple[type[BaseException], ...] = (zstandard.ZstdError,)
        reader = zstandard.ZstdDecompressor().stream_reader(packed)

        def piece(n: int) -> bytes:
            return reader.read(n)

    elif compression == "lz4":
        import lz4.frame

        errors = (RuntimeError,)  # lz4 reports a damaged frame as RuntimeError
        dec = lz4.frame.LZ4FrameDecompressor()
        pending = [packed]

        def piece(n: int) -> bytes:
            if dec.eof:
                return b""
            return dec.decompress(pending.pop() if pending else b"", max_length=n)

    else:
        raise DamagedMcap(f"chunk at byte {pos}: unknown compression {compression!r}")
    parts: list[bytes] = []
    got = 0
    try:
        while got <= size:
            part = piece(min(_PIECE, size + 1 - got))
            if not part:
                break
            parts.append(part)
            got += len(part)
    except errors as e:
        raise DamagedMcap(f"chunk at byte {pos}: cannot decompress {compression} ({type(e).__name__}: {e})") from None
    return b"".join(parts)
