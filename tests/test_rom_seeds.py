"""``minetwin rom evaluate --rom-seeds N``: the ROM scored over its own seeds as well
as over the DEM replicas."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom import evaluate, heldout_layout
from surrogate.rom.model import RomModel
from surrogate.rom.storage import DEFAULT_MODEL

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = ROOT / "surrogate" / "rom" / "data" / "paper_heldout"


def test_the_rom_is_scored_over_its_seeds_and_seed_0_is_the_single_run():
    model = RomModel.load(DEFAULT_MODEL)
    with heldout_layout.scenes_laid_out(HELDOUT, ["heldout_q2000"]) as (folder, _):
        scene = folder / "heldout_q2000"
        one = evaluate.evaluate_scenario(model, scene)
        two = evaluate.evaluate_scenario(model, scene, rom_seeds=2)
        replicas = evaluate.stable_replicas(scene)
        t0 = float(replicas[0]["t0"])
        seed_1, _, _ = evaluate.run_storage("rom", scene, model, seed=1)
        seed_1_score = evaluate.ensemble_score(
            seed_1, [evaluate.outflow_of(r) for r in replicas], t0,
            t0 + evaluate.scenario_duration(scene))["tracking_error"]
    assert one["rom_tracking_error_by_seed"] == [one["tracking_error"]["rom"]]
    assert two["rom_tracking_error_by_seed"] == [one["tracking_error"]["rom"], seed_1_score]
    assert two["tracking_error"]["rom"] == pytest.approx(
        np.mean(two["rom_tracking_error_by_seed"]), rel=1e-12)
    assert two["tracking_error_spread"]["rom"]["n"] == 2 * len(replicas)
    # FIFO and mixing draw no random numbers: one run each, as before
    assert two["tracking_error"]["fifo"] == one["tracking_error"]["fifo"]
    assert two["tracking_error_spread"]["fifo"]["n"] == len(replicas)
    # the pile's shape beside its outflow: the DEM's ends resting on its base (the
    # committed replicas' last fields: exactly 0), the fixed grid's too (0 on every
    # seed and held-out scene measured, seeds 0-4), under the limit either way
    from surrogate.rom.hanging import HANGING_LIMIT

    assert two["hanging_mass_share"]["dem"] == 0.0
    assert 0.0 <= two["hanging_mass_share"]["rom"] <= HANGING_LIMIT


def test_a_seed_count_outside_1_to_100_is_refused(tmp_path):
    with pytest.raises(ValidationError, match="rom_seeds"):
        evaluate.evaluate(RomModel.load(DEFAULT_MODEL), tmp_path, rom_seeds=0)
    result = subprocess.run(
        [sys.executable, "-m", "minetwin.cli", "rom", "evaluate", "--model", str(DEFAULT_MODEL),
         "--data", str(HELDOUT), "--out", str(tmp_path), "--rom-seeds", "0", "--workers", "1"],
        cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 2 and "rom_seeds" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr


def test_a_negative_landing_spread_is_refused_by_name(tmp_path):
    """``--landing-spread`` reaches the ROM storage, whose check names it."""
    result = subprocess.run(
        [sys.executable, "-m", "minetwin.cli", "rom", "evaluate", "--model", str(DEFAULT_MODEL),
         "--data", str(HELDOUT), "--out", str(tmp_path), "--landing-spread", "-1",
         "--workers", "1"],
        cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 2 and "landing_spread" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "summary.json").exists()
