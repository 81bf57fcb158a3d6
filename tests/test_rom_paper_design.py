"""The paper-scale DEM design (surrogate.rom.paper_design) on its reduced design:
content keys, resume (skip finished runs, continue a killed run from its
checkpoint), the compact result's schema, the strict manifest and the export
that ``minetwin rom train`` reads. Invariants only (mass, ids, shapes), never
one DEM trajectory's values."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cosim.errors import ValidationError
from surrogate.rom import doe
from surrogate.rom import paper_design as pd

ROOT = Path(__file__).resolve().parents[1]
LAG = int(round(doe.VELOCITY_WINDOW / doe.CONTROL_STEP))


def _strict(text: str):
    def refuse(name):
        raise ValueError(f"non-strict JSON constant {name}")
    return json.loads(text, parse_constant=refuse)


@pytest.fixture(scope="module")
def reduced_run(tmp_path_factory):
    """The reduced design run once, in this process (one worker)."""
    work = tmp_path_factory.mktemp("design")
    messages = []
    design = pd.reduced_design()
    manifest = pd.run_design(design, work, workers=1, progress=messages.append)
    return design, work, manifest, messages


# ------------------------------------------------------------------ keys
def test_same_inputs_give_the_same_key_and_any_changed_input_a_new_one():
    design = pd.reduced_design()
    run = design.runs[0]
    key = pd.run_key(design, run)
    assert key == pd.run_key(pd.reduced_design(), run)
    assert key == pd.run_key(design, dataclasses.replace(run, name="renamed"))  # names are labels
    changed = [dataclasses.replace(run, discharge_rate=run.discharge_rate + 1.0),
               dataclasses.replace(run, inflow_rate=run.inflow_rate + 1.0),
               dataclasses.replace(run, duration=run.duration + 1.0),
               dataclasses.replace(run, seed=run.seed + 1),
               dataclasses.replace(run, first_tracking_id=run.first_tracking_id + 1),
               dataclasses.replace(run, inlet=1)]
    keys = {pd.run_key(design, r) for r in changed}
    assert len(keys) == len(changed) and key not in keys
    other_config = dataclasses.replace(design, config=pd.paper_config(friction=0.7))
    assert pd.run_key(other_config, run) != key
    # a run's key follows its start state: change the pile, the runs on it change
    pile = design.piles[0]
    other_pile = dataclasses.replace(design, piles=(dataclasses.replace(pile, seed=9),))
    assert pd.pile_key(other_pile, other_pile.piles[0]) != pd.pile_key(design, pile)
    assert pd.run_key(other_pile, run) != key
    child = design.run("small_depleted_out500_in1500")
    parent = design.run("small_drain_out1500")
    longer = dataclasses.replace(design, runs=tuple(
        dataclasses.replace(r, duration=9.0) if r.name == parent.name else r
        for r in design.runs))
    assert pd.run_key(longer, child) != pd.run_key(design, child)
    original = pd.DESIGN_VERSION
    try:
        pd.DESIGN_VERSION = "another"
        assert pd.run_key(design, run) != key
    finally:
        pd.DESIGN_VERSION = original


def test_the_paper_design_is_paper_scale():
    design = pd.paper_design()
    cfg = design.config
    assert (cfg.diameter_min, cfg.diameter_max) == (0.2, 0.48)
    assert 10.0 < float(cfg.sphere_mass(0.2)) < 13.0 and 150.0 < float(cfg.sphere_mass(0.48)) < 162.0
    assert len(cfg.inlets) == 2 and min(y for _, y in cfg.inlets) >= 60.0
    assert len(cfg.outlets) == 1
    assert cfg.stable_dt == pytest.approx(pd.STEP_FRACTION * cfg.contact_time)
    base = design.pile("base_1700t")
    assert base.particles == 20_000
    rates = [(r.discharge_rate, r.inflow_rate) for r in design.runs]
    assert min(q for q, _ in rates) == 0.0 and max(q for q, _ in rates) == 2000.0
    assert min(q for _, q in rates) == 0.0 and max(q for _, q in rates) == 2000.0
    # piles built from the inlet: a fill of a partial pile, first in line
    assert design.runs[0].start.startswith("pile:") and design.runs[0].inflow_rate == 2000.0
    assert design.runs[0].discharge_rate == 0.0
    # most mass of the design: about 2 kt at the end of the base pile's fill
    mean = pd.mean_disk_mass(cfg)
    fill = design.run("fill_base_in2000")
    assert 1.9e6 < base.particles * mean + fill.inflow_rate * fill.duration < 2.1e6
    keys = [pd.run_key(design, r) for r in design.runs]
    assert len(set(keys)) == len(keys)
    starts = {r.name for r in design.runs}
    assert all(r.start[4:] in starts for r in design.runs if r.start.startswith("run:"))


# ---------------------------------------------------------- run + result
def test_every_run_finishes_with_the_compact_schema(reduced_run):
    design, work, manifest, _ = reduced_run
    assert {r["name"] for r in manifest["runs_finished"]} == {r.name for r in design.runs}
    ny, nx = design.grid.shape
    for run in design.runs:
        key = pd.run_key(design, run)
        record = _strict((work / "runs" / f"{key}.json").read_text())
        assert record["status"] == "done" and record["key"] == key
        samples = int(round(run.duration)) - LAG + 1
        with np.load(work / "runs" / f"{key}.npz") as data:
            result = {k: data[k] for k in data.files}
        inflow = {f"in_{k}" for k in pd._OUTFLOW_KEYS} if run.inflow_rate > 0 else set()
        assert set(result) == (set(pd.SAMPLE_KEYS) | {f"out_{k}" for k in pd._OUTFLOW_KEYS}
                               | inflow)
        if inflow:  # the fed particles, exactly: one row per id, the run's whole inflow
            assert result["in_id"].dtype == np.uint64 and result["in_mass"].dtype == np.float64
            assert np.unique(result["in_id"]).size == result["in_id"].size
            assert result["in_mass"].sum() == pytest.approx(run.inflow_rate * run.duration,
                                                            rel=1e-12)
        shapes = {"mass": (samples, ny, nx), "velocity": (samples, ny, nx, 2),
                  "grade": (samples, ny, nx), "hardness": (samples, ny, nx),
                  "dispersion_fit": (samples, 2)}
        for name in pd.SAMPLE_KEYS:
            assert result[name].dtype == np.float32, name
            assert result[name].shape == shapes.get(name, (samples,)), name
        for name in ("out_id", "out_tracking_id"):
            assert result[name].dtype == np.uint64
        for name in ("out_time", "out_mass", "out_grade", "out_hardness"):
            assert result[name].dtype == np.float32
        assert np.all(np.diff(result["time"]) > 0)
        assert np.all(result["setpoint"] == run.discharge_rate)
        assert np.all(result["inflow_rate"] == run.inflow_rate)
        assert np.isfinite(result["mass"]).all() and np.isfinite(result["velocity"]).all()
        assert record["samples"] == samples and record["result_bytes"] > 0


def test_runs_conserve_mass_and_ids(reduced_run):
    from surrogate.dem import Dem

    design, work, _, _ = reduced_run
    for run in design.runs:
        key = pd.run_key(design, run)
        record = _strict((work / "runs" / f"{key}.json").read_text())
        # held at the start + what entered = held at the end + what the feeder took
        assert record["inflow_mass_kg"] == pytest.approx(run.inflow_rate * run.duration,
                                                         rel=1e-12)
        balance = (record["held_mass_start_kg"] + record["inflow_mass_kg"]
                   - record["held_mass_end_kg"] - record["discharged_mass_kg"])
        assert abs(balance) <= 1e-9 * record["held_mass_start_kg"]
        assert record["mass_balance_error"] < 1e-12
        with np.load(work / "runs" / f"{key}.npz") as data:
            out_id, out_tracking = data["out_id"], data["out_tracking_id"]
            out_mass = data["out_mass"].astype(np.float64)
        assert out_mass.sum() == pytest.approx(record["discharged_mass_kg"], rel=1e-6)
        end = Dem.load_checkpoint(work / "states" / f"run_{key}.npz")
        assert np.unique(out_id).size == out_id.size
        assert np.unique(end.id).size == end.n and not np.isin(out_id, end.id).any()
        start = Dem.load_checkpoint(pd._state_path(work, None, pd.start_key(design, run.start)))
        # every disk of the start state is still there or left by the feeder, once;
        # every other disk is new (an id above the start state's) and carries the run's lots
        new_end, new_out = end.id >= start.next_id, out_id >= start.next_id
        assert np.isin(end.id[~new_end], start.id).all()
        assert np.isin(out_id[~new_out], start.id).all()
        assert (~new_end).sum() + (~new_out).sum() == start.n
        assert new_end.sum() + new_out.sum() == end.next_id - start.next_id
        lots = np.concatenate([end.tracking_id[new_end], out_tracking[new_out]])
        assert np.all((lots >= run.first_tracking_id) & (lots < run.first_tracking_id + 10_000))
        assert (lots.size > 0) == (run.inflow_rate > 0)


def test_a_restarted_design_skips_finished_runs(reduced_run):
    design, work, _, _ = reduced_run
    stamps = {p: p.stat().st_mtime_ns for p in (work / "runs").glob("*.npz")}
    messages = []
    manifest = pd.run_design(design, work, workers=1, progress=messages.append)
    assert "0 jobs to do" in messages[0]
    assert {p: p.stat().st_mtime_ns for p in (work / "runs").glob("*.npz")} == stamps
    assert len(manifest["runs_finished"]) == len(design.runs)
    _strict((work / "manifest.json").read_text())
    assert {row["state"] for row in pd.status(design, work)} == {"done"}


def test_export_is_what_train_reads_and_counts_as_done(reduced_run, tmp_path):
    design, work, _, _ = reduced_run
    data = tmp_path / "data"
    manifest = pd.export(design, work, data)
    text = (data / "manifest.json").read_text()
    assert _strict(text) == json.loads(text)
    assert manifest["runs_done"] == manifest["runs_total"] == len(design.runs)
    assert {r["name"] for r in manifest["runs"]} == {r.name for r in design.runs}
    for record in manifest["runs"]:
        assert record["git_commit"] and record["particle_steps"] > 0 and record["wall_s"] > 0
        assert record["seed"] == record["spec"]["seed"]
    samples = doe.load_samples(data)
    assert samples["mass"].shape[1:] == design.grid.shape
    assert samples["run"].max() == len(design.runs) - 1
    meta = doe.read_meta(data)
    assert meta["grid"] == design.grid.to_dict() and meta["container"]["areal_density"] > 0
    from surrogate.rom.evaluate import train

    model = train(data, data / "model.npz", n_mass_modes=2, n_velocity_modes=2, ridge=1.0)
    assert model.n_samples == samples["time"].size and model.grid.shape == design.grid.shape
    # the random walk adds only what the ROM's own scheme, run on the training
    # runs, leaves short of the dispersion measured on the DEM
    spread = model.validation["dispersivity"]
    assert spread["dem"] > 0 and spread["rom_without_walk"] > 0
    assert model.dispersivity == max(spread["dem"] - spread["rom_without_walk"], 0.0)
    # a fresh work directory with this data folder has nothing to do
    messages = []
    pd.run_design(design, tmp_path / "fresh", data=data, workers=1, progress=messages.append)
    assert "0 jobs to do" in messages[0]


def test_a_killed_run_resumes_from_its_checkpoint(reduced_run, tmp_path):
    """Kill the design (SIGKILL, as at the end of a session) right after the
    first checkpoint of a run, export, restart from the export alone: the run
    completes from that checkpoint, with the result of the uninterrupted run."""
    design, finished, _, _ = reduced_run
    work = tmp_path / "work"
    run = design.run("small_out1000_in1000")
    key = pd.run_key(design, run)
    partial = work / "partial" / key
    command = [sys.executable, "-m", "minetwin.cli", "rom", "design", "--design", "reduced",
               "--work", str(work), "--workers", "1"]
    process = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while pd.latest_checkpoint(partial) is None:
            assert process.poll() is None, process.stderr.read().decode()
            assert time.monotonic() < deadline, "no checkpoint within 120 s"
            time.sleep(0.01)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        process.stderr.close()
    assert not (work / "runs" / f"{key}.npz").exists()
    row = next(r for r in pd.status(design, work) if r["name"] == run.name)
    assert row["state"] == "partial" and 0 < row["simulated_s"] < run.duration
    # what a session commits at its end: the start states and the checkpoint;
    # the next session, without the work directory, continues from them
    data = tmp_path / "data"
    manifest = pd.export(design, work, data, with_partial=True)
    assert manifest["runs_done"] == 0 and manifest["state_bytes"] > 0
    assert (data / "states" / f"{pd.start_key(design, run.start)}.npz").is_file()
    assert pd.latest_checkpoint(data / "partial" / key) is not None
    work = tmp_path / "next_session"
    pd.run_design(design, work, data=data, workers=1, progress=None)
    assert not (work / "states" / f"{pd.start_key(design, run.start)}.npz").exists()
    record = _strict((work / "runs" / f"{key}.json").read_text())
    assert record["status"] == "done" and len(record["resumed_at_s"]) == 1
    assert 0 < record["resumed_at_s"][0] < run.duration
    assert not (work / "partial" / key).exists()  # the checkpoints go once the run is done
    with np.load(work / "runs" / f"{key}.npz") as resumed, \
            np.load(finished / "runs" / f"{key}.npz") as whole:
        assert set(resumed.files) == set(whole.files)
        for name in whole.files:  # the same computation: bit for bit
            np.testing.assert_array_equal(resumed[name], whole[name], err_msg=name)


def test_a_run_that_blows_up_is_recorded_and_the_design_goes_on(tmp_path):
    """A start state whose (forced) step is far above the limit: its runs stop
    at the guard, are recorded unstable, the run that starts from one of them
    is skipped, and the design ends."""
    from surrogate.dem import Dem

    design = pd.reduced_design()
    pile = design.piles[0]
    dem = pd.layered_pile(design.config, pile.particles, pile.seed)
    dem.set_dt(4.0 * design.config.contact_time, force=True)
    states = tmp_path / "states"
    states.mkdir()
    dem.save_checkpoint(states / f"pile_{pd.pile_key(design, pile)}.npz")
    assert Dem.load_checkpoint(states / f"pile_{pd.pile_key(design, pile)}.npz").dt > 1e-3
    messages = []
    manifest = pd.run_design(design, tmp_path, workers=1, progress=messages.append)
    status = {r["name"]: r["status"] for r in manifest["runs_finished"]}
    assert status == {"small_out1000_in1000": "unstable", "small_drain_out1500": "unstable"}
    assert any("skipped" in m and "small_depleted_out500_in1500" in m for m in messages)
    for record in manifest["runs_finished"]:
        assert record["unstable_reason"]
    _strict((tmp_path / "manifest.json").read_text())
    # recorded failures are not retried
    messages.clear()
    pd.run_design(design, tmp_path, workers=1, progress=messages.append)
    assert "0 jobs to do" in messages[0]


def test_cli_plan_and_bad_input():
    command = [sys.executable, "-m", "minetwin.cli", "rom", "design", "--design", "reduced",
               "--work", "/nonexistent-never-written", "--plan"]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    plan = _strict(done.stdout)
    assert [r["name"] for r in plan["runs"]] == [r.name for r in pd.reduced_design().runs]
    assert plan["planned_particle_steps_total"] > 0
    assert not Path("/nonexistent-never-written").exists()
    bad = subprocess.run(command[:5] + ["--design", "nope", "--work", "x", "--plan"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--design" in bad.stderr and "Traceback" not in bad.stderr


def test_a_missing_start_state_reruns_the_parent_of_an_unfinished_run(reduced_run, tmp_path):
    """Only results of the parent are kept, not its end state: to run the child
    the design runs the parent again (the same key, the same result)."""
    import shutil

    design, finished, _, _ = reduced_run
    work = tmp_path / "work"
    shutil.copytree(finished, work)
    parent = pd.run_key(design, design.run("small_drain_out1500"))
    child = pd.run_key(design, design.run("small_depleted_out500_in1500"))
    (work / "states" / f"run_{parent}.npz").unlink()
    for suffix in (".npz", ".json"):
        (work / "runs" / f"{child}{suffix}").unlink()
    messages = []
    pd.run_design(design, work, workers=1, progress=messages.append)
    assert "2 jobs to do" in messages[0]
    for key in (parent, child):
        with np.load(work / "runs" / f"{key}.npz") as again, \
                np.load(finished / "runs" / f"{key}.npz") as first:
            for name in first.files:
                np.testing.assert_array_equal(again[name], first[name], err_msg=name)


def test_the_committed_runs_keep_their_keys_as_dem_settings_are_added():
    """Settings added to the DEM after the design began (the nonsmooth method, the
    feeder's Beverloo bound, the guard, threads) leave the key of a run at their
    defaults, so the committed runs stay done; a setting that changes the physics
    changes every key."""
    from surrogate.rom import paper_design as pd

    design = pd.get_design("paper")
    done = pd.committed_keys(pd.DATA_DIR)
    assert len(done) >= 2
    keys = {pd.run_key(design, run) for run in design.runs}
    assert set(done) <= keys
    for changes in ({"method": "nonsmooth"}, {"beverloo_c": 0.5}, {"friction": 0.3}):
        other = dataclasses.replace(design, config=dataclasses.replace(design.config, **changes))
        assert not {pd.run_key(other, run) for run in design.runs} & keys, changes
    threads = dataclasses.replace(design, config=dataclasses.replace(design.config, threads=2))
    assert {pd.run_key(threads, run) for run in design.runs} == keys


@pytest.fixture(scope="module")
def heldout_run(tmp_path_factory):
    """The reduced held-out design run once, in this process (one worker)."""
    work = tmp_path_factory.mktemp("heldout")
    design = pd.get_design("reduced_heldout")
    manifest = pd.run_design(design, work, workers=1, progress=None)
    return design, work, manifest


def test_heldout_replicas_share_their_inflow_and_start_and_keep_the_design_keys(heldout_run):
    """The held-out design's replicas of a scene are fed the very same particles
    (ids, masses, lots) from the same start state; only the perturbed ones get a
    key of their own, and the paper design's runs keep theirs (checked above).
    Invariants only: the replicas' outflows are chaotic."""
    design, work, manifest = heldout_run
    runs = design.runs
    assert len(runs) == pd.HELDOUT_REPLICAS
    assert [r.perturbation for r in runs] == [0.0] + [pd.HELDOUT_PERTURBATION] * (len(runs) - 1)
    assert len({pd.run_key(design, r) for r in runs}) == len(runs)
    # the replica number seeds the perturbation only: without one, it is no input
    assert pd.run_key(design, dataclasses.replace(runs[0], replica=5)) == \
        pd.run_key(design, runs[0])
    assert {r["name"] for r in manifest["runs_finished"]} == {r.name for r in runs}
    keys = [pd.run_key(design, run) for run in runs]
    results, records = [], []
    for key in keys:
        with np.load(work / "runs" / f"{key}.npz") as data:
            results.append({k: data[k] for k in data.files})
        records.append(_strict((work / "runs" / f"{key}.json").read_text()))
    for other in results[1:]:
        for name in (f"in_{k}" for k in pd._OUTFLOW_KEYS):
            assert np.array_equal(other[name], results[0][name]), name
    for record in records:
        assert record["held_mass_start_kg"] == records[0]["held_mass_start_kg"]
        assert abs(record["mass_balance_error"]) < 1e-9


@pytest.mark.slow  # about 25 s: trains a ROM, scores 3 models, 2 CLI runs
def test_an_exported_heldout_design_is_laid_out_and_scored(reduced_run, heldout_run, tmp_path):
    """Export keeps the start state though every run is done; the layout gives
    ``evaluate`` its scene: the start state, replica 0's inflow and one DEM file
    per replica, each conserving mass; a storage model runs it with every
    particle accounted for; ``rom evaluate`` scores a ROM trained on the reduced
    design there, and refuses the folder without --out."""
    from surrogate.dem import Dem
    from surrogate.rom import evaluate, heldout_layout

    pd.export(reduced_run[0], reduced_run[1], tmp_path / "train_data")
    model = tmp_path / "model.npz"
    evaluate.train(tmp_path / "train_data", model, n_mass_modes=2, n_velocity_modes=2,
                   ridge=1.0)
    design, work, _ = heldout_run
    data = tmp_path / "data"
    manifest = pd.export(design, work, data)
    assert manifest["runs_done"] == len(design.runs)
    start = data / "states" / f"{pd.start_key(design, design.runs[0].start)}.npz"
    assert start.is_file()
    assert heldout_layout.is_heldout_data(data) and not heldout_layout.is_heldout_data(work)
    layout = heldout_layout.write_layout(data, tmp_path / "scenes")
    assert [s["name"] for s in layout["scenes"]] == ["small_heldout_q1000"]
    assert layout["skipped"] == {}
    scene = tmp_path / "scenes" / "small_heldout_q1000"
    records = manifest["runs"]
    replicas = evaluate.stable_replicas(scene)
    assert len(replicas) == pd.HELDOUT_REPLICAS
    initial = Dem.load_checkpoint(scene / "initial.npz")
    for run, record in zip(replicas, records):
        assert float(run["t0"]) == initial.time
        assert int(run["particles"]) == initial.n == record["particles_start"]
        assert float(run["out_mass"].sum()) == pytest.approx(record["discharged_mass_kg"],
                                                             rel=1e-6)  # float32 masses
        assert run["field_mass"].shape[1:] == (design.grid.ny, design.grid.nx)
    with np.load(scene / "emissions.npz") as emissions:
        inflow = float(emissions["mass"].sum())
        assert inflow == pytest.approx(records[0]["inflow_mass_kg"], rel=1e-12)
        assert float(emissions["duration"]) == design.runs[0].duration
    outflow, _, storage = evaluate.run_storage("fifo", scene)
    assert outflow["mass"].sum() + storage.held_mass() == pytest.approx(
        initial.held_mass() + inflow, rel=1e-12)
    meta = doe.read_meta(tmp_path / "scenes")
    assert [s["name"] for s in evaluate.heldout_scenarios(tmp_path / "scenes")] == \
        ["small_heldout_q1000"]
    assert meta["heldout_scenarios"][0]["replicas"] == [r.name for r in design.runs]
    command = [sys.executable, "-m", "minetwin.cli", "rom", "evaluate", "--model", str(model),
               "--data", str(data)]
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 2 and "--out" in result.stderr, result.stderr
    result = subprocess.run([*command, "--out", str(tmp_path / "eval")], cwd=ROOT,
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    summary = _strict((tmp_path / "eval" / "summary.json").read_text())
    # the command scored on its process pool: the same scores as in this process
    here = evaluate.evaluate(evaluate.RomModel.load(model), tmp_path / "eval" / "scenes",
                             rom_options={"surface": "dem"})
    for key in ("tracking_error", "grade_error", "hardness_error"):
        assert summary[key] == here[key], key
    scored = summary["scenarios"]["small_heldout_q1000"]
    assert scored["dem_replicas"] == pd.HELDOUT_REPLICAS
    assert set(scored["tracking_error"]) == {"fifo", "mixing", "rom"}
    assert scored["tracking_error_spread"]["dem_noise_floor"]["n"] == 3  # every pair
    _choices_agree_with_every_model_run(summary, scored)


def test_train_chooses_by_tracking_on_validation_scenes(reduced_run, heldout_run, tmp_path):
    """``train(validation=...)`` fits every candidate on the whole design, runs each
    through the validation design's scenes under the storage options and keeps
    the one that tracks best; the record is what the chosen options score when
    refitted alone and run again (seeded: exactly), and the model keeps the
    storage options as its defaults. The scores are compared with each other,
    never with a DEM trajectory's value."""
    from surrogate.rom import evaluate, heldout_layout, validation
    from surrogate.rom.hanging import HANGING_LIMIT
    from surrogate.rom.storage import RomStorage

    pd.export(reduced_run[0], reduced_run[1], tmp_path / "train_data")
    design, work, _ = heldout_run
    pd.export(design, work, tmp_path / "validation")
    options = {"packing": "none", "landing_spread": 0.5}
    out = tmp_path / "chosen.npz"
    model = evaluate.train(tmp_path / "train_data", out, n_mass_modes=2, n_velocity_modes=2,
                           validation=tmp_path / "validation", storage_options=options,
                           rom_seeds=1)
    record = model.validation
    assert record["selected_by"] == "tracking on validation scenes"
    assert set(record["candidates"]) == {"2/2/0.1", "2/2/1", "2/2/10", "2/2/100"}
    assert record["candidates"][f"2/2/{model.ridge:g}"] == record["validation_tracking_error"]
    assert list(record["validation_scenes"]) == ["small_heldout_q1000"]
    assert record["validation_scenes"]["small_heldout_q1000"]["n"] == pd.HELDOUT_REPLICAS
    # the choice is the best tracker among the candidates whose bulk rests on its base
    hanging = record["candidates_hanging_mass_share"]
    assert set(hanging) == set(record["candidates"])
    assert all(0.0 <= share <= 1.0 for share in hanging.values())
    resting = [key for key, share in hanging.items() if share <= record["hanging_limit"]]
    assert record["hanging_limit"] == HANGING_LIMIT
    assert record["hanging_limit_met"] is bool(resting)
    assert record["validation_tracking_error"] == min(
        record["candidates"][key] for key in (resting or record["candidates"]))
    loaded = evaluate.RomModel.load(out)
    assert loaded.storage_settings == model.storage_settings == options
    assert loaded.provenance["options"]["validation"] == str(tmp_path / "validation")
    storage = RomStorage(loaded)
    assert (storage.packing, storage.landing_spread) == ("none", 0.5)
    alone = evaluate.train(tmp_path / "train_data", None, n_mass_modes=2, n_velocity_modes=2,
                           ridge=model.ridge, storage_options=options)
    assert alone.storage_settings == options  # the scores run it under them
    again = validation.tracking_scores({"chosen": alone}, tmp_path / "validation", 1)
    assert again["chosen"]["tracking_error"] == record["validation_tracking_error"]
    assert again["chosen"]["hanging_mass_share"] == hanging[f"2/2/{model.ridge:g}"]
    # scored in a worker process (rom train --workers): the very same scores
    assert validation.tracking_scores({"chosen": alone}, tmp_path / "validation", 1,
                                      workers=2) == again
    with pytest.raises(ValidationError, match="workers"):
        validation.tracking_scores({"chosen": alone}, tmp_path / "validation", 1, workers=0)
    # at limit 0 only a candidate hanging nothing qualifies; with none, tracking alone
    strict = evaluate.train(tmp_path / "train_data", None, n_mass_modes=2, n_velocity_modes=2,
                            validation=[tmp_path / "validation"], storage_options=options,
                            rom_seeds=1, hanging_limit=0.0)
    flawless = [key for key, share in hanging.items() if share <= 0.0]
    assert strict.validation["hanging_limit_met"] is bool(flawless)
    assert strict.validation["validation_tracking_error"] == min(
        record["candidates"][key] for key in (flawless or record["candidates"]))
    with pytest.raises(ValidationError, match="distinct names"):
        validation.tracking_scores({"chosen": alone}, [tmp_path / "validation"] * 2, 1)
    # beside the mean, each candidate's excess over the scene's DEM floor (its replicas'
    # error against each other), which select_by="floor-excess" minimises instead
    assert record["select_by"] == "mean" and "select_by" not in loaded.provenance["options"]
    with heldout_layout.scenes_laid_out(tmp_path / "validation") as (folder, names):
        replicas = evaluate.stable_replicas(folder / names[0])
        references = [evaluate.outflow_of(run) for run in replicas]
        t0 = float(replicas[0]["t0"])
        floor = evaluate.noise_floor(references, t0, t0 + evaluate.scenario_duration(
            folder / names[0]))["tracking_error"]
    assert record["validation_scene_floors"] == {"small_heldout_q1000": floor}
    assert record["candidates_floor_excess"] == pytest.approx(
        {key: error - floor for key, error in record["candidates"].items()}, abs=1e-15)
    by_excess = evaluate.train(tmp_path / "train_data", tmp_path / "by_excess.npz", n_mass_modes=2,
                               n_velocity_modes=2, validation=tmp_path / "validation",
                               storage_options=options, rom_seeds=1, select_by="floor-excess")
    assert by_excess.validation["select_by"] == "floor-excess"
    assert by_excess.validation["validation_floor_excess"] == min(
        record["candidates_floor_excess"][key] for key in (resting or record["candidates"]))
    assert by_excess.provenance["options"]["select_by"] == "floor-excess"
    assert by_excess.provenance["regenerate"].endswith(
        "--rom-seeds 1 --select-by floor-excess --packing none --landing-spread 0.5")
    with pytest.raises(ValidationError, match="select_by.*mean, floor-excess"):
        evaluate.train(tmp_path / "train_data", None, n_mass_modes=2, n_velocity_modes=2,
                       validation=tmp_path / "validation", select_by="worst")


def _choices_agree_with_every_model_run(summary: dict, scored: dict) -> None:
    """Fidelity cards calibrated from this evaluation, where FIFO, mixing, the ROM and
    three DEM replicas ran on one scene: for a tracking-error target at each model's
    measured error, the chosen model meets it and no cheaper model does; a target
    below the DEM's noise floor is refused, naming the floor. Only the choice rule is
    checked, so this holds whatever the chaotic replicas measured."""
    from cosim.errors import ValidationError
    from cosim.fidelity import OperatingPoint, choose
    from surrogate.rom.fidelity_cards import cards_from_evaluation

    cards = cards_from_evaluation(summary, provenance={"test": "reduced held-out design"})
    scene = scored["scenario"]
    point = OperatingPoint(float(scene["discharge_rate"]), float(scene["fill"]),
                           float(summary["window_s"]))
    floor = float(scored["tracking_error_dem_noise_floor"])
    measured = {**{name: float(scored["tracking_error"][name])
                   for name in ("fifo", "mixing", "rom")}, "dem": floor}
    cost = {card.model: card.cost_at(point) for card in cards}
    chosen = set()
    for target in sorted(set(measured.values())):
        if target < floor:
            with pytest.raises(ValidationError, match="noise floor"):
                choose(cards, point, tracking_error=target)
            continue
        choice = choose(cards, point, tracking_error=target)
        chosen.add(choice.model)
        assert measured[choice.model] <= target
        assert all(measured[name] > target for name in measured
                   if cost[name] < cost[choice.model]), (target, measured, cost)
    assert "dem" in chosen or measured["dem"] > min(measured.values())


def test_the_rock_scene_is_the_heldout_pile_at_rock_stiffness_for_both_methods():
    """``paper_rock``: the held-out 17,500-disk pile at 1e10 N/m, its step the same
    fraction of the (16 times shorter) contact time; ``paper_rock_nonsmooth``: the
    same scene, pile and seeds by the nonsmooth method at the paper's 11 ms."""
    soft, rock, nonsmooth = (pd.get_design(name) for name in
                             ("paper_heldout", "paper_rock", "paper_rock_nonsmooth"))
    assert rock.config.normal_stiffness == pd.ROCK_STIFFNESS == 1e10
    assert nonsmooth.config.normal_stiffness == pd.ROCK_STIFFNESS
    assert rock.config.method == "explicit" and nonsmooth.config.method == "nonsmooth"
    assert soft.config.contact_time / rock.config.contact_time == pytest.approx(
        (1e10 / soft.config.normal_stiffness) ** 0.5)
    assert rock.config.stable_dt / rock.config.contact_time == pytest.approx(pd.STEP_FRACTION)
    assert rock.piles == soft.piles == nonsmooth.piles  # the same laid-out disks
    assert len({pd.pile_key(d, d.piles[0]) for d in (soft, rock, nonsmooth)}) == 3
    assert [r.replica for r in rock.runs] == [0, 1, 2]
    # as many realisations, with the same feeder, seeds, tracking ids and perturbations
    assert nonsmooth.runs == rock.runs
    assert all(r.duration == pd.ROCK_DURATION and r.inflow_rate == 0.0 for r in rock.runs)


def test_the_rock_inflow_scene_feeds_the_same_pile_and_leaves_the_drain_runs_keys():
    """``paper_rock_inflow``: the rock drain's pile (one settled pile key per method)
    fed 2 t/s from the inlet while drained at 2 t/s, new seeds and tracking ids; the
    committed drain runs keep their keys."""
    rock, inflow, inflow_ns = (pd.get_design(name) for name in
                               ("paper_rock", "paper_rock_inflow", "paper_rock_inflow_nonsmooth"))
    assert pd.pile_key(rock, rock.piles[0]) == pd.pile_key(inflow, inflow.piles[0])
    assert inflow.config == rock.config and inflow_ns.config.method == "nonsmooth"
    assert [r.replica for r in inflow.runs] == [0, 1, 2]
    assert all(r.inflow_rate == r.discharge_rate == 2000.0 for r in inflow.runs)
    assert inflow_ns.runs == inflow.runs
    assert not {r.seed for r in inflow.runs} & {r.seed for r in rock.runs}
    for design in (rock, inflow, inflow_ns):
        committed = pd.committed_keys(pd.DATA_DIR.parent / design.name)
        assert set(committed) == {pd.run_key(design, run) for run in design.runs}
    for name in ("paper_rock_nonsmooth", "paper_rock_inflow_nonsmooth"):  # over-relaxed
        relaxed = pd.with_settings(pd.get_design(name), {"solver_relaxation": 1.9})
        committed = pd.committed_keys(pd.DATA_DIR.parent / f"{name}_sor19")
        assert set(committed) == {pd.run_key(relaxed, run) for run in relaxed.runs}


def test_design_help_names_every_design():
    done = subprocess.run([sys.executable, "-m", "minetwin.cli", "rom", "design", "--help"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    text = " ".join(done.stdout.split())
    assert all(name in text for name in pd.DESIGNS), text


def test_a_design_with_changed_settings_gets_new_keys_and_says_how_to_regenerate(tmp_path):
    design = pd.get_design("paper_rock_nonsmooth")
    more = pd.with_settings(design, {"solver_iterations": 200})
    assert more.config.solver_iterations == 200 and more.changed == (("solver_iterations", 200),)
    assert pd.with_settings(design, {}) is design
    assert pd.run_key(more, more.runs[0]) != pd.run_key(design, design.runs[0])
    assert pd.pile_key(more, more.piles[0]) != pd.pile_key(design, design.piles[0])
    manifest = pd.export(more, tmp_path / "work", tmp_path / "data")
    assert manifest["regenerate"].endswith("--set solver_iterations=200")
    with pytest.raises(ValidationError, match="unknown key"):
        pd.with_settings(design, {"sweeps": 200})
    with pytest.raises(ValidationError, match="solver_iterations: must be an integer"):
        pd.with_settings(design, {"solver_iterations": 0.5})
    from minetwin.cli import main

    assert main(["rom", "design", "--design", "paper", "--work", str(tmp_path / "w"),
                 "--set", "friction=0.5"]) == 2  # not into the package's data


def test_only_runs_keeps_the_named_runs_their_start_runs_and_their_keys():
    design = pd.get_design("reduced")
    only = pd.only_runs(design, ["small_depleted_out500_in1500"])
    # the depleted run starts from the drain's end, so the drain runs too
    assert [r.name for r in only.runs] == ["small_drain_out1500", "small_depleted_out500_in1500"]
    assert all(pd.run_key(only, r) == pd.run_key(design, r) for r in only.runs)
    assert [r.name for r in pd.only_runs(design, ["small_out1000_in1000"]).runs] == [
        "small_out1000_in1000"]


def test_only_refuses_a_run_the_design_does_not_have_by_name(tmp_path):
    done = subprocess.run([sys.executable, "-m", "minetwin.cli", "rom", "design", "--design",
                           "reduced", "--only", "no_such_run", "--work", str(tmp_path / "w")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert "--only" in done.stderr and "small_drain_out1500" in done.stderr
    assert "no_such_run" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "w").exists()  # nothing run


@pytest.mark.parametrize("name", ["paper_validation", "paper_validation_drain",
                                  "paper_validation_q2000", "paper_validation_q2000_b"])
def test_the_committed_validation_scenes_are_their_designs_and_rest_on_their_base(name):
    """The committed validation folders hold every run of their design (by content
    key), laid out as ``rom train --validation`` reads them, and the DEM's own piles
    hang no more than ``hanging.HANGING_LIMIT`` over emptied cells in any sampled
    field (the limit is set above the DEM's largest share)."""
    from surrogate.rom import heldout_layout
    from surrogate.rom.hanging import HANGING_LIMIT, hanging_share

    folder = pd.DATA_DIR.parent / name
    design = pd.DESIGNS[name]()
    manifest = json.loads((folder / "manifest.json").read_text())
    assert {run["key"] for run in manifest["runs"]} == {pd.run_key(design, run)
                                                        for run in design.runs}
    assert heldout_layout.is_heldout_data(folder)
    grid, container = doe.grid_and_container(folder)
    for run in design.runs:
        with np.load(folder / "train" / f"{run.name}.npz") as stored:
            shares = [hanging_share(field, grid, container) for field in stored["mass"]]
        assert max(shares) <= HANGING_LIMIT
