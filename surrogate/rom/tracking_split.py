"""Which part of the outflow's composition the ROM gets wrong: the inflow or the pile it started with.

A diagnosis of the ROM on the scenes of an exported held-out design
(``surrogate/rom/README.md``, "What the tracking error is made of"). The
tracking error (``surrogate.rom.metrics``: the total-variation distance of the
per-window outflow compositions by tracking id, issue 10) is split three ways:

- ``lumped``: the same error with every tracking id that came in during the
  scene counted as one id. What it still sees is whether the outflow carries
  the right share of inflow and the right lots of the start pile (on the
  paper-scale held-out design those lots are layers, laid as the pile was
  built from the inlet), not which inflow lots.
- ``inflow_share``: per window, the share of the outflow mass that came in
  during the scene.
- ``inflow_lots``: per window, the 10, 50 and 90 % mass quantiles of the
  outflow's inflow lots by their order of arrival (0: the first lot in);
  a plug flow keeps them close together, a dispersing one spreads them.

Each is given for the ROM (``evaluate.run_storage``, the model and storage
options given) against every DEM replica (their mean) and between the replicas,
every pair once (the floor); both errors are scored by ``evaluate.ensemble_score``
and ``evaluate.noise_floor``, the lumped one on the lumped outflows.

Run::

    python -m surrogate.rom.tracking_split --data surrogate/rom/data/paper_heldout \\
        --out DIR [--scene S] [--model FILE] [--rest-fraction SHARE] [--seed N]

Writes ``tracking_split.json`` and prints one block per scene.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

from cosim import jsonio
from cosim.errors import ValidationError
from surrogate.rom import metrics

QUANTILES = (0.1, 0.5, 0.9)
"""Mass quantiles [-] of the inflow lots' order that ``inflow_lots`` reports."""


def lumped(outflow: dict, inflow_ids: np.ndarray) -> dict:
    """``outflow`` with every tracking id in ``inflow_ids`` replaced by the first of them."""
    tracking_id = np.asarray(outflow["tracking_id"])
    inflow = np.isin(tracking_id, inflow_ids)
    return {**outflow, "tracking_id": np.where(inflow, np.min(inflow_ids), tracking_id)}


def inflow_share(outflow: dict, inflow_ids: np.ndarray, t0: float, t1: float) -> list:
    """Per window [t0, t1) the share [-] of the outflow mass with an inflow id
    (None for a window without outflow)."""
    matrix, ids = metrics.window_compositions(outflow, t0, t1)
    total = matrix.sum(axis=1)
    inflow = matrix[:, np.isin(ids, inflow_ids)].sum(axis=1)
    return [float(i / t) if t > 0 else None for i, t in zip(inflow, total)]


def arrival_order(emissions: dict) -> dict:
    """Inflow tracking id -> its rank in the order the lots first came in (0 first)."""
    tracking_id = np.asarray(emissions["tracking_id"])
    ids, first = np.unique(tracking_id, return_index=True)
    by_time = np.argsort(np.asarray(emissions["time"], dtype=np.float64)[first], kind="stable")
    return {int(ids[i]): rank for rank, i in enumerate(by_time)}


def inflow_lots(outflow: dict, order: dict, t0: float, t1: float) -> list:
    """Per window the ``QUANTILES`` of the outflow's inflow mass over the lots'
    arrival ranks (``order``, ``arrival_order``); None where no inflow left."""
    matrix, ids = metrics.window_compositions(outflow, t0, t1)
    inflow = np.array([int(i) in order for i in ids], dtype=bool)
    rank = np.array([order[int(i)] for i in ids[inflow]], dtype=np.int64)
    by_rank = np.argsort(rank, kind="stable")
    ranked = rank[by_rank]
    rows = []
    for window in matrix[:, inflow][:, by_rank]:
        if window.sum() <= 0:
            rows.append(None)
            continue
        cumulative = np.cumsum(window) / window.sum()
        rows.append([int(ranked[np.searchsorted(cumulative, q)]) for q in QUANTILES])
    return rows


