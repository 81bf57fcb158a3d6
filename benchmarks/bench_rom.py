"""ROM stockpile throughput at the paper's particle count (20,000) on one core.

The held-out initial DEM pile of a ROM data directory (``minetwin rom
evaluate --quick --out DIR``) is refined: every DEM particle becomes k
particles of 1/k its mass, jittered within its radius, so the pile holds
>= 20,000 pseudo-particles of the same total mass; the inflow particles are
refined the same way. The trained ROM (``--surface dem``, the default, or
``rule``) then runs the held-out controls for ``--seconds`` simulated seconds. Prints JSON: particles, wall seconds per
simulated second and the real-time factor.

    .venv/bin/python benchmarks/bench_rom.py --data DIR --model DIR/rom_model.npz
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

from cosim import jsonio


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--model", required=True)
    parser.add_argument("--particles", type=int, default=20_000)
    parser.add_argument("--seconds", type=float, default=120.0)
    parser.add_argument("--surface", choices=("dem", "rule"), default="dem",
                        help="surface layer of the ROM (default dem)")
    args = parser.parse_args(argv)

    from cosim.particles import ParticleStore
    from surrogate.dem import Dem
    from surrogate.rom import doe
    from surrogate.rom.model import RomModel
    from surrogate.rom.storage import RomStorage

    heldout = Path(args.data) / "heldout"
    snap = Dem.load_checkpoint(heldout / "initial.npz").snapshot()
    emissions = dict(np.load(heldout / "emissions.npz"))
    k = int(np.ceil(args.particles / len(snap["id"])))
    rng = np.random.default_rng(0)
    count = len(snap["id"]) * k
    jitter = rng.uniform(-1, 1, (count, 2)) * np.repeat(snap["radius"], k)[:, None]
    store = ParticleStore(capacity=2 * count)
    ids = store.add(mass=np.repeat(snap["mass"] / k, k), f=doe.FEED_F,
                    grade=np.repeat(snap["grade"], k), hardness=np.repeat(snap["hardness"], k),
                    owner=1)
    storage = RomStorage(RomModel.load(args.model), rng=np.random.default_rng(1),
                         surface=args.surface)
    storage.bind(store, 1)
    storage.place(ids, np.repeat(snap["position"], k, axis=0) + jitter)
    rate = float(emissions["discharge_rate"])
    inflow_mass = rate * doe.CONTROL_STEP
    piece = float(np.median(snap["mass"])) / k
    per_step = int(round(inflow_mass / piece))
    steps = int(args.seconds / doe.CONTROL_STEP)
    wall = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        storage.step(0.0, doe.CONTROL_STEP, rate)  # compile
        for s in range(steps):
            t = (s + 1) * doe.CONTROL_STEP
            new = store.add(mass=np.full(per_step, inflow_mass / per_step), f=doe.FEED_F,
                            grade=0.5, hardness=1.5, owner=1)
            tic = time.perf_counter()
            storage.receive(new, t)
            leaving = storage.step(t, doe.CONTROL_STEP, rate)
            wall += time.perf_counter() - tic
            store.remove(leaving)
    per_s = wall / (steps * doe.CONTROL_STEP)
    print(jsonio.dumps({"benchmark": "rom_stockpile_throughput", "surface": args.surface,
                      "particles_start": count,
                      "particles_end": int(storage.held_ids().size),
                      "simulated_s": steps * doe.CONTROL_STEP, "wall_s": wall,
                      "wall_s_per_simulated_s": per_s, "real_time_factor": 1.0 / per_s,
                      "discharge_rate_kg_s": rate}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
