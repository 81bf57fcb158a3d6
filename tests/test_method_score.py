"""Scoring another DEM method's held-out runs against the explicit replicas
(surrogate.rom.method_score), on the shipped paper-scale held-out data."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom import metrics
from surrogate.rom.method_score import score_dem_method

HELDOUT = Path(__file__).resolve().parents[1] / "surrogate" / "rom" / "data" / "paper_heldout"


def _method_folder(tmp_path, run_name: str | tuple, shift_s: float = 0.0,
                   stop_after_s: float | None = None, velocity_scale: float = 1.0) -> Path:
    """A design folder holding one run of the reference data (or several: a tuple
    of names), renamed realisation 0 (1, ...) of its scene, its times moved by
    ``shift_s`` (another method's pile that settled to a later time); with
    ``stop_after_s``, its feeder delivers nothing after that many seconds (a jam);
    with ``velocity_scale``, the first realisation's cells move that many times
    faster (a creep)."""
    manifest = json.loads((HELDOUT / "manifest.json").read_text())
    folder = tmp_path / "method"
    (folder / "train").mkdir(parents=True)
    records = []
    names = (run_name,) if isinstance(run_name, str) else run_name
    for realisation, name in enumerate(names):
        record = next(r for r in manifest["runs"] if r["name"] == name)
        scene = name.rsplit("_r", 1)[0]
        record = dict(record, name=f"{scene}_r{realisation}",
                      spec=dict(record["spec"], replica=realisation))
        with np.load(HELDOUT / "train" / f"{name}.npz") as stored:
            arrays = {k: stored[k] for k in stored.files}
        if stop_after_s is not None:
            kept = arrays["out_time"] <= arrays["time"][0] + stop_after_s
            for key in [k for k in arrays if k.startswith("out_")]:
                arrays[key] = arrays[key][kept]
            record["discharged_mass_kg"] = float(arrays["out_mass"].astype(np.float64).sum())
        if realisation == 0:
            arrays["velocity"] = arrays["velocity"] * np.float32(velocity_scale)
        for key in ("time", "out_time", "in_time"):
            arrays[key] = arrays[key] + np.asarray(shift_s, dtype=arrays[key].dtype)
        np.savez_compressed(folder / "train" / f"{record['name']}.npz", **arrays)
        records.append(record)
    (folder / "manifest.json").write_text(json.dumps(
        {"design": "test", "dem_config": dict(manifest["dem_config"], method="nonsmooth"),
         "runs": records}))
    return folder


def _outflow(name):
    with np.load(HELDOUT / "train" / f"{name}.npz") as stored:
        return {k: np.asarray(stored[f"out_{k}"], dtype=np.float64)
                for k in ("time", "tracking_id", "mass", "grade", "hardness")}


def test_a_replica_scored_as_another_method_gets_its_mean_error_against_the_replicas(tmp_path):
    scores = score_dem_method(_method_folder(tmp_path, "heldout_q2000_r1"), HELDOUT)
    assert scores["method"] == "nonsmooth"
    assert list(scores["scenes"]) == ["heldout_q2000"]
    row = scores["scenes"]["heldout_q2000"]
    with np.load(HELDOUT / "train" / "heldout_q2000_r0.npz") as stored:
        t0 = float(stored["time"][0])
    t1 = t0 + 180.0
    expected = [metrics.tracking_error(_outflow("heldout_q2000_r1"), _outflow(f"heldout_q2000_r{k}"),
                                       t0, t1) for k in range(3)]
    assert expected[1] == 0.0  # against itself
    assert row["tracking_error"] == pytest.approx(np.mean(expected), rel=1e-12)
    assert row["tracking_error_spread"]["n"] == 3
    assert row["explicit_replicas"] == [f"heldout_q2000_r{k}" for k in range(3)]
    assert set(scores["explicit_costs"]) == {"heldout_q1200", "heldout_q2000",
                                             "heldout_out1500_in700"}
    assert row["method_cost"]["cpu_s_per_simulated_s"] > 0
    replicas = {r["name"]: r for r in json.loads((HELDOUT / "manifest.json").read_text())["runs"]}
    assert row["discharged_kg"] == replicas["heldout_q2000_r1"]["discharged_mass_kg"]
    assert row["explicit_discharged_kg"] == pytest.approx(np.mean(
        [replicas[f"heldout_q2000_r{k}"]["discharged_mass_kg"] for k in range(3)]), rel=1e-12)
    assert row["jammed"] is False and row["window_s"] == 30.0
    assert row["last_discharge_s"] > 179.0
    assert row["bulk_speed_m_s"] == row["explicit_bulk_speed_m_s"][1] > 0.0
    assert row["creeping"] is False


def test_several_realisations_of_the_method_are_each_scored_and_averaged(tmp_path):
    """Two replicas scored as two realisations of another method: the scene's error
    is the mean over every realisation against every replica, the realisations'
    own errors and spread are kept, a creep in one of them flags the scene."""
    names = ("heldout_q2000_r1", "heldout_q2000_r2")
    scores = score_dem_method(_method_folder(tmp_path / "a", names), HELDOUT)
    row = scores["scenes"]["heldout_q2000"]
    with np.load(HELDOUT / "train" / "heldout_q2000_r0.npz") as stored:
        t0 = float(stored["time"][0])
    expected = [[metrics.tracking_error(_outflow(name), _outflow(f"heldout_q2000_r{k}"),
                                        t0, t0 + 180.0) for k in range(3)] for name in names]
    assert [r["run"] for r in row["realisations"]] == ["heldout_q2000_r0", "heldout_q2000_r1"]
    for realisation, errors in zip(row["realisations"], expected):
        assert realisation["tracking_errors"] == pytest.approx(errors, rel=1e-12)
        assert realisation["tracking_error"] == pytest.approx(np.mean(errors), rel=1e-12)
    assert row["tracking_error"] == pytest.approx(np.mean(expected), rel=1e-12)
    assert row["tracking_error_spread"]["n"] == 6 and row["realisation_spread"]["n"] == 2
    assert row["realisation_spread"]["min"] == pytest.approx(min(np.mean(expected, axis=1)))
    assert row["method_runs"] == ["heldout_q2000_r0", "heldout_q2000_r1"]
    assert row["creeping"] is False and row["jammed"] is False
    one_creeps = score_dem_method(_method_folder(tmp_path / "b", names, velocity_scale=4.0),
                                  HELDOUT)["scenes"]["heldout_q2000"]
    assert [r["creeping"] for r in one_creeps["realisations"]] == [True, False]
    assert one_creeps["creeping"] is True


def test_a_bulk_that_keeps_moving_beside_the_funnel_is_flagged_creeping(tmp_path):
    """The replica's cells made 4 times faster: beyond 12 m of the feeder its bulk
    moves more than 3 times as fast as every replica's (they differ by a few per cent),
    while its outflow, and so its tracking error, is the replica's."""
    plain = score_dem_method(_method_folder(tmp_path / "a", "heldout_q2000_r1"), HELDOUT)
    fast = score_dem_method(_method_folder(tmp_path / "b", "heldout_q2000_r1",
                                           velocity_scale=4.0), HELDOUT)
    before, after = plain["scenes"]["heldout_q2000"], fast["scenes"]["heldout_q2000"]
    assert after["bulk_speed_m_s"] == pytest.approx(4.0 * before["bulk_speed_m_s"], rel=1e-6)
    assert after["creeping"] is True and after["jammed"] is False
    assert after["tracking_error"] == before["tracking_error"]


def test_a_feeder_that_stops_delivering_is_flagged_jammed_with_when(tmp_path):
    jammed = score_dem_method(_method_folder(tmp_path / "a", "heldout_q2000_r1",
                                             stop_after_s=100.0), HELDOUT)
    row = jammed["scenes"]["heldout_q2000"]
    assert row["jammed"] is True
    assert 99.0 < row["last_discharge_s"] <= 100.0
    assert row["discharged_kg"] < 0.9 * row["explicit_discharged_kg"]
    short = score_dem_method(_method_folder(tmp_path / "b", "heldout_q2000_r1",
                                            stop_after_s=170.0), HELDOUT)
    assert short["scenes"]["heldout_q2000"]["jammed"] is False  # 0.94 of the mass


def test_the_window_is_a_setting_checked_against_the_scene(tmp_path):
    folder = _method_folder(tmp_path, "heldout_q1200_r1")
    with np.load(HELDOUT / "train" / "heldout_q1200_r0.npz") as stored:
        t0 = float(stored["time"][0])
    row = score_dem_method(folder, HELDOUT, window=10.0)["scenes"]["heldout_q1200"]
    assert row["window_s"] == 10.0
    assert row["tracking_error_spread"]["max"] == pytest.approx(max(
        metrics.tracking_error(_outflow("heldout_q1200_r1"), _outflow(f"heldout_q1200_r{k}"),
                               t0, t0 + 180.0, 10.0) for k in range(3)), rel=1e-12)
    for window, allowed in ((0.0, "> 0"), (400.0, "at most the scene's 180 s")):
        with pytest.raises(ValidationError, match=allowed):
            score_dem_method(folder, HELDOUT, window=window)


def test_a_method_run_that_started_later_is_compared_over_its_own_first_seconds(tmp_path):
    at_start = score_dem_method(_method_folder(tmp_path / "a", "heldout_q1200_r2"), HELDOUT)
    later = score_dem_method(_method_folder(tmp_path / "b", "heldout_q1200_r2", shift_s=0.5),
                             HELDOUT)
    assert (later["scenes"]["heldout_q1200"]["tracking_error"]
            == pytest.approx(at_start["scenes"]["heldout_q1200"]["tracking_error"], abs=1e-6))


def test_a_scene_without_explicit_replicas_is_refused_by_name(tmp_path):
    folder = _method_folder(tmp_path, "heldout_q1200_r0")
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["runs"][0]["name"] = "unknown_scene_r0"
    shutil.move(folder / "train" / "heldout_q1200_r0.npz", folder / "train" / "unknown_scene_r0.npz")
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValidationError, match="unknown_scene: 0 explicit replicas"):
        score_dem_method(folder, HELDOUT)


