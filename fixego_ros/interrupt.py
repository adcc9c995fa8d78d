"""Ctrl-C and SIGTERM as one exception, for the commands that must clean up before they exit.

SIGTERM's default ends a process on the spot, which would orphan a worker process or leave a half-written
bag; raising :class:`Interrupted` instead unwinds through the command's ``finally`` blocks like Ctrl-C does.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived; ``signum`` says which (exit code 128 + signum)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextlib.contextmanager
def signals_interrupt() -> Iterator[None]:
    """SIGINT and SIGTERM raise :class:`Interrupted` in the main thread, once: a second signal during the
    (bounded) cleanup is ignored, so it cannot turn a clean stop into a traceback. A signal that lands inside C
    code (e.g. pybind11 converting a return value) comes out wrapped in another exception (a TypeError): once the
    signal has fired, whatever escapes the block is re-raised as the :class:`Interrupted` it is. The previous
    handlers come back afterwards. Outside the main thread (where handlers cannot be set) it does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    fired: int | None = None

    def handler(signum: int, _frame) -> None:
        nonlocal fired
        if fired is None:
            fired = signum
            raise Interrupted(signum)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    except BaseException as e:
        if fired is not None and not isinstance(e, KeyboardInterrupt):
            raise Interrupted(fired) from e
        raise
    finally:
        for s, h in previous.items():
            signal.signal(s, signal.SIG_DFL if h is None else h)


@contextlib.contextmanager
def sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while a child process is started (the disposition survives exec, so the child boots
    immune to the Ctrl-C the terminal sends to the whole process group); no-op outside the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)
