"""Progress lines (cosim.progress, by tqdm): labels, speed and remaining time, plain
lines in logs, frames on a terminal."""

from __future__ import annotations

import io

import pytest

from cosim import progress as progress_module
from cosim.master import Component, Master
from cosim.progress import Progress


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


class Terminal(io.StringIO):
    def isatty(self):
        return True


@pytest.fixture
def clock(monkeypatch):
    fake = Clock()
    monkeypatch.setattr(progress_module.wallclock, "perf_counter", fake)
    return fake


def test_log_gets_plain_throttled_lines_with_label_speed_and_remaining_time(clock):
    log = io.StringIO()
    lines = Progress("reference run", 1200.0, stream=log, log_every_s=10.0)
    lines.update(0.5)
    clock.now += 4.0
    lines.update(400.0)           # within 10 s of the last line: not written
    clock.now += 6.0
    lines.update(600.0)
    clock.now += 10.0
    lines.close()
    text = log.getvalue()
    assert "\r" not in text and text.isascii()
    first, second, last = text.splitlines()
    assert first.startswith("reference run:   0%|") and "0.5/1200.0" in first
    assert "?sim-s/s" in first  # nothing measured yet
    # speed and remaining time from the first line on (start-up excluded): 599.5 s in 10 s
    assert "50%|#####     | 600.0/1200.0 [00:10<00:10, 59.95sim-s/s]" in second
    # the run ended there, halfway through its estimate: the last line says so
    assert last.endswith("600.0/600.0 [00:20<00:00, 29.98sim-s/s, "
                         "ended at 600 s of the estimated 1200 s]")


def test_terminal_gets_tqdm_frames_and_a_final_line_break():
    terminal = Terminal()
    lines = Progress("simulate", 100.0, stream=terminal, every_s=0.0)
    lines.update(10.0)
    lines.update(50.0)
    lines.note("a message")
    lines.close()
    text = terminal.getvalue()
    assert text.count("\r") >= 2 and "simulate:  50%|" in text
    assert "simulate: a message\n" in text and text.endswith("\n")


def test_unknown_total_has_no_bar_and_no_remaining_time(clock):
    log = io.StringIO()
    lines = Progress("dem pile", None, stream=log, log_every_s=1.0)
    lines.update(0.0, "0 particles")
    clock.now += 3.0
    lines.update(1.5, "12 particles")
    first, second = log.getvalue().splitlines()
    assert first == "dem pile: 0.0 s [00:00, ?sim-s/s, 0 particles]"
    assert second == "dem pile: 1.5 s [00:03,  2.00s/sim-s, 12 particles]"


class Idle(Component):
    name = "idle"

    def step(self, t, dt):
        pass


def test_master_reports_with_its_label_in_plain_lines(capsys):
    master = Master(step=1.0, progress="unit run")
    master.add(Idle())
    master.run(5.0)
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.splitlines()
    assert lines[0].startswith("unit run: ") and lines[-1].startswith("unit run: 100%|")
    assert "5.0/5.0" in lines[-1]


def test_a_run_past_its_estimated_total_says_so(clock):
    log = io.StringIO()
    lines = Progress("dem pile", 12.5, stream=log)
    clock.now += 2.0
    lines.update(13.0, force=True)
    assert log.getvalue() == "dem pile: 13.0 s [00:02, ?sim-s/s, estimated 12.5 s]\n"


def test_a_run_that_ends_before_its_estimated_total_ends_its_bar_there(clock):
    log = io.StringIO()
    lines = Progress("dem pile", 2.0, stream=log)
    lines.update(0.5)
    clock.now += 3.0
    lines.update(1.5)
    lines.close("300 particles")
    last = log.getvalue().splitlines()[-1]
    assert last == ("dem pile: 100%|##########| 1.5/1.5 [00:03<00:00,  3.00s/sim-s, "
                    "300 particles, ended at 1.5 s of the estimated 2 s]")
    terminal = Terminal()
    bar = Progress("dem pile", 2.0, stream=terminal, every_s=0.0)
    bar.update(0.5)
    bar.update(1.5)
    bar.close()
    assert "100%" in terminal.getvalue().rsplit("\r", 1)[-1]
    assert "ended at 1.5 s of the estimated 2 s" in terminal.getvalue()
