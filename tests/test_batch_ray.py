"""Batches on a real Ray cluster: a head node and a worker node on 127.0.0.1, each
started with ``ray start`` (its own processes, free ports, one CPU, bounded
memory), stopped by ending exactly the processes they started.

* The reduced DEM design on Ray, with one Ray worker killed (SIGKILL) while it
  is in the middle of a run: Ray runs the task again, which resumes from the
  run's checkpoint, and every result and end state equals the local
  executor's bit for bit.
* A plant sweep with a deliberately failing run (an ore body of 0.5 m is
  exhausted by the first load): recorded as failed with its error, the rest
  completes; locally the sweep is interrupted with Ctrl-C after its first run
  and restarted (it skips the stored run), and one process of the local pool
  is killed mid-run (the pool is replaced and its runs run again); every time
  series and summary number (not the wall times) equals the Ray sweep's bit
  for bit.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cosim import batch
from surrogate.rom import paper_design

# Ray is in the test extras: without it these tests fail, they do not skip
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
# 30 s of plant time, about 3 s of wall time per finished run, so that the worker the
# test kills is still running one: with 10 s (about 1 s per run) a loaded clean-clone
# run reported no run to repeat, most likely because all had ended before the kill
SWEEP = ["examples/step_response.toml", "--set", "assets.left.length_m=300,0.5",
         "--set", "assets.trucks.trucks.0.start_s=0", "--seeds", "2", "--until", "30"]
WALL_KEYS = {"wall_s", "realtime_factor", "host", "code_version", "folder"}
# A shell without job control starts background commands with SIGINT ignored, and
# Python keeps an ignored SIGINT ignored: under `make test &` the sweep would not see
# the Ctrl-C at all. A terminal's foreground job has the default disposition.
AS_FROM_A_TERMINAL = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
                      "os.execv(sys.executable, [sys.executable, '-m', 'minetwin.cli', "
                      "*sys.argv[1:]])")


@pytest.fixture(scope="module")
def cluster():
    import ray

    from minetwin.testing.ray_cluster import LocalRayCluster

    with LocalRayCluster(workers=1, cpus_per_node=1) as running:
        yield running
        ray.shutdown()


def _arrays(folder: Path) -> dict:
    arrays = {}
    for path in sorted(folder.glob("*.npz")):
        with np.load(path, allow_pickle=False) as data:
            arrays.update({f"{path.name}:{k}": data[k] for k in data.files})
    return arrays


def _assert_same_arrays(a: dict, b: dict) -> None:
    assert a.keys() == b.keys() and a
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def _unfinished(design_folder: Path, keys: set[str]) -> set[str]:
    """The runs among ``keys`` that have written no record yet."""
    return {key for key in keys if not (design_folder / "runs" / f"{key}.json").exists()}


def test_a_dem_design_on_ray_with_a_killed_worker_equals_the_local_one(cluster, tmp_path):
    from minetwin.ray_executor import RayExecutor

    design = paper_design.reduced_design()
    local, remote = tmp_path / "local", tmp_path / "ray"
    with batch.LocalExecutor(1) as executor:
        paper_design.run_design(design, local, executor=executor, progress=lambda m: None)
    executor = RayExecutor(cluster.address, retries=2)
    assert executor.workers == 2  # the head's CPU and the worker node's
    outcome = {}
    thread = threading.Thread(target=lambda: outcome.update(manifest=paper_design.run_design(
        design, remote, executor=executor, progress=lambda m: None)))
    thread.start()
    killed = None
    deadline = time.monotonic() + 300
    while thread.is_alive() and killed is None and time.monotonic() < deadline:
        # a run is past its first checkpoint: kill the worker processes under the runs.
        # Every one of them, as nothing tells which worker runs which: killing one, a
        # loaded run once hit the other run, which had no checkpoint yet
        past_a_checkpoint = {p.parent.name for p in (remote / "partial").glob("*/ckpt_*.run.npz")}
        if _unfinished(remote, past_a_checkpoint):
            for pid in cluster.task_workers("call"):
                os.kill(pid, signal.SIGKILL)
            # a run's record is written within its task, so a run with no record now
            # was under a killed worker (and not one that ended before the kill)
            killed = next(iter(_unfinished(remote, past_a_checkpoint)), None)
        time.sleep(0.2)
    thread.join(timeout=600)
    executor.close()
    assert killed is not None, "no run past a checkpoint was under way to kill"
    manifest = outcome["manifest"]
    assert {r["status"] for r in manifest["runs_finished"]} == {"done"}
    records = {r["key"]: r for r in (json.loads(p.read_text())
                                     for p in sorted((remote / "runs").glob("*.json")))}
    assert len(records) == len(design.runs)
    # the killed run was run again from its checkpoint, not from scratch
    assert records[killed]["resumed_at_s"]  # the simulated times it was resumed at
    _assert_same_arrays(_arrays(local / "runs"), _arrays(remote / "runs"))
    _assert_same_arrays(_arrays(local / "states"), _arrays(remote / "states"))


WORKER_CPU_S = 0.3
"""CPU time [s] a child must have used to count as a pool worker under a run (a run of
the sweep takes about 3 s)."""


def _command_line(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:  # it has ended
        return b""


def _cpu_seconds(pid: int) -> float:
    """User plus system CPU time [s] the process has used (0 once it has ended)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _pool_workers(pid: int) -> list[int]:
    """The sweep's forked pool workers that are running a run: children that run the
    sweep's own command line and have used CPU time of their own. Other children come
    and go (a loaded run once killed ``ldconfig -p``, which ``ctypes.util.find_library``
    runs, instead of a worker); a child between fork and exec still shows the parent's
    command line, and under a busy loop it may keep it for longer than any fixed wait,
    but it has used next to no CPU time (a fork starts at 0): a worker under a run has."""
    children = Path(f"/proc/{pid}/task/{pid}/children")
    if not children.exists():
        return []
    own = _command_line(pid)
    return [c for c in (int(c) for c in children.read_text().split())
            if _command_line(c) == own and _cpu_seconds(c) >= WORKER_CPU_S]


