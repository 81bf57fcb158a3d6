"""DEM throughput per core and on both cores, side by side with LAMMPS (issues 5, 22).

Scene: a settled dense 2D pile of 20,000 disks (0.2-0.48 m, ~1.7 kt at
2700 kg/m^3) on the default stockpile floor, built once with
``packed_pile`` + ``settle`` and cached (``--cache``). Both codes then run
the same fixed number of steps from that state:

* ours: ``Dem.step`` (numba) on one thread, and with ``--threads 2`` on two
  (``Dem.threads``);
* LAMMPS, if installed (prerequisite: the Debian/Ubuntu package ``lammps``,
  ``apt-get install lammps``, binary ``lmp``; it needs the GRANULAR package,
  listed by ``lmp -h``): ``pair_style granular`` with our contact law term by
  term (``write_lammps_input``: hooke normal spring with mass-scaled damping
  clipped at zero force, linear tangential spring with history and Coulomb
  limit, sds rolling resistance), the same time step and skin
  (``neigh_modify delay 0 every 1 check yes``: rebuild when a disk moved
  more than skin/2, our rule), ``fix nve/sphere``, ``fix enforce2d``, the
  same law on the floor and side walls, one MPI rank, one OpenMP thread;
  with ``--threads 2`` also on 2 MPI ranks (``mpirun -np 2``, Open MPI, a
  dependency of the Debian package). Masses are those of spheres in both
  (``read_data`` with a 3D density). LAMMPS's damping rates are set at the
  mean m_eff (ours is per pair). LAMMPS cannot read our tangential and
  rolling springs, so both codes start with them at zero. (With
  ``gran/hooke/history``, without rolling resistance, the pile slumps in
  LAMMPS and it is another scene.)

Timing: ``--pairs`` alternated pairs (ours, then LAMMPS) from the same state
in one run, so both see the same load on a shared machine; each pair gives
the ratio of particle-steps per wall second, ours / LAMMPS; the median and
range are reported, with the load average before and after. LAMMPS's time is
its "Loop time" (the run, not reading the data file); ours excludes the
numba compile. The kinetic energy at the end of every run shows both ran
the same scene. The first of our runs is profiled (force kernel,
list builds, the rest: integration, feeder, Python). Prints one JSON object.

Run: ``.venv/bin/python benchmarks/bench_dem.py --pairs 5 --threads 2`` (a
few minutes the first time, for settling). Not part of ``make test``: LAMMPS
is an optional prerequisite of this benchmark only.
"""

from __future__ import annotations

import os

# two threads in numba's pool for --threads 2; the per-core runs use one
# (Dem.threads = 1), whatever the pool holds
os.environ.setdefault("NUMBA_NUM_THREADS", "2")

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


