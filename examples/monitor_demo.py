"""Run a stockpile and the monitor, and save what the control room sees.

Starts two real processes on 127.0.0.1: a stockpile serving its REST
interface (``python -m minetwin.demo_stockpile``, or any stockpile URL given
with ``--stockpile``) and the monitor (``minetwin monitor``); lets the
simulation run, then opens the page in Debian's chromium (Playwright) and
saves ``OUT/monitor.png`` (coloured by grade), ``OUT/monitor_origin.png``
(coloured by origin), ``OUT/monitor_zoomed.png`` (the trends zoomed to
the middle third of the run by dragging across the held-mass trend), and
the page on a 1366 x 768 laptop and a 390 px phone
(``OUT/monitor_laptop.png``, ``OUT/monitor_phone.png``).
Everything is stopped at the end. With ``--scenario`` the stockpile is the
mine simulator's (``demo_stockpile --scenario``), e.g. the paper-scale
2,000 t pile of ``examples/paper_scale.toml``. With ``--integration-test DIR``
it is the paper's integration test itself (``minetwin integration-test
--duration S --speed 1 --out DIR``: the mock 800xA, the shipped paper-scale
ROM stockpile holding 1,500 t, over OPC UA), screenshot ``--seconds`` into
the run; the test then runs to its end and writes its report.

    .venv/bin/python examples/monitor_demo.py --out out/monitor [--seconds 20]
    .venv/bin/python examples/monitor_demo.py --out out/monitor_paper \
        --scenario examples/paper_scale.toml --speed 25
    .venv/bin/python examples/monitor_demo.py --out out/monitor_integration \
        --integration-test out/integration --duration 60 --seconds 40
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from minetwin.commands.integration import WARNING_PREFIX

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
SCREENS = {"laptop": {"viewport": {"width": 1366, "height": 768}},
           "phone": {"viewport": {"width": 390, "height": 844}, "is_mobile": True,
                     "has_touch": True, "device_scale_factor": 2}}
"""A common laptop screen and a phone's width (CSS pixels)."""


def start(args, pattern, stream):
    """Start a process; return it and the first match of ``pattern`` in its output."""
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in getattr(proc, stream):
        match = re.search(pattern, line)
        if match:
            return proc, match.group(0)
    proc.wait()
    raise SystemExit(f"{args[0]} stopped before serving: {proc.stderr.read()}")


def print_verdict(report: dict, log: str) -> None:
    """The integration test's audit in one line; the warnings the test printed at
    its end (``log``: its stderr, which the demo keeps in a file) go to stderr."""
    print(f"integration-test: {report['tracking_ids_lost']} ids lost, "
          f"{report['tracking_ids_duplicated']} duplicated, mass balance "
          f"{report['mass_balance_rel_error']:.1e}, lag p99 {report['lag_p99_s']:.2f} s, "
          f"step p99 {report['step_time_p99_ms']:.0f} ms, kept real time: "
          f"{'yes' if report['keeps_up'] else 'NO'}", flush=True)
    for line in log.splitlines():
        if line.startswith(WARNING_PREFIX):
            print(line, file=sys.stderr)


