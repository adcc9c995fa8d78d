"""Pan/tilt at an image stamp without waiting for the next reading (ROS-free).

At 9600 baud a position inquiry round trip takes 25-50 ms, so an image waiting for the reading *after* its stamp
(to interpolate, :meth:`JointHistory.at`) waits that long. :class:`JointPredictor`
answers at once instead: from the last reading it replays the motion the servo itself commanded (each
AbsolutePosition/Home: a target and a speed per axis, from the moment the camera received it), the way a VISCA
head moves - each axis at its commanded speed straight to its target. A reading rounds the angle to a unit (EVI-D30:
0.1125 deg pan), and a moving head's readings round it at different points of the unit, so the readings of the last
``anchor_window_s``, carried along the same motion, place the last one within its unit first (:meth:`_anchor`; the
bench's prediction error p50 0.022 -> 0.015 deg, docs/results.md "Stop 85"). Without a known command it
extrapolates the rate of the last two readings. The answer carries a 1-sigma per axis that grows with the
extrapolation time and the commanded rate (reading quantisation, command timing, the head's speed being only
nominal - real heads accelerate), so a consumer can weigh it; :class:`SigmaCalibration` checks that model against
each new reading (:meth:`JointPredictor.add_reading`) and raises it for a head that shows more error; a move that
starts within a few ``timing_s`` of the stamp counts its start's timing on either side, and a command still being
written counts from its expected arrival. A later reading simply joins the history: images before it interpolate.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections import deque
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np
from scipy.special import erf as _erf


class JointHistory:
    """Timed joint readings; linear interpolation to an image stamp (bounded extrapolation)."""

    def __init__(self, maxlen: int = 512) -> None:
        self._t: deque[float] = deque(maxlen=maxlen)
        self._q: deque[tuple[float, float]] = deque(maxlen=maxlen)
        self._lock = threading.Lock()

    def add(self, t: float, pan: float, tilt: float) -> None:
        with self._lock:
            if self._t and t <= self._t[-1]:
                return
            self._t.append(t)
            self._q.append((pan, tilt))

    def __len__(self) -> int:
        return len(self._t)

    def times(self) -> list[float]:
        """The readings' times, oldest first."""
        with self._lock:
            return list(self._t)

    def latest(self) -> tuple[float, float, float] | None:
        with self._lock:
            return (self._t[-1], *self._q[-1]) if self._t else None

    def rate(self, window_s: float, min_span_s: float = 0.05) -> tuple[float, float, float] | None:
        """(time of the latest reading, pan rate, tilt rate) over the latest ``window_s`` of readings (fewer when
        the history is younger, but at least ``min_span_s``); None without that."""
        with self._lock:
            if not self._t:
                return None
            t1, (p1, q1) = self._t[-1], self._q[-1]
            i = bisect.bisect_left(list(self._t), t1 - window_s)
            t0, (p0, q0) = self._t[i], self._q[i]
            if t1 - t0 < min_span_s:
                return None
            return t1, (p1 - p0) / (t1 - t0), (q1 - q0) / (t1 - t0)

    def bracket(self, t: float) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
        """The readings (t, pan, tilt) just at/before and at/after ``t`` (the same one twice when a reading is
        at ``t``); None outside the readings."""
        with self._lock:
            ts = list(self._t)
            i = bisect.bisect_left(ts, t)
            if i == len(ts) or (i == 0 and ts[0] > t):
                return None
            if ts[i] == t:
                return (ts[i], *self._q[i]), (ts[i], *self._q[i])
            return (ts[i - 1], *self._q[i - 1]), (ts[i], *self._q[i])

    def between(self, t0: float, t1: float) -> list[tuple[float, float, float]]:
        """The readings (t, pan, tilt) with ``t0 <= t < t1``, oldest first."""
        with self._lock:
            ts = list(self._t)
            i, j = bisect.bisect_left(ts, t0), bisect.bisect_left(ts, t1)
            return [(ts[k], *self._q[k]) for k in range(i, j)]

    def before(self, t: float) -> tuple[float, float, float] | None:
        """The newest reading (t, pan, tilt) strictly before ``t``."""
        with self._lock:
            i = bisect.bisect_left(list(self._t), t)
            return (self._t[i - 1], *self._q[i - 1]) if i > 0 else None

    def at(self, t: float, max_extrapolation_s: float = 0.05) -> tuple[float, float] | None:
        with self._lock:
            if not self._t:
                return None
            ts = list(self._t)
            i = bisect.bisect_left(ts, t)
            if i == 0:
                return self._q[0] if ts[0] - t <= max_extrapolation_s else None
            if i == len(ts):
                # beyond the last reading: hold it (the joints may be still) only for a short while
                return self._q[-1] if t - ts[-1] <= max_extrapolation_s else None
            return _lerp((ts[i - 1], *self._q[i - 1]), (ts[i], *self._q[i]), t)


