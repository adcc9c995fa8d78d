"""Storage core of ``fixego record``: serialised messages in, a rosbag2 (version 9) MCAP bag out.

ROS-free on purpose (no rclpy import, not even lazily), so the storage side can be tested and reused
without DDS. Writing goes through ``rosbags``' :class:`~rosbags.rosbag2.Writer` with zstd-compressed MCAP
chunks (like rosbag2's mcap plugin with ``--compression-mode`` left unset and a zstd chunk profile), so
``metadata.yaml`` has no rosbag2-level compression and ``ros2 bag info/play`` read it directly. The MCAP
file carries real CRCs (:mod:`fixego_ros.bags.mcap_storage`): each chunk's as it is closed (so also in a
killed recording's prefix), the data section's and the summary's at :meth:`~BagRecorder.close`.

Threading: :meth:`BagRecorder.put` is called from subscription callbacks and must never stall them,
so it only counts and appends to an unbounded queue; one writer thread owns the ``Writer`` and does
every file operation (adding connections, writing, flushing, closing). A message accepted by
:meth:`~BagRecorder.put` is never dropped by the recorder: :meth:`~BagRecorder.close` drains the queue
before it writes the MCAP summary and ``metadata.yaml``. The only way ``dropped`` becomes non-zero is a
storage failure (disk full, I/O error), which is reported in :attr:`RecordSummary.error`.

Crash safety: rosbags keeps the current chunk in memory until it reaches 1 MiB, so a killed recorder
would lose up to that much. Every ``flush_period_s`` the writer thread therefore closes the pending
chunk and flushes the file (``McapWriter.close_chunk()`` and ``McapWriter.bio.flush()``; these are
public names of rosbags' MCAP storage class, but not part of its documented API: if a rosbags version
lacks them, periodic flushing switches itself off and :attr:`RecordSummary.flushing` says so). After a
SIGKILL the ``.mcap`` file then holds every message up to the last flush, readable with
:class:`fixego_ros.bags.reader.Bag` (no footer, no ``metadata.yaml``). No ``fsync``: a killed process
leaves its data in the OS page cache; only a power cut can lose the last seconds.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# rosbag2 (Jazzy) spells an infinite duration as rmw's RMW_DURATION_INFINITE split into sec/nsec
_INFINITE = {'sec': 9223372036, 'nsec': 854775807}
_STOP = object()


class RecordError(Exception):
    """Something the recorder cannot do (the message says what, in one line)."""


@dataclass
class TopicCounts:
    msgtype: str
    received: int = 0      # accepted by put()
    written: int = 0       # handed to the MCAP writer

    @property
    def dropped(self) -> int:
        return self.received - self.written


@dataclass
class RecordSummary:
    """Counts of a recording (live while it runs, final after :meth:`BagRecorder.close`)."""

    path: Path
    topics: dict[str, TopicCounts] = field(default_factory=dict)
    pending: int = 0               # queued, not written yet
    bytes: int = 0                 # size of the bag directory's files
    closed: bool = False           # close() finished: MCAP summary and metadata.yaml written
    flushing: bool = True          # periodic chunk flushing works with this rosbags version
    error: str = ''                # '' = no storage problem

    @property
    def received(self) -> int:
        return sum(c.received for c in self.topics.values())

    @property
    def written(self) -> int:
        return sum(c.written for c in self.topics.values())

    @property
    def dropped(self) -> int:
        return self.received - self.written

    @property
    def ok(self) -> bool:
        return self.closed and not self.error and self.dropped == 0

    def line(self) -> str:
        """One line for a terminal: messages per topic, received vs written, dropped, size, path."""
        per = ', '.join(f'{name} {c.written}' for name, c in sorted(self.topics.items())) or 'no topic recorded'
        text = (f'{self.written} messages on {len(self.topics)} topics ({per}); received {self.received}, '
                f'written {self.written}, dropped {self.dropped}; {_size(self.bytes)} in {self.path}')
        if self.error:
            text += f'; ERROR: {self.error}'
        elif not self.closed:
            text += '; not closed cleanly'
        return text


def _size(n: int) -> str:
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if n < 1024 or unit == 'GiB':
            return f'{n} {unit}' if unit == 'B' else f'{n:.1f} {unit}'
        n /= 1024
    return f'{n} B'  # pragma: no cover


def qos_from_dict(d: dict[str, Any]) -> Any:
    """``rosbags.interfaces.Qos`` of one offered-QoS dict with rosbag2 (version 9) keys and names."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    def enum(cls, key: str):
        value = d.get(key, 'unknown')
        try:
            return cls(value) if isinstance(value, int) else cls.__members__[str(value).upper()]
        except (KeyError, ValueError):
            return cls.UNKNOWN

    def duration(key: str) -> QosTime:
        value = d.get(key) or _INFINITE
        try:
            return QosTime(int(value['sec']), int(value['nsec']))
        except (KeyError, TypeError, ValueError):
            raise RecordError(f'offered QoS {key} {value!r} is not {{sec, nsec}}') from None

    return Qos(history=enum(QosHistory, 'history'), depth=int(d.get('depth', 0)),
               reliability=enum(QosReliability, 'reliability'), durability=enum(QosDurability, 'durability'),
               deadline=duration('deadline'), lifespan=duration('lifespan'),
               liveliness=enum(QosLiveliness, 'liveliness'),
               liveliness_lease_duration=duration('liveliness_lease_duration'),
               avoid_ros_namespace_conventions=bool(d.get('avoid_ros_namespace_conventions', False)))


