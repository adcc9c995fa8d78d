"""JointPredictor on synthetic histories: the head runs each commanded axis at its rate straight to its target
(as a VISCA head, and the emulator, do); readings come every 30 ms; predictions past the last reading follow the
commands, stop at a target, turn at a reversal, and carry a 1-sigma that grows with the extrapolation and the rate,
is never NaN and is bounded."""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import pytest

from fixego_ros.tracking.joint_prediction import JointHistory, JointPredictor, PredictionParams

Q = PredictionParams().quantum_rad


def _truth(commands, t: float, start: float = 0.0) -> float:
    """Pan at t of a head starting at ``start`` and obeying ``commands`` [(t, target, rate)]."""
    pos, t_prev, cur = start, None, None
    for tc, target, rate in [*commands, (t, None, None)]:
        tc = min(tc, t)
        if cur is not None:
            step = min(abs(cur[0] - pos), cur[1] * (tc - t_prev))
            pos += math.copysign(step, cur[0] - pos)
        if target is None or tc >= t:
            break
        cur, t_prev = (target, rate), tc
    return pos


def _predictor(commands, t_readings, start: float = 0.0) -> JointPredictor:
    jp = JointPredictor()
    for tc, target, rate in commands:
        jp.add_command(tc, target, 0.0, rate, 0.0)
    for t in t_readings:
        jp.add_reading(t, _truth(commands, t, start), 0.0)
    return jp


def test_constant_rate_is_followed_past_the_last_reading():
    cmds = [(0.0, 1.0, 0.5)]
    jp = _predictor(cmds, np.arange(0.0, 0.301, 0.03))
    for dt in (0.005, 0.02, 0.05):
        e = jp.estimate(0.3 + dt)
        assert e.source == 'predicted' and e.horizon_s == pytest.approx(dt)
        assert e.pan == pytest.approx(_truth(cmds, 0.3 + dt), abs=1e-12) and e.tilt == 0.0
    # holding the last reading (what a waitless node without commands would do) is 10 mrad off at 20 ms
    assert abs(jp.estimate(0.32).pan - jp.history.latest()[1]) == pytest.approx(0.01)


def test_a_stop_at_the_target_is_predicted():
    cmds = [(0.0, 0.2, 1.0)]
    jp = _predictor(cmds, np.arange(0.0, 0.181, 0.03))      # last reading 0.18 rad at 0.18 s, still moving
    e = jp.estimate(0.26)
    assert e.pan == pytest.approx(0.2, abs=1e-12)            # not 0.26: the head stops on its target
    # the uncertainty counts only the 0.02 rad still travelled, not 80 ms at 1 rad/s
    assert e.pan_sigma < 0.2 * 0.02 + 0.01


def test_a_reversal_commanded_after_the_last_reading_is_predicted():
    cmds = [(0.0, 1.0, 0.5), (0.31, -1.0, 0.8)]
    jp = _predictor(cmds, np.arange(0.0, 0.301, 0.03))
    e = jp.estimate(0.36)
    assert e.pan == pytest.approx(0.15 + 0.005 - 0.04, abs=1e-12)
    assert e.pan == pytest.approx(_truth(cmds, 0.36), abs=1e-12)
    # a command that reached the head before the last reading is already in that reading
    jp.add_reading(0.33, _truth(cmds, 0.33), 0.0)
    assert jp.estimate(0.36).pan == pytest.approx(_truth(cmds, 0.36), abs=1e-12)


def test_uncertainty_grows_with_extrapolation_and_commanded_rate():
    slow = _predictor([(0.0, 1.0, 0.2)], np.arange(0.0, 0.301, 0.03))
    fast = _predictor([(0.0, 1.0, 0.8)], np.arange(0.0, 0.301, 0.03))
    sig = [slow.estimate(0.3 + dt).pan_sigma for dt in (0.0, 0.01, 0.03, 0.06, 0.09)]
    assert all(b > a for a, b in itertools.pairwise(sig)), sig
    for dt in (0.01, 0.05):
        assert fast.estimate(0.3 + dt).pan_sigma > slow.estimate(0.3 + dt).pan_sigma
    # the axis that does not move keeps the reading's quantisation only
    assert fast.estimate(0.35).tilt_sigma == pytest.approx(Q[1] / math.sqrt(12))
    # interpolation between two readings is as good as a reading
    assert fast.estimate(0.285).source == 'interpolated'
    assert fast.estimate(0.285).pan_sigma == pytest.approx(Q[0] / math.sqrt(12))


