"""The example user test folder examples/cosim_tests, run as a user runs it (pytest in a
subprocess): the plant as designed passes (including the OPC UA lockstep run's mass and
id checks); with the cone-crusher FMU swapped in, the reference comparison fails with a
readable table. The two runs go side by side to keep the wall time down."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FOLDER = ROOT / "examples" / "cosim_tests"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("example-runs")
    plots = tmp / "plots"
    variants = {"as designed": [],
                "cone crusher": ["--crusher", "cone_crusher", "-k", "reference",
                                 f"--minetwin-plots={plots}"]}
    procs = {name: subprocess.Popen(
        [sys.executable, "-m", "pytest", str(FOLDER), "-q", "-p", "no:cacheprovider",
         "--basetemp", str(tmp / name.replace(" ", "_")), *args],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for name, args in variants.items()}
    results = {}
    for name, proc in procs.items():
        out, _ = proc.communicate(timeout=300)
        results[name] = (proc.returncode, out)
    results["plots"] = plots
    return results


def test_example_folder_passes_as_designed(runs):
    code, out = runs["as designed"]
    assert code == 0, out[-4000:]
    assert "5 passed" in out


def test_swapping_in_the_cone_crusher_is_caught_with_a_table(runs):
    code, out = runs["cone crusher"]
    assert code == 1, out[-4000:]
    assert "1 failed" in out
    assert "result differs from the reference" in out and "plant_reference.csv" in out
    table = [line.split()[1:] for line in out.splitlines() if line.startswith("E   ")]
    assert any(cells[:4] == ["signal", "unit", "worst", "deviation"] for cells in table)
    verdicts = {cells[0]: cells[-1] for cells in table
                if len(cells) > 2 and cells[-1] in ("pass", "FAIL")}
    assert verdicts["stockpile.d_mean"] == "FAIL"       # the cone crusher's product is coarser
    assert verdicts["crusher.zone_hardness_avg"] == "pass"
    assert list(runs["plots"].rglob("stockpile.d_mean.png"))