def start_integration_test(minetwin: str, out: Path, duration: float):
    """Start ``minetwin integration-test`` (its monitor left out: the demo starts
    its own); return it and its stockpile's REST URL, read from its log."""
    out.mkdir(parents=True, exist_ok=True)
    log = out / "integration-test.log"
    with open(log, "w") as err, open(out / "integration-test.json", "w") as report:
        proc = subprocess.Popen([minetwin, "integration-test", "--duration", f"{duration:g}",
                                 "--speed", "1", "--out", str(out), "--no-monitor"],
                                stdout=report, stderr=err, text=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        match = re.search(r"stockpile REST (http://127\.0\.0\.1:\d+)", log.read_text())
        if match:
            return proc, match.group(1)
        time.sleep(0.2)
    stop(proc)
    raise SystemExit(f"integration-test did not start its stockpile: {log.read_text()}")


def stop(proc):
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/monitor"), help="output folder")
    parser.add_argument("--seconds", type=float, default=20.0,
                        help="wall seconds to let the simulation run before the screenshots")
    parser.add_argument("--speed", type=float, default=6.0,
                        help="simulated seconds per wall second of the demo stockpile")
    parser.add_argument("--stockpile", help="use a running stockpile at this URL instead")
    parser.add_argument("--scenario", type=Path,
                        help="serve this mine-simulator scenario's stockpile instead of the "
                             "integration test's")
    parser.add_argument("--integration-test", type=Path, metavar="DIR",
                        help="screenshot the paper's integration test (minetwin "
                             "integration-test --out DIR) while it runs")
    parser.add_argument("--duration", type=float, default=60.0,
                        help="simulated seconds of --integration-test, at real time (60)")
    args = parser.parse_args(argv)
    if args.integration_test and not args.seconds < args.duration:
        print("monitor_demo: error: --seconds must be below --duration with "
              "--integration-test", file=sys.stderr)
        return 2
    if not Path(CHROMIUM).exists():
        print(f"monitor_demo: error: {CHROMIUM} missing (apt-get install chromium)",
              file=sys.stderr)
        return 1
    from playwright.sync_api import sync_playwright

    args.out.mkdir(parents=True, exist_ok=True)
    processes = []
    integration = None
    minetwin = str(Path(sys.executable).with_name("minetwin"))
    try:
        url = args.stockpile
        if args.integration_test:
            integration, url = start_integration_test(minetwin, args.integration_test,
                                                      args.duration)
        elif url is None:
            scenario = ["--scenario", str(args.scenario)] if args.scenario else []
            stockpile, url = start([sys.executable, "-m", "minetwin.demo_stockpile", "--port", "0",
                                    "--speed", str(args.speed), *scenario],
                                   r"http://127\.0\.0\.1:\d+", "stdout")
            processes.append(stockpile)
        monitor, page_url = start([minetwin, "monitor", "--stockpile", url, "--port", "0"],
                                  r"http://127\.0\.0\.1:\d+/", "stderr")
        processes.append(monitor)
        print(f"stockpile {url}, monitor {page_url}; running {args.seconds:g} s", file=sys.stderr)
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            # every page opens now and follows the run, so that all are ready at once
            # (on a loaded machine a page opened late could miss the end of a short run)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(page_url)
            screens = {name: browser.new_page(**options) for name, options in SCREENS.items()}
            for small in screens.values():  # polling every 3 s: less load on the stockpile
                small.goto(page_url + "?poll=3000")
            time.sleep(args.seconds)
            page.wait_for_function("window.monitorState.updates >= 2", timeout=60_000)
            page.screenshot(path=str(args.out / "monitor.png"), full_page=True)
            page.select_option("#colour-by", "origin")
            page.screenshot(path=str(args.out / "monitor_origin.png"), full_page=True)
            over = page.locator("#trend-mass .u-over").bounding_box()
            middle = over["y"] + over["height"] / 2
            page.mouse.move(over["x"] + over["width"] / 3, middle)
            page.mouse.down()
            page.mouse.move(over["x"] + 2 * over["width"] / 3, middle, steps=8)
            page.mouse.up()
            page.wait_for_function("window.monitorState.zoom !== null", timeout=5_000)
            page.screenshot(path=str(args.out / "monitor_zoomed.png"), full_page=True)
            shown = page.evaluate("[document.getElementById('held-mass').textContent, "
                                  "document.getElementById('grade').textContent]")
            for name, small in screens.items():
                small.wait_for_function("window.monitorState.updates >= 2", timeout=60_000)
                small.screenshot(path=str(args.out / f"monitor_{name}.png"), full_page=True)
                small.close()
            browser.close()
        print(f"held mass {shown[0]} t, grade {shown[1]} %")
        print(args.out / "monitor.png")
        print(args.out / "monitor_origin.png")
        print(args.out / "monitor_zoomed.png")
        for name in SCREENS:
            print(args.out / f"monitor_{name}.png")
    finally:
        for proc in processes:
            stop(proc)
        if integration is not None and sys.exc_info()[0] is not None:
            stop(integration)
    if integration is not None:  # the test runs to its end and audits the exchange
        code = integration.wait(timeout=args.duration * 3 + 300)
        print(f"integration-test: exit {code}; {args.integration_test / 'report.json'}")
        report_file = args.integration_test / "report.json"
        if report_file.exists():
            print_verdict(json.loads(report_file.read_text()),
                          (args.integration_test / "integration-test.log").read_text())
        return code
    return 0


if __name__ == "__main__":
    sys.exit(main())
