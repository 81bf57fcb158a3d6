"""The monitor in a real browser (Debian chromium driven by Playwright).

Real processes on 127.0.0.1: a stockpile (``python -m minetwin.demo_stockpile``:
the stockpile asset with its REST interface) and the monitor
(``minetwin monitor``). The page must show the REST values, switch the
colouring, follow the simulation, say "unreachable" when the stockpile
stops and recover by itself when it restarts, while the monitor keeps
serving. Screenshots go to the test's tmp dir (and to
``$MINETWIN_SCREENSHOT_DIR`` when set).
"""

from __future__ import annotations

import datetime
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
MINETWIN = str(Path(sys.executable).with_name("minetwin"))
STEP_RESPONSE = Path(__file__).resolve().parents[1] / "examples" / "step_response.toml"


def _ensure_chromium() -> None:
    """Debian's chromium, a prerequisite that ``make test`` installs
    (tools/install_test_prereqs.sh); skipped without it, failed under ``make test``."""
    if os.path.exists(CHROMIUM):
        return
    message = f"{CHROMIUM} missing: run 'make test-prereqs' (installs Debian's chromium, needs root)"
    if os.environ.get("MINETWIN_REQUIRE_PREREQS") == "1":
        pytest.fail(message)
    pytest.skip(message)


def _start(args, pattern, stream="stdout", timeout=30.0):
    """Start a process and wait for the line matching ``pattern`` (returns proc, match)."""
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pipe = getattr(proc, stream)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = pipe.readline()
        if not line:
            break
        match = re.search(pattern, line)
        if match:
            # keep reading both pipes so that a chatty process never blocks on a full pipe
            proc.drains = [threading.Thread(target=pipe.read, daemon=True)
                           for pipe in (proc.stdout, proc.stderr)]
            for drain in proc.drains:
                drain.start()
            return proc, match
    proc.kill()
    rest = proc.communicate(timeout=10)
    raise AssertionError(f"{args} did not print {pattern!r}: {rest}")


