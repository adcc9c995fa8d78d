"""A plain-text progress bar for long command-line jobs (``fixego sim``, ``fixego replay``)."""

from __future__ import annotations

import sys
import time


class Progress:
    """Plain-text progress bar on stderr (at most ~4 updates per second); ``total`` 0 = unknown (count only)."""

    def __init__(self, total: int, label: str, enabled: bool = True, stream=None, unit: str = 'frames') -> None:
        self.total, self.label, self.enabled, self.unit = max(int(total), 0), label, enabled, unit
        self.stream = stream or sys.stderr
        self.start = time.monotonic()
        self._last = -1.0
        self._done = 0
        self._open = False      # a line without its newline is on the terminal

    def update(self, done: int) -> None:
        self._done = done
        now = time.monotonic()
        if not self.enabled or (now - self._last < 0.25 and (self.total == 0 or done < self.total)):
            return
        self._last = now
        rate = done / max(now - self.start, 1e-9)
        if self.total:
            frac = min(done / self.total, 1.0)
            eta = max(self.total - done, 0) / rate if rate > 0 else 0.0
            bar = '#' * int(30 * frac) + '.' * (30 - int(30 * frac))
            text = f'[{bar}] {done}/{self.total} {self.unit}  {rate:5.1f}/s  ETA {eta:5.1f} s'
        else:
            text = f'{done} {self.unit}  {rate:5.1f}/s'
        self.stream.write(f'\r{self.label} {text}')
        self._open = True
        if self.total and done >= self.total:
            self.finish()
        self.stream.flush()

    def finish(self) -> None:
        """End the bar's line (once)."""
        if self.enabled and self._open:
            self.stream.write('\n')
            self.stream.flush()
        self._open = False