def time_ours(cache: Path, steps: int, threads: int = 1, profile: bool = False) -> dict:
    """Run ``steps`` steps of the cached pile on ``threads`` threads; with
    ``profile``, also where the CPU time goes (best-of-5 timing of the force
    kernel and one list build on the end state)."""
    dem = Dem.load_checkpoint(cache)
    dem.threads = threads
    for name in ("ht", "hr", "wall_ht", "wall_hr"):
        # LAMMPS cannot read our tangential and rolling springs: both start without
        getattr(dem, name)[:] = 0.0
    dem.step(5)  # compile / load the numba cache outside the timing
    builds0 = dem.list_builds
    start, cpu0 = time.perf_counter(), time.process_time()
    dem.step(steps)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu0
    builds = dem.list_builds - builds0
    result = {
        "threads": dem.kernel_threads(), "wall_s": wall, "cpu_s": cpu, "steps": steps,
        "particles": dem.n, "particle_steps_per_s": dem.n * steps / wall,
        "particle_steps_per_cpu_s": dem.n * steps / cpu, "list_builds": builds,
        "kinetic_energy_end_J": float(0.5 * (dem.body_mass * (dem.vel ** 2).sum(axis=1)).sum()),
    }
    if not profile:
        return result
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
    result.update({
        "pairs_in_list_per_particle": dem.nbr.size / dem.n,
        "contacts_per_particle": contacts / dem.n,
        "cpu_time_share": {
            "force_kernel": force_s * steps / cpu,
            "list_builds": build_s * builds / cpu,
            "integration_feeder_python": 1.0 - (force_s * steps + build_s * builds) / cpu,
        },
        "force_kernel_cpu_s_per_step": force_s,
        "list_build_cpu_s": build_s,
    })
    return result


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
    # LAMMPS's granular model, term by term ours (README "Contact law"): hooke
    # with damping m_eff gamma_n v_n (mass_velocity) clipped at zero force
    # (limit_damping); linear_history tangential spring with damping
    # sqrt(k_t / k_n) times the normal one and Coulomb limit mu; sds rolling
    # spring on the rolling displacement R theta: ours, k_r = 2.25 k_n mu_r^2 R^2
    # on the angle, is 2.25 k_n mu_r^2 on it, limited by mu_r F_n
    gamma_n = 2.0 * cfg.damping_ratio * np.sqrt(kn / mean_meff)
    k_roll = 2.25 * kn * cfg.rolling_resistance ** 2
    gamma_roll = 2.0 * cfg.damping_ratio * np.sqrt(0.4 * k_roll * mean_meff)
    gran = (f"hooke {kn:.9g} {gamma_n:.9g} tangential linear_history {kt:.9g} "
            f"{np.sqrt(kt / kn):.9g} {cfg.friction:g} rolling sds {k_roll:.9g} "
            f"{gamma_roll:.9g} {cfg.rolling_resistance:g} damping mass_velocity limit_damping")
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
pair_style granular
pair_coeff * * {gran}
timestep {dem.dt:.17g}
fix integrate all nve/sphere
fix grav all gravity 9.81 vector 0 -1 0
fix floor all wall/gran granular {gran} yplane 0.0 NULL
fix sides all wall/gran granular {gran} xplane {-half:g} {half:g}
fix plane all enforce2d
compute kinetic all ke
thermo_style custom step c_kinetic
thermo_modify lost ignore norm no
thermo {max(steps // 4, 1)}
run {steps}
"""
    path = folder / "in.pile"
    path.write_text(script)
    return path


def mpirun_binary() -> str | None:
    return shutil.which("mpirun")


def time_lammps(binary: str, folder: Path, ranks: int = 1) -> dict:
    """Run the LAMMPS input written in ``folder`` on ``ranks`` MPI ranks."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [binary, "-in", "in.pile", "-log", "none"]
    if ranks > 1:
        mpirun = mpirun_binary()
        if mpirun is None:
            raise RuntimeError("mpirun not found")
        command = [mpirun, "--allow-run-as-root", "-np", str(ranks), *command]
    proc = subprocess.run(command, cwd=folder, env=env, capture_output=True, text=True,
                          timeout=3600)
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
    kinetic = re.findall(rf"^\s*{n_steps}\s+([0-9.eE+-]+)\s*$", log, re.MULTILINE)
    pair_share = re.search(r"Pair\s*\|[^|]*\|[^|]*\|[^|]*\|[^|]*\|\s*([0-9.]+)", log)
    neigh_share = re.search(r"Neigh\s*\|[^|]*\|[^|]*\|[^|]*\|[^|]*\|\s*([0-9.]+)", log)
    return {
        "binary": binary, "procs": procs, "steps": n_steps, "particles": atoms,
        "wall_s": loop, "particle_steps_per_s": atoms * n_steps / loop,
        "list_builds": int(rebuilds.group(1)) if rebuilds else None,
        "neighbors_per_particle": int(builds.group(1)) / atoms if builds else None,
        "kinetic_energy_end_J": float(kinetic[-1]) if kinetic else None,
        "time_share_percent": {"pair": float(pair_share.group(1)) if pair_share else None,
                               "neigh": float(neigh_share.group(1)) if neigh_share else None},
    }


def alternated(cache: Path, binary: str, folder: Path, steps: int, pairs: int,
               threads: int) -> dict:
    """``pairs`` alternated runs (ours on ``threads`` threads, then LAMMPS on as
    many MPI ranks); per-pair ratios of particle-steps per wall second."""
    rows, ratios = [], []
    for k in range(pairs):
        ours = time_ours(cache, steps, threads, profile=(k == 0 and threads == 1))
        theirs = time_lammps(binary, folder, threads)
        ratio = ours["particle_steps_per_s"] / theirs["particle_steps_per_s"]
        print(f"{threads} thread(s)/rank(s), pair {k + 1}: ours {ours['wall_s']:.2f} s, "
              f"LAMMPS {theirs['wall_s']:.2f} s, ratio {ratio:.2f}", file=sys.stderr, flush=True)
        kinetic = (ours["kinetic_energy_end_J"] / theirs["kinetic_energy_end_J"]
                   if theirs["kinetic_energy_end_J"] else None)
        rows.append({"ours": ours, "lammps": theirs, "ratio_ours_over_lammps": ratio,
                     "kinetic_energy_end_ours_over_lammps": kinetic})
        ratios.append(ratio)
    return {"threads_and_ranks": threads, "pairs": rows,
            "ratio_median": float(np.median(ratios)), "ratio_min": min(ratios),
            "ratio_max": max(ratios)}


def load_average() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--particles", type=int, default=20_000)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--pairs", type=int, default=5,
                        help="alternated ours/LAMMPS pairs per thread count (5)")
    parser.add_argument("--threads", type=int, choices=(1, 2), default=1,
                        help="2: also ours on 2 threads against LAMMPS on 2 MPI ranks (1)")
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
    result = {"scene": scene, "load_average_before": load_average(),
              "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "unset (OpenMP default)")}
    binary = None if args.no_lammps else lammps_binary()
    if binary is None:
        result["ours_one_thread"] = time_ours(cache, args.steps, 1, profile=True)
        result["lammps"] = "skipped" if args.no_lammps else "not installed"
    else:
        with tempfile.TemporaryDirectory(prefix="bench_dem_lammps_") as tmp:
            folder = Path(tmp)
            write_lammps_input(dem, args.steps, folder)
            result["per_core"] = alternated(cache, binary, folder, args.steps, args.pairs, 1)
            if args.threads == 2:
                if mpirun_binary() is None:
                    result["two_cores"] = "mpirun not found: no 2-rank LAMMPS run"
                else:
                    result["two_cores"] = alternated(cache, binary, folder, args.steps,
                                                     args.pairs, 2)
    result["load_average_after"] = load_average()
    print(jsonio.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
