"""Progress of a long run on stderr: a label, how far, how fast, and when it ends.

One helper for every long run (the co-simulation master, ``reproduce``,
``dem pile``/``discharge``). On a terminal it redraws one line (``\\r``
frames) at most every ``every_s`` seconds; when stderr is not a terminal (a
log file, a pipe, CI) it writes plain lines instead, at most every
``log_every_s`` seconds, so a log holds readable lines and no ``\\r`` frames.
A line reads

    simulate: [#######       ] t = 300.0 / 1200 s (25 %), 88x real time, 3 s elapsed, ETA 10 s

The speed and the ETA are measured from the first line on, so the start-up
(building, compiling) does not count in them, and the first line has neither
(no "0x real time"). ``note`` prints a one-off message, e.g.
that the first call compiles the numerical kernels.

Parameters (``Progress``)
-------------------------
label : str
    What runs, e.g. ``"simulate"`` or ``"reference run"``.
total : float or None
    Simulated time [s] the run goes to, or an estimate of it; None when
    unknown (no bar, no ETA).
stream : file
    Where to write, default ``sys.stderr``.
every_s, log_every_s : float
    Least wall time [s] between two updates on a terminal (default 1) and
    in a log (default 10).
"""

from __future__ import annotations

import sys
import time as wallclock

BAR_WIDTH = 24


def _duration(seconds: float) -> str:
    seconds = max(seconds, 0.0)
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


class Progress:
    """Progress lines for one run (see module docstring)."""

    def __init__(self, label: str, total: float | None = None, *, stream=None,
                 every_s: float = 1.0, log_every_s: float = 10.0):
        self.label = label
        self.total = total
        self.stream = stream if stream is not None else sys.stderr
        self.terminal = bool(getattr(self.stream, "isatty", lambda: False)())
        self.every_s = every_s if self.terminal else log_every_s
        self.start = wallclock.perf_counter()
        self.last = None
        self.done = 0.0
        self._first = None  # (wall time, done) of the first line
        self._open_frame = False

    def line(self, done: float, extra: str = "") -> str:
        """The progress text at ``done`` simulated seconds (no line break)."""
        now = wallclock.perf_counter()
        elapsed = now - self.start
        if self._first is None:
            self._first = (now, done)
        measured_s, measured = now - self._first[0], done - self._first[1]
        parts = []
        if self.total and done > self.total:  # the total was an estimate
            parts.append(f"t = {done:.1f} s (estimated {self.total:g} s)")
        elif self.total:
            fraction = min(max(done / self.total, 0.0), 1.0)
            bar = "#" * int(BAR_WIDTH * fraction)
            parts.append(f"[{bar:<{BAR_WIDTH}}] t = {done:.1f} / {self.total:g} s "
                         f"({100 * fraction:.0f} %)")
        else:
            parts.append(f"t = {done:.1f} s")
        rate = measured / measured_s if measured_s > 0.5 and measured > 0 else None
        if rate is not None:
            parts.append(f"{rate:,.0f}x real time" if rate >= 10 else f"{rate:.2g}x real time")
        parts.append(f"{_duration(elapsed)} elapsed")
        if self.total and rate is not None and done < self.total:
            parts.append(f"ETA {_duration((self.total - done) / rate)}")
        if extra:
            parts.append(extra)
        return f"{self.label}: " + ", ".join(parts)

    def update(self, done: float, extra: str = "", *, force: bool = False) -> None:
        """Report ``done`` simulated seconds; throttled unless ``force``."""
        self.done = done
        now = wallclock.perf_counter()
        if not force and self.last is not None and now - self.last < self.every_s:
            return
        self.last = now
        text = self.line(done, extra)
        if self.terminal:
            print(f"\r{text}\033[K", end="", file=self.stream, flush=True)
            self._open_frame = True
        else:
            print(text, file=self.stream, flush=True)

    def note(self, text: str) -> None:
        """A one-off message on its own line."""
        self._end_frame()
        print(f"{self.label}: {text}", file=self.stream, flush=True)

    def close(self, extra: str = "") -> None:
        """The final line: where the run ended and how long it took."""
        self.update(self.done, extra, force=True)
        self._end_frame()

    def _end_frame(self) -> None:
        if self._open_frame:
            print(file=self.stream, flush=True)
            self._open_frame = False
