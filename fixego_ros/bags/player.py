"""When each message of a bag is due during playback, and with which QoS: the ROS-free core of ``bag_player``.

Kept free of rclpy so the timing rules can be tested with a fake clock and no DDS. The rules:

* **Timing.** Playback starts at wall time ``t_start``; the first played message (after the topic filter
  and the start offset) is due then and message ``i`` at ``t_start + (log_time_i - log_time_0) / rate``.
  ``rate`` 0 (or infinity) means as fast as possible: everything is due at ``t_start``.
* **Out-of-order log times** (a recorder with several writer threads, or bags merged by hand) are played in
  file order and never make playback wait backwards: a message older than the newest one played so far is
  due at once (at the newest one's due time), and ``/clock`` stays at the newest time rather than going
  back. They are counted in :attr:`ScheduleStats.non_monotonic` (at every pass when looping).
* **Looping** replays the bag with the clock carried on: pass ``k`` is scheduled on, and announces on
  ``/clock``, the bag time ``log_time + k * period``, so both keep increasing across passes. ``period`` is
  the played span of the first pass plus its mean gap between messages (the first message of a pass
  follows the last one of the previous pass like any other message), or 1 s of bag time when all the
  messages share one stamp. A pass that plays nothing ends the loop.
* **Start offset** skips the messages logged before ``bag start + offset``, bag start being the log time of
  the first message in the file (any topic).
* **QoS**: see :func:`qos_from_profiles`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

from fixego_ros.bags.reader import BagMessage

DEFAULT_DEPTH = 10
DEFAULT_LOOP_PERIOD_NS = 1_000_000_000

# rosbag2 metadata writes the policies as names since format 9 (Jazzy) and as rmw enum values before
_RELIABILITY: dict[Any, bool] = {'reliable': True, 'best_effort': False, 1: True, 2: False}
_DURABILITY: dict[Any, bool] = {'transient_local': True, 'volatile': False, 1: True, 2: False}
_HISTORY: dict[Any, str] = {'keep_last': 'keep_last', 'keep_all': 'keep_all', 1: 'keep_last', 2: 'keep_all'}


class PlayError(ValueError):
    """A playback setting that cannot work (negative rate, negative offset)."""


class MessageSource(Protocol):
    """What the schedule needs from a bag (:class:`~fixego_ros.bags.reader.Bag` or a test double)."""

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]: ...


# -------------------------------------------------------------------------------------------------- QoS
@dataclass(frozen=True)
class PlayQos:
    """The publisher QoS of one played topic, without rclpy types (the node converts it)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = DEFAULT_DEPTH


def _policy(table: dict[Any, Any], value: Any) -> Any:
    if isinstance(value, str):
        value = value.strip().lower()
    elif isinstance(value, bool) or not isinstance(value, int):
        return None
    return table.get(value)


def qos_from_profiles(profiles: Iterable[dict] | None) -> PlayQos:
    """Publisher QoS for a topic recorded with these offered profiles (rosbag2 keys).

    No usable profile gives reliable / volatile / keep-last 10. Several profiles (several publishers were
    recorded) follow rosbag2's player: best effort as soon as one publisher offered best effort (the recorded
    subscribers coped with losses on the topic, and a reliable replay would not behave like the original),
    transient local only when every publisher offered it (late joiners would otherwise get a history no
    original publisher kept). The depth is the largest keep-last depth recorded (keep-all and unknown ignored).
    """
    profiles = [p for p in (profiles or []) if isinstance(p, dict)]
    if not profiles:
        return PlayQos()
    reliability = [_policy(_RELIABILITY, p.get('reliability')) for p in profiles]
    durability = [_policy(_DURABILITY, p.get('durability')) for p in profiles]
    depths = []
    for p in profiles:
        depth = p.get('depth')
        if (_policy(_HISTORY, p.get('history')) in (None, 'keep_last') and isinstance(depth, int)
                and not isinstance(depth, bool) and depth > 0):
            depths.append(depth)
    return PlayQos(reliable=False not in reliability,
                   transient_local=all(d is True for d in durability),
                   depth=max(depths) if depths else DEFAULT_DEPTH)