def _stop(proc) -> None:
    """Stop (SIGTERM, then kill), let the pipe readers finish, close the pipes."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    for drain in getattr(proc, "drains", ()):
        drain.join(timeout=10)
    for pipe in (proc.stdout, proc.stderr):
        pipe.close()


def _start_stockpile(port=0):
    return _start([sys.executable, "-m", "minetwin.demo_stockpile", "--port", str(port),
                   "--speed", "4", "--seed", "1"], r"http://127\.0\.0\.1:(\d+)")


def get(url):
    try:
        with urllib.request.urlopen(url, timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def _launch(playwright):
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)


def _check_shown_values_equal_rest(page, stockpile_url):
    """The held mass and grade shown equal the stockpile's REST values at
    the simulation time shown (the history row of that time)."""
    shown = page.evaluate("""() => ({
        time: Number(document.getElementById('sim-time').dataset.value),
        mass: document.getElementById('held-mass').dataset.value,
        massText: document.getElementById('held-mass').textContent,
        grade: document.getElementById('grade').dataset.value,
        gradeText: document.getElementById('grade').textContent})""")
    status, history = get(f"{stockpile_url}/history?since={shown['time'] - 1e-6}")
    assert status == 200
    row = history["rows"][0]
    assert row["time_s"] == shown["time"]
    assert float(shown["mass"]) == row["held_mass_kg"] > 0
    assert shown["massText"] == f"{row['held_mass_kg'] / 1000:.1f}"
    assert float(shown["grade"]) == row["grade"]
    assert shown["gradeText"] == f"{row['grade'] * 100:.2f}"
    return shown


def _start_monitor(stockpile_url):
    return _start([MINETWIN, "monitor", "--stockpile", stockpile_url, "--port", "0"],
                  r"http://127\.0\.0\.1:\d+/", stream="stderr")


@pytest.fixture
def processes():
    """Running stockpile and monitor; stops whatever is still running after the test."""
    _ensure_chromium()
    running = {}
    try:
        running["stockpile"], match = _start_stockpile()
        stockpile_url = match.group(0)
        running["monitor"], match = _start_monitor(stockpile_url)
        yield running, stockpile_url, match.group(0)
    finally:
        for proc in running.values():
            _stop(proc)


def test_monitor_page_against_a_running_stockpile(processes, tmp_path):
    sync_api = pytest.importorskip("playwright.sync_api")
    running, stockpile_url, monitor_url = processes
    shots = [tmp_path / "monitor_live.png", tmp_path / "monitor_unreachable.png",
             tmp_path / "monitor_recovered.png"]
    with sync_api.sync_playwright() as playwright:
        browser = _launch(playwright)
        try:
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            requested, errors = [], []
            page.on("request", lambda request: requested.append(request.url))
            page.on("pageerror", lambda error: errors.append(str(error)))
            # the 503s while the stockpile is down are expected; page faults are not
            page.on("console", lambda message: message.type == "error"
                    and not message.text.startswith("Failed to load resource")
                    and errors.append(message.text))
            page.goto(monitor_url + "?poll=400")
            expect = sync_api.expect
            expect(page.locator("#status")).to_have_text("LIVE", timeout=15_000)
            page.wait_for_function("window.monitorState.updates >= 2", timeout=10_000)

            _check_shown_values_equal_rest(page, stockpile_url)
            assert int(page.locator("#pile").get_attribute("data-drawn")) > 0

            # the monitor passes the stockpile's refusals through, and only its endpoints
            status, body = get(monitor_url + "api/fields?nx=0")
            assert status == 400 and body["field"] == "nx"
            status, body = get(monitor_url + "api/shutdown")
            assert status == 404 and body["field"] == "endpoint"

            # switching the colouring redraws the pile with the new attribute
            pile = page.locator("#pile")
            before = page.evaluate("document.getElementById('pile').toDataURL()")
            for attribute, label in (("hardness", "hardness (relative) [-]"),
                                     ("residence_time", "residence time [s]"),
                                     ("origin", "origin")):
                page.select_option("#colour-by", attribute)
                expect(pile).to_have_attribute("data-colour-by", attribute)
                expect(page.locator("#legend-label")).to_have_text(label)
            # source 1 delivers from 27.5 s of simulation (7 s of wall time at speed 4); the
            # key names both sources as the stockpile calls them
            expect(page.locator("#legend-min")).to_contain_text("ore body B (80 % grade)",
                                                                timeout=30_000)
            expect(page.locator("#legend-min")).to_contain_text("ore body A (20 % grade)")
            assert page.evaluate("document.getElementById('pile').toDataURL()") != before
            page.select_option("#colour-by", "grade")

            # the page follows the simulation
            updates, t0, mass0 = page.evaluate("""() => [window.monitorState.updates,
                Number(document.getElementById('sim-time').dataset.value),
                document.getElementById('held-mass').dataset.value]""")
            page.wait_for_function(
                f"Number(document.getElementById('sim-time').dataset.value) > {t0 + 2}",
                timeout=10_000)
            assert page.evaluate("window.monitorState.updates") > updates
            # inflow and outflow can cancel over a couple of seconds: wait for a change
            page.wait_for_function(
                f"document.getElementById('held-mass').dataset.value !== '{mass0}'",
                timeout=15_000)
            assert page.evaluate("window.monitorState.history.length") >= 5
            page.screenshot(path=str(shots[0]), full_page=True)

            # the stockpile stops: the page says so, the monitor keeps serving
            last_time = float(page.locator("#sim-time").get_attribute("data-value"))
            _stop(running["stockpile"])
            expect(page.locator("#status")).to_have_text("STOCKPILE UNREACHABLE", timeout=10_000)
            expect(page.locator("#unreachable-banner")).to_be_visible()
            assert get(monitor_url + "monitor/health")[0] == 200
            status, body = get(monitor_url + "api/totals")
            assert status == 503 and body["error"] == "stockpile unreachable"
            page.screenshot(path=str(shots[1]), full_page=True)

            # it restarts on the same port: the page recovers by itself, new run
            port = stockpile_url.rsplit(":", 1)[1]
            running["stockpile"], _ = _start_stockpile(port)
            expect(page.locator("#status")).to_have_text("LIVE", timeout=15_000)
            expect(page.locator("#unreachable-banner")).to_be_hidden()
            page.wait_for_function("window.monitorState.updates > 0 && "
                                   "window.monitorState.history.length > 0", timeout=10_000)
            first = page.evaluate("window.monitorState.history[0].time_s")
            assert first < last_time  # the chart restarted with the new run
            # and the page says so, naming the jump of the clock (from the last
            # time it saw, which may be a poll later than last_time)
            expect(page.locator("#restart-banner")).to_be_visible()
            restarts = page.evaluate("window.monitorState.restarts")
            assert len(restarts) == 1 and restarts[0]["from_s"] >= last_time > first
            expect(page.locator("#restart-detail")).to_contain_text(
                f"its clock went back from t = {restarts[0]['from_s']:.1f} s to "
                f"{restarts[0]['to_s']:.1f} s")
            page.screenshot(path=str(shots[2]), full_page=True)
            # the monitor server saw the clock go back too: the old run's LEVEL LOW (a few
            # t of the default 2000 t) cleared by the restart, and the new run raised its own
            deadline = time.monotonic() + 10
            while True:
                alarms = get(monitor_url + "monitor/alarms")[1]["alarms"]
                low = [o for o in alarms if o["id"] == "level_low"]
                if len(low) == 2 or time.monotonic() > deadline:
                    break
                time.sleep(0.2)
            assert [(o["state"], o["cleared_by"]) for o in low] == \
                [("CLEARED_UNACK", "restart"), ("ACTIVE_UNACK", None)]
            # both at the new run's first row: the old one clears as the new one is raised
            assert low[0]["cleared_s"] == low[1]["raised_s"] < last_time

            assert running["monitor"].poll() is None
            assert all(url.startswith(monitor_url) or url.startswith("data:")
                       for url in requested), [u for u in requested if monitor_url not in u]
            assert errors == []
        finally:
            browser.close()
    for shot in shots:
        assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    copy_to = os.environ.get("MINETWIN_SCREENSHOT_DIR")
    if copy_to:
        Path(copy_to).mkdir(parents=True, exist_ok=True)
        for shot in shots:
            shutil.copy(shot, Path(copy_to) / shot.name)


def test_monitor_page_against_the_mine_simulator(tmp_path):
    """The stockpile of the mine simulator (the step-response scenario that
    ``minetwin simulate`` runs), served by RestComponent in real time x 25."""
    _ensure_chromium()
    sync_api = pytest.importorskip("playwright.sync_api")
    stockpile, match = _start([sys.executable, "-m", "minetwin.demo_stockpile", "--port", "0",
                               "--speed", "25", "--scenario", str(STEP_RESPONSE)],
                              r"http://127\.0\.0\.1:(\d+)", timeout=60)
    monitor = None
    try:
        monitor, page_match = _start_monitor(match.group(0))
        with sync_api.sync_playwright() as playwright:
            browser = _launch(playwright)
            try:
                page = browser.new_page(viewport={"width": 1600, "height": 1000})
                page.goto(page_match.group(0) + "?poll=400")
                sync_api.expect(page.locator("#status")).to_have_text("LIVE", timeout=15_000)
                # the first truck loads reach the stockpile after about 100 s
                page.wait_for_function(
                    "Number(document.getElementById('held-mass').dataset.value) > 0",
                    timeout=30_000)
                _check_shown_values_equal_rest(page, match.group(0))
                # FIFO has no geometry: the picture says it is schematic
                sync_api.expect(page.locator("#pile")).to_have_attribute("data-layout",
                                                                         "schematic")
                sync_api.expect(page.locator("#pile-title")).to_contain_text("SCHEMATIC")
                # the events the page holds are the stockpile's, in order
                shown = page.evaluate("""() => window.monitorState.events.map(
                    (e) => [e.seq, e.kind, e.mass_kg, e.particle_count])""")
                status, served = get(match.group(0) + "/events")
                assert status == 200 and shown
                assert shown == [[e["seq"], e["kind"], e["mass_kg"], e["particle_count"]]
                                 for e in served["events"]][:len(shown)]
                page.select_option("#colour-by", "origin")
                sync_api.expect(page.locator("#pile")).to_have_attribute("data-colour-by",
                                                                         "origin")
                page.screenshot(path=str(tmp_path / "monitor_mine_simulator.png"), full_page=True)
            finally:
                browser.close()
    finally:
        for proc in (stockpile, monitor):
            if proc is not None:
                _stop(proc)
    assert (tmp_path / "monitor_mine_simulator.png").read_bytes()[:4] == b"\x89PNG"


def test_a_pile_with_geometry_is_drawn_as_particle_positions_with_a_metre_scale(tmp_path):
    """A ROM stockpile (particles with positions) is titled as particle positions,
    not schematic; its metre scale is a round length of a few tenths of the pile's
    width; the velocity key names a round speed; the origin key names the sources."""
    _ensure_chromium()
    sync_api = pytest.importorskip("playwright.sync_api")
    import warnings

    from surrogate.rest import serve_in_thread
    from surrogate.stockpile import StockpileAsset

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a small pile is outside the ROM's training range
        asset = StockpileAsset("rom", seed=0, source_names={0: "north pit", 1: "south pit"})
        for k in range(20):
            asset.receive_bin(k + 1, 7_500.0, 0.01, 1.0, source=k % 2)
        asset.set_discharge_rate(200.0)
        for _ in range(4):
            asset.step(0.5)
    rest = serve_in_thread(asset)
    monitor = None
    try:
        monitor, match = _start_monitor(f"http://127.0.0.1:{rest.port}")
        with sync_api.sync_playwright() as playwright:
            browser = _launch(playwright)
            try:
                page = browser.new_page(viewport={"width": 1600, "height": 1000})
                page.goto(match.group(0) + "?poll=400")
                pile = page.locator("#pile")
                sync_api.expect(pile).to_have_attribute("data-layout", "particles", timeout=20_000)
                sync_api.expect(page.locator("#pile-title")).to_have_text(
                    "Pile cross-section — particle positions")
                _, particles = get(f"http://127.0.0.1:{rest.port}/particles?limit=50000")
                width_m = max(particles["x"]) - min(particles["x"])
                metres = float(pile.get_attribute("data-scale-metres"))
                mantissa = metres / 10 ** math.floor(math.log10(metres))
                assert round(mantissa, 9) in (1.0, 2.0, 5.0)
                assert 0.05 * width_m <= metres <= 0.5 * width_m, (metres, width_m)
                speed = float(pile.get_attribute("data-velocity-key"))
                assert round(speed / 10 ** math.floor(math.log10(speed)), 9) in (1.0, 2.0, 5.0)
                page.select_option("#colour-by", "origin")
                sync_api.expect(page.locator("#legend-min")).to_have_text("north pitsouth pit")
                page.screenshot(path=str(tmp_path / "monitor_rom.png"), full_page=True)
            finally:
                browser.close()
    finally:
        if monitor is not None:
            _stop(monitor)
        rest.stop()


def test_monitor_command_refuses_a_bad_stockpile_url():
    done = subprocess.run([MINETWIN, "monitor", "--stockpile", "ftp://127.0.0.1:1", "--port", "0"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "stockpile: must be an http:// or https:// URL" in done.stderr


def test_monitor_command_fails_on_a_busy_port():
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = subprocess.run([MINETWIN, "monitor", "--stockpile", "http://127.0.0.1:9",
                               "--port", str(port)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1
    assert f"cannot serve on 127.0.0.1:{port}" in done.stderr


# ------------------------------------------------------- the operator's screen
CAPACITY_T = 50.0
LEVEL_HIGH_PCT = 60.0
LEVEL_DEADBAND_PCT = 4.0


@pytest.fixture
def driven_stockpile(tmp_path):
    """A stockpile asset served on 127.0.0.1 whose bins, feeder and steps the
    test drives, and the monitor (its own process) configured with a 50 t
    capacity and a 60 % high-level alarm that clears at 56 % (4 % dead band)."""
    _ensure_chromium()
    from surrogate.rest import serve_in_thread
    from surrogate.stockpile import StockpileAsset

    asset = StockpileAsset("fifo", seed=0, source_names={0: "north pit", 1: "south pit"})
    rest = serve_in_thread(asset)
    config = tmp_path / "monitor.toml"
    config.write_text(f"[stockpile]\ncapacity_t = {CAPACITY_T}\n[alarms]\n"
                      f"level_high_pct = {LEVEL_HIGH_PCT}\nlevel_low_pct = 0.0\n"
                      f"level_deadband_pct = {LEVEL_DEADBAND_PCT}\ncheck_interval_s = 0.2\n"
                      "grade_low_pct = 0.0\ngrade_high_pct = 100.0\n")
    stockpile_url = f"http://127.0.0.1:{rest.port}"
    monitor = None
    try:
        monitor, match = _start([MINETWIN, "monitor", "--stockpile", stockpile_url, "--port", "0",
                                 "--config", str(config)],
                                r"http://127\.0\.0\.1:\d+/", stream="stderr")
        yield asset, rest, stockpile_url, match.group(0)
    finally:
        if monitor is not None:
            _stop(monitor)
        rest.stop()


def _drive(page, asset, rest, bins=(), rate=0.0, steps=0):
    """Deliver ``bins`` (tracking id, mass [kg], grade, source), run the feeder at
    ``rate`` [kg/s] for ``steps`` steps of 1 s, and wait until the page shows that time
    (and the monitor's alarms checked up to it)."""
    with rest.lock:
        for tracking_id, mass, grade, source in bins:
            asset.receive_bin(tracking_id, mass, grade, 1.0 + grade, source=source)
        asset.set_discharge_rate(rate)
        for _ in range(steps):
            asset.step(1.0)
        time_s = asset.time
    page.wait_for_function(
        f"window.monitorState.history.length > 0 && "
        f"window.monitorState.history[window.monitorState.history.length - 1].time_s === {time_s}"
        f" && window.monitorState.lastSeq === {asset.lots.last_seq}"
        f" && window.monitorState.alarmsChecked === {time_s}", timeout=10_000)
    # one more poll, so that every element drawn shows the same state
    updates = page.evaluate("window.monitorState.updates")
    page.wait_for_function(f"window.monitorState.updates > {updates}", timeout=10_000)
    return time_s


def _shown(page, element_id):
    return page.evaluate(f"""() => {{ const el = document.getElementById('{element_id}');
        return [el.dataset.value, el.textContent]; }}""")


def test_monitor_operator_screen(driven_stockpile, tmp_path):
    """Capacity %, setpoint against actual, an alarm raised and cleared by the
    level the test drives, the event list against the lots delivered, a zoomed
    trend and the CSV export against /history, in Debian chromium."""
    sync_api = pytest.importorskip("playwright.sync_api")
    asset, rest, stockpile_url, monitor_url = driven_stockpile
    with sync_api.sync_playwright() as playwright:
        browser = _launch(playwright)
        try:
            page = browser.new_page(viewport={"width": 1600, "height": 1000},
                                    accept_downloads=True)
            errors = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            page.on("console", lambda message: message.type == "error"
                    and errors.append(message.text))
            page.goto(monitor_url + "?poll=250")
            sync_api.expect(page.locator("#status")).to_have_text("LIVE", timeout=15_000)

            # two lots in, the feeder at 500 kg/s for 4 s: 18 t held of 50 t
            lots = [(11, 10_000.0, 0.3, 0), (12, 10_000.0, 0.5, 1)]
            _drive(page, asset, rest, lots, rate=500.0, steps=4)
            _, totals = get(stockpile_url + "/totals")
            assert totals["held_mass_kg"] == pytest.approx(18_000.0)
            fill, fill_text = _shown(page, "fill-pct")
            assert float(fill) == pytest.approx(100 * totals["held_mass_kg"] / (1000 * CAPACITY_T),
                                                rel=1e-12)
            assert fill_text == "36.0"
            assert page.locator("#capacity").text_content() == "50"
            setpoint, setpoint_text = _shown(page, "discharge-rate")
            actual, actual_text = _shown(page, "discharge-actual")
            assert float(setpoint) == totals["discharge_rate_kg_s"] == 500.0
            assert float(actual) == totals["discharge_actual_kg_s"] == pytest.approx(500.0)
            assert setpoint_text == actual_text == "1800"  # t/h
            assert _shown(page, "alarm-count")[0] == "0"

            # the event list is the stockpile's /events, and its lots in are the bins delivered
            _, events = get(stockpile_url + "/events")
            rows = page.evaluate("""() => [...document.querySelectorAll('#event-list tr')]
                .map((tr) => [Number(tr.dataset.seq), tr.dataset.kind,
                              Number(tr.dataset.trackingId), Number(tr.dataset.mass)])""")
            assert rows == [[e["seq"], e["kind"], e["tracking_id"], e["mass_kg"]]
                            for e in reversed(events["events"])]
            assert [(e["tracking_id"], e["mass_kg"], e["grade"], e["source"])
                    for e in events["events"] if e["kind"] == "in"] == [lot for lot in lots]
            out = [e for e in events["events"] if e["kind"] == "out"]
            assert {e["tracking_id"] for e in out} == {11}  # FIFO: the first lot leaves first
            assert sum(e["mass_kg"] for e in out) == pytest.approx(2_000.0)
            assert page.locator("#event-list tr[data-kind='in'] td:nth-child(7)").all_text_contents() \
                == ["south pit", "north pit"]

            # grade alarms off (0-100 %): said so, and no limit lines on the grade trend
            assert page.locator("#grade-band").text_content() == "grade alarms off"
            assert page.evaluate("window.monitorState.charts.grade.series.map((s) => s.label)") \
                == ["t [s]", "grade [%]"]

            # coloured by origin, the feed bars are stacked by the sources the REST predicts
            feed = page.locator("#feed-chart")
            sync_api.expect(feed).to_have_attribute("data-coloured-by", "grade")
            page.select_option("#colour-by", "origin")
            _, predicted = get(stockpile_url + "/feed?horizon=30")
            assert predicted["profile"]["origins"] == [0, 1]  # the rest of lot 11, then lot 12
            sync_api.expect(feed).to_have_attribute("data-coloured-by", "origin")
            assert feed.get_attribute("data-origins") == "0,1"
            sync_api.expect(page.locator("#feed-caption")).to_contain_text(
                "the mass from each source")
            page.select_option("#colour-by", "grade")

            # two more lots: 37.5 t is 75 % of capacity, above the 60 % limit
            _drive(page, asset, rest, [(13, 10_000.0, 0.4, 0), (14, 10_000.0, 0.6, 1)],
                   rate=500.0, steps=1)
            high = page.locator("#alarm-list tr[data-alarm='level_high']")
            sync_api.expect(high).to_have_attribute("data-state", "ACTIVE_UNACK")
            assert _shown(page, "alarm-count") == ["1", "1 ALARM (1 UNACK)"]
            raised_at = asset.time
            # the feeder at 2000 kg/s for 4 s: 29.5 t, 59 % of capacity, below the limit
            # but inside the dead band: still the one alarm
            _drive(page, asset, rest, rate=2000.0, steps=4)
            assert asset.totals()["held_mass_kg"] == pytest.approx(29_500.0)
            assert high.get_attribute("data-state") == "ACTIVE_UNACK"
            # one second more: 27.5 t, 55 %, past the 56 % where it clears
            cleared_at = _drive(page, asset, rest, rate=2000.0, steps=1)
            sync_api.expect(high).to_have_attribute("data-state", "CLEARED_UNACK")
            assert high.count() == 1
            assert _shown(page, "alarm-count") == ["0", "NO ALARM (1 UNACK)"]
            alarm = page.evaluate("window.monitorState.alarms")[0]
            assert (alarm["raised_s"], alarm["cleared_s"]) == (raised_at, cleared_at)
            assert alarm["value"] == pytest.approx(75.0)

            # zoom: drag across the held-mass trend; every trend shows that time range
            _drive(page, asset, rest, [(15, 5_000.0, 0.5, 0)], rate=500.0, steps=6)
            over = page.locator("#trend-mass .u-over").bounding_box()
            y = over["y"] + over["height"] / 2
            page.mouse.move(over["x"] + 0.25 * over["width"], y)
            page.mouse.down()
            page.mouse.move(over["x"] + 0.6 * over["width"], y, steps=8)
            page.mouse.up()
            zoom = page.evaluate("window.monitorState.zoom")
            history = get(stockpile_url + "/history")[1]["rows"]
            assert history[0]["time_s"] < zoom["min"] < zoom["max"] < history[-1]["time_s"]
            updates = page.evaluate("window.monitorState.updates")
            page.wait_for_function(f"window.monitorState.updates > {updates + 1}")
            scales = page.evaluate("""() => Object.values(window.monitorState.charts)
                .map((u) => [u.scales.x.min, u.scales.x.max])""")
            assert len(scales) == 6  # held mass, grade, hardness, D80, discharge, particles
            assert scales == [[zoom["min"], zoom["max"]]] * 6  # kept through new data
            assert page.locator("#zoom-reset").is_enabled()
            page.screenshot(path=str(tmp_path / "monitor_operator.png"), full_page=True)

            # unzoomed, the trends show the whole run, and the CSV export is /history
            page.click("#zoom-reset")
            assert page.evaluate("window.monitorState.zoom") is None
            with page.expect_download() as download:
                page.click("#export-csv")
            exported = download.value.path().read_text().splitlines()
            history = get(stockpile_url + "/history")[1]["rows"]
            header = exported[0].split(",")
            assert header == list(history[0])
            assert len(exported) - 1 == len(history) == 4 + 1 + 4 + 1 + 6  # one row per step
            for line, row in zip(exported[1:], history):
                values = line.split(",")
                assert [None if v == "" else float(v) for v in values] == \
                    [None if row[k] is None else float(row[k]) for k in header]
            assert errors == []
        finally:
            browser.close()
    copy_to = os.environ.get("MINETWIN_SCREENSHOT_DIR")
    if copy_to:
        Path(copy_to).mkdir(parents=True, exist_ok=True)
        shutil.copy(tmp_path / "monitor_operator.png", Path(copy_to) / "monitor_operator.png")


def _x_scales(page):
    return page.evaluate("""() => Object.values(window.monitorState.charts)
        .map((u) => [u.scales.x.min, u.scales.x.max])""")


def _export(page):
    """The CSV the export button downloads: (file name, header, rows as floats or None)."""
    with page.expect_download() as download:
        page.click("#export-csv")
    lines = download.value.path().read_text().splitlines()
    header = lines[0].split(",")
    rows = [[None if v == "" else float(v) for v in line.split(",")] for line in lines[1:]]
    return download.value.suggested_filename, header, rows


def _rows(history, header, low, high):
    return [[None if row[k] is None else float(row[k]) for k in header]
            for row in history if low <= row["time_s"] <= high]


def test_monitor_time_range_selection(driven_stockpile):
    """A time range chosen in the list: every trend shows it, each y axis
    scales to the values inside it, it follows new data, a zoom inside it
    narrows it, and the CSV export holds the /history rows of what is shown."""
    sync_api = pytest.importorskip("playwright.sync_api")
    asset, rest, stockpile_url, monitor_url = driven_stockpile
    with sync_api.sync_playwright() as playwright:
        browser = _launch(playwright)
        try:
            page = browser.new_page(viewport={"width": 1600, "height": 1000},
                                    accept_downloads=True)
            errors = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            page.goto(monitor_url + "?poll=250")
            sync_api.expect(page.locator("#status")).to_have_text("LIVE", timeout=15_000)
            # 40 t in; 40 s at 500 kg/s down to 20 t, then 50 s with the feeder stopped:
            # the last minute (30-90 s) holds at most 25 t, the whole run 39.5 t
            lots = [(k, 10_000.0, 0.5, 0) for k in range(4)]
            _drive(page, asset, rest, lots, rate=500.0, steps=40)
            end = _drive(page, asset, rest, rate=0.0, steps=50)
            history = get(stockpile_url + "/history")[1]["rows"]
            assert (history[0]["time_s"], end) == (1.0, 90.0)
            whole = [[1.0, 90.0]] * 6
            assert _x_scales(page) == whole

            page.select_option("#trend-range", "60")
            assert _x_scales(page) == [[30.0, 90.0]] * 6
            assert page.locator("#range-shown").text_content() == "t = 30.0–90.0 s"
            shown_max = max(r["held_mass_kg"] for r in history if r["time_s"] >= 30.0) / 1000
            whole_max = max(r["held_mass_kg"] for r in history) / 1000
            assert (shown_max, whole_max) == (25.0, 39.5)
            y_max = page.evaluate("window.monitorState.charts.mass.scales.y.max")
            assert y_max == pytest.approx(1.1 * shown_max)
            name, header, rows = _export(page)
            assert header == list(history[0])
            assert rows == _rows(history, header, 30.0, 90.0) and len(rows) == 61
            assert name == "stockpile_history_t30-90s.csv"

            # ten seconds more: the window moves with the newest value
            _drive(page, asset, rest, rate=0.0, steps=10)
            assert _x_scales(page) == [[40.0, 100.0]] * 6
            history = get(stockpile_url + "/history")[1]["rows"]
            assert _export(page)[2] == _rows(history, header, 40.0, 100.0)

            # a zoom inside the window narrows every trend and the export to it
            over = page.locator("#trend-grade .u-over").bounding_box()
            y = over["y"] + over["height"] / 2
            page.mouse.move(over["x"] + 0.2 * over["width"], y)
            page.mouse.down()
            page.mouse.move(over["x"] + 0.5 * over["width"], y, steps=8)
            page.mouse.up()
            zoom = page.evaluate("window.monitorState.zoom")
            assert 40.0 < zoom["min"] < zoom["max"] < 100.0
            assert _x_scales(page) == [[zoom["min"], zoom["max"]]] * 6
            zoomed = _export(page)[2]
            assert zoomed == _rows(history, header, zoom["min"], zoom["max"])
            assert 0 < len(zoomed) < 61

            # choosing a range again replaces the zoom: the whole run, all of /history
            page.select_option("#trend-range", "0")
            assert page.evaluate("window.monitorState.zoom") is None
            assert _x_scales(page) == [[1.0, 100.0]] * 6
            y_max = page.evaluate("window.monitorState.charts.mass.scales.y.max")
            assert y_max == pytest.approx(1.1 * whole_max)
            assert _export(page)[2] == _rows(history, header, 1.0, 100.0)

            # hovering shows the values of the row under the cursor, in the trend's unit
            over = page.locator("#trend-mass .u-over").bounding_box()
            page.mouse.move(over["x"] + 0.3 * over["width"], over["y"] + over["height"] / 2)
            page.wait_for_function("window.monitorState.charts.mass.cursor.idx !== null")
            index, shown = page.evaluate("""() => {
                const u = window.monitorState.charts.mass;
                return [u.cursor.idx, [...u.root.querySelectorAll('.u-legend .u-value')]
                        .map((el) => el.textContent)]; }""")
            row = page.evaluate(f"window.monitorState.history[{index}]")
            assert row == history[index]
            assert shown[:2] == [f"{row['time_s']:.1f}", f"{row['held_mass_kg'] / 1000:.2f}"]
            assert 0.2 < (row["time_s"] - 1.0) / 99.0 < 0.4
            assert errors == []
        finally:
            browser.close()


def _post(url, body):
    request = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                     headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def test_monitor_alarm_acknowledgement_survives_a_reload(driven_stockpile, tmp_path):
    """The operator acknowledges an alarm with a name; the monitor server keeps
    who and when, so a reloaded page shows it; an alarm that clears before
    anyone acknowledged it waits as CLEARED, UNACK."""
    sync_api = pytest.importorskip("playwright.sync_api")
    expect = sync_api.expect
    asset, rest, stockpile_url, monitor_url = driven_stockpile
    with sync_api.sync_playwright() as playwright:
        browser = _launch(playwright)
        try:
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            errors = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            page.goto(monitor_url + "?poll=250")
            expect(page.locator("#status")).to_have_text("LIVE", timeout=15_000)
            # 35 t: 70 % of 50 t, above the 60 % limit
            _drive(page, asset, rest, [(1, 35_000.0, 0.5, 0)], steps=1)
            row = page.locator("#alarm-list tr[data-seq='1']")
            expect(row).to_have_attribute("data-state", "ACTIVE_UNACK")
            # no name, no acknowledgement
            row.locator("button.ack").click()
            expect(page.locator("#ack-note")).to_contain_text("type your name")
            assert get(monitor_url + "monitor/alarms")[1]["alarms"][0]["acked_by"] is None

            page.fill("#operator", "Ana Operator")
            row.locator("button.ack").click()
            expect(row).to_have_attribute("data-state", "ACTIVE_ACK")
            served = get(monitor_url + "monitor/alarms")[1]
            occurrence = served["alarms"][0]
            assert (occurrence["acked_by"], occurrence["acked_s"]) == ("Ana Operator", 1.0)
            acked_clock = time.strftime("%H:%M:%S", time.localtime(
                datetime.datetime.fromisoformat(occurrence["acked_at"].replace("Z", "+00:00"))
                .timestamp()))
            expect(row.locator("td").nth(6)).to_have_text(f"Ana Operator, {acked_clock}")
            assert served["limits"][0]["clears_at"] == LEVEL_HIGH_PCT - LEVEL_DEADBAND_PCT

            # the server refuses a second acknowledgement, a bad name and an unknown alarm
            status, body = _post(monitor_url + "monitor/alarms/ack", {"seq": 1, "operator": "Ben"})
            assert status == 409 and "acknowledged by 'Ana Operator'" in body["error"]
            status, body = _post(monitor_url + "monitor/alarms/ack", {"seq": 1, "operator": ""})
            assert status == 400 and body["field"] == "operator"
            status, body = _post(monitor_url + "monitor/alarms/ack", {"seq": 7, "operator": "Ben"})
            assert status == 404 and body["field"] == "seq"

            # a reload shows what the server kept, and the browser remembers the name
            page.reload()
            expect(page.locator("#status")).to_have_text("LIVE", timeout=15_000)
            expect(row).to_have_attribute("data-state", "ACTIVE_ACK")
            expect(row.locator("td").nth(6)).to_have_text(f"Ana Operator, {acked_clock}")
            assert page.input_value("#operator") == "Ana Operator"

            # 25 t (50 %): acknowledged and cleared, the occurrence is closed
            _drive(page, asset, rest, rate=2_000.0, steps=5)
            expect(row).to_have_attribute("data-state", "CLEARED")
            # up to 40 t and down to 24 t before anyone looks: it waits, unacknowledged
            _drive(page, asset, rest, [(2, 15_000.0, 0.5, 0)], rate=0.0, steps=1)
            _drive(page, asset, rest, rate=2_000.0, steps=8)
            second = page.locator("#alarm-list tr[data-seq='2']")
            expect(second).to_have_attribute("data-state", "CLEARED_UNACK")
            assert _shown(page, "alarm-count") == ["0", "NO ALARM (1 UNACK)"]
            page.reload()
            expect(second).to_have_attribute("data-state", "CLEARED_UNACK", timeout=15_000)
            page.screenshot(path=str(tmp_path / "monitor_alarms.png"), full_page=True)
            page.click("#ack-all")
            expect(second).to_have_attribute("data-state", "CLEARED")
            assert _shown(page, "alarm-count") == ["0", "NO ALARM"]
            served = get(monitor_url + "monitor/alarms")[1]
            assert [(o["seq"], o["state"], o["acked_by"]) for o in served["alarms"]] == \
                [(1, "CLEARED", "Ana Operator"), (2, "CLEARED", "Ana Operator")]
            assert served["unacknowledged"] == 0
            assert errors == []
        finally:
            browser.close()


SCREENS = {"laptop_1366x768": {"viewport": {"width": 1366, "height": 768}},
           "phone_390x844": {"viewport": {"width": 390, "height": 844}, "is_mobile": True,
                             "has_touch": True, "device_scale_factor": 2}}
"""A common laptop screen and a phone's width (CSS pixels)."""

VISIBLE_IDS = ("status", "alarm-count", "sim-time", "held-mass", "fill-pct", "grade", "hardness",
               "d80", "discharge-actual", "discharge-rate", "trend-range", "export-csv",
               "operator", "ack-all", "colour-by")


@pytest.mark.slow  # 23 s here: two pages, full-page screenshots at a phone's pixel ratio
def test_monitor_fits_a_laptop_and_a_phone(processes, tmp_path):
    """At 1366 x 768 and at a phone's 390 px the page does not scroll sideways,
    every value and control lies inside the screen's width, and each trend
    fits its panel. Screenshots: monitor_<screen>.png."""
    sync_api = pytest.importorskip("playwright.sync_api")
    _, _, monitor_url = processes
    shots = []
    with sync_api.sync_playwright() as playwright:
        browser = _launch(playwright)
        try:
            for name, options in SCREENS.items():
                page = browser.new_page(**options)
                width = options["viewport"]["width"]
                page.goto(monitor_url + "?poll=400")
                sync_api.expect(page.locator("#status")).to_have_text("LIVE", timeout=15_000)
                page.wait_for_function("window.monitorState.updates >= 3", timeout=15_000)
                assert page.evaluate("document.documentElement.scrollWidth") <= width, name
                for element_id in VISIBLE_IDS:
                    box = page.locator(f"#{element_id}").bounding_box()
                    assert box is not None and box["width"] > 0, (name, element_id)
                    assert 0 <= box["x"] and box["x"] + box["width"] <= width, (name, element_id, box)
                # the state of the plant is on the first screen
                for element_id in ("status", "alarm-count", "sim-time"):
                    box = page.locator(f"#{element_id}").bounding_box()
                    assert box["y"] + box["height"] <= options["viewport"]["height"], (name, element_id)
                trends = page.evaluate("""() => [...document.querySelectorAll('.trend')].map(
                    (t) => [t.getBoundingClientRect().right, t.querySelector('.uplot')
                            .getBoundingClientRect().right, t.parentElement.getBoundingClientRect().right])""")
                assert len(trends) == 6
                for box_right, chart_right, grid_right in trends:
                    assert chart_right <= box_right + 1 and box_right <= grid_right + 1, (name, trends)
                shots.append(tmp_path / f"monitor_{name}.png")
                page.screenshot(path=str(shots[-1]), full_page=True)
                page.close()
        finally:
            browser.close()
    copy_to = os.environ.get("MINETWIN_SCREENSHOT_DIR")
    if copy_to:
        Path(copy_to).mkdir(parents=True, exist_ok=True)
        for shot in shots:
            shutil.copy(shot, Path(copy_to) / shot.name)
