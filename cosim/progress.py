"""Progress of a long run on stderr, by tqdm: a label, how far, how fast, when it ends.

One helper for every long run (the co-simulation master, ``reproduce``,
``dem pile``/``discharge``). On a terminal it is a tqdm bar, redrawn at most
every ``every_s`` seconds. When the stream is not a terminal (a log file, a
pipe, CI) tqdm's frames (``\\r`` redraws) would fill the log, so the same
tqdm line (``tqdm.format_meter``) is written as a plain line at most every
``log_every_s`` seconds. A line reads

    simulate:  25%|##5       | 300.0/1200.0 [00:03<00:10, 88.00sim-s/s]

where the rate is simulated seconds per wall second (the real-time factor).
The rate and the remaining time are measured from the first update on, so the
start-up (building, compiling) does not count in them. ``note`` prints a
one-off message, e.g. that the first call compiles the numerical kernels.

Parameters (``Progress``)
-------------------------
label : str
    What runs, e.g. ``"simulate"`` or ``"reference run"``.
total : float or None
    Simulated time [s] the run goes to, or an estimate of it; None when
    unknown (no bar, no remaining time).
stream : file
    Where to write, default ``sys.stderr``.
unit : str
    What is counted, default simulated seconds (``UNIT``); a whole count such as
    ``"run"`` is shown as integers.
every_s, log_every_s : float
    Least wall time [s] between two updates on a terminal (default 1) and
    in a log (default 10).
"""

from __future__ import annotations

import sys
import time as wallclock

from tqdm import tqdm

UNIT = "sim-s"
"""Unit of the progress count: simulated seconds. The rate reads "88.00sim-s/s"
(the real-time factor) or, slower than real time, "2.00s/sim-s" (tqdm inverts it)."""


class Progress:
    """Progress of one run (see module docstring)."""

    def __init__(self, label: str, total: float | None = None, *, stream=None,
                 every_s: float = 1.0, log_every_s: float = 10.0, unit: str = UNIT):
        self.label = label
        self.total = total
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.terminal = self.stream.isatty()
        self.every_s = every_s if self.terminal else log_every_s
        self.start = wallclock.perf_counter()
        self.done = 0.0
        self.last = None
        self._first = None  # (wall time, done) of the first update
        self._bar = None

    def _past_total(self, done: float) -> bool:
        # a run may step a hair past its end (a DEM's last step): not "past the estimate"
        return bool(self.total) and done > self.total * (1 + 1e-3)

    def _total_for(self, done: float):
        # past an estimated total: no bar rather than a bar over 100 %
        return None if not self.total or self._past_total(done) else self.total

    def _shown(self, done: float):
        return round(done, 2) if self.unit == UNIT else int(round(done))

    def line(self, done: float, extra: str = "") -> str:
        """The progress text at ``done`` simulated seconds (no line break)."""
        now = wallclock.perf_counter()
        if self._first is None:
            self._first = (now, done)
        measured_s = now - self._first[0]
        rate = (done - self._first[1]) / measured_s if measured_s > 0.5 else None
        postfix = extra
        if self._past_total(done):
            postfix = ", ".join(p for p in (f"estimated {self.total:g} s", extra) if p)
        shown = self._shown(min(done, self.total) if self._total_for(done) else done)
        return tqdm.format_meter(shown, self._total_for(done), now - self.start,
                                 prefix=self.label, unit=self.unit, rate=rate, ascii=True,
                                 initial=shown if rate is None else 0,
                                 postfix=postfix or None,
                                 bar_format=None if self._total_for(done) else
                                 "{desc}: {n:.1f} s [{elapsed}, {rate_fmt}{postfix}]")

    def update(self, done: float, extra: str = "", *, force: bool = False) -> None:
        """Report ``done`` simulated seconds; throttled unless ``force``."""
        self.done = done
        now = wallclock.perf_counter()
        if not force and self.last is not None and now - self.last < self.every_s:
            return
        self.last = now
        if not self.terminal:
            print(self.line(done, extra), file=self.stream, flush=True)
            return
        if self._bar is None or (self._bar.total and self._past_total(done)):
            if self._bar is not None:
                self._bar.close()
            self._bar = tqdm(total=self._total_for(done), initial=done, desc=self.label,
                             unit=self.unit, file=self.stream, mininterval=self.every_s,
                             dynamic_ncols=True, leave=True)
        self._bar.n = self._shown(min(done, self._bar.total) if self._bar.total else done)
        self._bar.set_postfix_str(extra, refresh=False)
        self._bar.refresh()

    def note(self, text: str) -> None:
        """A one-off message on its own line."""
        message = f"{self.label}: {text}"
        if self._bar is not None:
            self._bar.write(message, file=self.stream)
        else:
            print(message, file=self.stream, flush=True)

    def close(self, extra: str = "") -> None:
        """The final line: where the run ended and how long it took. A run that
        ends before its estimated total (a pile that settled early) ends its bar
        there, at 100 %, and says so."""
        if self.total and self.done < self.total * (1 - 1e-3):
            ended = (f"ended at {self.done:g} s of the estimated {self.total:g} s"
                     if self.unit == UNIT else f"ended after {self.done:g} of {self.total:g}")
            extra = ", ".join(p for p in (extra, ended) if p)
            self.total = self.done
            if self._bar is not None:
                self._bar.total = self._shown(self.done)
        self.update(self.done, extra, force=True)
        if self._bar is not None:
            self._bar.close()
            self._bar = None
