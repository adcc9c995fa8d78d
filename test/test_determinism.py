"""The same bag gives the same trajectory on any CPU: replays under other BLAS kernels and SIMD paths agree.

numpy (OpenBLAS kernels, its own SIMD loops) and OpenCV pick code paths by CPU, and those round the last bit
differently. An estimator that leaves a direction to the rounding (the scale on straights and arcs, a local
minimiser wandering in a flat valley) turns that into centimetres; ours must not (issue 15). Each replay runs in
its own process with the kernel forced, as another machine would run it.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fixego_ros.evaluation.tum import read_tum

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / 'bags'
RMS_LIMIT_M = 0.01      # issue 15: replays agree within 1 cm RMS across kernels


def _cpu_flags() -> set[str]:
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('flags'):
                return set(line.split(':', 1)[1].split())
    except OSError:
        pass
    return set()


def _machines() -> list[tuple[str, dict[str, str]]]:
    """Code paths of other x86-64 CPUs this one can run: an old SSE3-only one and an AVX2 one without AVX-512.
    (OpenCV's feature names are its own: ``SSE4.1``, ``AVX512F``; it ignores a name it does not know, with a
    warning on stderr, and until stop 87 this list named ``AVX512_SKX`` and ``SSE4_2``, which it ignored.)"""
    flags = _cpu_flags()
    out = [('sse3', {'OPENBLAS_CORETYPE': 'Prescott', 'NPY_DISABLE_CPU_FEATURES': 'X86_V3,X86_V4,AVX512_ICL,AVX512_SPR',
                     'OPENCV_CPU_DISABLE': 'AVX512F,AVX2,FP16,AVX,SSE4.2,SSE4.1'})]
    if {'avx2', 'fma'} <= flags:
        out.append(('avx2', {'OPENBLAS_CORETYPE': 'Haswell', 'NPY_DISABLE_CPU_FEATURES': 'X86_V4,AVX512_ICL,AVX512_SPR',
                             'OPENCV_CPU_DISABLE': 'AVX512F'}))
    return out


def _run(args: list[str], env_extra: dict[str, str]) -> None:
    """``fixego ARGS`` in its own process with the code paths ``env_extra`` forces."""
    env = {k: v for k, v in os.environ.items() if k not in ('OPENBLAS_CORETYPE', 'NPY_DISABLE_CPU_FEATURES',
                                                          'OPENCV_CPU_DISABLE')}
    env.update(env_extra)
    p = subprocess.run([sys.executable, '-m', 'fixego_ros.cli', *args], env=env, capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stderr
    assert 'unknown CPU feature' not in p.stderr, p.stderr      # a path the test meant to force, left as it was


def _replay(bag: Path, out: Path, env_extra: dict[str, str]) -> np.ndarray:
    _run(['replay', str(bag), '--out', str(out), '--workers', '1', '--no-progress', '--quiet'], env_extra)
    _, poses = read_tum(out)
    return np.array([q.t for q in poses])


@pytest.mark.slow
@pytest.mark.skipif(platform.machine() not in ('x86_64', 'AMD64'), reason='forces x86-64 BLAS kernels and SIMD paths')
@pytest.mark.parametrize('bag', ['paper', 'walk'])
def test_replays_agree_across_cpu_code_paths(tmp_path, bag):
    ref = _replay(BAGS / bag, tmp_path / 'default' / 'est.tum', {})
    assert len(ref) > 30
    for name, env in _machines():
        other = _replay(BAGS / bag, tmp_path / name / 'est.tum', env)
        assert other.shape == ref.shape, name
        rms = float(np.sqrt(np.mean(np.sum((other - ref) ** 2, axis=1))))
        assert rms < RMS_LIMIT_M, f'{bag}: {name} code path differs by {rms * 100:.2f} cm RMS'


def _sensors(bag: Path) -> dict[str, list[bytes]]:
    """The serialised images and joint states of a bag, by topic: what the cameras and heads measured."""
    from fixego_ros.bags.reader import Bag
    out: dict[str, list[bytes]] = {}
    for m in Bag(bag).messages():
        if m.topic.endswith(('image_raw', 'joint_states')):
            out.setdefault(m.topic, []).append(bytes(m.data))
    return out


@pytest.mark.skipif(platform.machine() not in ('x86_64', 'AMD64'), reason='forces x86-64 SIMD paths')
def test_simulated_images_are_the_same_on_any_cpu(tmp_path):
    """A bag the simulator writes has the same images and joint states, to the byte, under every CPU's code paths:
    the benchmarks replay bags written on the machine they run on, and OpenCV's SIMD warps round a texel here and
    there the other way (stop 87: the bench's seed 28 replayed 1.87 / 3.70 cm from the AVX2 paths' images, 2.01 /
    3.96 from the SSE3 or baseline paths'). The other numbers (ground truth, vergence) may round their last bit by
    CPU (:func:`~fixego_ros.bags.shipped.compare`'s tolerances). Each bag is written in a fresh process, where
    OpenCV's fast paths are on."""
    args = ['sim', '--trajectory', 'paper', '--duration', '1.5', '--fps', '4', '--width', '320', '--seed', '28',
            '--vergence', 'physical', '--no-progress']
    _run([*args, '--out', str(tmp_path / 'default')], {})
    ref = _sensors(tmp_path / 'default')
    assert len(ref) == 4 and all(len(v) >= 6 for v in ref.values())
    for name, env in _machines():
        _run([*args, '--out', str(tmp_path / name)], env)
        other = _sensors(tmp_path / name)
        assert other.keys() == ref.keys(), name
        for topic, msgs in ref.items():
            same = [a == b for a, b in zip(msgs, other[topic], strict=True)]
            assert all(same), f'{name}: {topic} differs in {same.count(False)} of {len(same)} messages'
