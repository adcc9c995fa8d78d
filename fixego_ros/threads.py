"""Process-wide settings of the numerical libraries: one compute thread per process (BLAS, OpenCV) unless the
environment sets a count, and OpenCV's portable code paths (:func:`portable_opencv`).

Why one thread: the live pipeline is six to eight processes (the simulated rig, two camera nodes, the flow node, the
estimator and its smoother child, a recorder) on a machine of a few cores. Each process's work per frame is small
(Lucas-Kanade on crops, matrices of 6 to a few hundred rows; GTSAM does its own linear algebra), so a second library
thread rarely has anything to do in parallel with the first; but OpenBLAS and OpenCV start a pool of one thread per
core in every process, and a call that hands work to a pool thread waits until the scheduler runs it, behind the
other processes. Measured on ``fixego demo``, 12 runs each way alternated (docs/results.md "Stop 51"): image -> pose
p95 median 55.5 -> 49.5 ms, lower in 8 of the 12 pairs; p50 unchanged. ``fixego replay`` gave the same time and the
same bytes either way, so only the nodes do this.

A count the user set (``OPENBLAS_NUM_THREADS`` or ``OMP_NUM_THREADS`` for BLAS, ``OPENCV_FOR_THREADS_NUM`` for
OpenCV) is kept. The variables are also set for processes started from this one (the estimator's smoother child is
spawned, a fresh interpreter that reads them when it loads the libraries).
"""

from __future__ import annotations

import os

import cv2

try:
    import threadpoolctl
except ImportError:     # a full ROS install without the PyPI extras (README): the processes it starts still get one
    threadpoolctl = None

# each library and the variables that set its thread count (OpenBLAS reads OMP_NUM_THREADS when its own is unset)
LIBRARIES: dict[str, tuple[str, ...]] = {'BLAS': ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS'),
                                         'OpenCV': ('OPENCV_FOR_THREADS_NUM',)}


def limit_threads() -> str:
    """Give BLAS and OpenCV one thread in this process and the processes it starts, except where the environment
    already sets a count. Returns one line for the start-up log. (No environment argument, unlike
    :func:`~fixego_ros.nodes.dds_profile.use_image_profile`: the limits are the process's own, not only variables.)"""
    limited, kept = [], []
    for library, names in LIBRARIES.items():
        chosen = next((n for n in names if os.environ.get(n)), None)
        if chosen is not None:
            kept.append(f'{library} {os.environ[chosen]} ({chosen})')
            continue
        limited.append(library)
        os.environ[names[0]] = '1'
    missing = ''
    if 'BLAS' in limited:
        if threadpoolctl is not None:
            threadpoolctl.threadpool_limits(1, user_api='blas')
        else:
            missing = ' (threadpoolctl not installed: BLAS keeps its pool in this process, not in those it starts)'
    if 'OpenCV' in limited:
        cv2.setNumThreads(1)
    parts = [f'one thread for {" and ".join(limited)}'] if limited else []
    parts += [f'{", ".join(kept)} as the environment says'] if kept else []
    return 'compute threads: ' + '; '.join(parts) + missing


def portable_opencv() -> None:
    """Run OpenCV's baseline code paths (``cv2.setUseOptimized(False)``) instead of those it picks for this CPU.

    Why: OpenCV dispatches its SIMD kernels (SSE4, AVX2, AVX-512) and IPP by the CPU it runs on, and those round
    differently. The front end's corners and flow feed an estimate whose weakly observed directions carry a last-bit
    difference on (the scale of an unaided walk most of all): at stop 67 the shipped ``walk`` bag replayed 8.1 cm RMS
    apart between this machine's AVX-512 paths and an SSE3 machine's (``OPENCV_CPU_DISABLE``), 0.0000 cm with the
    baseline paths, which are the same code on every x86-64 CPU the wheel runs on. The cost, measured with
    ``fixego_ros.bench.flow`` (full preset, one stereo frame): ~10 -> ~12 ms. Called by ``fixego replay`` and by the
    simulator that writes bags (:class:`~fixego_ros.sim.run.Simulation`: its warped and remapped images differed by a
    grey level here and there between the AVX2 and the SSE or baseline paths, and a replay of them by 0.3 cm, stop
    87). The setting is global: it stays off in a process once a replay has run. The
    nodes keep OpenCV's fast paths, since a live run depends on its timing anyway and its two cores are short (demo
    runs on a saturated machine at stop 67: flow_compute p50 53 and 37 ms in two with every node portable, 33 in two
    without)."""
    cv2.setUseOptimized(False)