def test_at_rest_without_commands_the_last_reading_holds_exactly_enough():
    jp = JointPredictor()
    for t in np.arange(0.0, 0.3, 0.03):
        jp.add_reading(t, 0.1, -0.05)
    e = jp.estimate(0.35)
    assert (e.pan, e.tilt) == (0.1, -0.05) and e.pan_sigma == pytest.approx(Q[0] / math.sqrt(12))
    # moved by someone else (no command known): the readings' rate, with a 100 % rate uncertainty
    jp2 = JointPredictor()
    for t in np.arange(0.0, 0.3, 0.03):
        jp2.add_reading(t, 0.3 * t, 0.0)
    e = jp2.estimate(0.29)
    assert e.pan == pytest.approx(0.3 * 0.29) and e.pan_sigma > 0.3 * 0.02


def test_later_reading_turns_a_prediction_into_interpolation():
    cmds = [(0.0, 1.0, 0.5)]
    jp = _predictor(cmds, np.arange(0.0, 0.301, 0.03))
    assert jp.estimate(0.31).source == 'predicted'
    jp.add_reading(0.33, _truth(cmds, 0.33), 0.0)
    e = jp.estimate(0.31)
    assert e.source == 'interpolated' and (e.pan, e.tilt) == pytest.approx(jp.history.at(0.31, 0.0))


def test_never_nan_and_bounded_without_readings():
    jp = JointPredictor(params=PredictionParams(max_horizon_s=0.1))
    jp.add_command(0.0, 1.0, 1.0, 0.5, 0.5)
    assert jp.estimate(0.1) is None                       # no reading ever: nothing to start from
    jp.add_command(0.01, math.nan, 0.0, 0.5, 0.5)         # ignored
    jp.add_command(-1.0, 0.0, 0.0, 0.5, 0.5)              # out of order: ignored
    assert len(jp.commands()) == 1
    jp.add_reading(0.05, 0.0, 0.0)
    assert jp.estimate(math.nan) is None and jp.estimate(math.inf) is None
    assert jp.estimate(0.2) is None                       # past the horizon: the caller waits instead
    assert jp.estimate(0.01) is None                      # before the first reading
    rng = np.random.default_rng(4)
    for _ in range(200):
        jp = JointPredictor(params=PredictionParams(max_rate_rad_s=1.0, max_horizon_s=0.1))
        t = 0.0
        for _ in range(rng.integers(1, 8)):
            t += rng.uniform(0.0, 0.05)
            if rng.random() < 0.5:
                jp.add_command(t, rng.uniform(-3, 3), rng.uniform(-1, 1), rng.uniform(0, 1), rng.uniform(0, 1))
            else:
                jp.add_reading(t, rng.uniform(-3, 3), rng.uniform(-1, 1))
        for tq in np.linspace(0.0, t + 0.15, 17):
            e = jp.estimate(float(tq))
            if e is None:
                continue
            vals = np.array([e.pan, e.tilt, e.pan_sigma, e.tilt_sigma])
            assert np.all(np.isfinite(vals)) and e.pan_sigma >= 0 and e.tilt_sigma >= 0
            if e.source == 'predicted':     # at most the top speed (1 rad/s) from the last reading; sigma bounded
                last = jp.history.latest()
                assert abs(e.pan - last[1]) <= e.horizon_s + 1e-9 and abs(e.tilt - last[2]) <= e.horizon_s + 1e-9
                assert max(e.pan_sigma, e.tilt_sigma) <= 0.003 + 0.1 + Q[0]


def test_history_bracket_and_before():
    h = JointHistory()
    for t, p in ((1.0, 0.1), (2.0, 0.2), (3.0, 0.3)):
        h.add(t, p, -p)
    assert h.bracket(0.5) is None and h.bracket(3.5) is None
    assert h.bracket(2.0) == ((2.0, 0.2, -0.2), (2.0, 0.2, -0.2))
    assert h.bracket(2.5) == ((2.0, 0.2, -0.2), (3.0, 0.3, -0.3))
    assert h.before(2.0) == (1.0, 0.1, -0.1) and h.before(1.0) is None


