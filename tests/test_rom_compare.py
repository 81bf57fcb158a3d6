"""The training-design diagnostics of the flux fit (``python -m
surrogate.rom.flux_compare``, ``python -m surrogate.rom.fill_compare``) on
test_rom's synthetic design: a report per discharging run, its table, strict
JSON, and bad input refused by name with exit code 2."""

import dataclasses
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_rom import CONTAINER, write_design  # noqa: E402

from surrogate.rom import fill_compare, flux_compare  # noqa: E402


def _strict(path: Path) -> dict:
    def refuse(constant):
        raise ValueError(f"{constant} in strict JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.mark.parametrize("module, container", [
    (flux_compare, CONTAINER),
    (fill_compare, dataclasses.replace(CONTAINER, outlet_width=2.0)),
])
def test_a_diagnostic_reports_every_discharging_run_as_json_and_a_table(module, container,
                                                                       tmp_path, capsys):
    data = write_design(tmp_path / "design", samples=24, runs=3, container=container)
    out = tmp_path / "report.json"
    assert module.main(["--data", str(data), "--flux", "4,4,1,0.5", "--json", str(out)]) == 0
    report = _strict(out)
    assert sorted(report) == ["run0", "run1", "run2"]
    table = capsys.readouterr().out.strip().splitlines()
    assert len(table) == 2 + 3 and all(line.startswith("| ") for line in table)
    for entry in report.values():
        assert entry["samples"] > 0 and entry["discharge_rate"] >= 100.0


@pytest.mark.parametrize("module", [flux_compare, fill_compare])
def test_a_diagnostic_refuses_bad_input_by_name(module, tmp_path, capsys):
    with pytest.raises(SystemExit) as stopped:
        module.main(["--data", str(tmp_path), "--flux", "4,four,1,0.5"])
    assert stopped.value.code == 2
    assert "--flux: must be 4 numbers >= 0" in capsys.readouterr().err
    assert module.main(["--data", str(tmp_path / "missing")]) == 2
    assert "--data: must be a design folder with doe.json" in capsys.readouterr().err
