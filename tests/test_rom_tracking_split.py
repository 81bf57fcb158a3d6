"""The split of the ROM's tracking error into the inflow and the start pile
(``surrogate.rom.tracking_split``)."""

import json
from pathlib import Path

import numpy as np
import pytest

from surrogate.rom import evaluate, heldout_layout, tracking_split
from surrogate.rom.model import RomModel
from surrogate.rom.storage import DEFAULT_MODEL, FIXED_GRID_MODEL

ROOT = Path(__file__).resolve().parents[1]
HELDOUT = ROOT / "surrogate" / "rom" / "data" / "paper_heldout"

# two 30 s windows; ids 1, 2 in the start pile, 10, 11 the inflow lots (11 came in first)
OUTFLOW = {"time": np.array([5.0, 10.0, 20.0, 35.0, 40.0, 50.0, 55.0]),
           "tracking_id": np.array([1, 1, 2, 2, 10, 11, 11], dtype=np.uint64),
           "mass": np.array([1.0, 1.0, 2.0, 1.0, 1.0, 1.0, 1.0])}
EMISSIONS = {"time": np.array([3.0, 1.0, 4.0]), "tracking_id": np.array([10, 11, 10])}


def test_shares_and_lot_order_per_window_by_hand():
    inflow = np.array([10, 11], dtype=np.uint64)
    assert tracking_split.inflow_share(OUTFLOW, inflow, 0.0, 60.0) == [0.0, 0.75]
    order = tracking_split.arrival_order(EMISSIONS)
    assert order == {11: 0, 10: 1}
    # second window: inflow mass 1 of lot 10 (rank 1), 2 of lot 11 (rank 0)
    assert tracking_split.inflow_lots(OUTFLOW, order, 0.0, 60.0) == [None, [0, 0, 1]]
    one = tracking_split.lumped(OUTFLOW, inflow)
    assert one["tracking_id"].tolist() == [1, 1, 2, 2, 10, 10, 10]
    assert one["mass"] is OUTFLOW["mass"]


def test_counting_the_inflow_as_one_id_can_only_lower_the_error():
    """Merging ids never raises a total-variation distance; here the second window's
    inflow share agrees (0.75) while its lots are swapped: TV 0.25 by id, 0 lumped."""
    inflow = np.array([10, 11], dtype=np.uint64)
    other = {**OUTFLOW, "tracking_id": np.array([1, 2, 2, 2, 11, 10, 10], dtype=np.uint64)}
    from surrogate.rom import metrics

    full = metrics.tracking_error(OUTFLOW, other, 0.0, 60.0)
    merged = metrics.tracking_error(tracking_split.lumped(OUTFLOW, inflow),
                                    tracking_split.lumped(other, inflow), 0.0, 60.0)
    assert full == pytest.approx(0.25) and merged == pytest.approx(0.125)


@pytest.mark.parametrize("model_args, model_file",
                         [([], DEFAULT_MODEL), (["--model", str(FIXED_GRID_MODEL)], FIXED_GRID_MODEL)],
                         ids=["default", "fixed-grid"])
def test_the_split_of_a_shipped_rom_on_a_held_out_scene(tmp_path, model_args, model_file):
    """Without ``--model`` the split is the default ROM's; with it, the file's."""
    code = tracking_split.main(["--data", str(HELDOUT), "--scene", "heldout_q2000",
                                "--out", str(tmp_path)] + model_args)
    assert code == 0
    result = json.loads((tmp_path / "tracking_split.json").read_text())["heldout_q2000"]
    assert result["replicas"] == 3
    for key in ("tracking_error", "lumped"):
        assert set(result[key]) == {"rom", "dem_noise_floor"}
    for who in ("rom", "dem_noise_floor"):
        assert result["lumped"][who] <= result["tracking_error"][who]
    windows = 6  # 180 s in 30 s windows
    shares = [result["inflow_share"]["rom"]] + result["inflow_share"]["dem"]
    assert len(shares) == 4 and all(len(s) == windows for s in shares)
    assert all(0.0 <= v <= 1.0 for s in shares for v in s)
    for rows in [result["inflow_lots"]["rom"]] + result["inflow_lots"]["dem"]:
        assert all(row is None or row == sorted(row) for row in rows)
    # its full error is the one `minetwin rom evaluate` scores the same run by
    with heldout_layout.scenes_laid_out(HELDOUT, ["heldout_q2000"]) as (folder, _):
        scene = folder / "heldout_q2000"
        replicas = evaluate.stable_replicas(scene)
        t0 = float(replicas[0]["t0"])
        rom, _, _ = evaluate.run_storage("rom", scene, RomModel.load(model_file))
        scored = evaluate.ensemble_score(rom, [evaluate.outflow_of(r) for r in replicas], t0,
                                         t0 + evaluate.scenario_duration(scene))
    assert result["tracking_error"]["rom"] == pytest.approx(scored["tracking_error"], rel=1e-12)


def test_an_unknown_scene_or_folder_exits_2(tmp_path, capsys):
    assert tracking_split.main(["--data", str(HELDOUT), "--scene", "nope",
                                "--out", str(tmp_path)]) == 2
    assert "--scene" in capsys.readouterr().err
    assert tracking_split.main(["--data", str(tmp_path), "--out", str(tmp_path)]) == 2
    assert "--data" in capsys.readouterr().err
