"""Approximate-time synchroniser for the two cameras' images, joint states and fixation pixels.

``message_filters`` is not available as a wheel, and the flow node needs more than a pair matcher: a
frame is ready only when each camera's pan/tilt at its image stamp is known (the joint state may
arrive after the image) and its fixation message has arrived: a pixel, or camera_node's explicit "no valid
fixation at this stamp" (id :data:`~fixego_ros.tracking.fixation.NO_FIXATION_ID`), which completes the camera at
once, without one. A camera's fixation messages come in stamp order (its node processes its images in order), so
one for a later stamp also says this one will not come (its node never got the image: a dropped sensor-data
sample): the camera enters without a fixation at once (``fixation_skipped``). A stream that sends nothing for
frames without a fixation (bags recorded before camera_node published the explicit message) still works: the
camera waits until a later fixation arrives or ``max_wait_s`` has passed (``fixation_timeouts``), and enters the
frame without one. Every wait is bounded by ``max_wait_s`` of the caller's clock, so
a silent stream degrades to single-camera frames or frames without a fixation, never to a stall.
Frames come out in stamp order; anything older than the last emitted frame is dropped and counted.

Pairing tolerance ``slop_s``: 0 (the default) means automatic, half the median frame period measured from
the images' own stamps (the consecutive stamps of each camera, the last :data:`AUTO_PERIOD_SAMPLES`
intervals of both), so two unsynchronised cameras at 30 Hz (up to 16.7 ms apart) always pair with their
nearest partner. It is bounded to [:data:`AUTO_SLOP_MIN_S`, :data:`AUTO_SLOP_MAX_S`] (a 10 Hz camera or
slower gets 50 ms); until two images of one camera have arrived, the upper bound is used. An explicit
value > 0 is used as given.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

from fixego_ros.geometry.rig import SIDES
from fixego_ros.tracking.fixation import NO_FIXATION_ID
from fixego_ros.tracking.servo import JointHistory

AUTO_SLOP_MIN_S, AUTO_SLOP_MAX_S = 0.001, 0.05   # bounds of the automatic slop (half the frame period)
AUTO_PERIOD_SAMPLES = 31                         # frame intervals the median is taken over


@dataclass(frozen=True)
class SyncParams:
    slop_s: float = 0.0               # two images closer than this belong to the same frame; 0 = automatic
    max_wait_s: float = 0.25          # how long a frame may wait for a partner, joints or fixation
    joint_extrapolation_s: float = 0.0  # how far beyond the newest joint reading an image may be
    fixation_tolerance_s: float = 1e-4  # a fixation belongs to an image with this stamp difference
    max_queue: int = 30               # images kept per camera while waiting

    def __post_init__(self) -> None:
        for name in ('slop_s', 'max_wait_s', 'joint_extrapolation_s', 'fixation_tolerance_s'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f'{name} must be finite and >= 0, got {v}')
        if self.max_queue < 2:
            raise ValueError(f'max_queue must be >= 2, got {self.max_queue}')


@dataclass
class SyncedCamera:
    stamp: float
    image: Any                                 # whatever the caller queued (grey array in the nodes)
    pan: float                                 # joint readings at the image stamp (rad)
    tilt: float
    fixation_px: tuple[float, float] | None
    fixation_id: int
    joint_sigma: float = 0.0                   # 1-sigma (rad) of the readings given at this stamp; 0 = not given


@dataclass
class SyncedFrame:
    stamp: float                               # the right image's stamp (the rig's base), else the left's
    cameras: dict[str, SyncedCamera | None]


@dataclass
class _Pending:
    stamp: float
    image: Any
    arrived: float                             # caller's clock when queued


@dataclass
class SyncStats:
    frames: int = 0
    stereo_frames: int = 0
    single_camera_frames: int = 0
    late_images: int = 0                       # older than the last emitted frame: dropped
    overflow_images: int = 0                   # queue full: oldest dropped
    no_joints: int = 0                         # camera dropped from a frame: no pan/tilt at its stamp
    no_fixation: int = 0                       # camera in a frame without a fixation pixel
    fixation_skipped: int = 0                  # ... of which its camera's next message came first (image not seen)
    fixation_timeouts: int = 0                 # ... of which after waiting max_wait_s for a message that never came
    partner_timeouts: int = 0                  # single-camera frames after waiting max_wait_s for the other image
    partner_missing: int = 0                   # single-camera frames whose other image never came (lost on the way)
    rejected: int = 0                          # non-finite stamps/values


class StereoSync:
    """Feed images, joint readings and fixation pixels as they arrive; :meth:`pop_ready` returns frames.

    ``now`` is the caller's clock (node time, or bag time in replays); only differences matter.
    """

    def __init__(self, params: SyncParams | None = None) -> None:
        self.params = params or SyncParams()
        self.stats = SyncStats()
        self.reset()

    def reset(self) -> None:
        self._periods: deque[float] = deque(maxlen=AUTO_PERIOD_SAMPLES)   # consecutive-stamp intervals
        self._last_stamp: dict[str, float] = {}
        self._images: dict[str, deque[_Pending]] = {s: deque() for s in SIDES}
        self._joints: dict[str, JointHistory] = {s: JointHistory(maxlen=2048) for s in SIDES}
        # stamp -> (pixel, id); (None, NO_FIXATION_ID) = the camera said it has no fixation at that stamp
        self._fix: dict[str, dict[float, tuple[tuple[float, float] | None, int]]] = {s: {} for s in SIDES}
        self._joint_sigma: dict[str, dict[float, float]] = {s: {} for s in SIDES}     # stamp -> 1-sigma (rad)
        self._fix_newest: dict[str, float] = dict.fromkeys(SIDES, -math.inf)    # newest fixation stamp per camera
        self._last_emitted = -math.inf

    @property
    def frame_period_s(self) -> float | None:
        """Median interval between consecutive images of one camera so far (None before two of one camera)."""
        if not self._periods:
            return None
        return float(sorted(self._periods)[len(self._periods) // 2])

    @property
    def slop_s(self) -> float:
        """The pairing tolerance in use: ``params.slop_s``, or the automatic one when that is 0."""
        if self.params.slop_s > 0:
            return self.params.slop_s
        period = self.frame_period_s
        if period is None:
            return AUTO_SLOP_MAX_S
        return min(max(0.5 * period, AUTO_SLOP_MIN_S), AUTO_SLOP_MAX_S)

    # ------------------------------------------------------------------------------------------ input
    def add_image(self, side: str, stamp: float, image: Any, now: float) -> bool:
        """Queue an image; False (and counted) when it is late or its stamp is not finite."""
        if not math.isfinite(stamp):
            self.stats.rejected += 1
            return False
        if stamp <= self._last_emitted:
            self.stats.late_images += 1
            return False
        q = self._images[side]
        if q and stamp <= q[-1].stamp:
            self.stats.late_images += 1         # out of order within one camera
            return False
        last = self._last_stamp.get(side)
        if last is not None and stamp > last:
            self._periods.append(stamp - last)
        self._last_stamp[side] = stamp
        if len(q) >= self.params.max_queue:
            q.popleft()
            self.stats.overflow_images += 1
        q.append(_Pending(stamp, image, now))
        return True

    def add_joints(self, side: str, stamp: float, pan: float, tilt: float, sigma: float = 0.0) -> bool:
        """Joint readings (rad) at ``stamp``; ``sigma`` their 1-sigma (rad) when the source gives one (camera_node
        does, per image stamp): a frame at exactly that stamp carries it on."""
        if not all(math.isfinite(v) for v in (stamp, pan, tilt)):
            self.stats.rejected += 1
            return False
        latest = self._joints[side].latest()
        if latest is not None and stamp <= latest[0]:
            return False                        # JointHistory keeps readings in time order
        self._joints[side].add(stamp, pan, tilt)
        if sigma > 0.0 and math.isfinite(sigma):
            sig = self._joint_sigma[side]
            sig[stamp] = float(sigma)
            if len(sig) > 4 * self.params.max_queue:
                del sig[next(iter(sig))]        # the oldest (added in time order)
        return True

    def add_fixation(self, side: str, stamp: float, pixel: tuple[float, float] | None, fixation_id: int) -> bool:
        """The fixation at an image stamp; ``pixel`` None or a negative id: no valid fixation there (the camera
        completes without waiting). False (non-finite values counted) when rejected or late."""
        none = pixel is None or fixation_id < 0
        if not (math.isfinite(stamp) and (none or all(math.isfinite(v) for v in pixel))):
            self.stats.rejected += 1
            return False
        self._fix_newest[side] = max(self._fix_newest[side], stamp)
        if stamp <= self._last_emitted:
            return False
        fix = self._fix[side]
        fix[stamp] = (None, NO_FIXATION_ID) if none else ((float(pixel[0]), float(pixel[1])), int(fixation_id))
        if len(fix) > 4 * self.params.max_queue:
            for k in sorted(fix)[: len(fix) - 4 * self.params.max_queue]:
                del fix[k]
        return True

    # ------------------------------------------------------------------------------------------ output
    def pop_ready(self, now: float, flush: bool = False) -> list[SyncedFrame]:
        """Frames whose inputs are complete or whose waits have expired (all of them with ``flush``)."""
        out: list[SyncedFrame] = []
        while True:
            frame = self._next(now, flush)
            if frame is None:
                return out
            out.append(frame)

    def _next(self, now: float, flush: bool) -> SyncedFrame | None:
        p = self.params
        heads = {s: self._images[s][0] for s in SIDES if self._images[s]}
        if not heads:
            return None
        first = min(heads.values(), key=lambda x: x.stamp)
        slop = self.slop_s
        members: dict[str, _Pending] = {}
        for s, h in heads.items():
            if abs(h.stamp - first.stamp) <= slop:
                members[s] = h
        partner_timeout = partner_past = False
        if len(members) < len(SIDES):
            # a partner may still come: wait unless the other camera is already past this stamp
            missing = [s for s in SIDES if s not in members]
            partner_past = all(self._images[s] and self._images[s][0].stamp > first.stamp + slop
                               for s in missing)
            partner_timeout = not (flush or partner_past)
            if partner_timeout and now - first.arrived <= p.max_wait_s:
                return None
        cameras: dict[str, SyncedCamera | None] = {s: None for s in SIDES}
        for s, m in members.items():
            ready = self._camera(s, m, now, flush)
            if ready is _WAIT:
                return None
            cameras[s] = ready
        for s in members:
            self._images[s].popleft()
        stamp = members['right'].stamp if 'right' in members else members['left'].stamp
        self._last_emitted = max(m.stamp for m in members.values())
        self._prune(self._last_emitted)
        present = [c for c in cameras.values() if c is not None]
        if not present:
            return self._next(now, flush)        # nothing usable in this frame: move on
        self.stats.frames += 1
        self.stats.partner_timeouts += partner_timeout
        self.stats.partner_missing += partner_past and not flush
        if len(present) == 2:
            self.stats.stereo_frames += 1
        else:
            self.stats.single_camera_frames += 1
        return SyncedFrame(stamp, cameras)

    def _camera(self, side: str, m: _Pending, now: float, flush: bool):
        p = self.params
        expired = flush or now - m.arrived > p.max_wait_s
        hist = self._joints[side]
        latest = hist.latest()
        joints = None
        if latest is not None and latest[0] >= m.stamp:
            joints = hist.at(m.stamp, max_extrapolation_s=0.0)
        elif latest is not None and m.stamp - latest[0] <= p.joint_extrapolation_s:
            joints = hist.at(m.stamp, max_extrapolation_s=p.joint_extrapolation_s)
        fix = self._fixation_at(side, m.stamp)      # None: no message yet (an explicit "none" is not None)
        superseded = fix is None and self._fix_newest[side] > m.stamp + p.fixation_tolerance_s
        if (joints is None or (fix is None and not superseded)) and not expired:
            return _WAIT    # an older stream sends no fixation message for a frame without one: wait, bounded
        if joints is None:
            self.stats.no_joints += 1
            return None
        if fix is None:
            if superseded:
                self.stats.fixation_skipped += 1
            else:
                self.stats.fixation_timeouts += 1
        px, fid = fix if fix is not None else (None, NO_FIXATION_ID)
        if px is None:
            self.stats.no_fixation += 1
        return SyncedCamera(m.stamp, m.image, float(joints[0]), float(joints[1]), px, fid,
                            self._joint_sigma[side].get(m.stamp, 0.0))

    def _fixation_at(self, side: str, stamp: float) -> tuple[tuple[float, float] | None, int] | None:
        fix = self._fix[side]
        if stamp in fix:
            return fix[stamp]
        tol = self.params.fixation_tolerance_s
        for k, v in fix.items():
            if abs(k - stamp) <= tol:
                return v
        return None

    def _prune(self, upto: float) -> None:
        for s in SIDES:
            fix = self._fix[s]
            for k in [k for k in fix if k <= upto + self.params.fixation_tolerance_s]:
                del fix[k]


_WAIT = object()