class BagRecorder:
    """A rosbag2/MCAP bag being recorded: :meth:`add_topic`, then :meth:`put` from any thread, :meth:`close`."""

    def __init__(self, path: str | Path, compression: bool = True, flush_period_s: float = 1.0,
                 typestore: Any = None) -> None:
        from rosbags.rosbag2 import WriterError
        from rosbags.typesys import Stores, get_typestore

        from fixego_ros.bags.mcap_storage import bag_writer

        self.path = Path(path)
        self.flush_period_s = float(flush_period_s)
        self._store = typestore if typestore is not None else get_typestore(Stores.ROS2_JAZZY)
        if self.path.exists():
            raise RecordError(f'{self.path} exists already (a recording never overwrites)')
        self._writer = bag_writer(self.path, compression)
        try:
            self._writer.open()
        except (WriterError, OSError) as e:
            raise RecordError(f'cannot create {self.path}: {e}') from None
        self._lock = threading.Lock()
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._counts: dict[str, TopicCounts] = {}
        self._pending = 0
        self._closing = False
        self._closed = False
        self._flushing = True
        self._error = ''
        self._thread = threading.Thread(target=self._run, name=f'bag writer {self.path.name}', daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------------------------------ API
    def add_topic(self, name: str, msgtype: str, offered_qos: list[dict] | tuple = (), type_hash: str = '') -> str:
        """Register a topic before its first :meth:`put`; returns a warning ('' = none).

        ``type_hash`` is the publishers' RIHS01 hash; '' = take the Jazzy type store's. A type the
        store does not know raises :class:`RecordError` (the bag could not carry its schema).
        """
        if msgtype not in self._store.fielddefs:
            raise RecordError(f'{name}: type {msgtype} is unknown to the rosbags Jazzy type store, '
                              f'so its schema cannot be stored; topic not recorded')
        try:
            msgdef, _ = self._store.generate_msgdef(msgtype, ros_version=2)
            known = self._store.hash_rihs01(msgtype)
        except Exception as e:  # rosbags raises assorted errors for odd definitions
            raise RecordError(f'{name}: cannot build the schema of {msgtype} ({type(e).__name__}: {e})') from None
        qos = [qos_from_dict(q) for q in offered_qos]
        note = ''
        if type_hash and type_hash != known:
            note = (f'{name}: the publishers\' {msgtype} hash {type_hash} differs from the Jazzy definition\'s '
                    f'{known}; the bag stores the Jazzy schema, which may not describe the data')
        with self._lock:
            if self._closing:
                raise RecordError(f'{name}: recorder closed')
            if name in self._counts:
                raise RecordError(f'{name}: topic added twice')
            self._counts[name] = TopicCounts(msgtype)
            self._queue.put(('add', name, msgtype, msgdef, type_hash or known, qos))
        return note

    def put(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Queue one serialised message (thread-safe, O(1), never blocks on the disk)."""
        with self._lock:
            if self._closing:
                raise RecordError(f'{topic}: recorder closed')
            counts = self._counts.get(topic)
            if counts is None:
                raise RecordError(f'{topic}: put() before add_topic()')
            counts.received += 1
            self._pending += 1
            self._queue.put((topic, int(log_time_ns), data))   # under the lock: close() cannot overtake it

    def summary(self) -> RecordSummary:
        """Current counts (a copy)."""
        with self._lock:
            topics = {k: TopicCounts(v.msgtype, v.received, v.written) for k, v in self._counts.items()}
            s = RecordSummary(self.path, topics, self._pending, 0, self._closed, self._flushing, self._error)
        s.bytes = sum(f.stat().st_size for f in self.path.glob('*') if f.is_file()) if self.path.is_dir() else 0
        return s

    def close(self, timeout_s: float = 60.0) -> RecordSummary:
        """Write everything queued, the MCAP summary and ``metadata.yaml``; idempotent, bounded by ``timeout_s``."""
        with self._lock:
            if not self._closing:
                self._closing = True
                self._queue.put(_STOP)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            with self._lock:
                self._error = self._error or (f'writer still busy after {timeout_s:.0f} s '
                                              f'({self._pending} messages queued); bag left without summary')
        return self.summary()

    @property
    def closed(self) -> bool:
        return self._closed

    # ------------------------------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        connections: dict[str, Any] = {}
        last_flush = time.monotonic()
        dirty = False                      # messages written since the last flush (or its start)
        while True:
            timeout = None                 # nothing to flush: sleep until the next item
            if dirty and self.flush_period_s > 0:
                timeout = max(0.01, self.flush_period_s - (time.monotonic() - last_flush))
            try:
                item = self._queue.get(timeout=timeout)
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if item is not None and self._handle(item, connections) and not dirty:
                dirty, last_flush = True, time.monotonic()    # flush this burst one period from now
            if dirty and self.flush_period_s > 0 and time.monotonic() - last_flush >= self.flush_period_s:
                self._flush()
                last_flush, dirty = time.monotonic(), False
        self._finish()

    def _handle(self, item: tuple, connections: dict[str, Any]) -> bool:
        """Do one queued operation; returns whether a message was written."""
        if item[0] == 'add':
            _, name, msgtype, msgdef, rihs01, qos = item
            if self._error:
                return False
            try:
                connections[name] = self._writer.add_connection(name, msgtype, msgdef=msgdef, rihs01=rihs01,
                                                                offered_qos_profiles=qos)
            except Exception as e:  # storage failures must not kill the thread
                self._fail(f'{name}: cannot add the topic ({type(e).__name__}: {e})')
            return False
        topic, t, data = item
        ok = False
        if not self._error and topic in connections:
            try:
                self._writer.write(connections[topic], t, data)
                ok = True
            except Exception as e:  # disk full, I/O error: count, report, keep draining
                self._fail(f'write failed ({type(e).__name__}: {e})')
        with self._lock:
            self._pending -= 1
            if ok:
                self._counts[topic].written += 1
        return ok

    def _flush(self) -> None:
        """Close the in-memory chunk and flush the file, so a killed recorder leaves a readable prefix."""
        storage = self._writer.storage
        close_chunk, bio, chunk = (getattr(storage, a, None) for a in ('close_chunk', 'bio', 'chunk'))
        if close_chunk is None or bio is None:
            self._flushing = False
            return
        try:
            if getattr(chunk, 'msgs', True):       # the size limit may just have closed it
                close_chunk()
            bio.flush()
        except Exception as e:
            self._fail(f'flush failed ({type(e).__name__}: {e})')

    def _finish(self) -> None:
        """MCAP summary and metadata.yaml (also after a write error: what was written stays indexed)."""
        try:
            self._writer.close()
        except Exception as e:
            self._fail(f'closing the bag failed ({type(e).__name__}: {e})')
            with contextlib.suppress(Exception):      # the file is broken already; the error says so
                self._writer.abort()
            return
        with self._lock:
            self._closed = True

    def _fail(self, text: str) -> None:
        with self._lock:
            self._error = self._error or text
