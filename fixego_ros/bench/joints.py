"""Benchmark: joint angles at an image stamp predicted at once vs waited for (ROS-free).

The servo loop drives an emulated EVI-D30 at real 9600-baud timing through saccade-like moves (a new far target
at a high speed every 0.3-0.7 s) and pursuit-like ones (a small step every ~70 ms, as the fixation servo sends).
Images come at 30 Hz; for each, as camera_node does in ``joint_mode`` predict, the
:class:`~fixego_ros.tracking.joint_prediction.JointPredictor` answers at once with what the loop knows then; in
wait mode the node waits for the reading after the stamp and interpolates. Prints and returns the error of each
against the emulator's true angles at the stamp (deg, the worse axis: p50/p95/max), that of holding the last
reading (no prediction), how often the prediction stayed within 2 sigma, and the wait it saves (ms). Also how the
servo dates what the camera did against the emulator's own log: each reading's time minus the moment the emulator
sampled the head for it, each command's minus the moment the head took it (ms, p50/p95), and the lag of the angles
between readings (``wait`` mode) fitted along the motion (ms; positive = late) - a bias there is common to every
frame of a vergence step and does not average (docs/results.md "Stop 79").

    python -m fixego_ros.bench.joints
"""

from __future__ import annotations

import json
import math
import time
from collections import deque

import numpy as np

from fixego_ros.tracking.joint_prediction import JointSource
from fixego_ros.tracking.servo import ServoLoop, ServoParams, Target
from fixego_ros.visca import protocol as vp
from fixego_ros.visca.driver import ViscaCamera
from fixego_ros.visca.emulator import ViscaEmulator