def test_history_rate_over_the_latest_window_or_what_there_is():
    h = JointHistory()
    assert h.rate(0.2) is None
    for k in range(31):             # 30 Hz readings, pan at 0.4 rad/s, tilt at -0.1 rad/s
        h.add(k / 30.0, 0.4 * k / 30.0, -0.1 * k / 30.0)
        if k == 1:
            assert h.rate(0.2) is None          # 33 ms of readings: under min_span_s
        if k == 3:                              # 0.1 s of readings: the rate over what there is
            t, rp, rt = h.rate(0.2)
            assert t == 0.1 and rp == pytest.approx(0.4) and rt == pytest.approx(-0.1)
    t, rp, rt = h.rate(0.2)
    assert t == 1.0 and rp == pytest.approx(0.4) and rt == pytest.approx(-0.1)
    h.add(1.1, 0.4 + 0.1, -0.1)     # a faster last 0.1 s counts only within the window
    assert h.rate(0.1)[1] == pytest.approx(1.0) and 0.5 < h.rate(0.2)[1] < 0.9


def test_interpolation_follows_a_command_that_arrives_between_two_readings():
    """A straight line between readings cuts the commanded path's corners: the head rests, gets a command and runs,
    or reaches its target and stops, between two readings. The commanded path is replayed instead, and what it
    misses at the second reading is spread over the interval."""
    cmds = [(0.01, 1.0, 2.0), (0.1, 0.12, 3.0)]       # runs at 2 rad/s from 0.01 s, then stops at 0.12 rad
    jp = _predictor(cmds, [0.0, 0.03, 0.06, 0.09, 0.12])
    line = jp.history
    for t in np.arange(0.0, 0.12, 0.0025):
        e = jp.estimate(float(t))
        assert e.source == 'interpolated'
        assert e.pan == pytest.approx(_truth(cmds, t), abs=1e-12), t
    # the straight line is 10 mrad off just after the start, and 20 mrad where the head stopped
    assert abs(line.at(0.01, 0.0)[0] - _truth(cmds, 0.01)) == pytest.approx(0.04 / 3, abs=1e-9)
    assert abs(line.at(0.1, 0.0)[0] - _truth(cmds, 0.1)) > 0.01
    # a head slower than commanded: the replay overshoots the second reading; the miss is spread and counted
    slow = JointPredictor()
    slow.add_command(0.0, 1.0, 0.0, 2.0, 0.0)
    slow.add_reading(0.0, 0.0, 0.0)
    slow.add_reading(0.03, 0.05, 0.0)                 # 0.06 commanded
    e = slow.estimate(0.015)
    assert e.pan == pytest.approx(0.025) and e.pan_sigma > 0.0025
    # no command known (moved by hand): the straight line
    hand = JointPredictor()
    hand.add_reading(0.0, 0.0, 0.0)
    hand.add_reading(0.03, 0.03, 0.0)
    assert hand.estimate(0.01).pan == pytest.approx(0.01)


class _Camera:
    """Just what ServoLoop.step reads: PositionReadings from a list, the EVI-D30 profile."""

    def __init__(self, readings) -> None:
        from fixego_ros.visca.profiles import PROFILES
        self.profile = PROFILES['evi_d30']
        self.byte_time = 10 / 9600
        self.readings = list(readings)

    def position_timed(self):
        return self.readings.pop(0)