def _sweep(out: Path, *options: str, wait_for_one: bool = False,
           kill_a_worker: bool = False) -> tuple[int, str]:
    command = [sys.executable, "-c", AS_FROM_A_TERMINAL, "sweep", *SWEEP, "--out", str(out),
               *options]
    process = subprocess.Popen(command, cwd=ROOT, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)
    deadline = time.monotonic() + 300
    if wait_for_one:  # Ctrl-C once the first run is stored
        while not list((out / "records").glob("*.json")) and time.monotonic() < deadline:
            time.sleep(0.2)
        os.killpg(process.pid, signal.SIGINT)
    if kill_a_worker:  # SIGKILL one process of the local pool while the runs are under way
        # at once: on an idle machine the runs may all end within the 2 s this waited
        while not (workers := _pool_workers(process.pid)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert workers, "the sweep started no worker process"
        os.kill(workers[0], signal.SIGKILL)
    _, err = process.communicate(timeout=600)
    return process.returncode, err


def _without_wall_time(frame: pd.DataFrame) -> pd.DataFrame:
    return frame.drop(columns=[c for c in frame.columns if c in WALL_KEYS])


def test_a_sweep_with_a_failing_run_on_ray_equals_the_local_one_interrupted(cluster, tmp_path):
    local, remote = tmp_path / "local", tmp_path / "ray"
    code, err = _sweep(local, "--workers", "1", wait_for_one=True)
    assert code == 130, err
    first = {p.name: p.read_text() for p in (local / "records").glob("*.json")}
    assert len(first) == 1
    code, err = _sweep(local, "--workers", "2", kill_a_worker=True)
    assert code == 1, err  # a run failed
    assert "1 already stored" in err
    assert "worker process died" in err and "run again" in err
    assert {n: (local / "records" / n).read_text() for n in first} == first  # not rerun
    code, err = _sweep(remote, "--executor", "ray", "--address", cluster.address)
    assert code == 1, err
    tables = [pd.read_parquet(folder / "summary.parquet") for folder in (local, remote)]
    for frame in tables:
        assert list(frame["status"]) == ["done", "done", "failed", "failed"]
        assert list(frame["seed"]) == [1, 2, 1, 2]
        assert list(frame["set.assets.left.length_m"]) == [300.0, 300.0, 0.5, 0.5]
        assert frame["error"].iloc[2].startswith("CosimulationError")
        assert "ore body exhausted" in frame["error"].iloc[2]
        assert (frame["simulated_s"].iloc[:2] == 30.0).all()
    pd.testing.assert_frame_equal(_without_wall_time(tables[0]), _without_wall_time(tables[1]),
                                  check_exact=True)
    sweep = json.loads((remote / "sweep.json").read_text())
    assert sweep["done"] == 2 and [f["name"] for f in sweep["failed"]] == list(
        tables[1]["name"].iloc[2:])
    for key in tables[0]["key"]:
        series = [pd.read_parquet(folder / "runs" / key / "timeseries.parquet")
                  for folder in (local, remote)]
        pd.testing.assert_frame_equal(series[0], series[1], check_exact=True)

