"""Read rosbag2/MCAP bags, including damaged ones, without ROS (used by replay, play and the tests).

A bag is a rosbag2 directory (``metadata.yaml`` + one or more ``.mcap`` files) or a single ``.mcap``
file. Messages are streamed in file order by a strict MCAP walker of this module, which needs neither the
summary at the end of the file nor ``metadata.yaml``; so:

* a recording cut by power loss (no footer, the last chunk half written) yields every message up to
  the cut, and :attr:`ReadReport.truncated` says where and why it stopped;
* a **corrupt** file (bit rot, a wrong length, a damaged chunk or index) yields every message *before* the
  first damaged record and none from it on (a record after a damaged one cannot be trusted: its framing
  may be off), and :attr:`ReadReport.corrupt` says where and what. Damage is found by the CRCs of the MCAP
  format (chunk, data section, summary), validated whenever they are non-zero (0 means "not computed" in
  the MCAP spec, as in bags of other writers, and is accepted), by decompression, and by records whose
  framing does not add up (lengths, sizes, opcodes out of place). A chunk is checked whole before any of
  its messages is given out. Cut or corrupt? A file that ends with a valid footer was closed, so anything
  that does not fit in it is corruption; a file without one ends inside a record because it was cut;
* a directory without ``metadata.yaml``, or with one that cannot be parsed, is read from its ``.mcap``
  files (topics, types and QoS come from the MCAP channels), with a note in the report (``metadata.yaml``
  only repeats what the MCAP files hold, so nothing is lost);
* messages are decoded with the ``rosbags`` Jazzy type store; types it does not know are registered
  from the schema stored in the bag; topics of a type that cannot be decoded are listed, not fatal.

Every problem raises :class:`BagError` with a one-line message (never a library traceback) or, where
reading can go on, is recorded in :class:`ReadReport`.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import yaml

METADATA = 'metadata.yaml'
MAGIC = b'\x89MCAP0\r\n'
_FOOTER_SIZE = 1 + 8 + 8 + 8 + 4           # opcode, record length, summary start, summary offset start, CRC
_DATA_END_SIZE = 1 + 8 + 4                 # opcode, record length, data section CRC
_MAX_CHUNK = 4 << 30                       # uncompressed chunk size beyond which we do not even try (mcap's limit)

# MCAP opcodes (https://mcap.dev/spec)
(HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX, CHUNK_INDEX, ATTACHMENT, ATTACHMENT_INDEX,
 STATISTICS, METADATA_RECORD, METADATA_INDEX, SUMMARY_OFFSET, DATA_END) = range(1, 16)
_NAMES = {0: 'invalid (opcode 0x00)', HEADER: 'header', FOOTER: 'footer', SCHEMA: 'schema', CHANNEL: 'channel',
          MESSAGE: 'message', CHUNK: 'chunk', MESSAGE_INDEX: 'message index', CHUNK_INDEX: 'chunk index',
          ATTACHMENT: 'attachment', ATTACHMENT_INDEX: 'attachment index', STATISTICS: 'statistics',
          METADATA_RECORD: 'metadata', METADATA_INDEX: 'metadata index', SUMMARY_OFFSET: 'summary offset',
          DATA_END: 'data end'}
_SKIPPED_IN_DATA = {MESSAGE_INDEX, ATTACHMENT, METADATA_RECORD}     # covered by the data section CRC only
_SUMMARY_OPS = {SCHEMA, CHANNEL, CHUNK_INDEX, ATTACHMENT_INDEX, STATISTICS, METADATA_INDEX, SUMMARY_OFFSET}


def _name(op: int) -> str:
    return _NAMES.get(op, f'unknown (opcode {op:#04x})')


class BagError(Exception):
    """A bag that cannot be read at all (the message says why, in one line)."""


class DecodeError(Exception):
    """One message that cannot be decoded (unknown type, malformed CDR)."""


@dataclass
class Topic:
    name: str
    msgtype: str                                   # e.g. 'sensor_msgs/msg/Image'
    count: int | None = None                       # from metadata.yaml or the MCAP statistics; None = unknown
    qos: list[dict] = field(default_factory=list)  # offered QoS profiles, rosbag2 keys; [] = unknown
    type_hash: str = ''                            # RIHS01 hash when the bag records it
    serialization: str = 'cdr'


@dataclass
class BagMessage:
    topic: str
    msgtype: str
    log_time_ns: int       # when the recorder received it (rosbag2's timestamp)
    data: bytes            # serialised CDR, as published


@dataclass
class ReadReport:
    """What reading the bag found; filled while :meth:`Bag.messages` runs."""

    files: list[Path] = field(default_factory=list)
    has_metadata: bool = False
    truncated: str = ''                  # '' = every file read to its end; else where and why reading stopped
    corrupt: str = ''                    # '' = no damage found; else where and what (the first damage found)
    messages: int = 0
    per_topic: Counter = field(default_factory=Counter)
    notes: list[str] = field(default_factory=list)
    expected: int | None = None          # message count the metadata lists, when it does

    def corrupt_line(self) -> str:
        """One line about the damage ('' = none): what, where, and how much was read."""
        if not self.corrupt:
            return ''
        if self.truncated:       # reading stopped at the damage
            return f'corrupt: {self.corrupt}; reading stopped there, {self.messages} messages read before it'
        return f'corrupt: {self.corrupt}; {self.messages} messages read (none from a record that failed its checks)'

    def lines(self) -> list[str]:
        out = list(self.notes)
        if self.corrupt:
            out.append(self.corrupt_line())
        elif self.truncated:
            out.append(f'truncated: {self.truncated}; {self.messages} messages read before that')
        if self.expected is not None and self.messages < self.expected and not (self.truncated or self.corrupt):
            out.append(f'{self.expected - self.messages} of {self.expected} messages listed in the metadata '
                       f'were not read')
        return out


def _qos_list(raw: Any) -> list[dict]:
    """Offered QoS profiles as a list of dicts (rosbag2 stores a YAML string before version 9)."""
    if isinstance(raw, str):
        try:
            raw = yaml.safe_load(raw) if raw.strip() else []
        except yaml.YAMLError:
            return []
    return [q for q in raw if isinstance(q, dict)] if isinstance(raw, list) else []


# -------------------------------------------------------------------------------------------- MCAP records
@dataclass
class _Schema:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass
class _Channel:
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


class _MalformedError(Exception):
    """A record whose content does not add up (the message says what; the caller adds where)."""


class _DamagedError(Exception):
    """Reading a file must stop at byte ``offset``: ``kind`` is 'truncated' (cut) or 'corrupt'."""

    def __init__(self, kind: str, offset: int, text: str) -> None:
        super().__init__(text)
        self.kind, self.offset, self.text = kind, offset, text


class _Buf:
    """Strict little-endian reader of one record: reading past its end raises :class:`_MalformedError`."""

    def __init__(self, data: bytes | memoryview) -> None:
        self.data = memoryview(data)
        self.pos = 0

    @property
    def left(self) -> int:
        return len(self.data) - self.pos

    def take(self, n: int) -> memoryview:
        if n > self.left:
            raise _MalformedError(f'a field of {n} bytes runs past the end of the record ({self.left} bytes left)')
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def _int(self, fmt: str, n: int) -> int:
        return struct.unpack(fmt, self.take(n))[0]

    def u8(self) -> int:
        return self._int('<B', 1)

    def u16(self) -> int:
        return self._int('<H', 2)

    def u32(self) -> int:
        return self._int('<I', 4)

    def u64(self) -> int:
        return self._int('<Q', 8)

    def string(self) -> str:
        try:
            return str(self.take(self.u32()), 'utf-8')
        except UnicodeDecodeError:
            raise _MalformedError('a string is not UTF-8') from None

    def blob(self) -> bytes:
        return bytes(self.take(self.u32()))

    def string_map(self) -> dict[str, str]:
        inner = _Buf(self.take(self.u32()))
        out = {}
        while inner.left:
            key = inner.string()
            out[key] = inner.string()
        return out


def _schema(b: _Buf) -> _Schema:
    return _Schema(b.u16(), b.string(), b.string(), b.blob())


def _channel(b: _Buf) -> _Channel:
    return _Channel(b.u16(), b.u16(), b.string(), b.string(), b.string_map())


def _message(b: _Buf) -> tuple[int, int, bytes]:
    """(channel id, log time, data)."""
    channel_id, _sequence, log_time, _publish_time = b.u16(), b.u32(), b.u64(), b.u64()
    return channel_id, log_time, bytes(b.take(b.left))


def _decompress(compression: str, data: memoryview, size: int) -> bytes:
    if size > _MAX_CHUNK:
        raise _MalformedError(f'uncompressed size of {size} bytes is not plausible')
    if compression == '':
        return bytes(data)
    if compression == 'zstd':
        import zstandard
        try:
            declared = zstandard.get_frame_parameters(data).content_size
            if declared not in (size, zstandard.CONTENTSIZE_UNKNOWN):
                raise _MalformedError(f'zstd frame holds {declared} bytes, the chunk says {size}')
            return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        except zstandard.ZstdError as e:
            raise _MalformedError(f'zstd data cannot be decompressed ({e})') from None
    if compression == 'lz4':
        import lz4.frame
        try:
            return lz4.frame.decompress(bytes(data))
        except Exception as e:  # lz4 raises RuntimeError and others on damaged frames
            raise _MalformedError(f'lz4 data cannot be decompressed ({type(e).__name__}: {e})') from None
    raise _MalformedError(f'unknown compression {compression!r}')


def _chunk_records(body: bytes) -> list[_Schema | _Channel | tuple[int, int, bytes]]:
    """Every record of a chunk, checked whole (sizes, CRC when non-zero, framing) before any is used."""
    b = _Buf(body)
    b.u64(), b.u64()                     # message start and end time
    size, crc, compression, compressed_size = b.u64(), b.u32(), b.string(), b.u64()
    if compressed_size != b.left:
        raise _MalformedError(f'compressed size {compressed_size} does not match the record ({b.left} bytes left)')
    data = _decompress(compression, b.take(compressed_size), size)
    if len(data) != size:
        raise _MalformedError(f'decompressed to {len(data)} bytes, the chunk says {size}')
    if crc and (actual := zlib.crc32(data)) != crc:
        raise _MalformedError(f'CRC mismatch (stored {crc:#010x}, computed {actual:#010x})')
    inner = _Buf(data)
    out: list[_Schema | _Channel | tuple[int, int, bytes]] = []
    while inner.left:
        op, length = inner.u8(), inner.u64()
        rec = _Buf(inner.take(length))
        if op == MESSAGE:
            out.append(_message(rec))
        elif op == CHANNEL:
            out.append(_channel(rec))
        elif op == SCHEMA:
            out.append(_schema(rec))
        else:
            raise _MalformedError(f'{_name(op)} record inside the chunk')
    return out


def _check_skipped(op: int, body: bytes) -> None:
    """Framing (and, for an attachment, the CRC) of a data record whose content is not used: a bit flipped in
    the opcode of a chunk must not make the chunk pass for one of these and vanish."""
    b = _Buf(body)
    if op == MESSAGE_INDEX:
        b.u16()
        n = b.u32()
        if n % 16 or n != b.left:
            raise _MalformedError(f'{n} bytes of index entries in a record with {b.left} left')
    elif op == METADATA_RECORD:
        b.string()
        b.string_map()
    elif op == ATTACHMENT:
        b.u64(), b.u64(), b.string(), b.string()
        b.take(b.u64())
        end = b.pos
        crc = b.u32()
        if crc and (actual := zlib.crc32(body[:end])) != crc:
            raise _MalformedError(f'CRC mismatch (stored {crc:#010x}, computed {actual:#010x})')


def _footer(fh: BinaryIO, size: int) -> tuple[int, int] | None:
    """(summary start, summary CRC) when the file ends with a valid footer and magic (= it was closed), else None."""
    if size < 2 * len(MAGIC) + _FOOTER_SIZE:
        return None
    fh.seek(size - len(MAGIC) - _FOOTER_SIZE)
    tail = fh.read(_FOOTER_SIZE + len(MAGIC))
    op, length, summary_start, _offsets, crc = struct.unpack('<BQQQI', tail[:_FOOTER_SIZE])
    if op != FOOTER or length != _FOOTER_SIZE - 9 or tail[_FOOTER_SIZE:] != MAGIC:
        return None
    return summary_start, crc


def _records(fh: BinaryIO, size: int, closed: bool) -> Iterator[tuple[int, int, bytes, bytes]]:
    """(offset, opcode, 9-byte head, body) of each record after the magic; :class:`_DamagedError` at the end of the
    file (it must end at the footer, which the caller stops at)."""
    pos = fh.seek(len(MAGIC))
    while True:
        head = fh.read(9)
        if len(head) < 9:
            if closed:
                raise _DamagedError('corrupt', pos, 'the file ends before its footer (a record length is wrong)')
            raise _DamagedError('truncated', pos, 'the file ends ' + ('inside a record header' if head else
                                                                 'without footer (recording cut?)'))
        op, length = struct.unpack('<BQ', head)
        if op == FOOTER and length != _FOOTER_SIZE - 9:     # fixed: readers find the footer by its size
            raise _DamagedError('corrupt', pos, f'footer record of {length} bytes ({_FOOTER_SIZE - 9} expected)')
        if length > size - pos - 9:
            if closed:
                raise _DamagedError('corrupt', pos, f'{_name(op)} record of {length} bytes runs past the end of '
                                                    f'the file')
            raise _DamagedError('truncated', pos, f'the file ends inside a {_name(op)} record (recording cut?)')
        body = fh.read(length)
        if len(body) != length:
            raise _DamagedError('truncated', pos, 'the file got shorter while it was read')
        yield pos, op, head, body
        pos += 9 + length


class _BadMetadataError(Exception):
    """metadata.yaml does not have the structure rosbag2 writes (the message says what)."""


class Bag:
    """One bag; iterate :meth:`messages` (any number of times) and :meth:`decode` what you need."""

    def __init__(self, path: str | Path) -> None:
        path = Path(path)
        if not path.exists():
            raise BagError(f'{path}: no such bag (expected a rosbag2 directory or an .mcap file)')
        self.path = path
        self.topics: dict[str, Topic] = {}
        self.start_ns: int | None = None
        self.end_ns: int | None = None
        self.custom_data: dict[str, str] = {}
        self.report = ReadReport()
        self._schemas: dict[str, tuple[str, bytes]] = {}   # msgtype -> (encoding, text) found in the bag
        self._typestore = None
        self._undecodable: dict[str, str] = {}
        self._closed: dict[Path, bool] = {}                 # file -> ends with a valid footer
        self._data_end: dict[Path, int] = {}                # file -> where its DataEnd record should be
        self._corrupt_summary = ''                          # damage found when opening (summary section)
        if path.is_file():
            if path.suffix != '.mcap':
                raise BagError(f'{path}: not an .mcap file (sqlite3 .db3 bags are not supported: convert them '
                               f'with `ros2 bag convert` to the mcap storage)')
            self.dir = path.parent
            self.files = [path]
            self.report.notes.append(f'reading {path.name} directly, without metadata.yaml')
        else:
            self.dir = path
            self.files = self._files_from_metadata() if (path / METADATA).exists() else self._files_without_metadata()
        self.report.files = list(self.files)
        for f in self.files:
            self._summary(f)
        self.report.corrupt = self._corrupt_summary

    # ---------------------------------------------------------------------------------------- opening
    def _files_from_metadata(self) -> list[Path]:
        try:
            info = self._metadata()
        except _BadMetadataError as e:
            self.report.notes.append(f'{METADATA} unreadable ({e}): reading the .mcap files directly')
            self.topics.clear()
            self.custom_data.clear()
            return self._files_without_metadata()
        self.report.has_metadata = True
        files = []
        for rel in info['relative_file_paths']:
            f = self.dir / rel
            if not f.exists():
                raise BagError(f'{self.dir}: {METADATA} lists {rel}, which is missing')
            if f.suffix != '.mcap':
                raise BagError(f'{self.dir}: {rel} is not an .mcap file')
            files.append(f)
        return files

    def _metadata(self) -> dict:
        """The rosbag2_bagfile_information block, checked for the structure used here; fills topics and
        custom data. :class:`BagError` for what this reader cannot read, :class:`_BadMetadataError` when malformed."""
        try:
            info = yaml.safe_load((self.dir / METADATA).read_text())['rosbag2_bagfile_information']
        except (yaml.YAMLError, OSError, KeyError, TypeError, UnicodeDecodeError, ValueError) as e:
            raise _BadMetadataError(type(e).__name__) from None
        if not isinstance(info, dict):
            raise _BadMetadataError('rosbag2_bagfile_information is not a mapping')
        storage = str(info.get('storage_identifier', 'mcap'))
        if storage != 'mcap':
            raise BagError(f'{self.dir}: storage {storage!r} is not supported (only mcap; convert with '
                           f'`ros2 bag convert`)')
        mode = str(info.get('compression_mode', '') or '').lower()
        if mode not in ('', 'none'):
            raise BagError(f'{self.dir}: rosbag2 {mode}-level compression is not supported (record with '
                           f'MCAP chunk compression instead, as `fixego record` does)')
        paths = info.get('relative_file_paths')
        if not isinstance(paths, list) or not paths or not all(isinstance(p, str) and p for p in paths):
            raise _BadMetadataError('relative_file_paths is not a list of file names')
        custom = info.get('custom_data') or {}
        if not isinstance(custom, dict):
            raise _BadMetadataError('custom_data is not a mapping')
        count = info.get('message_count')
        if count is not None and (isinstance(count, bool) or not isinstance(count, int) or count < 0):
            raise _BadMetadataError(f'message_count {count!r} is not a count')
        entries = info.get('topics_with_message_count') or []
        if not isinstance(entries, list):
            raise _BadMetadataError('topics_with_message_count is not a list')
        for item in entries:
            try:
                tm = item['topic_metadata']
                name, msgtype = tm['name'], tm['type']
                if not (isinstance(name, str) and isinstance(msgtype, str)):
                    raise TypeError
                self.topics[name] = Topic(name, msgtype, int(item.get('message_count', 0)),
                                          _qos_list(tm.get('offered_qos_profiles', [])),
                                          str(tm.get('type_description_hash', '') or ''),
                                          str(tm.get('serialization_format', 'cdr')))
            except (KeyError, TypeError, ValueError, AttributeError):
                self.report.notes.append(f'{METADATA}: a malformed topic entry was ignored')
        self.report.expected = count
        self.custom_data = {str(k): str(v) for k, v in custom.items()}
        return info

    def _files_without_metadata(self) -> list[Path]:
        files = sorted(self.dir.glob('*.mcap'))
        if not files:
            extra = ' (sqlite3 .db3 bags are not supported)' if any(self.dir.glob('*.db3')) else ''
            raise BagError(f'{self.dir}: not a bag: no {METADATA} and no .mcap file{extra}')
        self.report.notes.append(f'no {METADATA}: reading {", ".join(f.name for f in files)} directly '
                                 f'(topics and QoS from the MCAP channels)')
        return files

    def _summary(self, f: Path) -> None:
        """Topics, counts and time range from the MCAP summary when the file has one (it does not when cut);
        a summary whose CRC fails, or that does not parse in a closed file, is corruption, and is not used."""
        try:
            with f.open('rb') as fh:
                if fh.read(len(MAGIC)) != MAGIC:
                    raise BagError(f'{f}: not an MCAP file (bad magic bytes)')
                size = os.fstat(fh.fileno()).st_size
                footer = _footer(fh, size)
                self._closed[f] = footer is not None
                if footer is None:
                    self.report.notes.append(f'{f.name} has no summary (recording not closed cleanly?): topics are '
                                             f'discovered while reading')
                    return
                start, crc = footer
                footer_at = size - len(MAGIC) - _FOOTER_SIZE
                if start == 0:
                    self.report.notes.append(f'{f.name} has no summary section: topics are discovered while reading')
                    return
                if not len(MAGIC) < start <= footer_at:
                    return self._bad_summary(f, f'the footer puts the summary at byte {start}, outside the file')
                self._data_end[f] = start - _DATA_END_SIZE       # DataEnd closes the data section
                fh.seek(start)
                data = fh.read(footer_at - start)
                head = fh.read(_FOOTER_SIZE - 4)
        except OSError as e:
            raise BagError(f'{f}: cannot read ({e.strerror or e})') from None
        if crc and (actual := zlib.crc32(head, zlib.crc32(data))) != crc:
            return self._bad_summary(f, f'summary section at byte {start}: CRC mismatch (stored {crc:#010x}, '
                                        f'computed {actual:#010x})')
        schemas: dict[int, _Schema] = {}
        channels: list[_Channel] = []
        counts: dict[int, int] = {}
        span: tuple[int, int] | None = None
        b = _Buf(data)
        try:
            while b.left:
                op, length = b.u8(), b.u64()
                rec = _Buf(b.take(length))
                if op == SCHEMA:
                    s = _schema(rec)
                    schemas[s.id] = s
                elif op == CHANNEL:
                    channels.append(_channel(rec))
                elif op == STATISTICS:
                    n = rec.u64()
                    rec.u16(), rec.u32(), rec.u32(), rec.u32(), rec.u32()
                    lo, hi = rec.u64(), rec.u64()
                    pairs = _Buf(rec.take(rec.u32()))
                    while pairs.left:
                        cid = pairs.u16()
                        counts[cid] = pairs.u64()
                    span = (lo, hi) if n else None
                elif op not in _SUMMARY_OPS:
                    raise _MalformedError(f'{_name(op)} record')
        except _MalformedError as e:
            return self._bad_summary(f, f'summary section at byte {start} malformed: {e}')
        for ch in channels:
            self._add_channel(ch, schemas.get(ch.schema_id), counts.get(ch.id))
        if span is not None:
            lo, hi = span
            self.start_ns = lo if self.start_ns is None else min(self.start_ns, lo)
            self.end_ns = hi if self.end_ns is None else max(self.end_ns, hi)

    def _bad_summary(self, f: Path, text: str) -> None:
        self._corrupt_summary = self._corrupt_summary or f'{f.name}: {text}'
        self.report.notes.append(f'{f.name}: summary not used (damaged): topics are discovered while reading')

    def _add_channel(self, ch: _Channel, schema: _Schema | None, count: int | None = None) -> None:
        msgtype = schema.name if schema is not None else ''
        if schema is not None and schema.data:
            self._schemas.setdefault(msgtype, (schema.encoding, bytes(schema.data)))
        known = self.topics.get(ch.topic)
        if known is None:
            qos = _qos_list(ch.metadata.get('offered_qos_profiles', ''))
            self.topics[ch.topic] = Topic(ch.topic, msgtype, count, qos, ch.metadata.get('type_description_hash', ''),
                                          ch.message_encoding)
        elif not self.report.has_metadata and count is not None:
            known.count = (known.count or 0) + count

    @property
    def duration_s(self) -> float | None:
        if self.start_ns is None or self.end_ns is None:
            return None
        return (self.end_ns - self.start_ns) * 1e-9

    # ---------------------------------------------------------------------------------------- reading
    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Messages in file order (which is recording order); stops cleanly at a cut or at the first corrupt
        record (module docstring), saying where in :attr:`report`."""
        wanted = None if topics is None else set(topics)
        rep = self.report
        rep.messages, rep.per_topic, rep.truncated, rep.corrupt = 0, Counter(), '', self._corrupt_summary
        for f in self.files:
            try:
                yield from self._file_messages(f, wanted)
            except _DamagedError as d:
                rep.truncated = f'{f.name} at byte {d.offset}: {d.text}'
                if d.kind == 'corrupt':
                    rep.corrupt = rep.corrupt or rep.truncated
                return

    def _corrupt(self, text: str) -> None:
        """Damage that does not stop reading (everything before it has been read already)."""
        self.report.corrupt = self.report.corrupt or text

    def _file_messages(self, f: Path, wanted: set[str] | None) -> Iterator[BagMessage]:
        schemas: dict[int, _Schema] = {}
        channels: dict[int, tuple[str, str]] = {}
        closed = self._closed.get(f, False)
        unknown_ops: set[int] = set()
        try:
            fh = f.open('rb')
        except OSError as e:
            raise _DamagedError('corrupt', 0, f'cannot be opened ({e.strerror or e})') from None
        with fh:
            size = os.fstat(fh.fileno()).st_size
            crc = zlib.crc32(MAGIC)
            in_data = True
            try:
                strict = self._data_crc_fails(f, fh)
                for pos, op, head, body in _records(fh, size, closed):
                    if not in_data:                  # summary section: framing only (its CRC was checked on open)
                        if op == FOOTER:
                            tail = fh.read(len(MAGIC) + 1)
                            if tail[:len(MAGIC)] != MAGIC:
                                kind = 'truncated' if not closed and MAGIC.startswith(tail) else 'corrupt'
                                raise _DamagedError(kind, pos + 9 + len(body), 'no MCAP magic after the footer')
                            if len(tail) > len(MAGIC):
                                self._corrupt(f'{f.name}: bytes after the closing MCAP magic')
                            return
                        if op not in _SUMMARY_OPS and op in _NAMES:
                            raise _DamagedError('corrupt', pos, f'{_name(op)} record in the summary section')
                        continue
                    before = crc
                    crc = zlib.crc32(body, zlib.crc32(head, crc))
                    try:
                        items = self._data_record(f, pos, op, body, before, unknown_ops, strict)
                    except _MalformedError as e:
                        raise _DamagedError('corrupt', pos, f'{_name(op)} record: {e}') from None
                    if items is None:                # DataEnd: the summary section follows
                        in_data = False
                        continue
                    for item in items:
                        if isinstance(item, _Schema):
                            schemas[item.id] = item
                        elif isinstance(item, _Channel):
                            schema = schemas.get(item.schema_id)
                            self._add_channel(item, schema)
                            channels[item.id] = (item.topic, schema.name if schema is not None else '')
                        else:
                            msg = self._message(channels, item, wanted)
                            if msg is not None:
                                yield msg
            except OSError as e:
                raise _DamagedError('corrupt', fh.tell(), f'read error ({e.strerror or e})') from None

    def _data_crc_fails(self, f: Path, fh: BinaryIO) -> bool:
        """Whether the file has a data section CRC and it fails, checked before any message is given out.

        The walker skips records of unknown type (MCAP: later versions, private records), so a bit flipped in a
        chunk's opcode would make the chunk vanish and reading go on after a silent gap; when the CRC says the
        data section is damaged, an unknown record is taken for what it then most likely is: damage."""
        at = self._data_end.get(f)
        if at is None:
            return False
        fh.seek(at)
        rec = fh.read(_DATA_END_SIZE)
        if len(rec) != _DATA_END_SIZE:
            return False
        op, length, stored = struct.unpack('<BQI', rec)
        if op != DATA_END or length != 4 or not stored:
            return False
        fh.seek(0)
        crc, left = 0, at
        while left > 0:
            block = fh.read(min(left, 1 << 20))
            if not block:
                return True
            crc = zlib.crc32(block, crc)
            left -= len(block)
        return crc != stored

    def _data_record(self, f: Path, pos: int, op: int, body: bytes, crc_before: int,
                     unknown_ops: set[int], strict: bool) -> list | None:
        """What one data-section record holds (schemas, channels, messages); None at DataEnd. ``strict``: the
        data section CRC fails, so a record of unknown type is damage, not skipped (:meth:`_data_crc_fails`)."""
        if pos == len(MAGIC) and op != HEADER:
            raise _MalformedError('the file does not start with a header record')
        if op in (MESSAGE, CHUNK):
            return [_message(_Buf(body))] if op == MESSAGE else _chunk_records(body)
        if op == SCHEMA:
            return [_schema(_Buf(body))]
        if op == CHANNEL:
            return [_channel(_Buf(body))]
        if op == DATA_END:
            stored = _Buf(body).u32()
            if stored and stored != crc_before:
                self._corrupt(f'{f.name}: data section CRC mismatch (stored {stored:#010x}, computed '
                              f'{crc_before:#010x}): a record without a check of its own (an index, or one '
                              f'skipped as unknown) is damaged')
            return None
        if op in _SKIPPED_IN_DATA:
            _check_skipped(op, body)
            return []
        if op == HEADER and pos == len(MAGIC):
            return []
        if op in _NAMES:
            raise _MalformedError('out of place in the data section')
        if strict:
            raise _MalformedError('unknown record type, and the data section CRC fails')
        if op not in unknown_ops:            # a record type of a later MCAP version or a private one: skipped
            unknown_ops.add(op)
            self.report.notes.append(f'{f.name}: records of unknown opcode {op:#04x} skipped (first at byte {pos})')
        return []

    def _message(self, channels: dict[int, tuple[str, str]], item: tuple[int, int, bytes],
                 wanted: set[str] | None) -> BagMessage | None:
        cid, t, data = item
        topic, msgtype = channels.get(cid, ('', ''))
        if not topic:
            return None
        self.report.messages += 1
        self.report.per_topic[topic] += 1
        self.start_ns = t if self.start_ns is None else min(self.start_ns, t)
        self.end_ns = t if self.end_ns is None else max(self.end_ns, t)
        if wanted is None or topic in wanted:
            return BagMessage(topic, msgtype, t, data)
        return None

    # ---------------------------------------------------------------------------------------- decoding
    def decode(self, msg: BagMessage) -> Any:
        """The message as a ``rosbags`` message object; :class:`DecodeError` when that is impossible."""
        store = self._store()
        if msg.msgtype in self._undecodable:
            raise DecodeError(self._undecodable[msg.msgtype])
        if msg.msgtype not in store.fielddefs:
            self._register(msg.msgtype)
        try:
            return store.deserialize_cdr(msg.data, msg.msgtype)
        except Exception as e:  # rosbags raises assorted errors on malformed CDR
            raise DecodeError(f'{msg.topic}: malformed {msg.msgtype} message ({type(e).__name__})') from None

    def _store(self):
        if self._typestore is None:
            from rosbags.typesys import Stores, get_typestore
            self._typestore = get_typestore(Stores.ROS2_JAZZY)
        return self._typestore

    def _register(self, msgtype: str) -> None:
        from rosbags.typesys import get_types_from_idl, get_types_from_msg
        enc, text = self._schemas.get(msgtype, ('', b''))
        try:
            if enc == 'ros2msg' and text:
                types = get_types_from_msg(text.decode(), msgtype)
                # a ros2msg schema carries its dependencies after '=====' separators with 'MSG: ' headers
                for block in text.decode().split('=' * 80)[1:]:
                    head, _, body = block.strip().partition('\n')
                    if head.startswith('MSG: '):
                        name = head[5:].strip()
                        name = name if '/msg/' in name else name.replace('/', '/msg/')
                        types.update(get_types_from_msg(body, name))
            elif enc == 'ros2idl' and text:
                types = get_types_from_idl(text.decode())
            else:
                raise DecodeError(f'{msgtype}: unknown message type and the bag has no schema for it')
            self._store().register({k: v for k, v in types.items() if k not in self._store().fielddefs})
        except DecodeError as e:
            self._undecodable[msgtype] = str(e)
            raise
        except Exception as e:  # the schema text comes from an arbitrary file
            self._undecodable[msgtype] = f'{msgtype}: schema in the bag cannot be parsed ({type(e).__name__})'
            raise DecodeError(self._undecodable[msgtype]) from None
        if msgtype not in self._store().fielddefs:
            self._undecodable[msgtype] = f'{msgtype}: the schema in the bag does not define it'
            raise DecodeError(self._undecodable[msgtype])