def test_a_reading_the_host_took_late_is_dated_by_the_commanded_motion():
    """A reading was sampled somewhere in its window; the narrowest window is the camera's own delay, on either side
    of the sample. Within reading_window_s of the narrowest a reading is dated in the middle of its window; wider
    (the host read the reply late), where the commanded motion puts its value in it; a head at rest fits any time
    there, and gets the middle."""
    from fixego_ros.tracking.servo import ServoLoop, ServoParams
    from fixego_ros.visca.driver import PositionReading
    base = 1000.0
    cam = _Camera([])
    units_s = 80.0 * cam.profile.pan_units_per_deg          # the head at 80 deg/s from base on (commanded)
    # sample time, window: on time (the narrowest: the camera's 1 ms, half before the sample), then read 11 ms and
    # 21 ms late
    spec = [(0.0110, 0.0010), (0.0410, 0.0120), (0.0800, 0.0220)]
    cam.readings = [PositionReading(round(units_s * ts), 0, base + ts - 0.0005, base + ts - 0.0005 + w)
                    for ts, w in spec]
    loop = ServoLoop(cam, ServoParams(reading_window_s=0.003), clock=time.monotonic)
    loop.predictor.add_command(base, math.radians(90.0), 0.0, math.radians(80.0), 0.0)
    for _ in spec:
        loop.step()
    ts = [t - base for t in loop.history._t]        # the loop's clock is the driver's (monotonic)
    assert len(ts) == 3 and loop.stats['late_readings'] == 2
    assert loop.predictor.calibration.samples == 0      # dated by the motion: no check of the motion's prediction
    assert ts[0] == pytest.approx(0.011, abs=1e-6)              # on time: the middle of its (narrowest) window
    for dated, (true, w) in zip(ts[1:], spec[1:], strict=True):
        assert abs(dated - true) < 0.0015                       # the middle would be off by ~(w - 1 ms) / 2
        assert abs(dated - (true - 0.0005 + 0.5 * w)) > 0.004   # where the middle of the window is
    # a head at rest: every time in the window fits its reading, and the middle is taken
    rest = _Camera([PositionReading(5, 0, base + 0.0, base + 0.001), PositionReading(5, 0, base + 0.03, base + 0.041)])
    still = ServoLoop(rest, ServoParams(reading_window_s=0.003), clock=time.monotonic)
    still.step()
    still.step()
    assert still.history._t[-1] - base == pytest.approx(0.5 * (0.03 + 0.041), abs=1e-6)


def test_a_command_is_dated_in_the_middle_of_its_window(monkeypatch):
    """The camera took a command between its last byte's arrival (write + serial time) and the start of its ACK: on
    time, its own delay lies on either side of it; a wider window means the ACK was read late (or the camera was
    slow). Either way the command is dated in the middle of the window rather than at the (late) ACK."""
    from fixego_ros.tracking import servo as servo_mod
    from fixego_ros.tracking.servo import ServoLoop
    cam = _Camera([])
    byte = cam.byte_time
    now = [0.0]
    monkeypatch.setattr(servo_mod.time, 'monotonic', lambda: now[0])
    loop = ServoLoop(cam, clock=lambda: now[0])
    for arrival, ack_start in ((10.0, 10.0004), (11.0, 11.0104)):     # answered at once; then read 10 ms late
        cam.last_arrival = arrival
        now[0] = ack_start + 3 * byte
        loop._commanded(100, 0, 10, 10)
    first, second = loop.predictor.commands()
    assert first.t == pytest.approx(10.0002, abs=1e-9)
    assert second.t == pytest.approx(11.0052, abs=1e-9)
    assert second.pan == pytest.approx(math.radians(100 / cam.profile.pan_units_per_deg))


def test_a_move_dated_near_the_stamp_makes_the_reading_uncertain():
    """A command is dated to within ``timing_s``: a head told to move 2 ms after the stamp may have left already (on
    a demo such frames were 2-6 mrad off at the reading's 0.57 mrad). Further away, or on an axis already at its
    target, the reading holds as before."""
    p = PredictionParams()
    rate = math.radians(80.0)
    jp = _predictor([(0.302, 1.0, rate)], np.arange(0.0, 0.301, 0.03))    # at rest at 0 until 0.302
    e = jp.estimate(0.3005)
    assert e.source == 'predicted' and e.pan == 0.0
    assert e.pan_sigma == pytest.approx(math.hypot(Q[0] / math.sqrt(12), rate * p.timing_s))
    assert e.tilt_sigma == pytest.approx(Q[1] / math.sqrt(12))              # tilt is told to stay where it is
    far = _predictor([(0.302 + 4 * p.timing_s, 1.0, rate)], np.arange(0.0, 0.301, 0.03)).estimate(0.3005)
    assert far.pan == 0.0 and far.pan_sigma == pytest.approx(Q[0] / math.sqrt(12))
    # between two readings: the same for a stamp just before the dated start
    cmds = [(0.2495, 1.0, rate)]
    jp = _predictor(cmds, np.arange(0.0, 0.301, 0.03))
    e = jp.estimate(0.248)
    assert e.source == 'interpolated' and e.pan_sigma >= rate * p.timing_s
    assert jp.estimate(0.21).pan_sigma == 0.0                                   # at rest: read exactly