def test_the_example_charts_both_dem_methods_beside_the_storage_models(tmp_path):
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "examples" / "paper_scale_methods.py"
    spec = importlib.util.spec_from_file_location("paper_scale_methods", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    out = tmp_path / "out"
    assert example.main(["--method-data", str(_method_folder(tmp_path, "heldout_q2000_r1")),
                         "--out", str(out)]) == 0
    result = json.loads((out / "paper_scale_methods.json").read_text())
    models = [p["model"] for p in result["points"]["heldout_q2000"]]
    assert models == ["fifo", "mixing", "rom", "dem_explicit", "dem_nonsmooth"]
    assert all(p["cost_s_per_s"] > 0 for p in result["points"]["heldout_q2000"])
    assert (out / "paper_scale_methods.png").stat().st_size > 10_000
    assert (out / "scene_heldout_q2000_nonsmooth_11ms_100sweeps.png").stat().st_size > 10_000
    assert example.main(["--method-data", str(tmp_path / "missing"), "--out", str(out)]) == 2


def test_a_run_the_guard_stopped_is_exported_with_its_picture_and_charted(tmp_path):
    """A design run that blew up has no result: export lists its record (when, why)
    with its picture at the failure, and the method's score reports it as failed."""
    from surrogate.rom import paper_design

    design = paper_design.paper_heldout_nonsmooth_design()
    run = design.runs[0]
    key = paper_design.run_key(design, run)
    work, data = tmp_path / "work", tmp_path / "data"
    (work / "runs" / f"{key}_failure").mkdir(parents=True)
    (work / "runs" / f"{key}_failure" / "pile_speed.png").write_bytes(b"\x89PNG picture")
    record = {"kind": "run", "name": run.name, "key": key, "spec": {"replica": 0,
                                                                     "duration": 180.0},
              "start_key": paper_design.start_key(design, run.start), "status": "unstable",
              "wall_s": 420.0, "cpu_s": 400.0, "dt_s": 0.011, "particles_start": 17500,
              "start_time_s": 8.008, "unstable_dem_time_s": 26.246,
              "unstable_in_control_step": 18, "unstable_reason": "an overlap of 0.599",
              "failure_picture": f"runs/{key}_failure/pile_speed.png"}
    (work / "runs" / f"{key}.json").write_text(json.dumps(record))
    manifest = paper_design.export(design, work, data)
    assert manifest["runs_done"] == 0 and [r["key"] for r in manifest["runs_unstable"]] == [key]
    exported = manifest["runs_unstable"][0]
    assert exported["failure_picture"] == f"failures/{run.name}_speed.png"
    assert (data / exported["failure_picture"]).read_bytes() == b"\x89PNG picture"
    assert not list((data / "states").glob("*.npz"))  # no start state for a run that failed
    again = paper_design.export(design, tmp_path / "gone", data)  # kept without the work dir
    assert [r["key"] for r in again["runs_unstable"]] == [key]
    scores = score_dem_method(data, HELDOUT)
    failed = scores["failed"]["heldout_q1200"]
    assert scores["scenes"] == {}
    assert failed["after_s"] == pytest.approx(18.238)
    assert failed["method_cost"]["cpu_s_per_simulated_s"] == pytest.approx(400.0 / 18.238)
    assert failed["picture"] == str(data / f"failures/{run.name}_speed.png")