def _stats(prefix: str, values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    if not len(a):
        return {f'{prefix}_p50': math.nan, f'{prefix}_p95': math.nan, f'{prefix}_max': math.nan}
    return {f'{prefix}_p50': round(float(np.median(a)), 4), f'{prefix}_p95': round(float(np.percentile(a, 95)), 4),
            f'{prefix}_max': round(float(a.max()), 4)}


def _dating_ms(dated: list[float], true: list[float]) -> list[float]:
    """Each dated time minus the nearest true one (ms), for those within 5 ms of one (the emulator's log starts
    later than the servo's history when the run is long)."""
    if not true:
        return []
    t = np.sort(np.asarray(true, dtype=float))
    out = []
    for d in dated:
        i = int(np.clip(np.searchsorted(t, d), 1, len(t) - 1))
        near = t[i - 1] if abs(d - t[i - 1]) <= abs(d - t[i]) else t[i]
        if abs(d - near) < 0.005:
            out.append(1e3 * (d - near))
    return out


def _lag_ms(errors: list[float], rates: list[float]) -> float:
    """The time shift (ms) that best explains angle errors by the head's rates: least squares of e = -lag * rate."""
    e, v = np.asarray(errors, dtype=float), np.asarray(rates, dtype=float)
    return round(float(-1e3 * (e @ v) / (v @ v)), 3) if len(v) and v @ v > 0 else math.nan


def run_moves(duration_s: float = 8.0, baud: int = 9600, fps: float = 30.0, seed: int = 0,
              verbose: bool = False) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    emu = ViscaEmulator('evi_d30', baud=baud)
    emu.log = deque(maxlen=1_000_000)      # every packet of the run, to date the servo's readings and commands by
    port = emu.start()
    driver = ViscaCamera(port, baud=baud).open()
    pr = driver.profile
    loop = ServoLoop(driver, ServoParams())
    pred = loop.predictor
    frames: list[dict] = []          # per image: stamp, truth, prediction at arrival, when the wait ended
    loop.start()
    t0 = time.monotonic()
    next_frame, next_move, phase = t0 + 0.3, t0 + 0.3, 'saccade'
    pursuit = (0.0, 0.0)
    try:
        while (now := time.monotonic()) - t0 < duration_s:
            if now >= next_move:
                el = now - t0
                phase = 'saccade' if int(el / 2.0) % 2 == 0 else 'pursuit'     # 2 s of each in turn
                if phase == 'saccade':
                    pan, tilt = rng.uniform(-40, 40), rng.uniform(-15, 15)
                    speed = rng.uniform(15, 75)
                    next_move = now + rng.uniform(0.3, 0.7)
                    target = Target(pr.pan_units(pan), pr.tilt_units(tilt), pr.pan_code_for(speed),
                                    pr.tilt_code_for(speed * 0.6))
                else:                   # follow a point drifting at ~10 deg/s, small steps like the servo's
                    pursuit = (20 * math.sin(el * 0.5), 8 * math.sin(el * 0.7))
                    next_move = now + 1 / 15
                    target = Target(pr.pan_units(pursuit[0]), pr.tilt_units(pursuit[1]), pr.pan_code_for(12.0),
                                    pr.tilt_code_for(6.0))
                loop.set_target(target)
            if now >= next_frame:
                next_frame += 1 / fps
                t_img = now
                pan, tilt = emu.pan_tilt_rad(t_img)
                # what camera_node would publish when the image arrives (a few ms later: DDS)
                time.sleep(0.002)
                est = pred.estimate(t_img)
                frames.append({'t': t_img, 'truth': (pan, tilt), 'est': est, 'waited': None, 'phase': phase})
            latest = loop.history.latest()
            for f in frames[-4:]:
                if f['waited'] is None and latest is not None and latest[0] >= f['t']:
                    f['waited'] = time.monotonic() - f['t']
            time.sleep(0.001)
        time.sleep(0.1)                 # a reading after the last frame
    finally:
        loop.stop()
        driver.close()
        emu.stop()
    hist = loop.history
    # each frame's true pan rate, from its neighbours
    rates = [(b['truth'][0] - a['truth'][0]) / (b['t'] - a['t']) for a, b in zip(frames[:-2], frames[2:], strict=True)]
    err_pred, err_wait, err_hold, err_line, waits, within, horizons = [], [], [], [], [], [], []
    predicted = 0
    for f in frames:
        tp, tt = f['truth']
        e = f['est']
        # wait mode: what the node publishes once the reading after the stamp is in (the commanded path between
        # the readings), and the straight line between them for comparison
        w = pred.estimate(f['t'])
        line = hist.at(f['t'], max_extrapolation_s=0.0)
        if e is None or w is None or w.source is not JointSource.INTERPOLATED or line is None:
            continue
        err_line.append(math.degrees(max(abs(line[0] - tp), abs(line[1] - tt))))
        err_pred.append(math.degrees(max(abs(e.pan - tp), abs(e.tilt - tt))))
        err_wait.append(math.degrees(max(abs(w.pan - tp), abs(w.tilt - tt))))
        if e.source is JointSource.PREDICTED:
            predicted += 1
            horizons.append(1e3 * e.horizon_s)
            last = hist.before(f['t'] + 1e-9)
            err_hold.append(math.degrees(max(abs(last[1] - tp), abs(last[2] - tt))))
            within.append(abs(e.pan - tp) <= 2 * e.pan_sigma + 1e-12 and abs(e.tilt - tt) <= 2 * e.tilt_sigma + 1e-12)
        else:
            err_hold.append(err_pred[-1])
        if f['waited'] is not None:
            waits.append(1e3 * f['waited'])
    out: dict[str, float] = {'frames': float(len(err_pred)),
                             'predicted_fraction': round(predicted / max(1, len(err_pred)), 3),
                             'predict_within_2sigma': round(float(np.mean(within)) if within else math.nan, 3)}
    out.update(_stats('predict_err_deg', err_pred))
    out.update(_stats('wait_err_deg', err_wait))
    out.update(_stats('hold_err_deg', err_hold))
    out.update(_stats('line_err_deg', err_line))
    out.update(_stats('wait_saved_ms', waits))
    out.update(_stats('horizon_ms', horizons))
    inquiry = vp.pan_tilt_pos_inquiry(driver.address)
    sampled = [t for t, way, pkt in emu.log if way == 'rx' and pkt == inquiry]
    taken = [t for t, way, pkt in emu.log if way == 'rx' and pkt[1:4] == b'\x01\x06\x02']   # AbsolutePosition
    out.update(_stats('reading_dated_late_ms', _dating_ms(hist.times(), sampled)))
    out.update(_stats('command_dated_late_ms', _dating_ms([c.t for c in pred.commands()], taken)))
    lag_err, lag_rate = [], []
    for f, rate in zip(frames[1:-1], rates, strict=True):
        w = pred.estimate(f['t'])
        if abs(rate) > math.radians(5.0) and w is not None and w.source is JointSource.INTERPOLATED:
            lag_err.append(w.pan - f['truth'][0])
            lag_rate.append(rate)
    out['wait_lag_ms'] = _lag_ms(lag_err, lag_rate)
    out['commands'] = float(len(pred.commands()))
    out['servo_loop_hz'] = round(loop.stats['cycles'] / duration_s, 2)
    if verbose:
        print(json.dumps(out, indent=2))
    return out


def run() -> dict[str, float]:
    """Benchmark entry point: 8 s of saccades and pursuit at 9600 baud, 30 Hz images."""
    return run_moves(verbose=True)


if __name__ == '__main__':
    run()