def test_a_command_being_written_counts_before_its_ack_dates_it():
    """The head takes a command when its last byte arrives; the ACK that dates it is read later. In between, an
    estimate replays the expected command (the head has started), the ACK-dated one replaces it, and a write that
    failed leaves nothing behind."""
    rate = math.radians(80.0)
    jp = _predictor([], np.arange(0.0, 0.301, 0.03))             # at rest at 0
    jp.expect_command(0.3, 1.0, 0.0, rate, 0.0)
    e = jp.estimate(0.32)
    assert e.pan == pytest.approx(0.02 * rate) and e.pan_sigma >= rate * PredictionParams().timing_s
    jp.add_command(0.305, 1.0, 0.0, rate, 0.0)                   # the ACK: dated 5 ms later
    assert jp.estimate(0.32).pan == pytest.approx(0.015 * rate) and len(jp.commands()) == 1
    jp2 = _predictor([], np.arange(0.0, 0.301, 0.03))
    jp2.expect_command(0.3, 1.0, 0.0, rate, 0.0)
    jp2.forget_expected()
    assert jp2.estimate(0.32).pan == 0.0 and jp2.commands() == []
    jp2.expect_command(math.nan, 1.0, 0.0, rate, 0.0)             # ignored
    assert jp2.commands() == []


def _calibrated(speed_factor: float, timing_noise_s: float = 0.0, n: int = 120, calibrate: bool = True,
                seed: int = 0) -> JointPredictor:
    """A head commanded back and forth at 0.7 rad/s that really runs at ``speed_factor`` times that, read every 30 ms
    (quantised like a VISCA head, each reading dated ``timing_noise_s`` rms off), each reading checked against the
    prediction before it joins (``add_reading(calibrate=...)``)."""
    rng = np.random.default_rng(seed)
    jp, rate, pos = JointPredictor(), 0.7, 0.0
    target = 0.3
    jp.add_command(0.0, target, 0.0, rate, 0.0)
    t_prev = 0.0
    for k in range(1, n + 1):
        t = 0.03 * k
        step = min(abs(target - pos), speed_factor * rate * (t - t_prev))
        pos += math.copysign(step, target - pos)
        t_prev = t
        if pos == target:                   # at the target: turn back (a new command at the reading)
            target = -target
            jp.add_command(t, target, 0.0, rate, 0.0)
        reading = round(pos / Q[0]) * Q[0]
        jp.add_reading(t + rng.normal(0.0, timing_noise_s) if timing_noise_s else t, reading, 0.0, calibrate=calibrate)
    return jp


def _model_only(jp: JointPredictor) -> JointPredictor:
    """A predictor on the same readings and commands that never calibrated: the model's sigma as it is."""
    other = JointPredictor(jp.history)
    for c in jp.commands():
        other.add_command(c.t, c.pan, c.tilt, c.pan_rate, c.tilt_rate)
    return other


def test_sigma_calibration_keeps_the_model_for_a_head_that_keeps_its_table_speed():
    # predicted far better than the model says (its 15 % speed error is a real head's): measured, not applied
    jp = _calibrated(1.0, timing_noise_s=0.0005)
    cal = jp.calibration
    assert cal.samples >= cal.min_samples and cal.measured < 0.6 and cal.scale == 1.0
    t = jp.history.latest()[0] + 0.02
    assert jp.estimate(t) == _model_only(jp).estimate(t)


def test_sigma_calibration_grows_the_sigma_of_a_head_slower_than_its_table():
    # 40 % slow: the model's 15 % speed error understates it, and the predicted sigmas take the measured scale
    jp = _calibrated(0.6)
    cal = jp.calibration
    assert cal.measured > 1.5 and cal.scale == pytest.approx(min(cal.measured, cal.max_scale))
    t = jp.history.latest()[0] + 0.02
    e, e0 = jp.estimate(t), _model_only(jp).estimate(t)
    assert e.source == 'predicted' and e.pan == e0.pan and e.pan_sigma == pytest.approx(cal.scale * e0.pan_sigma)