def split_scene(model, heldout: Path, options: dict | None = None, seed: int = 0) -> dict:
    """The split (module docstring) of the ROM ``model`` on the held-out scene folder
    ``heldout`` (``evaluate``'s layout)."""
    from surrogate.rom import evaluate

    replicas = evaluate.stable_replicas(heldout)
    references = [evaluate.outflow_of(run) for run in replicas]
    t0 = float(replicas[0]["t0"])
    t1 = t0 + evaluate.scenario_duration(heldout)
    with np.load(heldout / "emissions.npz") as stored:
        emissions = {key: stored[key] for key in ("time", "tracking_id")}
    inflow_ids = np.unique(emissions["tracking_id"])
    order = arrival_order(emissions)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rom, _, _ = evaluate.run_storage("rom", heldout, model, seed=seed, options=options)

    result = {"replicas": len(references), "window_s": metrics.WINDOW_S}
    lumped_references = [lumped(r, inflow_ids) for r in references]
    for key, run, against in (("tracking_error", rom, references),
                              ("lumped", lumped(rom, inflow_ids), lumped_references)):
        result[key] = {
            "rom": evaluate.ensemble_score(run, against, t0, t1)["tracking_error"],
            "dem_noise_floor": evaluate.noise_floor(against, t0, t1)["tracking_error"]}
    result["inflow_share"] = {"rom": inflow_share(rom, inflow_ids, t0, t1),
                              "dem": [inflow_share(r, inflow_ids, t0, t1) for r in references]}
    result["inflow_lots"] = {"quantiles": list(QUANTILES),
                             "rom": inflow_lots(rom, order, t0, t1),
                             "dem": [inflow_lots(r, order, t0, t1) for r in references]}
    return result


def split(data, scenes=None, model=None, options: dict | None = None, seed: int = 0) -> dict:
    """``split_scene`` on ``scenes`` (default all) of the exported held-out design
    ``data``: ``{scene: result}``."""
    from surrogate.rom import heldout_layout
    from surrogate.rom.storage import load_model

    model = load_model(model)
    with heldout_layout.scenes_laid_out(data, scenes) as (folder, names):
        return {name: split_scene(model, folder / name, options, seed) for name in names}


def _windows(rows) -> str:
    return "  ".join("-" if row is None else "/".join(str(v) for v in row) for row in rows)


def _shares(values) -> str:
    return " ".join("-" if v is None else f"{v:.2f}" for v in values)


def report(scene: str, result: dict) -> str:
    """The printed block of one scene."""
    full, lump = result["tracking_error"], result["lumped"]
    lines = [f"{scene}: tracking error ROM {full['rom']:.3f} (DEM floor "
             f"{full['dem_noise_floor']:.3f}); inflow ids as one: ROM {lump['rom']:.3f} "
             f"(floor {lump['dem_noise_floor']:.3f})",
             f"  inflow share per {result['window_s']:g} s window: ROM "
             f"{_shares(result['inflow_share']['rom'])}"]
    lines += [f"{'':31}DEM {_shares(d)}" for d in result["inflow_share"]["dem"]]
    lines.append("  inflow lots' order, " + "/".join(f"{q:.0%}" for q in QUANTILES)
                 + f" per window: ROM {_windows(result['inflow_lots']['rom'])}")
    lines += [f"{'':37}DEM {_windows(d)}" for d in result["inflow_lots"]["dem"]]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m surrogate.rom.tracking_split",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="exported held-out design folder")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--scene", action="append", default=None,
                        help="held-out scene, e.g. heldout_q2000 (repeatable; default all)")
    parser.add_argument("--model", default=None,
                        help="ROM model file (default: the default ROM, "
                             "data/paper_rom_loose.npz)")
    parser.add_argument("--rest-fraction", type=float, default=None,
                        help="RomStorage's rest_fraction (default: the model file's; 0: off; "
                             "surrogate.rom.rest)")
    parser.add_argument("--seed", type=int, default=0, help="ROM seed (0)")
    args = parser.parse_args(argv)
    options = {} if args.rest_fraction is None else {"rest_fraction": args.rest_fraction}
    try:
        results = split(args.data, args.scene, args.model, options, args.seed)
    except (ValidationError, OSError) as error:
        print(f"tracking_split: error: {error}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    jsonio.write(args.out / "tracking_split.json", results, indent=1)
    for scene, result in results.items():
        print(report(scene, result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
