"""Read rosbag2/MCAP bags, including damaged ones, without ROS (used by replay, play and the tests).

A bag is a rosbag2 directory (``metadata.yaml`` + one or more ``.mcap`` files) or a single ``.mcap``
file. Messages are streamed in file order with ``mcap``'s :class:`~mcap.stream_reader.StreamReader`,
which needs neither the summary at the end of the file nor ``metadata.yaml``; so:

* a recording cut by power loss (no footer, the last chunk half written) yields every message up to
  the cut, and :attr:`Bag.report` says where and why it stopped;
* a directory without ``metadata.yaml`` is read from its ``.mcap`` files (topics, types and QoS come
  from the MCAP channels), with a note in the report;
* messages are decoded with the ``rosbags`` Jazzy type store; types it does not know are registered
  from the schema stored in the bag; topics of a type that cannot be decoded are listed, not fatal.

Every problem raises :class:`BagError` with a one-line message (never a library traceback) or, where
reading can go on, is recorded in :class:`ReadReport`.
"""

from __future__ import annotations

import struct
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

METADATA = 'metadata.yaml'


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
    messages: int = 0
    per_topic: Counter = field(default_factory=Counter)
    notes: list[str] = field(default_factory=list)
    expected: int | None = None          # message count the metadata lists, when it does

    def lines(self) -> list[str]:
        out = list(self.notes)
        if self.truncated:
            out.append(f'truncated: {self.truncated}; {self.messages} messages read before that')
        if self.expected is not None and self.messages < self.expected and not self.truncated:
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

    # ---------------------------------------------------------------------------------------- opening
    def _files_from_metadata(self) -> list[Path]:
        meta_path = self.dir / METADATA
        try:
            info = yaml.safe_load(meta_path.read_text())['rosbag2_bagfile_information']
        except (yaml.YAMLError, OSError, KeyError, TypeError, UnicodeDecodeError) as e:
            self.report.notes.append(f'{METADATA} unreadable ({type(e).__name__}): reading the .mcap files directly')
            return self._files_without_metadata()
        storage = str(info.get('storage_identifier', 'mcap'))
        if storage != 'mcap':
            raise BagError(f'{self.dir}: storage {storage!r} is not supported (only mcap; convert with '
                           f'`ros2 bag convert`)')
        mode = str(info.get('compression_mode', '') or '').lower()
        if mode not in ('', 'none'):
            raise BagError(f'{self.dir}: rosbag2 {mode}-level compression is not supported (record with '
                           f'MCAP chunk compression instead, as `fixego record` does)')
        self.report.has_metadata = True
        for item in info.get('topics_with_message_count') or []:
            try:
                tm = item['topic_metadata']
                self.topics[tm['name']] = Topic(tm['name'], tm['type'], int(item.get('message_count', 0)),
                                                _qos_list(tm.get('offered_qos_profiles', [])),
                                                str(tm.get('type_description_hash', '') or ''),
                                                str(tm.get('serialization_format', 'cdr')))
            except (KeyError, TypeError, ValueError):
                self.report.notes.append(f'{METADATA}: a malformed topic entry was ignored')
        self.report.expected = int(info['message_count']) if 'message_count' in info else None
        self.custom_data = {str(k): str(v) for k, v in (info.get('custom_data') or {}).items()}
        files = []
        for rel in info.get('relative_file_paths') or []:
            f = self.dir / rel
            if not f.exists():
                raise BagError(f'{self.dir}: {METADATA} lists {rel}, which is missing')
            if f.suffix != '.mcap':
                raise BagError(f'{self.dir}: {rel} is not an .mcap file')
            files.append(f)
        if not files:
            raise BagError(f'{self.dir}: {METADATA} lists no storage files')
        return files

    def _files_without_metadata(self) -> list[Path]:
        files = sorted(self.dir.glob('*.mcap'))
        if not files:
            extra = ' (sqlite3 .db3 bags are not supported)' if any(self.dir.glob('*.db3')) else ''
            raise BagError(f'{self.dir}: not a bag: no {METADATA} and no .mcap file{extra}')
        self.report.notes.append(f'no {METADATA}: reading {", ".join(f.name for f in files)} directly '
                                 f'(topics and QoS from the MCAP channels)')
        return files

    def _summary(self, f: Path) -> None:
        """Topics, counts and time range from the MCAP summary when the file has one (it does not when cut)."""
        from mcap.exceptions import McapError
        from mcap.reader import make_reader
        try:
            with f.open('rb') as fh:
                if fh.read(8) != b'\x89MCAP0\r\n':
                    raise BagError(f'{f}: not an MCAP file (bad magic bytes)')
                fh.seek(0)
                summary = make_reader(fh).get_summary()
        except (McapError, struct.error, ValueError, OSError, EOFError):
            summary = None
        if summary is None:
            self.report.notes.append(f'{f.name} has no summary (recording not closed cleanly?): topics are '
                                     f'discovered while reading')
            return
        stats = summary.statistics
        counts = stats.channel_message_counts if stats is not None else {}
        for cid, ch in summary.channels.items():
            self._add_channel(ch, summary.schemas.get(ch.schema_id), counts.get(cid))
        if stats is not None and stats.message_count:
            lo, hi = stats.message_start_time, stats.message_end_time
            self.start_ns = lo if self.start_ns is None else min(self.start_ns, lo)
            self.end_ns = hi if self.end_ns is None else max(self.end_ns, hi)

    def _add_channel(self, ch, schema, count: int | None = None) -> None:
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
        """Messages in file order (which is recording order); stops cleanly at a cut or corrupt record."""
        from mcap.exceptions import McapError
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader

        wanted = None if topics is None else set(topics)
        self.report.messages, self.report.per_topic, self.report.truncated = 0, Counter(), ''
        for f in self.files:
            schemas: dict[int, Any] = {}
            channels: dict[int, tuple[str, str]] = {}
            with f.open('rb') as fh:
                try:
                    for rec in StreamReader(fh, validate_crcs=False).records:
                        if isinstance(rec, Message):
                            topic, msgtype = channels.get(rec.channel_id, ('', ''))
                            if not topic:
                                continue
                            self.report.messages += 1
                            self.report.per_topic[topic] += 1
                            t = rec.log_time
                            self.start_ns = t if self.start_ns is None else min(self.start_ns, t)
                            self.end_ns = t if self.end_ns is None else max(self.end_ns, t)
                            if wanted is None or topic in wanted:
                                yield BagMessage(topic, msgtype, t, rec.data)
                        elif isinstance(rec, Schema):
                            schemas[rec.id] = rec
                        elif isinstance(rec, Channel):
                            schema = schemas.get(rec.schema_id)
                            self._add_channel(rec, schema)
                            channels[rec.id] = (rec.topic, schema.name if schema is not None else '')
                except (McapError, struct.error, ValueError, EOFError, OSError, MemoryError) as e:
                    where = f'{f.name} at byte {fh.tell()}'
                    self.report.truncated = f'{where}: {type(e).__name__}: {e}'.rstrip(': ')
                    return

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
