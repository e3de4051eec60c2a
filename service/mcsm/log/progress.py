"""Progress over the bytes of a recording being read (``replay``, ``recover``, ``serve
--restore``): a tqdm bar on a terminal, plain lines in a log."""

from __future__ import annotations

import sys
import time
from typing import Any


class Progress:
    """Progress over bytes: a tqdm bar when ``stream`` is a terminal; otherwise a plain line
    (``label: 40% (12.0 of 30.0 MB)``) every ``every_s`` seconds and a last one at the end
    (none for a run shorter than ``every_s``), so that logs get what a bar would say and
    never a ``\\r``."""

    def __init__(self, label: str, stream: Any = None, every_s: float = 10.0) -> None:
        self.label = label
        self.out = stream if stream is not None else sys.stderr
        self.every_s = every_s
        self._bar: Any = None
        self._tty = bool(getattr(self.out, "isatty", lambda: False)())
        self._last = time.monotonic()
        self._lines = 0
        self.done = False

    def __call__(self, done: int, total: int) -> None:
        if self.done:
            return
        if self._tty:
            if self._bar is None:
                from tqdm import tqdm

                self._bar = tqdm(total=total, desc=self.label, unit="B", unit_scale=True,
                                 file=self.out, leave=True, dynamic_ncols=True)
            self._bar.update(done - self._bar.n)
        else:
            now = time.monotonic()
            if now - self._last >= self.every_s or (done >= total and self._lines):
                self._last = now
                self._lines += 1
                frac = 1.0 if total <= 0 else min(1.0, done / total)
                self.out.write(f"{self.label}: {100 * frac:.0f}% ({done / 1e6:.1f} of "
                               f"{total / 1e6:.1f} MB)\n")
                self.out.flush()
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._bar is not None and not self.done:
            self._bar.close()
        self.done = True


def progress_bar(stream: Any = None, label: str = "replaying the recording") -> Progress:
    """A :class:`Progress` over bytes read (a bar on a terminal, plain lines otherwise)."""
    return Progress(label, stream)
