"""Live pipeline: latency image -> pose (and by stage, :func:`fixego_ros.demo.report.latency_stages`), dropped
frames, how the poses were made and accuracy of ``fixego demo`` (every node a separate process over DDS, 640x480 at
30 Hz) over the whole paper loop, as ``make demo`` runs it.

Until stop 60 it ran the first 12 s only, where the smoother child keeps up (0.3 s behind): p50 27 ms. Over the
whole loop the child falls 2-6 s behind, most frames are then solved rather than carried on its velocity, and the
demo's p50 is about twice that (docs/results.md "Stop 60").

    python -m fixego_ros.bench.live [--joint-mode predict|wait]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path


def run(joint_mode: str | None = None) -> dict[str, float]:
    """One demo run; ``joint_mode`` sets the camera nodes' (default: theirs)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'demo'
        env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', MPLBACKEND='Agg')
        cmd = [sys.executable, '-P', '-m', 'fixego_ros.cli', 'demo', '--out', str(out), '--quiet', '--domain-id',
               str(190 + os.getpid() % 10)]
        if joint_mode:
            cmd += ['--joint-mode', joint_mode]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
        if proc.returncode != 0:
            print(f'live bench: demo failed: {proc.stderr[-500:]}', file=sys.stderr)
            return {}
        rep = json.loads((out / 'report.json').read_text())
    lat, frames = rep['latency_image_to_pose_ms'], rep['frames']
    res = {'latency_p50_ms': lat.get('p50', float('nan')), 'latency_p95_ms': lat.get('p95', float('nan')),
           'frames_rendered': frames['rendered'], 'frames_without_pose': frames['dropped']}
    for stage, v in rep.get('latency_stages_ms', {}).items():
        res.update({f'stage_{stage}_{q}_ms': v[q] for q in ('p50', 'p95') if q in v})
    est = rep.get('diagnostics', {}).get('fixego estimator_node', {})
    for q in ('p50', 'p95'):         # the smoother process's lag behind the newest frame (s), its time per frame
        if f'smoother_behind_s_{q}' in est:
            res[f'smoother_behind_{q}_s'] = float(est[f'smoother_behind_s_{q}'])
        if f'smoother_update_ms_{q}' in est:
            res[f'smoother_update_{q}_ms'] = float(est[f'smoother_update_ms_{q}'])
    steps = rep.get('fast_pose_steps', {})
    if steps:                        # carried on the smoother's velocity (cheap) or solved (it too far behind)
        res['poses_carried_share'] = steps.get('carried', 0) / sum(steps.values())
    for label in ('raw', 'refined'):
        pe = rep.get(label, {}).get('position_error_m')
        if pe:
            res[f'{label}_mean_error_cm'] = 100 * pe['mean']
            res[f'{label}_terminal_error_cm'] = 100 * pe['terminal']
    return res


if __name__ == '__main__':
    import argparse

    from fixego_ros.tracking.joint_prediction import MODES

    ap = argparse.ArgumentParser(prog='python -m fixego_ros.bench.live')
    ap.add_argument('--joint-mode', choices=MODES, help="camera nodes' joint_mode (default: theirs)")
    print(json.dumps(run(ap.parse_args().joint_mode), indent=1))