# -------------------------------------------------------------------------------------------------- schedule
@dataclass(frozen=True)
class PlayItem:
    """One message to publish: due ``due_s`` seconds of wall time after the start of playback."""

    due_s: float
    clock_ns: int        # bag time to announce on /clock: newest log time so far + loop * period (never decreases)
    loop: int            # 0 for the first pass
    msg: BagMessage


@dataclass
class ScheduleStats:
    """What scheduling found (updated while iterating; read at the end or for progress)."""

    scheduled: int = 0
    non_monotonic: int = 0         # played at once because an earlier message carried a later log time
    before_offset: int = 0         # skipped by the start offset (first pass)
    filtered_out: int = 0          # not in the topic filter (first pass)
    loops_completed: int = 0
    period_ns: int | None = None   # loop period, known once the first pass ended
    bag_time_ns: int | None = None  # newest clock time scheduled


class Schedule:
    """Iterable of :class:`PlayItem` in play order; iterates the bag lazily (once per loop pass)."""

    def __init__(self, bag: MessageSource, rate: float = 1.0, topics: Iterable[str] | None = None,
                 loop: bool = False, start_offset_s: float = 0.0) -> None:
        rate = float(rate)
        if math.isnan(rate) or rate < 0:
            raise PlayError(f'rate must be > 0, or 0 for as fast as possible; got {rate}')
        start_offset_s = float(start_offset_s)
        if not math.isfinite(start_offset_s) or start_offset_s < 0:
            raise PlayError(f'start offset must be finite and >= 0 s, got {start_offset_s}')
        self.bag = bag
        self.rate = rate
        self.scale = 0.0 if rate == 0 or math.isinf(rate) else 1.0 / rate   # wall seconds per bag second
        self.topics = frozenset(topics) if topics else None
        self.loop = bool(loop)
        self.offset_ns = round(start_offset_s * 1e9)
        self.stats = ScheduleStats()

    @property
    def as_fast_as_possible(self) -> bool:
        return self.scale == 0.0

    def __iter__(self) -> Iterator[PlayItem]:
        st = self.stats
        start_ns: int | None = None    # bag time where playback begins (first message + offset)
        origin: int | None = None      # clock time of the first played message: due 0
        newest: int | None = None      # newest clock time played so far (the due times never go back)
        k = 0
        while True:
            played = 0
            for m in self.bag.messages():
                if start_ns is None:
                    start_ns = m.log_time_ns + self.offset_ns
                if m.log_time_ns < start_ns:
                    st.before_offset += k == 0
                    continue
                if self.topics is not None and m.topic not in self.topics:
                    st.filtered_out += k == 0
                    continue
                t = m.log_time_ns + k * (st.period_ns or 0)
                if origin is None:
                    origin = newest = t
                if t < newest:
                    st.non_monotonic += 1
                else:
                    newest = t
                played += 1
                st.scheduled += 1
                st.bag_time_ns = newest
                yield PlayItem((newest - origin) * 1e-9 * self.scale, newest, k, m)
            if not self.loop or played == 0:
                return
            if k == 0:
                span = newest - origin
                gap = span // (played - 1) if played > 1 else 0
                st.period_ns = span + gap if span + gap > 0 else DEFAULT_LOOP_PERIOD_NS
            k += 1
            st.loops_completed = k


def play(items: Iterable[PlayItem], publish: Callable[[PlayItem], None], t_start: float,
         now: Callable[[], float], wait: Callable[[float], bool], max_wait_s: float = 0.1) -> bool:
    """Call ``publish(item)`` at ``t_start + item.due_s`` on the clock ``now``, in order.

    ``wait(seconds)`` sleeps at most that long and returns True when playback must stop
    (``threading.Event.wait`` does both); it is called with at most ``max_wait_s`` and once per item
    even when nothing is to wait for, so a stop request is honoured promptly even at full speed.
    A late message is published at once (nothing is dropped). Returns False when stopped, True at the end.
    """
    for item in items:
        deadline = t_start + item.due_s
        while True:
            remaining = deadline - now()
            if wait(min(max(remaining, 0.0), max_wait_s)):
                return False
            if remaining <= 0 or now() >= deadline:
                break
        publish(item)
    return True
