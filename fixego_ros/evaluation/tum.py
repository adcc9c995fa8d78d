"""TUM trajectory files: ``stamp tx ty tz qx qy qz qw`` per line (DESIGN.md §6).

Stamps in seconds, the pose of ``base_link`` in ``odom``. One line formatter serves both the batch
writer and the incremental one, so a file written live by a node and one written after the fact are
byte-identical for the same poses (evo and other tools read either).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO

import numpy as np

from fixego_ros.geometry.rotation import Pose, from_quat_xyzw, quat_xyzw

HEADER = '# timestamp tx ty tz qx qy qz qw (pose of base_link in odom; s, m)'


class TumError(ValueError):
    """A TUM file that cannot be read or a pose that cannot be written; names the file and line."""


def _fmt(x: float, digits: int) -> str:
    s = f'{x:.{digits}f}'
    # no "-0.000": equal poses should give equal bytes whatever the sign of a rounding residue
    return s[1:] if s.startswith('-') and float(s) == 0.0 else s


def format_tum_line(stamp: float, pose: Pose) -> str:
    """One line (no newline). 9 decimals for stamp and position (ns, nm); 12 for the quaternion, so
    the rotation read back agrees with the written one to ~1e-12."""
    t = np.asarray(pose.t, dtype=float).reshape(3)
    if not (math.isfinite(float(stamp)) and pose.is_finite()):
        raise TumError(f'refusing to write a non-finite pose at stamp {stamp}')
    q = quat_xyzw(np.asarray(pose.R, dtype=float))
    return ' '.join([_fmt(float(stamp), 9), *(_fmt(float(v), 9) for v in t), *(_fmt(float(v), 12) for v in q)])


def write_tum(path: str | os.PathLike, stamps: Sequence[float] | np.ndarray, poses: Sequence[Pose],
              header: bool = True) -> Path:
    """Write a whole trajectory (creates parent folders); returns the path.

    Atomic: the lines go to a temporary file in the same folder, which then replaces ``path``, so an
    interrupted or failed write (Ctrl-C, disk full) never leaves a half-written trajectory behind.
    """
    if len(stamps) != len(poses):
        raise TumError(f'{path}: {len(stamps)} stamps but {len(poses)} poses')
    lines = [HEADER] if header else []
    lines += [format_tum_line(float(s), p) for s, p in zip(stamps, poses, strict=True)]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f'.{path.name}.{os.getpid()}.tmp')
    try:
        with tmp.open('w', encoding='ascii', newline='\n') as f:
            f.write(''.join(line + '\n' for line in lines))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


class TumWriter:
    """Incremental TUM writer for a running node: open once, ``append`` per pose, ``flush`` when the
    file should be readable by others (e.g. after each frame), ``close`` at shutdown."""

    def __init__(self, path: str | os.PathLike, header: bool = True) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: IO[str] | None = self.path.open('w', encoding='ascii', newline='\n')
        self.count = 0
        if header:
            self._f.write(HEADER + '\n')

    def append(self, stamp: float, pose: Pose) -> None:
        if self._f is None:
            raise TumError(f'{self.path}: writer is closed')
        self._f.write(format_tum_line(stamp, pose) + '\n')
        self.count += 1

    def extend(self, items: Iterable[tuple[float, Pose]]) -> None:
        for stamp, pose in items:
            self.append(stamp, pose)

    def flush(self) -> None:
        if self._f is not None:
            self._f.flush()

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
            self._f = None

    @property
    def closed(self) -> bool:
        return self._f is None

    def __enter__(self) -> TumWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, list[Pose]]:
    """Read a TUM file: ``(stamps (N,), poses)``. Skips blank lines and ``#`` comments; raises
    :class:`TumError` naming file and line for a wrong column count, a non-number, a non-finite value,
    a zero quaternion or a stamp that does not increase (association needs sorted stamps)."""
    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except FileNotFoundError:
        raise TumError(f'{path}: no such file') from None
    except (OSError, UnicodeDecodeError) as e:
        raise TumError(f'{path}: cannot read ({e})') from None
    stamps: list[float] = []
    poses: list[Pose] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith('#'):
            continue
        fields = line.replace(',', ' ').split()
        where = f'{path}:{lineno}'
        if len(fields) != 8:
            raise TumError(f'{where}: expected 8 columns (stamp tx ty tz qx qy qz qw), got {len(fields)}')
        try:
            vals = [float(f) for f in fields]
        except ValueError:
            raise TumError(f'{where}: not a number in {line!r}') from None
        if not all(math.isfinite(v) for v in vals):
            raise TumError(f'{where}: non-finite value in {line!r}')
        if stamps and vals[0] <= stamps[-1]:
            raise TumError(f'{where}: stamp {vals[0]!r} does not increase (previous {stamps[-1]!r})')
        q = np.array(vals[4:8])
        scale = float(np.max(np.abs(q)))
        try:      # any positive multiple is the same rotation: rescaled first, so 1e200 does not overflow the norm
            R = from_quat_xyzw(q / scale if scale > 0 else q)
        except ValueError as e:
            raise TumError(f'{where}: {e}') from None
        stamps.append(vals[0])
        poses.append(Pose(R, np.array(vals[1:4])))
    return np.array(stamps, dtype=float), poses
