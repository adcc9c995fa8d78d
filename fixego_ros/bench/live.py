"""Live pipeline: latency image -> pose, dropped frames and accuracy of ``fixego demo`` (every node a
separate process over DDS, 640x480 at 30 Hz) over the first ``DURATION_S`` of the paper loop."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

DURATION_S = 12.0


def run() -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'demo'
        env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', MPLBACKEND='Agg')
        cmd = [sys.executable, '-m', 'fixego_ros.cli', 'demo', '--out', str(out), '--duration', str(DURATION_S),
               '--quiet', '--domain-id', str(190 + os.getpid() % 10)]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
        if proc.returncode != 0:
            print(f'live bench: demo failed: {proc.stderr[-500:]}', file=sys.stderr)
            return {}
        rep = json.loads((out / 'report.json').read_text())
    lat, frames = rep['latency_image_to_pose_ms'], rep['frames']
    res = {'latency_p50_ms': lat.get('p50', float('nan')), 'latency_p95_ms': lat.get('p95', float('nan')),
           'frames_rendered': frames['rendered'], 'frames_without_pose': frames['dropped']}
    for label in ('raw', 'refined'):
        pe = rep.get(label, {}).get('position_error_m')
        if pe:
            res[f'{label}_mean_error_cm'] = 100 * pe['mean']
            res[f'{label}_terminal_error_cm'] = 100 * pe['terminal']
    return res


if __name__ == '__main__':
    print(run())
