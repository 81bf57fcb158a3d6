"""Where the inflow joins the bulk, DEM against the ROM's surface layer
(``surrogate.rom.landing``), on the reduced paper design (300 disks)."""

import json

import numpy as np
import pytest

from surrogate.rom import landing
from surrogate.rom import paper_design as pd


def test_a_measurement_places_every_newcomer_that_reached_the_bulk_age_and_repeats_itself():
    design = pd.reduced_design()
    first = landing.measure(design, "base_small", 1000.0, 8, seed=0)
    # 1000 kg per step of 11-156 kg disks; those of steps 0-3 are 4 s old by the end
    assert 4 * 1000.0 / 156.0 <= first["newcomers"] <= 4 * 1000.0 / 11.0
    for side in ("dem", "rom"):
        quantiles = first[f"{side}_quantiles_m"]
        assert len(quantiles) == len(landing.QUANTILES)
        assert quantiles == sorted(quantiles)
        assert quantiles[0] >= -80.0 - first["inlet_x_m"] and quantiles[-1] <= 80.0
    assert first["extra_spread_m"] == pytest.approx(
        np.sqrt(max(first["dem_std_m"] ** 2 - first["rom_std_m"] ** 2, 0.0)), rel=1e-9)
    again = landing.measure(design, "base_small", 1000.0, 8, seed=0)
    timing = ("wall_s", "cpu_s")
    assert {k: v for k, v in again.items() if k not in timing} == \
        {k: v for k, v in first.items() if k not in timing}


def test_the_command_writes_strict_json_with_the_summary(tmp_path):
    code = landing.main(["--design", "reduced", "--run", "base_small:1000:8:0",
                         "--run", "base_small:1500:8:1", "--workers", "1",
                         "--out", str(tmp_path)])
    assert code == 0
    result = json.loads((tmp_path / "landing.json").read_text(),
                        parse_constant=lambda name: pytest.fail(f"{name} in strict JSON"))
    extra = [m["extra_spread_m"] for m in result["measurements"]]
    assert [m["rate_kg_s"] for m in result["measurements"]] == [1000.0, 1500.0]
    assert result["extra_spread_m"]["n"] == 2
    assert result["extra_spread_m"]["mean"] == pytest.approx(np.mean(extra), rel=1e-12)
    assert result["extra_spread_m"]["min"] == min(extra)


@pytest.mark.parametrize("run, field", [
    ("nope:1000:8:0", "--run"),
    ("base_small:fast:8:0", "--run"),
    ("base_small:1000:8", "--run"),
    ("base_small:0:8:0", "--run rate"),
    ("base_small:1000:3:0", "--run seconds"),
])
def test_a_bad_run_exits_2_naming_the_field(run, field, tmp_path, capsys):
    assert landing.main(["--design", "reduced", "--run", run, "--out", str(tmp_path)]) == 2
    assert field in capsys.readouterr().err
    assert not (tmp_path / "landing.json").exists()


def test_another_design_without_runs_exits_2_naming_run(tmp_path, capsys):
    assert landing.main(["--design", "reduced", "--out", str(tmp_path)]) == 2
    assert "--run" in capsys.readouterr().err
    assert not (tmp_path / "landing.json").exists()


def test_a_missing_model_file_exits_2_before_any_worker_starts(tmp_path, capsys):
    code = landing.main(["--design", "reduced", "--run", "base_small:1000:8:0", "--out",
                         str(tmp_path), "--model", str(tmp_path / "none.npz")])
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("must be an existing model file") == 1  # once, not once per worker
    assert "none.npz" in err
    assert "measurements on" not in err and not (tmp_path / "landing.json").exists()
