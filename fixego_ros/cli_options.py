"""Checks of command-line options shared by the ``fixego`` sub-commands (sim, demo, paper-sim, play, record).

Every bad option ends the same way: one ``fixego <cmd>: ...`` line naming the option, its value and what is
allowed, exit code 2, before any work is done or anything is created (:class:`OptionError`).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import re
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import NoReturn

ROS_DOMAIN_IDS = (0, 232)      # the ids ROS 2 accepts


class OptionError(ValueError):
    """An option that cannot be used; the message is one line naming the option, its value and what is allowed."""


def one_line_errors(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """argparse's own errors of ``parser`` (``--fps abc``, a missing ``--out``, ``--fps -inf`` read as an
    option, ...) as one ``PROG: ...`` line and exit code 2, like the checks below (not usage + error)."""
    def error(message: str) -> NoReturn:
        parser.exit(2, f'{parser.prog}: {" ".join(message.split())} (see {parser.prog} --help)\n')

    parser.error = error     # type: ignore[method-assign]
    return parser


def _interval(lo: float, hi: float, lo_open: bool, hi_open: bool) -> str:
    return f'{"(" if lo_open else "["}{lo:g}, {hi:g}{")" if hi_open else "]"}'


def check_float(value: float, option: str, lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = False,
                unit: str = '', note: str = '') -> float:
    """``value`` if finite and within the interval, else :class:`OptionError` naming ``option`` and the value."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
    if not ok:
        raise OptionError(f'{option} must be a finite number in {_interval(lo, hi, lo_open, hi_open)}'
                          f'{" " + unit if unit else ""}{note}, got {value!r}')
    return v


def check_int(value: int, option: str, lo: int, hi: int, *, also: Iterable[int] = (), note: str = '') -> int:
    """``value`` if an integer in ``lo..hi`` (or one of ``also``), else :class:`OptionError`."""
    also = tuple(also)
    if isinstance(value, bool) or not isinstance(value, int) or not (lo <= value <= hi or value in also):
        extra = ''.join(f' or {a}' for a in also)
        raise OptionError(f'{option} must be an integer in {lo}..{hi}{extra}{note}, got {value!r}')
    return value


def why(e: OSError) -> str:
    return e.strerror or type(e).__name__


def check_new_dir(text: str, option: str = '--out') -> Path:
    """A directory that the command will create: a non-empty path that does not exist, in an existing writable
    directory. Probed by creating and removing it, so ``/proc/x`` (which root may 'access') is refused too."""
    if not text or not text.strip():
        raise OptionError(f'{option} must name a directory to create, got an empty path')
    path = Path(text)
    if path.exists() or path.is_symlink():
        raise OptionError(f'{option} {text}: exists already (bags are never overwritten; choose a new directory)')
    parent = path.parent
    if not parent.exists():
        raise OptionError(f'{option} {text}: the parent directory {parent} does not exist')
    if not parent.is_dir():
        raise OptionError(f'{option} {text}: {parent} is not a directory')
    try:
        path.mkdir()
    except OSError as e:
        raise OptionError(f'{option} {text}: cannot create the directory ({why(e)})') from None
    try:
        path.rmdir()
    except OSError as e:     # pragma: no cover - we just made it
        raise OptionError(f'{option} {text}: cannot remove the probe directory ({why(e)})') from None
    return path


def prepare_out_dir(text: str, option: str = '--out') -> Path:
    """An output folder that may exist already (then reused) or is created with its parents, and that takes a
    file (probed with a temporary one). Call it last, after every other check; on refusal nothing it made is
    left behind."""
    if not text or not text.strip():
        raise OptionError(f'{option} must name an output directory, got an empty path')
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise OptionError(f'{option} {text}: exists and is not a directory')
    made: list[Path] = []
    if not path.exists():
        missing = [path, *(p for p in path.parents if not p.exists())]
        blocker = next((p for p in path.parents if p.exists()), None)
        if blocker is not None and not blocker.is_dir():
            raise OptionError(f'{option} {text}: {blocker} is not a directory')
        for p in reversed(missing):
            try:
                p.mkdir()
            except FileExistsError:
                continue
            except OSError as e:
                _remove_dirs(made)
                raise OptionError(f'{option} {text}: cannot create {p} ({why(e)})') from None
            made.append(p)
    try:
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as e:
        _remove_dirs(made)
        raise OptionError(f'{option} {text}: cannot write there ({why(e)})') from None
    return path


def _remove_dirs(dirs: list[Path]) -> None:
    for d in reversed(dirs):
        with contextlib.suppress(OSError):
            d.rmdir()


# a ROS 2 topic name (absolute, relative or private): tokens of letters, digits and _, not starting with a digit
_TOPIC = re.compile(r'[~/]?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*')


def check_topic_name(name: str, option: str) -> str:
    """``name`` if ROS 2 accepts it as a topic name, else :class:`OptionError` (rclpy would raise deep inside)."""
    if not _TOPIC.fullmatch(name or ''):
        raise OptionError(f'{option}: {name!r} is not a valid ROS topic name (letters, digits, _ and /; no token '
                          'may start with a digit)')
    return name


def check_out_file(path: Path, option: str = '--out') -> Path:
    """A file the command will write at the end (its folders are created then): a real file name, not an existing
    directory, under a folder that takes files (probed). Checked first, so a long run cannot fail at its end."""
    if not str(path).strip() or path.name in ('', '.', '..'):
        raise OptionError(f'{option} must name a file, got {str(path)!r}')
    if path.is_dir():
        raise OptionError(f'{option} {path}: is a directory')
    base = next((p for p in path.parents if p.exists()), Path('.'))
    if not base.is_dir():
        raise OptionError(f'{option} {path}: {base} is not a directory')
    try:
        with tempfile.TemporaryFile(dir=base):
            pass
    except OSError as e:
        raise OptionError(f'{option} {path}: cannot write under {base} ({why(e)})') from None
    return path
