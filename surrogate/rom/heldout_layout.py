"""An exported held-out design (``paper_design``) as the scoring layout of ``evaluate``.

Source: issue 15 (the paper-scale ROM scored on held-out paper-scale scenes,
at least 3 DEM replicas each) and ``surrogate.rom.evaluate`` (the layout it
scores: ``<scene>/initial.npz``, ``emissions.npz``, ``dem.npz``,
``dem_perturbed.npz``, ``dem_replica<k>.npz`` and ``doe.json``'s
``heldout_scenarios``).

A held-out design (``Design.keep_start_states``) runs each scene as replicas
``<scene>_r<k>`` from one exported start state, fed the very same particles
(each run records them: ``in_*``). ``write_layout`` turns its data folder
into that layout: the start state becomes ``initial.npz``, replica 0's inflow
``emissions.npz``, and each finished replica one DEM run file, with the
run's record for its wall time and step. A scene with fewer than 2 finished
replicas has no noise floor and is left out (named in ``skipped``).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError
from surrogate.rom import doe
from surrogate.rom.evaluate import DEM_REPLICAS, OUTFLOW_KEYS, replica_names
from surrogate.rom.paper_design import _OUTFLOW_KEYS as INFLOW_KEYS

def is_heldout_data(data) -> bool:
    """Whether ``data`` is the exported data folder of a held-out design."""
    from surrogate.rom import paper_design

    manifest = Path(data) / "manifest.json"
    if not (manifest.is_file() and (Path(data) / "train").is_dir()):  # a work folder has no train/
        return False
    name = json.loads(manifest.read_text()).get("design")
    return name in paper_design.DESIGNS and paper_design.get_design(name).keep_start_states


def scene_of(record: dict) -> str:
    """The scene a held-out run's record belongs to: its name without ``_r<replica>``."""
    return record["name"].removesuffix(f"_r{record['spec']['replica']}")


def finished_scenes(records: list) -> dict:
    """Finished replicas by scene (``scene_of``), ordered by replica number."""
    scenes = {}
    for record in sorted(records, key=lambda r: r["spec"]["replica"]):
        if record.get("status") == "done":
            scenes.setdefault(scene_of(record), []).append(record)
    return scenes


def _emissions(result: dict, record: dict) -> dict:
    return {**{k: result[f"in_{k}"] for k in INFLOW_KEYS},
            "discharge_rate": np.array(record["spec"]["discharge_rate"]),
            "duration": np.array(record["spec"]["duration"])}


def _dem_run(result: dict, record: dict, t0: float) -> dict:
    return {**{f"out_{k}": np.asarray(result[f"out_{k}"]) for k in OUTFLOW_KEYS},
            "wall_s": np.array(record["wall_s"]), "dt": np.array(record["dt_s"]),
            "steps": np.array(int(round(record["spec"]["duration"] / doe.CONTROL_STEP))),
            "particles": np.array(record["particles_start"]), "t0": np.array(t0),
            "discharge_rate": np.array(record["spec"]["discharge_rate"]),
            "unstable": np.array(0), "field_time": result["time"],
            "field_mass": result["mass"], "field_velocity": result["velocity"],
            "field_grade": result["grade"], "field_hardness": result["hardness"]}


def write_layout(data, out, progress=None) -> dict:
    """Write the scoring layout of the held-out data folder ``data`` into ``out``.

    Returns ``{"scenes": [...], "skipped": {scene: reason}}``; raises
    ``ValidationError`` when no scene has 2 finished replicas."""
    from surrogate.dem import Dem

    data, out = Path(data), Path(out)
    if not is_heldout_data(data):
        raise ValidationError("--data", "an exported held-out design (manifest.json of "
                              "`minetwin rom design --design paper_heldout --export`)",
                              f"{data} is not one")
    manifest = json.loads((data / "manifest.json").read_text())
    scenes, skipped = [], {}
    names = replica_names(DEM_REPLICAS)
    for scene, records in finished_scenes(manifest["runs"]).items():
        if len(records) < 2:
            skipped[scene] = f"{len(records)} of {DEM_REPLICAS} replicas finished (2 needed)"
            continue
        start = data / "states" / f"{records[0]['start_key']}.npz"
        if not start.is_file():
            skipped[scene] = f"its start state {start} is missing"
            continue
        if progress:
            progress(f"held-out scene {scene}: {len(records)} DEM replicas from {data}")
        folder = out / scene
        folder.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(start, folder / "initial.npz")
        t0 = float(Dem.load_checkpoint(start).time)
        for k, record in enumerate(records[:DEM_REPLICAS]):
            with np.load(data / "train" / f"{record['name']}.npz") as stored:
                result = {key: stored[key] for key in stored.files}
            if k == 0:
                np.savez_compressed(folder / "emissions.npz", **_emissions(result, record))
            np.savez_compressed(folder / f"{names[k]}.npz", **_dem_run(result, record, t0))
        spec = records[0]["spec"]
        scenes.append({"name": scene, "start": spec["start"],
                       "discharge_rate": spec["discharge_rate"],
                       "inflow_rate": spec["inflow_rate"], "duration": spec["duration"],
                       "particles": records[0]["particles_start"],
                       # the pile's mass at the start [kg], named as doe.Scenario names it
                       "fill": records[0]["held_mass_start_kg"],
                       "replicas": [r["name"] for r in records],
                       "design": manifest["design"]})
    if not scenes:
        why = "; ".join(f"{s}: {r}" for s, r in skipped.items()) or \
            f"{manifest['runs_done']} of {manifest['runs_total']} runs finished"
        raise ValidationError("--data", "a held-out design with 2 finished replicas of a scene",
                              f"{data}: {why}")
    meta = doe.read_meta(data)
    meta.update(heldout_scenarios=scenes, heldout_source=str(data), skipped=skipped)
    (out / "doe.json").write_text(json.dumps(meta, indent=1, allow_nan=False))
    return {"scenes": scenes, "skipped": skipped}


@contextmanager
def scenes_laid_out(data, scenes=None):
    """``write_layout`` of the held-out design ``data`` in a temporary folder, for
    the diagnostics that score scenes of it: yields ``(folder, names)``, ``names``
    the ``scenes`` asked for (default every scene laid out), each refused with the
    field ``--scene`` unless the design has it. The folder goes when the block ends."""
    with tempfile.TemporaryDirectory() as folder:
        names = [s["name"] for s in write_layout(data, folder)["scenes"]]
        for scene in scenes or ():
            if scene not in names:
                raise ValidationError("--scene", f"one of {names}", f"got {scene!r}")
        yield Path(folder), list(scenes or names)
