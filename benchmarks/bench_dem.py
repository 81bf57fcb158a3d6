"""DEM throughput on one core, side by side with LAMMPS (issue 5).

Scene: a settled dense 2D pile of 20,000 disks (0.2-0.48 m, ~1.7 kt at
2700 kg/m^3) on the default stockpile floor, built once with
``packed_pile`` + ``settle`` and cached (``--cache``). Both codes then run
the same fixed number of steps from that state:

* ours: ``Dem.step`` (numba, ``NUMBA_NUM_THREADS=1``);
* LAMMPS (Debian package, binary ``lmp``), if installed: ``pair_style
  gran/hooke/history`` with the same k_n, k_t = 2/7 k_n, friction, time step
  and skin (``neigh_modify delay 0 every 1 check yes``: rebuild when a disk
  moved more than skin/2, our rule), ``fix nve/sphere``, ``fix enforce2d``,
  granular walls (floor and side planes), one MPI rank, one OpenMP thread.
  LAMMPS's normal damping is a rate gamma_n (force m_eff gamma_n v_n); it is
  set to ours, 2 zeta sqrt(k_n / m_eff), at the mean m_eff; LAMMPS has no
  rolling resistance, ours does (extra work on our side).

Prints one JSON object: particle-steps per second of each (per wall second
and per CPU second: on a shared machine the CPU-time figure is steadier), the
ratios ours / LAMMPS, and where our time goes (force kernel, list builds, the
rest: integration, feeder, Python). Run: ``.venv/bin/python
benchmarks/bench_dem.py`` (a few minutes the first time, for settling).
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from cosim import jsonio
from surrogate.dem import Dem, DemConfig, kernels  # noqa: E402
from surrogate.dem.builders import packed_pile, settle  # noqa: E402


def settled_pile(n: int, cache: Path, settle_time: float) -> Dem:
    """Load the cached settled pile (if built with today's defaults), or build,
    settle and cache it."""
    if cache.is_file():
        dem = Dem.load_checkpoint(cache)
        if dem.cfg == DemConfig() and dem.n == n:
            return dem
        print("cached pile has other parameters; rebuilding", file=sys.stderr)
    start = time.perf_counter()
    dem = packed_pile(DemConfig(), n, seed=0)

    def report(d):
        speed = float(np.hypot(d.vel[:, 0], d.vel[:, 1]).max())
        print(f"settling: t = {d.time:.2f} s, max speed {speed:.3f} m/s, "
              f"wall {time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)

    settle(dem, max_time=settle_time, speed=0.05, chunk=0.25, progress=report)
    cache.parent.mkdir(parents=True, exist_ok=True)
    dem.save_checkpoint(cache)
    return dem


def time_ours(dem: Dem, steps: int) -> dict:
    dem.step(5)  # compile / load the numba cache outside the timing
    builds0 = dem.list_builds
    start, cpu0 = time.perf_counter(), time.process_time()
    dem.step(steps)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu0
    builds = dem.list_builds - builds0
    # where the time goes (CPU time, steadier on a shared machine): the force
    # kernel alone, and one list build, on this state
    force, torque = np.zeros((dem.n, 2)), np.zeros(dem.n)
    ht, hr, wht, whr = dem.ht.copy(), dem.hr.copy(), dem.wall_ht.copy(), dem.wall_hr.copy()
    args = (dem.pos, dem.vel, dem.omega, dem.radius, dem.body_mass, dem.inv_inertia, force,
            torque, dem.start, dem.nbr, ht, hr, dem.wall_start, dem.wall, wht, whr, dem.walls,
            dem.params, dem.dt, *dem._pair_buffers())
    kernels.compute_forces(*args)  # the first call loads the compiled kernel
    force_s = np.inf
    for _ in range(5):  # best of 5 blocks: other jobs on the machine only add time
        t0 = time.process_time()
        for _ in range(20):
            kernels.compute_forces(*args)
        force_s = min(force_s, (time.process_time() - t0) / 20)
    t0 = time.process_time()
    dem._mark_rows_changed(np.arange(dem.n))
    dem._rebuild()
    build_s = time.process_time() - t0
    contacts = int(_count_contacts(dem))
    return {
        "wall_s": wall, "cpu_s": cpu, "steps": steps, "particles": dem.n,
        "particle_steps_per_s": dem.n * steps / wall,
        "particle_steps_per_cpu_s": dem.n * steps / cpu,
        "list_builds": builds,
        "pairs_in_list_per_particle": dem.nbr.size / dem.n,
        "contacts_per_particle": contacts / dem.n,
        "cpu_time_share": {
            "force_kernel": force_s * steps / cpu,
            "list_builds": build_s * builds / cpu,
            "integration_feeder_python": 1.0 - (force_s * steps + build_s * builds) / cpu,
        },
        "force_kernel_cpu_s_per_step": force_s,
        "list_build_cpu_s": build_s,
    }


def _count_contacts(dem: Dem) -> int:
    i = np.repeat(np.arange(dem.n), np.diff(dem.start))
    j = dem.nbr
    d = np.hypot(*(dem.pos[i] - dem.pos[j]).T)
    return int((d < dem.radius[i] + dem.radius[j]).sum())


def lammps_binary() -> str | None:
    for name in ("lmp", "lmp_serial", "lmp_stable", "lammps"):
        path = shutil.which(name)
        if path:
            return path
    return None


def write_lammps_input(dem: Dem, steps: int, folder: Path) -> Path:
    """LAMMPS data + input files for the same scene (nothing is downloaded)."""
    cfg = dem.cfg
    half = cfg.floor_width / 2
    top = float(dem.pos[:, 1].max()) + 10.0
    lines = ["MineTwin DEM benchmark pile", "", f"{dem.n} atoms", "1 atom types", "",
             f"{-half - 1:.6f} {half + 1:.6f} xlo xhi", f"-1.0 {top:.6f} ylo yhi",
             "-0.5 0.5 zlo zhi", "", "Atoms # sphere", ""]
    density = dem.body_mass / (4.0 / 3.0 * np.pi * dem.radius ** 3)
    for k in range(dem.n):
        lines.append(f"{k + 1} 1 {2 * dem.radius[k]:.17g} {density[k]:.17g} "
                     f"{dem.pos[k, 0]:.17g} {dem.pos[k, 1]:.17g} 0.0")
    lines += ["", "Velocities", ""]
    for k in range(dem.n):
        lines.append(f"{k + 1} {dem.vel[k, 0]:.17g} {dem.vel[k, 1]:.17g} 0.0 0.0 0.0 "
                     f"{dem.omega[k]:.17g}")
    (folder / "pile.data").write_text("\n".join(lines) + "\n")
    kn = cfg.normal_stiffness
    kt = cfg.tangential_stiffness
    mean_meff = float(dem.body_mass.mean()) / 2.0
    gamma_n = 2.0 * cfg.damping_ratio * np.sqrt(kn / mean_meff)
    gamma_t = gamma_n * np.sqrt(kt / kn)
    gran = f"{kn:.6g} {kt:.6g} {gamma_n:.6g} {gamma_t:.6g} {cfg.friction:g} 1"
    script = f"""# MineTwin DEM benchmark: the same settled 2D pile as surrogate.dem
units si
dimension 2
atom_style sphere
boundary f fm p
newton off
comm_modify vel yes
read_data pile.data
neighbor {cfg.skin:g} bin
neigh_modify delay 0 every 1 check yes
pair_style gran/hooke/history {gran}
pair_coeff * *
timestep {dem.dt:.17g}
fix integrate all nve/sphere
fix grav all gravity 9.81 vector 0 -1 0
fix floor all wall/gran hooke/history {gran} yplane 0.0 NULL
fix sides all wall/gran hooke/history {gran} xplane {-half:g} {half:g}
fix plane all enforce2d
thermo_modify lost ignore norm no
thermo {max(steps // 4, 1)}
run {steps}
"""
    path = folder / "in.pile"
    path.write_text(script)
    return path


def time_lammps(binary: str, dem: Dem, steps: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench_dem_lammps_") as tmp:
        folder = Path(tmp)
        script = write_lammps_input(dem, steps, folder)
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        proc = subprocess.run([binary, "-in", script.name, "-log", "log.lammps"], cwd=folder,
                              env=env, capture_output=True, text=True, timeout=1800)
        log = proc.stdout
    if proc.returncode != 0:
        raise RuntimeError(f"LAMMPS failed ({proc.returncode}): {proc.stderr[-2000:]}")
    match = re.search(r"Loop time of ([0-9.eE+-]+) on (\d+) procs for (\d+) steps with (\d+) atoms",
                      log)
    if not match:
        raise RuntimeError("LAMMPS output has no 'Loop time' line")
    loop, procs, n_steps, atoms = (float(match.group(1)), int(match.group(2)),
                                   int(match.group(3)), int(match.group(4)))
    builds = re.search(r"Total # of neighbors = (\d+)", log)
    rebuilds = re.search(r"Neighbor list builds = (\d+)", log)
    cpu_use = re.search(r"([0-9.]+)% CPU use", log)
    cpu = loop * float(cpu_use.group(1)) / 100.0 if cpu_use else loop
    pair_share = re.search(r"Pair\s*\|[^|]*\|[^|]*\|[^|]*\|[^|]*\|\s*([0-9.]+)", log)
    neigh_share = re.search(r"Neigh\s*\|[^|]*\|[^|]*\|[^|]*\|[^|]*\|\s*([0-9.]+)", log)
    return {
        "binary": binary, "procs": procs, "steps": n_steps, "particles": atoms,
        "wall_s": loop, "cpu_s": cpu, "particle_steps_per_s": atoms * n_steps / loop,
        "particle_steps_per_cpu_s": atoms * n_steps / cpu,
        "list_builds": int(rebuilds.group(1)) if rebuilds else None,
        "neighbors_per_particle": int(builds.group(1)) / atoms if builds else None,
        "time_share_percent": {"pair": float(pair_share.group(1)) if pair_share else None,
                               "neigh": float(neigh_share.group(1)) if neigh_share else None},
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=20_000)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--settle-time", type=float, default=6.0,
                        help="longest settling of the pile before timing [s]")
    parser.add_argument("--cache", type=Path,
                        help="settled pile checkpoint (default: /tmp/minetwin_bench_dem_N.npz)")
    parser.add_argument("--no-lammps", action="store_true")
    args = parser.parse_args(argv)
    cache = args.cache or Path(tempfile.gettempdir()) / f"minetwin_bench_dem_{args.particles}.npz"
    dem = settled_pile(args.particles, cache, args.settle_time)
    scene = {"particles": dem.n, "mass_t": dem.held_mass() / 1e3,
             "height_m": float((dem.pos[:, 1] + dem.radius).max()), "dt_s": dem.dt,
             "normal_stiffness_N_per_m": dem.cfg.normal_stiffness, "skin_m": dem.cfg.skin,
             "max_speed_m_s": float(np.hypot(dem.vel[:, 0], dem.vel[:, 1]).max()),
             "max_overlap_over_diameter": dem.max_overlap_ratio()}
    lammps_dem = Dem.load_checkpoint(cache)
    ours = time_ours(dem, args.steps)
    result = {"scene": scene, "ours": ours, "numba_threads": os.environ["NUMBA_NUM_THREADS"]}
    binary = None if args.no_lammps else lammps_binary()
    if binary:
        theirs = time_lammps(binary, lammps_dem, args.steps)
        result["lammps"] = theirs
        result["ratio_ours_over_lammps"] = (ours["particle_steps_per_s"]
                                            / theirs["particle_steps_per_s"])
        # on a shared machine the CPU-time ratio is the steadier figure
        result["ratio_ours_over_lammps_cpu_time"] = (ours["particle_steps_per_cpu_s"]
                                                     / theirs["particle_steps_per_cpu_s"])
    else:
        result["lammps"] = "not installed" if not args.no_lammps else "skipped"
    print(jsonio.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
