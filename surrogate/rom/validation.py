"""Choosing among fitted ROMs by tracking on validation scenes.

Source: issue 15 (the ROM scored by its tracking error against DEM replicas,
``surrogate.rom.metrics``) and the train / validation / test split of model
selection (Hastie, Tibshirani and Friedman 2009, "The Elements of Statistical
Learning", 2nd ed., section 7.2): the candidates are fitted on the training
design, chosen on validation scenes, and scored on held-out scenes that took
no part in either.

Why: the leave-one-run-out error of the velocity field (``evaluate.train``'s
default selection) is dominated by the DEM's own fluctuations (its floor is
0.39-0.56 on the paper-scale held-out scenes) and ties models that track
differently (surrogate/rom/README.md, "A registered fit"); the tracking error
is what the ROM is for.

A validation data folder is an exported held-out design
(``paper_design.Design.keep_start_states``; ``minetwin rom design --design
paper_validation --export``); several folders are scored together. Each
candidate runs through every scene laid out from them (``heldout_layout``) once
per ROM seed 0 .. ``rom_seeds`` - 1 under the storage settings it keeps
(``RomModel.storage_settings``), and is scored against every stable DEM replica
of the scene (``evaluate.ensemble_score``); its score is the mean over scenes of
the mean over (seed, replica) pairs. Beside it, its excess over each scene's DEM
noise floor (the error between the scene's replicas, ``evaluate.noise_floor``) at
the scene where that excess is largest: issue 15's pass condition is the tracking
error within 0.02 of the floor on every scene, and a mean over scenes lets a scene
whose replicas disagree widely (a high floor) hide one that is tracked badly.
Beside both, the share of its bulk hanging over
emptied cells at each scene's end (``surrogate.rom.hanging``; mean over seeds),
which the pile's shape, not its outflow, shows.
"""

from __future__ import annotations

import sys
import warnings
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError
from surrogate.rom import evaluate, heldout_layout


def folders(data) -> list:
    """``data`` (one folder or several) as a list of folders."""
    return [data] if isinstance(data, (str, Path)) else list(data)


def tracking_scores(models: dict, data, rom_seeds: int = 2, progress=None,
                    workers: int = 1) -> dict:
    """Each model's tracking error on the validation scenes of ``data`` (one folder or
    several).

    ``models``: ``{key: RomModel}``, each run by ``RomStorage`` as it ships (its
    ``storage_settings``); ``rom_seeds``: 1-100 (default 2); ``workers``: scenes
    scored at once in processes of this machine (default 1: one after the other in
    this process; the scores are the same either way, each run being seeded).
    Returns ``{key: {"tracking_error": mean over scenes, "scenes": {scene:
    spread over (seed, replica) pairs}, "floor_excess": the largest over scenes of
    the scene's mean less its floor, "scene_floors": {scene: DEM noise floor},
    "hanging_mass_share": the largest over scenes, "hanging_by_scene": {scene: mean
    over seeds}}}`` (``evaluate.spread``).
    """
    from cosim import batch

    rom_seeds = evaluate.check_rom_seeds(rom_seeds)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValidationError("workers", "a whole number >= 1", f"got {workers!r}")
    with ExitStack() as stack:
        scenes, seen = [], set()
        for folder_of_scenes in folders(data):
            folder, names = stack.enter_context(heldout_layout.scenes_laid_out(folder_of_scenes))
            if seen & set(names):
                raise ValidationError("validation", "folders whose scenes have distinct names",
                                      f"{sorted(seen & set(names))} twice")
            seen |= set(names)
            scenes += [folder / name for name in names]
        if workers == 1:
            results = [score_scene(models, scene, rom_seeds, progress) for scene in scenes]
        else:
            calls = [(score_scene, {"models": models, "scene": scene, "rom_seeds": rom_seeds,
                                    "progress": _print if progress is not None else None})
                     for scene in scenes]
            with batch.LocalExecutor(workers) as executor:
                results = batch.run_calls(calls, executor)
    scores = {key: {"scenes": {}, "scene_floors": {}, "hanging_by_scene": {}} for key in models}
    for scene, result in zip(scenes, results):
        for key, (spread, floor, hanging) in result.items():
            scores[key]["scenes"][scene.name] = spread
            scores[key]["scene_floors"][scene.name] = floor
            scores[key]["hanging_by_scene"][scene.name] = hanging
    for entry in scores.values():
        entry["tracking_error"] = float(np.mean([s["mean"] for s in entry["scenes"].values()]))
        entry["floor_excess"] = max(scene["mean"] - entry["scene_floors"][name]
                                    for name, scene in entry["scenes"].items())
        entry["hanging_mass_share"] = max(entry["hanging_by_scene"].values())
    return scores


def _print(message: str) -> None:
    """Progress from a worker process, on its stderr."""
    print(message, file=sys.stderr, flush=True)


def score_scene(models: dict, scene: Path, rom_seeds: int, progress=None) -> dict:
    """Every model on one laid-out validation scene: ``{key: (spread over (seed,
    replica) pairs, the scene's DEM noise floor, hanging share: mean over seeds)}``."""
    replicas = evaluate.stable_replicas(scene)
    references = [evaluate.outflow_of(run) for run in replicas]
    t0 = float(replicas[0]["t0"])
    t1 = t0 + evaluate.scenario_duration(scene)
    floor = evaluate.noise_floor(references, t0, t1)["tracking_error"]
    result = {}
    for number, (key, model) in enumerate(models.items(), start=1):
        if progress is not None:
            progress(f"validation scene {scene.name}: candidate {number} of {len(models)}")
        errors, hanging = [], []
        for seed in range(rom_seeds):
            with warnings.catch_warnings():
                # a candidate outside its training ranges is scored as it runs
                warnings.simplefilter("ignore")
                outflow, _, storage = evaluate.run_storage("rom", scene, model, seed=seed)
            errors += evaluate.ensemble_score(outflow, references, t0, t1)["tracking_errors"]
            hanging.append(evaluate.hanging_at_end(storage, model, t1))
        result[key] = (evaluate.spread(errors), floor, float(np.mean(hanging)))
    return result
