"""cosim.batch on the local executor: records in task order whatever the number of
workers, a failing run recorded while the rest completes, a restarted batch
skipping what its store holds, and the CLI's executor options refusing bad
input. The Ray executor and killed workers: tests/test_batch_ray.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cosim import batch
from minetwin import cli
from minetwin.commands import sweep
from minetwin.commands.sweep import parse_setting

# parse_setting is a real function of the project that refuses malformed input:
# "no_equals_sign" is the deliberately failing run
TEXTS = ["assets.left.grade=0.2,0.3", "no_equals_sign",
         "assets.trucks.trucks.0.speed_m_s=6,8,10", "assets.stockpile.model=fifo,mixing"]


def _tasks():
    return [batch.Task(f"parse {k}", parse_setting, {"text": text})
            for k, text in enumerate(TEXTS)]


def _outcome(records):
    return [(r["name"], r["key"], r["status"], r.get("value"), r.get("error")) for r in records]


def test_records_in_task_order_with_any_number_of_workers_and_failures_recorded(capsys):
    results = []
    for workers in (1, 2):
        with batch.LocalExecutor(workers) as executor:
            results.append(batch.run_batch(_tasks(), executor))
    assert _outcome(results[0]) == _outcome(results[1])
    records = results[0]
    assert [r["name"] for r in records] == [f"parse {k}" for k in range(len(TEXTS))]
    assert records[0]["value"] == ["assets.left.grade", [0.2, 0.3]]
    assert records[3]["value"] == ["assets.stockpile.model", ["fifo", "mixing"]]
    failed = records[1]
    assert failed["status"] == "failed" and "ValidationError" in failed["error"]
    assert "--set" in failed["error"]
    for record in records:
        assert record["inputs"] == {"text": TEXTS[int(record["name"].split()[-1])]}
        assert record["function"] == "minetwin.commands.sweep:parse_setting"
    assert all(r["code_version"] for r in records if r["status"] == "done")
    assert batch.summary(records) == {"runs": 4, "done": 3, "failed": [
        {"name": "parse 1", "key": failed["key"], "error": failed["error"]}]}
    err = capsys.readouterr().err
    assert "parse 1 FAILED" in err
    assert "| 4/4 [" in err and "3 done, 1 failed, 0 running" in err  # tqdm's line


def interrupted_in_a_kernel(text):
    """A run hit by Ctrl-C inside a numba kernel: SystemError caused by the interrupt."""
    if text == "no_equals_sign":
        raise SystemError("CPUDispatcher returned a result with an exception set") \
            from KeyboardInterrupt()
    return parse_setting(text)


def test_ctrl_c_inside_a_run_stops_the_batch_and_keeps_what_is_stored(tmp_path):
    tasks = [batch.Task(f"parse {k}", interrupted_in_a_kernel, {"text": text})
             for k, text in enumerate(TEXTS)]
    with batch.LocalExecutor(1) as executor, pytest.raises(KeyboardInterrupt):
        batch.run_batch(tasks, executor, store=tmp_path, progress=False)
    stored = [json.loads(p.read_text()) for p in (tmp_path / "records").glob("*.json")]
    assert [r["name"] for r in stored] == ["parse 0"]  # not recorded as a failed run


def test_the_cli_reports_ctrl_c_inside_a_numba_kernel_as_an_interrupt(monkeypatch, capsys):
    def sweep_interrupted_in_a_kernel(args):
        raise SystemError("CPUDispatcher returned a result with an exception set") \
            from KeyboardInterrupt()

    def failed_otherwise(args):
        raise SystemError("a bug")

    monkeypatch.setattr(sweep, "run", sweep_interrupted_in_a_kernel)
    assert cli.main(["sweep", "examples/step_response.toml", "--out", "x"]) == 130
    assert "minetwin sweep: interrupted" in capsys.readouterr().err
    monkeypatch.setattr(sweep, "run", failed_otherwise)
    with pytest.raises(SystemError, match="a bug"):  # not every SystemError is an interrupt
        cli.main(["sweep", "examples/step_response.toml", "--out", "x"])


def test_a_restarted_batch_skips_the_runs_its_store_holds(tmp_path):
    tasks = _tasks()
    with batch.LocalExecutor(1) as executor:
        first = batch.run_batch(tasks[:2], executor, store=tmp_path, progress=False)
        stored = (tmp_path / "records" / f"{first[0]['key']}.json").read_text()
        again = batch.run_batch(tasks, executor, store=tmp_path, progress=False)
    # the done run comes from the store as it was (its wall time too); the failed one reruns
    assert again[0] == json.loads(stored)
    assert (tmp_path / "records" / f"{first[0]['key']}.json").read_text() == stored
    assert again[1]["status"] == "failed" and again[2]["status"] == "done"
    assert len(list((tmp_path / "records").glob("*.json"))) == len(tasks)


def test_the_key_is_the_content_not_the_name_or_order():
    a = batch.Task("one", parse_setting, {"text": "a=1"}, seed=3)
    assert batch.task_key(a) == batch.task_key(batch.Task("other", parse_setting,
                                                          {"text": "a=1"}, seed=3))
    assert len({batch.task_key(a), batch.task_key(a, version="2"),
                batch.task_key(batch.Task("one", parse_setting, {"text": "a=2"}, seed=3)),
                batch.task_key(batch.Task("one", parse_setting, {"text": "a=1"}, seed=4))}) == 4
    with pytest.raises(Exception, match="distinct runs"):
        batch.run_batch([a, a], batch.LocalExecutor(1), progress=False)


@pytest.mark.parametrize("options, field", [
    (["--workers", "0"], "--workers"),
    (["--executor", "ray"], "--address"),
    (["--address", "127.0.0.1:1"], "--address"),
    (["--seeds", "0"], "--seeds"),
    (["--set", "assets.left.nothing=1,2"], "at assets.left.nothing one of ["),
    (["--set", "assets.left.grade=2.5"], "--set assets.left.grade: must be"),
])
def test_sweep_refuses_bad_options_with_exit_code_2(tmp_path, options, field):
    done = subprocess.run([sys.executable, "-m", "minetwin.cli", "sweep",
                           "examples/step_response.toml", "--out", str(tmp_path / "out"),
                           *options], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "MINETWIN_RAY_ADDRESS": ""})
    assert done.returncode == 2, done.stderr
    assert field in done.stderr and "Traceback" not in done.stderr


def test_a_local_pool_works_after_this_process_ran_numbas_parallel_threads(tmp_path):
    """Where TBB's library cannot be loaded numba runs its parallel loops on GNU
    OpenMP, which aborts a forked child ("fork() called from a process already using
    GNU OpenMP"); the pool then starts its workers from a fork server. Run in a fresh
    process, as a DEM design's driver would be after building its piles."""
    script = tmp_path / "driver.py"
    script.write_text(
        "import numba, numpy as np\n"
        "from cosim import batch\n"
        "@numba.njit(parallel=True)\n"
        "def total(a):\n"
        "    s = 0.0\n"
        "    for i in numba.prange(a.size):\n"
        "        s += a[i]\n"
        "    return s\n"
        "def task(k):\n"
        "    return {'k': k, 'total': float(total(np.ones(1000)))}\n"
        "if __name__ == '__main__':\n"
        "    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)\n"
        "    total(np.ones(100_000))\n"
        "    with batch.LocalExecutor(2) as executor:\n"
        "        records = batch.run_batch([batch.Task(f't{k}', task, {'k': k})\n"
        "                                   for k in range(4)], executor, progress=False)\n"
        "    print(numba.threading_layer(), [r['status'] for r in records])\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=300, cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split(" ", 1)[1].strip() == str(["done"] * 4), done.stdout


def test_the_code_version_is_read_once_per_process(monkeypatch):
    """A process runs the code it imported: the version is read from git on the first
    call and kept, so a record written minutes later names the same commit even if the
    tree was edited meanwhile."""
    calls = []
    real_run = subprocess.run

    def counting_run(*args, **kwargs):
        calls.append(args[0])
        return real_run(*args, **kwargs)

    batch.code_version.cache_clear()
    monkeypatch.setattr(batch.subprocess, "run", counting_run)
    first = batch.code_version()
    assert batch.code_version() == first and batch.code_version() == first
    assert [command[:2] for command in calls] == [["git", "rev-parse"], ["git", "status"]]