MODES = ('predict', 'wait')     # camera_node joint_mode: publish at once (predict), or wait for the next reading


@dataclass(frozen=True)
class Command:
    """One motion command as the head received it: from ``t`` each axis runs at its rate (rad/s, >= 0) towards
    its target (rad)."""

    t: float
    pan: float
    tilt: float
    pan_rate: float
    tilt_rate: float


class JointSource(StrEnum):
    """Where a :class:`JointEstimate` comes from."""

    INTERPOLATED = 'interpolated'   # readings on both sides of the stamp
    PREDICTED = 'predicted'         # beyond the last reading (``horizon_s`` past it)


@dataclass(frozen=True)
class JointEstimate:
    """Pan/tilt (rad) at ``t`` with 1-sigma (rad) and where it comes from."""

    t: float
    pan: float
    tilt: float
    pan_sigma: float
    tilt_sigma: float
    source: JointSource
    horizon_s: float = 0.0


@dataclass
class PredictionParams:
    quantum_rad: tuple[float, float] = (math.radians(0.1125), math.radians(0.075))   # one reading unit (pan, tilt)
    timing_s: float = 0.003          # uncertainty of a reading's sample time and of a command's start
    rate_rel: float = 0.15           # relative error of a commanded speed (nominal table; acceleration)
    unknown_rate_rel: float = 1.0    # relative error of a rate taken from the readings (no command known)
    rate_window_s: float = 0.1       # readings older than this give no rate
    max_horizon_s: float = 0.1       # no prediction further than this past the last reading
    max_rate_rad_s: float = math.radians(300.0)   # the head's top speed: bounds a rate taken from the readings
    anchor_window_s: float = 0.3     # readings this far before the last one place it within its unit (0: not)


