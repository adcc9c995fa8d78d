"""Benchmark of the flow front end at 640x480: ms per camera of ``track_flow`` (two-frame flow, corners
detected every frame) and per stereo pair of ``StereoFrontEnd.process`` (persistent tracks, predicted LK,
epipolar RANSAC, keyframes), for each preset with the shipped ``flow_node`` defaults, and the median
number of flow points kept / flow pairs per camera.

Images are the simulator's (default rig and room, noise 2 grey levels): two seconds of the papers' loop at
30 fps from :data:`START_FRAME` on, with the servo model's pan/tilt and fixation pixels, so the windows hold the
realistic mix of texture the live pipeline sees. ``track_flow`` is timed with OpenCV's default thread
count and with one thread (the two cores are shared with the rest of the pipeline); the global thread
setting is restored afterwards.

    python -c "from fixego_ros.bench.flow import run; run()"
"""

from __future__ import annotations

import itertools
import time

import cv2
import numpy as np

from fixego_ros.geometry.rig import SIDES, default_rig_path, load_rig
from fixego_ros.pipeline.frontend import CameraSample, StereoFrontEnd
from fixego_ros.pipeline.params import FLOW_PARAMS, flow_params, keyframe_policy, params_getter
from fixego_ros.sim.render import Renderer
from fixego_ros.sim.servo_model import FixationServo
from fixego_ros.sim.trajectories import paper
from fixego_ros.sim.world import make_room
from fixego_ros.tracking.flow import PRESETS, track_flow


def _frames(n: int, start: int = 0) -> list[dict[str, CameraSample]]:
    """``n`` consecutive synchronised frames of both cameras from frame ``start`` on (the servos run from the first
    frame, so the heads are where they would be)."""
    rig = load_rig(default_rig_path())
    world = make_room(0)
    stamps, poses = paper().sample(30.0)
    render = Renderer(world, rig, noise_sigma=2.0, seed=0)
    select = Renderer(world, rig, noise_sigma=0.0)
    servos = {s: FixationServo(world, rig, s, select) for s in SIDES}
    servos['right'].partner, servos['left'].partner = servos['left'], servos['right']
    frames = []
    for k in range(start + n):
        frame = {}
        for side, sv in servos.items():
            st = sv.start(stamps[k], poses[k]) if k == 0 else sv.step(stamps[k], poses[k])
            if k < start:
                continue
            img = render.render(side, poses[k], st.pan, st.tilt)
            px = tuple(float(x) for x in st.pixel) if np.all(np.isfinite(st.pixel)) else None
            frame[side] = CameraSample(img, st.pan_reading, st.tilt_reading, px, st.fixation_id)
        if frame:
            frames.append(frame)
    return frames


# 10 s into the loop: the rig at its cruising speed (the first second, from rest, costs half as much per frame)
START_FRAME = 300


def _median_ms(samples: list[float]) -> float:
    return 1e3 * float(np.median(samples))


def run(n_frames: int = 61, passes: int = 3, start: int = START_FRAME) -> dict[str, float]:
    rig = load_rig(default_rig_path())
    frames = _frames(n_frames, start)
    threads = cv2.getNumThreads()
    out: dict[str, float] = {}
    try:
        for preset in PRESETS:
            g = params_getter(FLOW_PARAMS, {'preset': preset})
            params = flow_params(g)
            for label, n_threads in (('', threads), ('_1thread', 1)):
                cv2.setNumThreads(n_threads)
                ms, points = [], []
                for _ in range(passes):
                    for prev, curr in itertools.pairwise(frames):
                        for side in SIDES:
                            t0 = time.perf_counter()
                            tr = track_flow(prev[side].gray, curr[side].gray, prev[side].fixation_px, params)
                            ms.append(time.perf_counter() - t0)
                            points.append(len(tr))
                out[f'{preset}.track_ms{label}.median'] = _median_ms(ms)
            out[f'{preset}.points.median'] = float(np.median(points))
            cv2.setNumThreads(threads)
            fe = StereoFrontEnd(rig, params, keyframe_policy(g))
            ms, pairs = [], []
            for _ in range(passes):
                fe.reset()
                for k, frame in enumerate(frames):
                    t0 = time.perf_counter()
                    obs = fe.process(k / 30.0, frame)
                    if k > 0:
                        ms.append(time.perf_counter() - t0)
                        pairs += [len(obs.camera(side).flow_prev) for side in SIDES]
            out[f'{preset}.process_ms.median'] = _median_ms(ms)
            out[f'{preset}.pairs.median'] = float(np.median(pairs))
    finally:
        cv2.setNumThreads(threads)
    for k, v in out.items():
        print(f'{k:40s} {v:8.2f}')
    return out


if __name__ == '__main__':
    run()
