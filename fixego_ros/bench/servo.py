"""Benchmark of the fixation servo over an emulated EVI-D30 at real 9600-baud timing (ROS-free).

A synthetic scene drifts as if the rig were turning; the tracker + servo keep their fixation point at
the image centre. Prints and returns the servo loop rate (PosInq cycles/s), the command rate, and the
fixation error in pixels (distance of the *true* fixated scene point from the principal point, after
the initial convergence).

    python -m fixego_ros.bench.servo
"""

from __future__ import annotations

import json
import math
import time

import cv2
import numpy as np

from fixego_ros.geometry.rig import CameraModel, default_rig_path, load_rig
from fixego_ros.tracking.fixation import FixationParams, FixationTracker
from fixego_ros.tracking.servo import FixationServo, ServoLoop, ServoParams
from fixego_ros.visca.driver import ViscaCamera
from fixego_ros.visca.emulator import ViscaEmulator


class SyntheticView:
    """What a pan/tilt camera sees of a far textured scene (small-angle model: pure image translation).

    A scene point has coordinates (X, Y) = (u - cx + fx*pan - ox, v - cy - fy*tilt - oy), where
    (ox, oy) is the scene's drift in pixels (the rig turning). Positive pan moves the view right.
    """

    def __init__(self, camera: CameraModel, seed: int = 1, margin_px: int = 400) -> None:
        self.camera = camera
        rng = np.random.default_rng(seed)
        h, w = camera.height + 2 * margin_px, camera.width + 2 * margin_px
        tex = rng.uniform(0, 255, size=(h // 4, w // 4)).astype(np.float32)
        tex = cv2.resize(tex, (w, h), interpolation=cv2.INTER_CUBIC)
        self.texture = cv2.GaussianBlur(tex, (0, 0), 1.5)
        self.margin = margin_px

    def shift(self, pan: float, tilt: float, ox: float = 0.0, oy: float = 0.0) -> tuple[float, float]:
        c = self.camera
        return c.fx * pan - ox, -c.fy * tilt - oy

    def render(self, pan: float, tilt: float, ox: float = 0.0, oy: float = 0.0) -> np.ndarray:
        sx, sy = self.shift(pan, tilt, ox, oy)
        m = np.array([[1.0, 0.0, -(sx + self.margin)], [0.0, 1.0, -(sy + self.margin)]])
        # out(u, v) = texture(u + sx + margin, v + sy + margin)
        img = cv2.warpAffine(self.texture, m, (self.camera.width, self.camera.height),
                             flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP * 0, borderMode=cv2.BORDER_REFLECT)
        return np.clip(img, 0, 255).astype(np.uint8)

    def scene_point(self, pixel: tuple[float, float], pan: float, tilt: float, ox: float = 0.0,
                    oy: float = 0.0) -> np.ndarray:
        sx, sy = self.shift(pan, tilt, ox, oy)
        return np.array([pixel[0] + sx, pixel[1] + sy])

    def pixel_of(self, scene: np.ndarray, pan: float, tilt: float, ox: float = 0.0,
                 oy: float = 0.0) -> np.ndarray:
        sx, sy = self.shift(pan, tilt, ox, oy)
        return np.array([scene[0] - sx, scene[1] - sy])


def run_closed_loop(duration_s: float = 6.0, baud: int = 9600, fps: float = 30.0,
                    drift_px_s: tuple[float, float] = (40.0, -15.0), settle_s: float = 1.5,
                    camera: CameraModel | None = None, start_offset_px: tuple[float, float] = (0.0, 0.0),
                    feedforward: bool = True, verbose: bool = False) -> dict[str, float]:
    """Closed loop tracker + servo + emulator; returns metrics (see module docstring)."""
    cam_model = camera or CameraModel(320, 240, 500.0, 500.0, 159.5, 119.5)
    view = SyntheticView(cam_model)
    tracker = FixationTracker(cam_model, FixationParams(search_radius_px=30.0, border_margin_px=25.0))
    sparams = ServoParams(feedforward=feedforward)
    emu = ViscaEmulator('evi_d30', baud=baud)
    port = emu.start()
    driver = ViscaCamera(port, baud=baud).open()
    loop = ServoLoop(driver, sparams)
    servo = FixationServo(cam_model, driver.profile, sparams)
    loop.start()
    errors: list[float] = []
    truth: list[tuple[float, float, float]] = []
    frames = reselections = 0
    scene = None
    fid = -1
    t0 = time.monotonic()
    try:
        next_frame = t0
        while True:
            now = time.monotonic()
            if now - t0 > duration_s:
                break
            if now < next_frame:
                time.sleep(next_frame - now)
                continue
            next_frame += 1.0 / fps
            t_img = time.monotonic()
            el = t_img - t0
            ox = start_offset_px[0] + drift_px_s[0] * el
            oy = start_offset_px[1] + drift_px_s[1] * el
            pan, tilt = emu.pan_tilt_rad(t_img)
            img = view.render(pan, tilt, ox, oy)
            frames += 1
            st = tracker.update(img, t_img)
            if not st.valid:
                continue
            if st.fixation_id != fid:
                fid = st.fixation_id
                reselections += st.fixation_id > 0
                servo.reset()
                scene = view.scene_point(st.pixel, pan, tilt, ox, oy)
            joints = loop.history.at(t_img, max_extrapolation_s=0.06)
            if joints is None:
                continue
            truth.append((t_img, pan, tilt))
            loop.set_target(servo.target(st.pixel, joints, t_img, time.monotonic()))
            if el > settle_s and scene is not None:
                true_px = view.pixel_of(scene, pan, tilt, ox, oy)
                errors.append(float(np.hypot(true_px[0] - cam_model.cx, true_px[1] - cam_model.cy)))
    finally:
        time.sleep(0.05)        # one more reading after the last frame, so every frame is bracketed
        loop.stop()
        rate = loop.stats['cycles'] / (time.monotonic() - t0)
        cmd_rate = loop.stats['commands'] / (time.monotonic() - t0)
        driver.close()
        emu.stop()
    # joint states as a node publishes them: interpolated between the readings around the image time
    joint_errors = []
    for t_img, pan, tilt in truth:
        j = loop.history.at(t_img, max_extrapolation_s=0.0)
        if j is not None:
            joint_errors.append(math.degrees(max(abs(j[0] - pan), abs(j[1] - tilt))))
    e = np.asarray(errors) if errors else np.asarray([math.nan])
    out = {
        'baud': float(baud),
        'servo_loop_hz': round(rate, 2),
        'command_rate_hz': round(cmd_rate, 2),
        'frames': float(frames),
        'fixation_err_px_mean': round(float(np.mean(e)), 3),
        'fixation_err_px_p95': round(float(np.percentile(e, 95)), 3),
        'fixation_err_px_max': round(float(np.max(e)), 3),
        'joint_interp_err_deg_p95': round(float(np.percentile(joint_errors, 95)) if joint_errors else math.nan, 4),
        'joint_interp_err_deg_max': round(float(np.max(joint_errors)) if joint_errors else math.nan, 4),
        'reselections': float(reselections),
        'servo_errors': float(loop.stats['errors']),
    }
    if verbose:
        print(json.dumps(out, indent=2))
    return out


TURN_DEG_S = 14.0       # the turn case: about half the heads' rate on the demo loop's arcs


def run() -> dict[str, float]:
    """Benchmark entry point: 8 s at 9600 baud with the scene drifting ~4.6 deg/s (rig turning), then 5 s of the
    demo's camera (the default rig file's right camera: 640x480, fx 1727) with the scene turning at ``TURN_DEG_S``
    (``turn_`` keys)."""
    out = run_closed_loop(duration_s=8.0, baud=9600, verbose=True)
    cam = load_rig(default_rig_path()).camera('right')
    turn = run_closed_loop(duration_s=5.0, baud=9600, drift_px_s=(math.radians(TURN_DEG_S) * cam.fx, 0.0),
                           settle_s=2.0, camera=cam, verbose=True)
    out.update({f'turn_{k}': v for k, v in turn.items() if k.startswith(('fixation_err', 'reselections'))})
    return out


if __name__ == '__main__':
    run()
