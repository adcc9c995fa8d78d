"""Benchmark of the simulator's renderer: ms per 640x480 camera frame (target <= 15 ms), mono8 and rgb8.

Renders the right and left cameras of the default rig along the papers' loop at the servo model's
pan/tilt (so the views are the realistic mix of walls, boxes, floor), one thread, noise included.

    python -m fixego_ros.bench.render
"""

from __future__ import annotations

import json
import time

import cv2
import numpy as np

from fixego_ros.geometry.rig import default_rig_path, load_rig
from fixego_ros.sim.render import Renderer
from fixego_ros.sim.servo_model import FixationServo
from fixego_ros.sim.trajectories import paper
from fixego_ros.sim.world import make_room


def run(frames: int = 120) -> dict:
    cv2.setNumThreads(1)  # the live node and bag writer share two cores with the rest of the pipeline
    rig = load_rig(default_rig_path())
    t0 = time.perf_counter()
    world = make_room(0)
    build_s = time.perf_counter() - t0
    stamps, poses = paper().sample(30.0)
    idx = np.linspace(0, len(stamps) - 1, frames).astype(int)
    select = Renderer(world, rig, noise_sigma=0.0)
    servos = {s: FixationServo(world, rig, s, select) for s in ('right', 'left')}
    angles = []
    for k, (t, pose) in enumerate(zip(stamps, poses, strict=True)):
        states = {s: (sv.start(t, pose) if k == 0 else sv.step(t, pose)) for s, sv in servos.items()}
        if k in set(idx):
            angles.append((pose, {s: (st.pan, st.tilt) for s, st in states.items()}))
    out: dict[str, float] = {'world_build_s': round(build_s, 3),
                             'texture_mb': round(world.memory_bytes() / 1e6, 1)}
    for enc in ('mono8', 'rgb8'):
        r = Renderer(world, rig, encoding=enc)
        for pose, a in angles[:5]:  # warm-up: texture pyramids and noise banks are built lazily
            for s in a:
                r.render(s, pose, *a[s])
        ms = []
        for pose, a in angles:
            for s in a:
                t1 = time.perf_counter()
                r.render(s, pose, *a[s])
                ms.append((time.perf_counter() - t1) * 1e3)
        out[f'render_{enc}_median_ms'] = round(float(np.median(ms)), 2)
        out[f'render_{enc}_p95_ms'] = round(float(np.percentile(ms, 95)), 2)
        out[f'render_{enc}_max_ms'] = round(float(np.max(ms)), 2)
    out['frames'] = 2 * len(angles)
    out['resolution'] = f'{rig.right.width}x{rig.right.height}'
    print(json.dumps(out, indent=2))
    return out


if __name__ == '__main__':
    run()
