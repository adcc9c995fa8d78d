"""Every node computes with one BLAS and one OpenCV thread unless the environment sets a count, and so do the
processes it spawns (the estimator's smoother child). Each case runs in a fresh interpreter: the limits are
process-wide."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from fixego_ros.threads import LIBRARIES

VARIABLES = sorted({n for names in LIBRARIES.values() for n in names})

REPORT = """
import json, multiprocessing as mp, os, sys
import cv2, numpy, scipy.linalg, threadpoolctl

def counts():
    blas = sorted({p['num_threads'] for p in threadpoolctl.threadpool_info() if p['user_api'] == 'blas'})
    return {'blas': blas, 'opencv': cv2.getNumThreads()}

def child(queue):
    queue.put(counts())

def main():
    out = {'before': counts()}
    if sys.argv[1] in ('limit', 'no_threadpoolctl'):
        if sys.argv[1] == 'no_threadpoolctl':
            sys.modules['threadpoolctl'] = None      # as if not installed: importing it fails
        from fixego_ros.threads import limit_threads
        out['note'] = limit_threads()
    elif sys.argv[1] == 'node':
        from fixego_ros.nodes.common import spin_node
        def factory():
            out['in_node'] = counts()
            raise KeyboardInterrupt     # spin_node ends as on Ctrl-C
        spin_node(factory, [])
    out['after'] = counts()
    out['env'] = {k: os.environ.get(k) for k in VARIABLES}
    ctx = mp.get_context('spawn')
    queue = ctx.Queue()
    p = ctx.Process(target=child, args=(queue,))
    p.start()
    out['child'] = queue.get(timeout=60)
    p.join(timeout=60)
    print(json.dumps(out))

if __name__ == '__main__':
    main()
""".replace('VARIABLES', repr(VARIABLES))


def _run(tmp_path, mode: str, **env: str) -> dict:
    script = tmp_path / 'report.py'
    script.write_text(REPORT)
    clean = {k: v for k, v in os.environ.items() if k not in VARIABLES}
    proc = subprocess.run([sys.executable, str(script), mode], capture_output=True, text=True, timeout=120,
                          env={**clean, **env})
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_one_thread_each_in_this_process_and_the_spawned_ones_when_nothing_is_set(tmp_path):
    out = _run(tmp_path, 'limit')
    one = {'blas': [1], 'opencv': 1}
    assert out['after'] == one and out['child'] == one
    assert out['env']['OPENBLAS_NUM_THREADS'] == '1' and out['env']['OPENCV_FOR_THREADS_NUM'] == '1'
    assert out['note'] == 'compute threads: one thread for BLAS and OpenCV'


def test_counts_the_environment_sets_are_kept(tmp_path):
    env = {'OPENBLAS_NUM_THREADS': '2', 'OPENCV_FOR_THREADS_NUM': '2'}
    untouched = _run(tmp_path, 'none', **env)          # what the libraries make of the variables themselves
    out = _run(tmp_path, 'limit', **env)
    assert out['after'] == untouched['after'] and out['child'] == untouched['child']
    assert out['env']['OPENBLAS_NUM_THREADS'] == '2' and out['env']['OPENCV_FOR_THREADS_NUM'] == '2'
    assert 'OPENBLAS_NUM_THREADS' in out['note'] and 'OPENCV_FOR_THREADS_NUM' in out['note']
    # one library set, the other limited; OMP_NUM_THREADS counts for BLAS (OpenBLAS reads it)
    out = _run(tmp_path, 'limit', OMP_NUM_THREADS='2')
    assert out['after']['opencv'] == 1 and out['env']['OPENBLAS_NUM_THREADS'] is None
    assert out['note'] == 'compute threads: one thread for OpenCV; BLAS 2 (OMP_NUM_THREADS) as the environment says'


def test_a_node_started_by_spin_node_computes_with_one_thread_each(tmp_path):
    out = _run(tmp_path, 'node')
    one = {'blas': [1], 'opencv': 1}
    assert out['in_node'] == one and out['child'] == one


def test_without_threadpoolctl_the_node_still_starts_and_its_children_get_one_blas_thread(tmp_path):
    out = _run(tmp_path, 'no_threadpoolctl')
    assert out['after']['opencv'] == 1 and out['child'] == {'blas': [1], 'opencv': 1}
    assert out['after']['blas'] == out['before']['blas']            # this process's pool cannot be changed
    assert 'threadpoolctl not installed' in out['note']