class SigmaCalibration:
    """How far off the predicted sigma is, measured on the head itself: before each new reading joins the history,
    the prediction for its time from the readings before it is compared with it, and the residual of each axis that
    moved is divided by the sigma stated for it. :attr:`measured` is the robust spread of those normalised residuals
    (median |r| / 0.6745 over the newest ``window``; 1 until ``min_samples``). :attr:`scale`, which multiplies the
    predicted sigmas, is that spread where it exceeds 1 (at most ``max_scale``): a head that moves worse than the
    model says (slower than its speed table, or a profile of another model) gets the sigma it shows.

    A head predicted better than the model says keeps the model's sigma. Its terms are a real head's (``rate_rel``:
    the speed 15 % off the table while it accelerates), and the emulator keeps its table speed: on demo runs its
    heads measure 0.18-0.27. Scaled down to that (stop 84: x 0.25, five demo runs against five of the old code,
    alternated), the sigmas were honest for the bulk of the frames (error / stated RMS 0.73-1.04 while turning) but
    1.3-1.8 % of the frames lay beyond 3 sigma (host timing, up to 1.3 deg), and the estimator, now trusting the turning
    cameras, failed twice (55 cm and 3 m terminal; the same inputs with the model's sigma: 4.8 cm). The model's
    margin is what covers those tails (docs/results.md "Stop 84")."""

    MAD_TO_SIGMA = 1.0 / 0.6745

    def __init__(self, window: int = 200, min_samples: int = 30, max_scale: float = 4.0) -> None:
        self._r: deque[float] = deque(maxlen=window)
        self.min_samples, self.max_scale = min_samples, max_scale
        self.measured = 1.0
        self.scale = 1.0
        self.samples = 0

    def add(self, residual: float, sigma: float) -> None:
        """One axis's residual (reading - prediction) and the sigma stated for that prediction (both rad, > 0)."""
        if not (math.isfinite(residual) and math.isfinite(sigma) and sigma > 0.0):
            return
        self._r.append(abs(residual) / sigma)
        self.samples += 1
        if len(self._r) >= self.min_samples:
            self.measured = self.MAD_TO_SIGMA * float(sorted(self._r)[len(self._r) // 2])
            self.scale = min(max(self.measured, 1.0), self.max_scale)


def _lerp(r0: tuple[float, float, float], r1: tuple[float, float, float], t: float) -> tuple[float, float]:
    """Pan/tilt at ``t`` on the line between two readings (t, pan, tilt); the first when they coincide."""
    a = 0.0 if r1[0] <= r0[0] else (t - r0[0]) / (r1[0] - r0[0])
    return r0[1] + a * (r1[1] - r0[1]), r0[2] + a * (r1[2] - r0[2])


ANCHOR_GRID = (np.arange(41) - 20) / 40.0   # where in the last reading's unit the head may be (units; symmetric)


def _sigma(quantum: float, rate: float, timing_s: float, spread: float) -> float:
    """1-sigma of a predicted axis: reading quantisation (uniform), the timing error at ``rate``, and
    ``spread`` (the share of the motion the speed being only nominal makes uncertain)."""
    return math.sqrt((quantum / math.sqrt(12.0)) ** 2 + (rate * timing_s) ** 2 + spread ** 2)


def _advance(pos: float, target: float, rate: float, dt: float) -> tuple[float, float]:
    """Axis position after ``dt`` at ``rate`` towards ``target``, and the distance travelled."""
    step = min(abs(target - pos), rate * max(dt, 0.0))
    return pos + math.copysign(step, target - pos), step


def _replay(reading: tuple[float, float, float], active: Command | None, later: list[Command],
            t: float) -> tuple[float, float, float, float, float, float]:
    """The commanded motion from ``reading`` (t, pan, tilt) to ``t``: ``active`` runs from the reading, each of
    ``later`` (in time order) from its arrival; before the first command the head rests. Returns pan, tilt, the
    distance each axis travelled and the fastest rate each moved at."""
    seg_start, cur = reading[0], active
    pan, tilt = reading[1], reading[2]
    moved_p = moved_t = rate_p = rate_t = 0.0
    for c in [*(c for c in later if c.t < t), None]:
        seg_end = c.t if c is not None else t
        if cur is not None:
            pan, dp = _advance(pan, cur.pan, cur.pan_rate, seg_end - seg_start)
            tilt, dq = _advance(tilt, cur.tilt, cur.tilt_rate, seg_end - seg_start)
            moved_p, moved_t = moved_p + dp, moved_t + dq
            rate_p = max(rate_p, cur.pan_rate if dp > 0 else 0.0)
            rate_t = max(rate_t, cur.tilt_rate if dq > 0 else 0.0)
        cur, seg_start = c, seg_end
    return pan, tilt, moved_p, moved_t, rate_p, rate_t


def _command(t: float, pan: float, tilt: float, pan_rate: float, tilt_rate: float) -> Command | None:
    """A command as the predictor keeps it (rates as speeds); None when a value is not finite."""
    if not all(math.isfinite(v) for v in (t, pan, tilt, pan_rate, tilt_rate)):
        return None
    return Command(t, pan, tilt, abs(pan_rate), abs(tilt_rate))


class JointPredictor:
    """Readings (a :class:`JointHistory`, shared with whoever adds to it) plus the
    commands sent to the head; :meth:`estimate` interpolates or predicts. Thread-safe (the servo loop adds from
    its thread)."""

    START_WINDOW = 3.0      # a command dated this many timing_s of the stamp may have started on either side of it

    def __init__(self, history: JointHistory | None = None, params: PredictionParams | None = None,
                 max_commands: int = 64) -> None:
        self.history = history if history is not None else JointHistory()
        self.params = params or PredictionParams()
        self._commands: deque[Command] = deque(maxlen=max_commands)
        self._expected: Command | None = None      # being written: not yet acknowledged (so not yet dated)
        self._lock = threading.Lock()
        self.calibration = SigmaCalibration()

    # ------------------------------------------------------------------------------------------ input
    def add_reading(self, t: float, pan: float, tilt: float, calibrate: bool = False) -> None:
        """A reading at ``t``. With ``calibrate`` (its time known to within the camera's own answering delay, not
        inferred from the motion), the prediction for ``t`` is first checked against it (:class:`SigmaCalibration`):
        each axis that the commanded motion moved by more than a reading unit gives a sample."""
        if calibrate:
            self._check(t, pan, tilt)
        self.history.add(t, pan, tilt)

    def _check(self, t: float, pan: float, tilt: float) -> None:
        last = self.history.latest()
        if last is None or not t > last[0] or t - last[0] > self.params.max_horizon_s:
            return
        active, later = self._since(last[0])
        if active is None and not any(c.t < t for c in later):
            return                                  # no command known: nothing the model claims
        e = self._predict(t, last, calibrated=False)
        _, _, moved_p, moved_t, _, _ = _replay(last, active, later, t)
        qp, qt = self.params.quantum_rad
        if moved_p > qp:
            self.calibration.add(pan - e.pan, e.pan_sigma)
        if moved_t > qt:
            self.calibration.add(tilt - e.tilt, e.tilt_sigma)

    def add_command(self, t: float, pan: float, tilt: float, pan_rate: float, tilt_rate: float) -> None:
        """A command the head received at ``t`` (rad, rad/s). Out-of-order or non-finite ones are ignored."""
        command = _command(t, pan, tilt, pan_rate, tilt_rate)
        if command is None:
            return
        with self._lock:
            self._expected = None
            if self._commands and t < self._commands[-1].t:
                return
            self._commands.append(command)

    def expect_command(self, t: float, pan: float, tilt: float, pan_rate: float, tilt_rate: float) -> None:
        """A command being written, which the head will take about ``t`` (its last byte's arrival). Its ACK, read
        15-20 ms after the write began (more on a busy host), dates it (:meth:`add_command` then replaces it); until
        then estimates count on it, since the head may be moving already: on a demo, frames stamped in that gap were
        published at the reading the head had just left, 2-5 mrad off at the reading's 0.57 mrad (docs/results.md
        "Stop 63"). Non-finite values are ignored."""
        command = _command(t, pan, tilt, pan_rate, tilt_rate)
        if command is not None:
            with self._lock:
                self._expected = command

    def forget_expected(self) -> None:
        """The command being written did not reach the head (the write failed)."""
        with self._lock:
            self._expected = None

    def commands(self) -> list[Command]:
        """The acknowledged commands in time order, then the one being written (when it is not older)."""
        with self._lock:
            out = list(self._commands)
            if self._expected is not None and (not out or self._expected.t >= out[-1].t):
                out.append(self._expected)
            return out

    # ------------------------------------------------------------------------------------------ output
    def estimate(self, t: float) -> JointEstimate | None:
        """Pan/tilt at ``t``: interpolated when a reading at or after ``t`` exists, else predicted up to
        ``max_horizon_s`` past the last reading; None without readings, before the first, or beyond the horizon."""
        last = self.history.latest()
        if last is None or not math.isfinite(t):
            return None
        t_r, pan_r, tilt_r = last
        if t <= t_r:
            return self._interpolate(t)
        horizon = t - t_r
        if horizon > self.params.max_horizon_s:
            return None
        return self._predict(t, (t_r, pan_r, tilt_r))

    def _since(self, t_reading: float, cmds: list[Command] | None = None) -> tuple[Command | None, list[Command]]:
        """The command the head was running at a reading (the last one it received by then; None before the
        first) and those it received after it, in order (of ``cmds``, default :meth:`commands`)."""
        cmds = self.commands() if cmds is None else cmds
        i = bisect.bisect_right(cmds, t_reading, key=lambda c: c.t)
        return (cmds[i - 1] if i > 0 else None), cmds[i:]

    def _interpolate(self, t: float) -> JointEstimate | None:
        """Between two readings. A straight line between them cuts the corners of the commanded path: the head
        that reaches its target and stops, or gets a command in between and starts or turns back, is off the line
        by up to its rate times the reading period. So the commanded motion is replayed from the first reading and
        what it misses at the second (timing, the speed being nominal) is spread linearly over the interval. With
        no command known (a head moved by someone else), the straight line."""
        pair = self.history.bracket(t)
        if pair is None:
            return None
        r0, r1 = pair
        qp, qt = self.params.quantum_rad
        # a head at rest reads exactly; a moving one to within a unit (uniform: unit / sqrt 12)
        sp = _sigma(qp, 0.0, 0.0, 0.0) if r0[1] != r1[1] else 0.0
        st = _sigma(qt, 0.0, 0.0, 0.0) if r0[2] != r1[2] else 0.0
        active, later = self._since(r0[0])
        if r1[0] <= r0[0] or (active is None and not any(c.t < r1[0] for c in later)):
            return JointEstimate(t, *_lerp(r0, r1, t), sp, st, JointSource.INTERPOLATED)
        at_t = _replay(r0, active, later, t)
        at_1 = _replay(r0, active, later, r1[0])
        a = (t - r0[0]) / (r1[0] - r0[0])
        miss_p, miss_t = r1[1] - at_1[0], r1[2] - at_1[1]
        pan, tilt = at_t[0] + a * miss_p, at_t[1] + a * miss_t
        # what the replay missed at the second reading is the model's error there (timing, nominal speed): half of
        # it counts as the uncertainty in between; a move that starts near the stamp adds its start's
        start_p, start_t = self._start_sigmas(t, pan, tilt, after=-math.inf)
        return JointEstimate(t, pan, tilt, math.hypot(sp, 0.5 * a * miss_p, start_p),
                             math.hypot(st, 0.5 * a * miss_t, start_t), JointSource.INTERPOLATED)

    def _start_sigmas(self, t: float, pan: float, tilt: float, after: float) -> tuple[float, float]:
        """1-sigma per axis for the start of a move near ``t``, of the commands dated after ``after``: a command is
        dated to within ``timing_s`` (rms), so within ``START_WINDOW`` of those of its start the head may already have
        left where the replay holds it, or not yet. Measured on a demo (docs/results.md "Stop 63"): frames at the start
        of a move published the reading the head had just left, 2-6 mrad off, at the reading's 0.57 mrad."""
        p = self.params
        reach = self.START_WINDOW * p.timing_s
        qp, qt = p.quantum_rad
        sp = st = 0.0
        for c in reversed(self.commands()):         # in time order: the newest first
            if c.t < t - reach:
                break
            if c.t > t + reach or c.t <= after:
                continue
            if abs(c.pan - pan) > 0.5 * qp:      # the axis has somewhere to go
                sp = max(sp, c.pan_rate * p.timing_s)
            if abs(c.tilt - tilt) > 0.5 * qt:
                st = max(st, c.tilt_rate * p.timing_s)
        return sp, st

    def _anchor(self, last: tuple[float, float, float]) -> tuple[float, float, float]:
        """Where the head was at the last reading. A reading rounds the angle to a unit, so the head was within half a
        unit of it; each reading of the last ``anchor_window_s`` carried to its time along the commanded motion says
        the same of its own unit, blurred by the model's timing and speed errors. The mean of the product of those
        (on a grid over the last reading's unit) is the answer: never outside that unit, and the reading itself when
        the others say nothing (a head at rest, no command known)."""
        p = self.params
        t_r = last[0]
        if p.anchor_window_s <= 0.0:
            return last
        earlier = self.history.between(t_r - p.anchor_window_s, t_r)
        cmds = self.commands()
        carried = []                              # (pan, tilt, moved_p, moved_t, rate_p, rate_t) at t_r
        for r in earlier:
            active, later = self._since(r[0], cmds)
            if active is not None or any(c.t < t_r for c in later):
                carried.append(_replay(r, active, later, t_r))
        if not carried:
            return last
        units = np.asarray(p.quantum_rad, float)
        x = ANCHOR_GRID[:, None, None] * units                  # offsets from the last reading (grid, 1, 2)
        c = np.asarray(carried, float)                          # (n, 6)
        centre = c[:, :2] - np.array(last[1:])
        blur = np.hypot(math.sqrt(2.0) * p.timing_s * c[:, 4:6], p.rate_rel * c[:, 2:4])     # (n, 2)
        blur = np.maximum(blur, 1e-3 * units)
        lo, hi = (x - centre + 0.5 * units) / blur, (x - centre - 0.5 * units) / blur         # (grid, n, 2)
        like = 0.5 * (_erf(lo / math.sqrt(2.0)) - _erf(hi / math.sqrt(2.0)))
        logp = np.log(np.maximum(like, 1e-300)).sum(axis=1)                                 # (grid, 2)
        w = np.exp(logp - logp.max(axis=0))
        half = len(ANCHOR_GRID) // 2               # paired from both ends: a symmetric spread gives exactly 0
        off = ((w[:half] - w[:half:-1]) * x[:half, 0, :]).sum(axis=0) / w.sum(axis=0)
        return t_r, last[1] + float(off[0]), last[2] + float(off[1])

    def _predict(self, t: float, last: tuple[float, float, float], calibrated: bool = True) -> JointEstimate:
        """The commanded motion replayed from the last reading (the rate of the readings without a command); its
        sigmas times :attr:`calibration`'s scale (>= 1) unless ``calibrated`` is False."""
        p = self.params
        last = self._anchor(last)
        active, later = self._since(last[0])
        if active is None and not any(c.t < t for c in later):
            e = self._extrapolate(t, last)
        else:
            pan, tilt, moved_p, moved_t, rate_p, rate_t = _replay(last, active, later, t)
            qp, qt = p.quantum_rad
            e = JointEstimate(t, pan, tilt, _sigma(qp, rate_p, p.timing_s, p.rate_rel * moved_p),
                              _sigma(qt, rate_t, p.timing_s, p.rate_rel * moved_t), JointSource.PREDICTED, t - last[0])
        # a move the replay has started already carries its start's timing (rate * timing_s); one dated just after
        # the stamp may have started before it
        start_p, start_t = self._start_sigmas(t, e.pan, e.tilt, after=t)
        sp, st = math.hypot(e.pan_sigma, start_p), math.hypot(e.tilt_sigma, start_t)
        k = self.calibration.scale if calibrated else 1.0
        return replace(e, pan_sigma=k * sp, tilt_sigma=k * st)

    def _extrapolate(self, t: float, last: tuple[float, float, float]) -> JointEstimate:
        """No command known (passive head, or moved by someone else): the rate of the last two readings."""
        p = self.params
        t_r, pan, tilt = last
        prev = self.history.before(t_r)
        vp = vt = 0.0
        if prev is not None and 0.0 < t_r - prev[0] <= p.rate_window_s:
            vp, vt = ((min(max(d / (t_r - prev[0]), -p.max_rate_rad_s), p.max_rate_rad_s))
                      for d in (pan - prev[1], tilt - prev[2]))
        dt = t - t_r
        qp, qt = p.quantum_rad
        sp = _sigma(qp, vp, p.timing_s, p.unknown_rate_rel * vp * dt)
        st = _sigma(qt, vt, p.timing_s, p.unknown_rate_rel * vt * dt)
        return JointEstimate(t, pan + vp * dt, tilt + vt * dt, sp, st, JointSource.PREDICTED, dt)
