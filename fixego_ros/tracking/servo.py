"""Fixation servo (ROS-free): absolute pan/tilt targets from the fixation pixel, and the serial loop.

Why absolute positions: the target is computed from the joint angles *at the image time* (interpolated
from timed PosInq readings), so the command is right however late it is sent; velocity commands would
integrate the latency into overshoot. The serial loop alternates one PosInq (~17 ms at 9600 baud)
with at most one AbsolutePosition (~20 ms incl. ACK) when a new target exists and the command-rate
limit allows, so the port is never flooded and joint readings keep coming at a steady rate.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fixego_ros.geometry.rig import CameraModel, PanTiltCalibration, pan_tilt_for_direction, pan_tilt_rotation
from fixego_ros.tracking.joint_prediction import JointHistory, JointPredictor, PredictionParams
from fixego_ros.visca import protocol as vp
from fixego_ros.visca.driver import PositionReading, ViscaCamera, prompt_serial_threads
from fixego_ros.visca.profiles import CameraProfile


@dataclass
class ServoParams:
    gain: float = 0.9                  # fraction of the angular error corrected per command
    deadband_px: float = 0.75          # no command when the point is this close to the centre
    move_time_s: float = 0.08          # speed chosen so the correction takes about this long
    max_command_rate_hz: float = 15.0  # AbsolutePosition commands per second at most
    min_inquiry_period_s: float = 0.0  # > 0 slows the PosInq loop (0 = as fast as the line allows)
    feedforward: bool = True           # lead a drifting fixation point by its estimated angular rate
    rate_window_s: float = 0.4         # history used to estimate that rate
    lead_extra_s: float = 0.04         # lead beyond the image age and one command period (command + motion start)
    reading_window_s: float = 0.003    # a reading whose sample window is this much wider than the narrowest is
                                       # dated by the commanded motion (ServoLoop._keep_reading)


@dataclass(frozen=True)
class Target:
    pan: int
    tilt: int
    pan_speed: int
    tilt_speed: int


def centring_angles(camera: CameraModel, pixel: tuple[float, float], pan: float, tilt: float,
                    calibration: PanTiltCalibration | None = None) -> tuple[float, float]:
    """Device angles (rad) that put ``pixel`` (seen at device angles pan, tilt) on the optical axis.

    Exact for the kinematics R_y(pan) R_x(tilt) of DESIGN.md §2, through the rig's sign/offset map.
    """
    cal = calibration or PanTiltCalibration()
    kp, kt = cal.kinematic(pan, tilt)
    ray = camera.pixels_to_rays(np.asarray(pixel, dtype=float).reshape(1, 2))[0]
    return cal.reading(*pan_tilt_for_direction(pan_tilt_rotation(kp, kt) @ ray))


def servo_target(camera: CameraModel, profile: CameraProfile, pixel: tuple[float, float],
                 joints: tuple[float, float], params: ServoParams,
                 calibration: PanTiltCalibration | None = None) -> Target | None:
    """The AbsolutePosition command (units, speed codes) that re-centres ``pixel``; None inside the deadband."""
    err = math.hypot(pixel[0] - camera.cx, pixel[1] - camera.cy)
    if err < params.deadband_px:
        return None
    pan, tilt = joints
    want_p, want_t = centring_angles(camera, pixel, pan, tilt, calibration)
    tp = pan + params.gain * (want_p - pan)
    tt = tilt + params.gain * (want_t - tilt)
    pan_u, tilt_u = profile.clamp(profile.pan_units(math.degrees(tp)), profile.tilt_units(math.degrees(tt)))
    dp = abs(math.degrees(tp - pan)) / max(params.move_time_s, 1e-3)
    dt = abs(math.degrees(tt - tilt)) / max(params.move_time_s, 1e-3)
    return Target(pan_u, tilt_u, profile.pan_code_for(dp), profile.tilt_code_for(dt))


class FixationServo:
    """:func:`servo_target` plus feed-forward: when the rig turns, the fixated point's centring angles
    drift; a line fitted to recent (image time, centring angles) gives their rate, and the command leads
    by the image's age plus :attr:`ServoParams.lead_extra_s` plus one command period: the head stops at each
    absolute target and the next one comes a period later, so it must aim where the point will be then.
    (Without the period the point trailed by its rate times about 0.1 s: ``bench.servo`` at 14 deg/s, 34 -> 9 px
    mean; the live demo's arcs, ~28 deg/s, 75 -> 28 px.) Removes the lag error a pure proportional servo has on
    a drifting scene. Call :meth:`reset` when the fixation point changes; a known drift of the new point (a
    vergence step's partner point turns with the right head) seeds the rate until four images have given their
    own (without it the head lagged the partner point by up to 100 px for its first 0.2 s on an arc)."""

    def __init__(self, camera: CameraModel, profile: CameraProfile, params: ServoParams | None = None,
                 calibration: PanTiltCalibration | None = None) -> None:
        self.camera, self.profile = camera, profile
        self.params = params or ServoParams()
        self.calibration = calibration
        self._hist: deque[tuple[float, float, float]] = deque(maxlen=64)
        self.rate = (0.0, 0.0)
        self._seed = (0.0, 0.0)

    def reset(self, rate: tuple[float, float] = (0.0, 0.0)) -> None:
        """Forget the old point's drift; ``rate`` (rad/s of the centring angles) is the new point's, when known."""
        self._hist.clear()
        self.rate = self._seed = (float(rate[0]), float(rate[1]))

    def target(self, pixel: tuple[float, float], joints: tuple[float, float], t_image: float,
               now: float) -> Target | None:
        p, cam, pr = self.params, self.camera, self.profile
        pan, tilt = joints
        want_p, want_t = centring_angles(cam, pixel, pan, tilt, self.calibration)
        self._hist.append((t_image, want_p, want_t))
        while self._hist and t_image - self._hist[0][0] > p.rate_window_s:
            self._hist.popleft()
        rp, rt = self._seed if p.feedforward else (0.0, 0.0)
        if p.feedforward and len(self._hist) >= 4:
            h = np.asarray(self._hist)
            tc = h[:, 0] - h[:, 0].mean()
            den = float(tc @ tc)
            if den > 1e-9:
                rp, rt = float(tc @ (h[:, 1] - h[:, 1].mean()) / den), float(tc @ (h[:, 2] - h[:, 2].mean()) / den)
        self.rate = (rp, rt)
        lead = max(0.0, now - t_image) + p.lead_extra_s + 1.0 / p.max_command_rate_hz
        goal_p, goal_t = want_p + rp * lead, want_t + rt * lead
        err_px = math.hypot(pixel[0] - cam.cx, pixel[1] - cam.cy)
        moving_px = math.hypot(rp * cam.fx, rt * cam.fy) * lead
        if err_px < p.deadband_px and moving_px < p.deadband_px:
            return None
        tp = pan + p.gain * (goal_p - pan)
        tt = tilt + p.gain * (goal_t - tilt)
        pan_u, tilt_u = pr.clamp(pr.pan_units(math.degrees(tp)), pr.tilt_units(math.degrees(tt)))
        dp = abs(math.degrees(tp - pan)) / max(p.move_time_s, 1e-3) + abs(math.degrees(rp))
        dt = abs(math.degrees(tt - tilt)) / max(p.move_time_s, 1e-3) + abs(math.degrees(rt))
        return Target(pan_u, tilt_u, pr.pan_code_for(dp), pr.tilt_code_for(dt))


def _beyond_narrowest(windows: deque[float], window: float) -> float:
    """Record a timing window (s) and return how much wider it is than the narrowest recent one: the narrowest is
    the camera's own delay, the rest how late the host (or a busy camera) was, i.e. how uncertain the time is."""
    windows.append(window)
    return max(0.0, window - min(windows))


class ServoLoop:
    """Owns the serial line of one camera on a thread: timed PosInq readings + rate-limited targets.

    ``clock`` gives the time base of :attr:`history` (the node passes ROS time so readings and image
    stamps compare directly); the driver's monotonic sample times are mapped onto it. Every motion command
    sent (target, speed, the moment the camera took it) goes to :attr:`predictor` too, which uses them to
    tell the joints at an image stamp past the last reading.
    """

    DATING_STEP_S = 5e-4        # a late reading's candidate times (at 80 deg/s a reading unit is 1.4 ms)

    def __init__(self, cam: ViscaCamera, params: ServoParams | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cam = cam
        self.params = params or ServoParams()
        self.clock = clock
        self.history = JointHistory()
        pr = cam.profile
        self.predictor = JointPredictor(self.history, PredictionParams(
            quantum_rad=(math.radians(1.0 / pr.pan_units_per_deg), math.radians(1.0 / pr.tilt_units_per_deg))))
        self._target: Target | None = None
        self._sent: Target | None = None
        self._home = False
        self._lock = threading.Lock()
        self._running = False
        self._thread: threading.Thread | None = None
        self._last_cmd = -math.inf
        self.stats = {'cycles': 0, 'commands': 0, 'errors': 0, 'disconnected_cycles': 0, 'late_readings': 0}
        self.last_error = ''
        self._t_start = 0.0
        self._windows: deque[float] = deque(maxlen=64)     # recent readings' sample windows (s)

    def set_target(self, target: Target | None) -> None:
        with self._lock:
            self._target = target

    def request_home(self) -> None:
        with self._lock:
            self._home = True

    def loop_rate_hz(self) -> float:
        dt = time.monotonic() - self._t_start
        return self.stats['cycles'] / dt if dt > 0 else 0.0

    def start(self) -> None:
        if self._running:
            return
        prompt_serial_threads()
        self._running = True
        self._t_start = time.monotonic()
        self._thread = threading.Thread(target=self._run, name='visca-servo', daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
            self._thread = None

    def _run(self) -> None:
        while self._running:
            t_cycle = time.monotonic()
            try:
                self.step()
            except vp.ViscaDisconnectedError as e:
                self.stats['disconnected_cycles'] += 1
                self.last_error = str(e)
                time.sleep(0.05)
            except vp.ViscaError as e:
                self.stats['errors'] += 1
                self.last_error = f'{type(e).__name__}: {e}'
                time.sleep(0.005)
            wait = self.params.min_inquiry_period_s - (time.monotonic() - t_cycle)
            if wait > 0:
                time.sleep(wait)

    def step(self) -> None:
        """One cycle: read the joints, then send the newest target if due. Public for tests/benchmarks."""
        reading = self.cam.position_timed()
        pan_u, tilt_u = reading.pan, reading.tilt
        pr = self.cam.profile
        self._keep_reading(reading)
        self.stats['cycles'] += 1
        with self._lock:
            home, self._home = self._home, False
            target = self._target
        if home:
            self.cam.home(wait=False)
            self._commanded(0, 0, pr.pan_speed_max, pr.tilt_speed_max)
            self._sent = None
            return
        if target is None or target == self._sent:
            return
        now = time.monotonic()
        if now - self._last_cmd < 1.0 / self.params.max_command_rate_hz:
            return
        if (target.pan, target.tilt) == (pan_u, tilt_u):
            self._sent = target
            return
        self._expect(target)
        sent = False
        try:
            self.cam.absolute(target.pan, target.tilt, target.pan_speed, target.tilt_speed, wait=False)
            sent = True
        except vp.BufferFullError:
            # a camera that does not supersede motions: free the oldest socket and retry next cycle
            busy = sorted(self.cam.busy_sockets)
            if busy:
                try:
                    self.cam.cancel(busy[0])
                except vp.ViscaReplyError:
                    self.cam.if_clear()
            raise
        finally:
            if not sent:
                self.predictor.forget_expected()
        self._commanded(target.pan, target.tilt, target.pan_speed, target.tilt_speed)
        self._last_cmd = now
        self._sent = target
        self.stats['commands'] += 1

    def _keep_reading(self, r: PositionReading) -> None:
        """Add a reading to the joint history at its sample time. The camera sampled it between the inquiry's arrival
        and the start of its reply (:class:`PositionReading`). The narrowest such window of the recent readings is the
        camera's own answering delay, whose share before the sample is unknown; the rest, ``excess``, is how late the
        host read the reply (or a busy camera answered). When that is at most :attr:`ServoParams.reading_window_s`,
        the reading is dated in the middle of its window. Dated at the window's end, as until stop 79 (the delay
        counted as all before the sample), readings were late by a median 0.3 ms against the emulator's own log
        (0.07 ms in the middle), and the joint angles between them lagged by about as much. Wider, the time is
        uncertain by the excess (at 80 deg/s, 8 ms is 0.64 deg): the reading is dated where the head's commanded
        motion since the earlier readings puts its value within the window (:meth:`_date_by_motion`). Before, such
        readings were left out unless none had come for 50 ms and then dated in the middle: on a demo (emulator's log
        against the servo's dates) the forced ones were off by up to 0.46 deg (5.8 ms at 80 deg/s), and every
        prediction from them by as much."""
        excess = _beyond_narrowest(self._windows, r.window_s)
        pr = self.cam.profile
        pan, tilt = pr.pan_rad(r.pan), pr.tilt_rad(r.tilt)
        lo, hi = self._to_clock(r.earliest), self._to_clock(r.latest)
        t = 0.5 * (lo + hi)
        late = excess > self.params.reading_window_s
        if late:
            self.stats['late_readings'] += 1
            t = self._date_by_motion(lo, hi, pan, tilt)
        # a late reading is dated by the motion the predictor expects: checking the prediction against it would
        # measure nothing, so only those dated by their own window calibrate the predictor's sigma
        self.predictor.add_reading(t, pan, tilt, calibrate=not late)

    def _date_by_motion(self, lo: float, hi: float, pan: float, tilt: float) -> float:
        """The time in [lo, hi] at which the predictor's motion (earlier readings, commands) is nearest the reading,
        to within half a reading unit; the middle of those times (the whole interval for a head at rest, whose
        reading fits any time in it; the end nearest to the motion when the head is not where it should be)."""
        qp, qt = self.predictor.params.quantum_rad
        ts = np.linspace(lo, hi, max(2, min(64, int((hi - lo) / self.DATING_STEP_S) + 1)))
        off = []
        for t in ts:
            e = self.predictor.estimate(float(t))
            if e is None:
                return 0.5 * (lo + hi)
            off.append(max(abs(e.pan - pan) / qp, abs(e.tilt - tilt) / qt))
        d = np.asarray(off)
        near = ts[d <= d.min() + 0.5]
        return float(0.5 * (near[0] + near[-1]))

    def _to_clock(self, t_mono: float) -> float:
        """A driver (monotonic) time on :attr:`clock`'s time base (itself when that is the monotonic clock: the offset
        read from two clock calls was a microsecond or more off whenever the thread was preempted between them)."""
        if self.clock is time.monotonic:
            return t_mono
        return t_mono + (self.clock() - time.monotonic())

    def _expect(self, target: Target) -> None:
        """Tell the predictor about a command about to be written: the head takes it when its last byte arrives, the
        packet's serial time from now (its ACK dates it properly, :meth:`_commanded`)."""
        packet = vp.absolute_position(self.cam.address, target.pan_speed, target.tilt_speed, target.pan, target.tilt)
        self.predictor.expect_command(self._to_clock(time.monotonic() + len(packet) * self.cam.byte_time),
                                      *self._in_rad(target.pan, target.tilt, target.pan_speed, target.tilt_speed))

    def _in_rad(self, pan_u: int, tilt_u: int, pan_code: int, tilt_code: int) -> tuple[float, float, float, float]:
        """A command's target (rad) and speed per axis (rad/s), as the predictor takes it."""
        pr = self.cam.profile
        return (pr.pan_rad(pan_u), pr.tilt_rad(tilt_u), math.radians(pr.pan_speed_deg_s(pan_code)),
                math.radians(pr.tilt_speed_deg_s(tilt_code)))

    def _commanded(self, pan_u: int, tilt_u: int, pan_code: int, tilt_code: int) -> None:
        """Tell the predictor about a command just ACKed, dated like the readings: the camera took it between its
        last byte's arrival (the write plus its serial time) and the start of its ACK (3 bytes before the host read
        it). A busy host reads the ACK late, a busy camera takes the command late, and the camera's own delay may lie on
        either side: the command is dated in the middle of the window. Dated at the ACK alone, as before stop 63, a
        command was late by p50 0.5-0.8 ms, p95 7-8 ms, at most 22-25 ms on a demo (270 commands per camera against the
        emulator's own log); in the middle of what the narrowest window seen left (until stop 79), rms 2.6 ms, at most
        13-16 ms, but a median 0.35 ms late on the bare emulator, 0.08 ms in the middle of the whole window (at
        50 deg/s, 1 ms is 0.05 deg)."""
        ack = time.monotonic() - 3 * self.cam.byte_time
        self.predictor.add_command(self._to_clock(0.5 * (ack + min(ack, self.cam.last_arrival))),
                                   *self._in_rad(pan_u, tilt_u, pan_code, tilt_code))