def test_sigma_calibration_needs_samples_and_the_callers_consent():
    few = _calibrated(0.6, n=5).calibration                         # too few samples: the model as it is
    assert 0 < few.samples < few.min_samples and few.measured == 1.0 and few.scale == 1.0
    uncalibrated = _calibrated(0.6, calibrate=False).calibration   # late readings (dated by the motion) say nothing
    assert uncalibrated.samples == 0 and uncalibrated.scale == 1.0


def _quantised_run(rate: float, anchor_window_s: float, reading_period: float = 0.03, seconds: float = 1.2,
                   outlier: int | None = None) -> tuple[JointPredictor, list[float]]:
    """A head commanded once at ``rate`` (rad/s) towards a far target, read every ``reading_period`` and rounded to
    the pan unit as a VISCA head reports it; reading number ``outlier`` (if given) is 5 units off. Returns the
    predictor and its pan error 15 ms past each reading (the prediction an image between readings gets)."""
    jp = JointPredictor(params=PredictionParams(anchor_window_s=anchor_window_s))
    cmds = [(0.0, 2.0, rate)]
    jp.add_command(0.0, 2.0, 0.0, rate, 0.0)
    errors = []
    for k, t in enumerate(np.arange(0.013, seconds, reading_period)):
        reading = round(_truth(cmds, t) / Q[0]) * Q[0] + (5 * Q[0] if k == outlier else 0.0)
        jp.add_reading(float(t), reading, 0.0)
        if k >= 10:        # once the window has readings
            errors.append(jp.estimate(float(t) + 0.015).pan - _truth(cmds, float(t) + 0.015))
    return jp, errors


def test_the_readings_before_the_last_place_it_within_its_unit():
    """A moving head's readings each round the angle to a unit; carried along the commanded motion to the last one's
    time they say where in its unit the head was, to within the model's timing and speed errors. Without them
    (``anchor_window_s`` 0) the prediction's error is the rounding's (~unit / sqrt 12 RMS). At 5 deg/s (a pursuit)
    those errors are a quarter of a unit and the error falls to less than half; at 20 deg/s they are about a unit
    (3 ms at that rate, and 15 % of the way carried) and it falls less, but it falls."""
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    for deg_s, gain in ((5.0, 0.5), (20.0, 0.9)):
        rate = math.radians(deg_s)
        _, alone = _quantised_run(rate, 0.0)
        _, anchored = _quantised_run(rate, 0.3)
        assert 0.2 * Q[0] < rms(alone) < 0.4 * Q[0], rms(alone)
        assert rms(anchored) < gain * rms(alone), (deg_s, rms(anchored), rms(alone))


def test_the_anchor_stays_in_the_last_readings_unit_and_changes_nothing_at_rest():
    """A reading 5 units off (a host that dated it badly) cannot move the prediction beyond the last reading's own
    unit; a head at rest, or one moved by nobody's command, keeps its last reading exactly."""
    rate = math.radians(10.0)
    _, alone = _quantised_run(rate, 0.0, outlier=20)
    _, anchored = _quantised_run(rate, 0.3, outlier=20)
    moved = np.abs(np.subtract(anchored, alone))
    assert moved.max() <= 0.5 * Q[0] + 1e-12 and moved[9:20].max() > 0.2 * Q[0]     # and it does move them
    at_rest = JointPredictor()
    at_rest.add_command(0.0, 0.3, 0.1, 1.0, 1.0)
    for t in np.arange(1.0, 1.5, 0.03):
        at_rest.add_reading(float(t), 0.3, 0.1)
    e = at_rest.estimate(1.5)
    assert (e.pan, e.tilt) == (0.3, 0.1)
    passive = JointPredictor()
    for t in np.arange(0.0, 0.3, 0.03):
        passive.add_reading(float(t), round(0.2 * t / Q[0]) * Q[0], 0.0)
    last = passive.history.latest()
    prev = passive.history.before(last[0])
    rate_seen = (last[1] - prev[1]) / (last[0] - prev[0])
    assert passive.estimate(last[0] + 0.01).pan == pytest.approx(last[1] + rate_seen * 0.01, abs=1e-15)
