"""Batches of independent runs behind one executor interface.

Every batch of the project (a DEM design, the held-out DEM runs of the ROM,
the location-error sweep of ``reproduce sensitivity``, a plant-scenario
``sweep``) is a list of ``Task``: a module-level function, its inputs and
its seed. ``run_batch`` runs them on an ``Executor`` and returns one
``record`` per task, in the tasks' order whatever the executor and its
number of workers:

* each record holds the task's inputs, seed, content key and the code
  version the worker ran (``code_version``), its value, wall time and host;
* a task that raises is recorded with ``status = "failed"`` and its error,
  and the batch goes on; ``summary(records)`` lists the failures;
* a worker process that dies mid-task (killed, out of memory) is retried,
  at most ``retries`` times, on a fresh worker; a deterministic task gives
  the value an undisturbed batch gives;
* with a ``store`` folder every finished record is written to
  ``store/records/<key>.json`` as it arrives, so a batch interrupted (Ctrl-C,
  a killed driver) and started again skips what is done. The key is the
  SHA-256 of the function's name, its inputs, its seed and the caller's
  ``version`` string, never of a name or the order;
* a task that declares ``writes_folder`` receives ``folder``
  (``store/runs/<key>``, created) and writes its large results (DEM
  snapshots, fields, time series) there; only its small value travels back.

Executors (a plug-in implements ``submit``, ``wait`` and ``outcome``):
``LocalExecutor`` (this module: ``workers`` processes, or in this process
with one worker) and ``RayExecutor`` (``minetwin.ray_executor``: a Ray
cluster started with ``ray start``). The core never imports Ray.

One progress display per batch on stderr (``BatchProgress``): done,
running, failed, elapsed and ETA.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import socket
import subprocess
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor
from concurrent.futures import wait as wait_futures
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path

from cosim import jsonio
from cosim.errors import ValidationError, raise_if_interrupted

RETRIES = 2
"""Default number of times a task whose worker died is run again."""


@dataclass(frozen=True)
class Task:
    """One run of a batch.

    Parameters
    ----------
    name : str
        Label in progress lines and records (plays no part in the key).
    function : callable
        A module-level function (importable on every worker), called as
        ``function(**inputs, **common[, seed=seed][, folder=folder])``.
    inputs : dict
        The run's own inputs, JSON-able (recorded and hashed).
    seed : int or None
        Passed as ``seed`` when not None.
    writes_folder : bool
        The function takes ``folder`` (its run folder) and writes its large
        results there.
    """

    name: str
    function: object
    inputs: dict = field(default_factory=dict)
    seed: int | None = None
    writes_folder: bool = False


class TaskFailed(Exception):
    """The task's own function raised (recorded; not retried)."""


class WorkerLost(Exception):
    """The worker process running the task died (retried)."""


def function_name(function) -> str:
    return f"{function.__module__}:{function.__qualname__}"


def task_key(task: Task, version: str = "") -> str:
    """Content key: SHA-256 (16 hex digits) of function, inputs, seed, version."""
    payload = {"function": function_name(task.function), "inputs": jsonio.plain(task.inputs),
               "seed": task.seed, "version": version}
    text = json.dumps(payload, sort_keys=True, allow_nan=False, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """The source tree's git commit (``+dirty`` with uncommitted changes) or
    ``unknown``, read on the first call in a process and kept: a process runs
    the code it imported, not what is edited in the tree later (a forked
    worker inherits the value read before the fork)."""
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                              text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (head + ("+dirty" if dirty.strip() else "")) if head else "unknown"


def call(function, kwargs: dict, common: dict | None = None) -> dict:
    """Run one task in a worker: its value, the code version, wall time, host."""
    started = time.perf_counter()
    try:
        value = function(**kwargs, **(common or {}))
    except Exception as exc:  # noqa: BLE001 - the task's failure is its record, not the batch's
        raise_if_interrupted(exc)
        raise TaskFailed(f"{type(exc).__name__}: {exc}") from None
    return {"value": value, "code_version": code_version(), "wall_s": time.perf_counter() - started,
            "host": socket.gethostname(), "pid": os.getpid()}


# -------------------------------------------------------------- executors
class Executor:
    """Runs calls of ``call``; a plug-in implements ``submit``, ``wait`` and
    ``outcome`` (and ``close`` if it holds resources).

    ``workers`` is how many tasks it runs at once (the scheduler keeps that
    many submitted); ``retries_on_its_own`` says that the engine itself runs
    a task again whose worker died (so ``run_batch`` does not).
    """

    name = "executor"
    retries_on_its_own = False

    def __init__(self, workers: int = 1, retries: int = RETRIES):
        if int(workers) < 1:
            raise ValidationError("--workers", ">= 1", f"got {workers}")
        if int(retries) < 0:
            raise ValidationError("retries", ">= 0", f"got {retries}")
        self.workers = int(workers)
        self.retries = int(retries)
        self.common = None

    def share(self, common: dict | None) -> None:
        """Inputs every task of the batch gets (large data sent once per worker)."""
        self.common = common

    def submit(self, function, kwargs: dict):
        """Start ``call(function, kwargs, common)``; a handle."""
        raise NotImplementedError

    def wait(self, handles: list, timeout: float | None) -> list:
        """The handles among ``handles`` that are finished (waits up to ``timeout``
        for at least one)."""
        raise NotImplementedError

    def outcome(self, handle) -> dict:
        """The finished call's dict, or raises ``TaskFailed`` / ``WorkerLost``."""
        raise NotImplementedError

    def close(self) -> None:
        """Release the workers (cancel what has not started)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


_COMMON = None  # a local pool worker's shared inputs (set once per worker process)


def _keep_common(common) -> None:
    global _COMMON
    _COMMON = common


def _pool_call(function, kwargs):
    return call(function, kwargs, _COMMON)


class _Done:
    """A handle of a call already run in this process."""

    def __init__(self, result=None, error=None):
        self.result, self.error = result, error


def _start_method():
    """How the pool starts its workers: forked, with this process's modules and compiled
    kernels already loaded, unless this process runs numba's OpenMP threads (the
    threading layer where TBB's library cannot be loaded): GNU OpenMP aborts a forked
    child ("fork() called from a process already using GNU OpenMP"), so the workers
    then come from a fork server, a fresh process."""
    import multiprocessing

    from numba.np.ufunc import parallel

    uses_openmp = parallel._is_initialized and parallel._threading_layer == "omp"
    return multiprocessing.get_context("forkserver" if uses_openmp else "fork")


class LocalExecutor(Executor):
    """``workers`` processes of this machine (``concurrent.futures``); with one
    worker the tasks run in this process, one after the other."""

    name = "local"

    def __init__(self, workers: int = 1, retries: int = RETRIES):
        super().__init__(workers, retries)
        self._pool = None

    def _ensure_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self.workers, initializer=_keep_common,
                                             initargs=(self.common,), mp_context=_start_method())
        return self._pool

    def share(self, common):
        if common is not self.common:  # the workers got the old one when they started
            self._drop_pool()
        super().share(common)

    def submit(self, function, kwargs):
        if self.workers == 1:
            try:
                return _Done(result=call(function, kwargs, self.common))
            except TaskFailed as exc:
                return _Done(error=exc)
        try:
            return self._ensure_pool().submit(_pool_call, function, kwargs)
        except BrokenProcessPool:  # a worker died since the last submit: a fresh pool
            self._drop_pool()
            return self._ensure_pool().submit(_pool_call, function, kwargs)

    def wait(self, handles, timeout):
        futures = [h for h in handles if not isinstance(h, _Done)]
        done = [h for h in handles if isinstance(h, _Done)]
        if done or not futures:
            return done + [f for f in futures if f.done()]
        return list(wait_futures(futures, timeout=timeout, return_when=FIRST_COMPLETED)[0])

    def outcome(self, handle):
        if isinstance(handle, _Done):
            if handle.error is not None:
                raise handle.error
            return handle.result
        try:
            return handle.result()
        except BrokenProcessPool as exc:
            # every call of the broken pool fails this way; the next submit starts a new pool
            self._drop_pool(wait=False)
            raise WorkerLost(f"worker process died ({exc})") from None

    def _drop_pool(self, wait: bool = True) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=wait, cancel_futures=True)
            self._pool = None

    def close(self):
        self._drop_pool()


# ---------------------------------------------------------------- progress
class BatchProgress:
    """Runs finished out of the batch on ``cosim.progress``'s tqdm line (a bar on a
    terminal, a plain line at most every ``log_every_s`` in a log), with how many
    are done, failed, already stored and running."""

    def __init__(self, label: str, total: int, *, stream=None, every_s: float = 1.0,
                 log_every_s: float = 10.0):
        from cosim.progress import Progress

        self.label, self.total = label, total
        self._progress = Progress(label, total, stream=stream, every_s=every_s,
                                  log_every_s=log_every_s, unit="run")
        self.done = self.running = self.failed = self.skipped = 0

    def _counts(self) -> str:
        return (f"{self.done} done, {self.failed} failed"
                + (f", {self.skipped} already stored" if self.skipped else "")
                + f", {self.running} running")

    def line(self) -> str:
        return self._progress.line(self.done + self.failed, self._counts())

    def update(self, *, force: bool = False, note: str = "") -> None:
        if note:
            self._progress.note(note)
        self._progress.update(self.done + self.failed, self._counts(), force=force)

    def close(self) -> None:
        self._progress.close(self._counts())


# ------------------------------------------------------------------- batch
def _write_record(path: Path, record: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    jsonio.write(tmp, record, indent=1, sort_keys=True)
    os.replace(tmp, path)


def stored_record(store, key: str) -> dict | None:
    """The finished record of ``key`` in ``store`` (None if not done there)."""
    path = Path(store) / "records" / f"{key}.json"
    if not path.is_file():
        return None
    record = json.loads(path.read_text())
    return record if record.get("status") == "done" else None


def run_batch(tasks: list[Task], executor: Executor, *, store=None, version: str = "",
              common: dict | None = None, label: str = "batch", progress: bool = True,
              stream=None) -> list[dict]:
    """Run ``tasks`` on ``executor``; one record per task, in the tasks' order.

    ``common`` inputs go to every task (sent once per worker; not part of the
    key: a store holds the results of one ``common``, name it in ``version``).
    With ``store`` finished runs are kept and skipped by the next call.
    """
    keys = [task_key(task, version) for task in tasks]
    if len(set(keys)) != len(keys):
        raise ValidationError("tasks", "distinct runs (same function, inputs and seed twice)")
    store = Path(store) if store is not None else None
    shown = BatchProgress(label, len(tasks), stream=stream) if progress else None
    records: list[dict | None] = [None] * len(tasks)
    pending = []
    for index, (task, key) in enumerate(zip(tasks, keys)):
        done = stored_record(store, key) if store is not None else None
        if done is not None:
            records[index] = done
            if shown:
                shown.done += 1
                shown.skipped += 1
        else:
            pending.append(index)
    executor.share(common)
    attempts = {index: 0 for index in pending}
    running: dict = {}  # handle -> task index
    try:
        while pending or running:
            while pending and len(running) < executor.workers:
                index = pending.pop(0)
                task, key = tasks[index], keys[index]
                kwargs = dict(task.inputs)
                if task.seed is not None:
                    kwargs["seed"] = task.seed
                if task.writes_folder:
                    if store is None:
                        raise ValidationError("store", f"a folder: task {task.name} writes one")
                    folder = store / "runs" / key
                    folder.mkdir(parents=True, exist_ok=True)
                    kwargs["folder"] = str(folder)
                attempts[index] += 1
                running[executor.submit(task.function, kwargs)] = index
            if shown:
                shown.running = len(running)
                shown.update()
            for handle in executor.wait(list(running), timeout=1.0):
                index = running.pop(handle)
                task, key = tasks[index], keys[index]
                record = {"name": task.name, "key": key, "function": function_name(task.function),
                          "inputs": jsonio.plain(task.inputs), "seed": task.seed,
                          "version": version, "executor": executor.name,
                          "attempts": attempts[index]}
                if task.writes_folder:
                    record["folder"] = str(store / "runs" / key)
                try:
                    result = executor.outcome(handle)
                except WorkerLost as exc:
                    if not executor.retries_on_its_own and attempts[index] <= executor.retries:
                        pending.insert(0, index)
                        if shown:
                            shown.update(note=f"{task.name}: {exc}; run again "
                                              f"(attempt {attempts[index] + 1})")
                        continue
                    record.update(status="failed", error=f"WorkerLost: {exc}")
                except TaskFailed as exc:
                    record.update(status="failed", error=str(exc))
                else:
                    record.update(status="done", value=jsonio.plain(result["value"]),
                                  code_version=result["code_version"],
                                  wall_s=result["wall_s"], host=result["host"])
                # as the store reads it back: a restarted batch's records equal a fresh one's
                record = json.loads(jsonio.dumps(record, sort_keys=True))
                records[index] = record
                if store is not None:
                    _write_record(store / "records" / f"{key}.json", record)
                if shown:
                    if record["status"] == "done":
                        shown.done += 1
                    else:
                        shown.failed += 1
                        shown.update(note=f"{task.name} FAILED: {record['error']}")
                    shown.running = len(running)
                    shown.update()
    finally:
        executor.share(None)
        if shown:
            shown.close()
    return records


def run_calls(calls: list, executor: Executor) -> list:
    """The values of ``(function, keyword arguments)`` calls, in their order,
    for batches whose results are files the functions write (no records, no
    store); a lost worker's call is run again (at most ``executor.retries``
    times); when calls failed, ``TaskFailed`` names them after all finished."""
    values, errors = [None] * len(calls), []
    pending, running, attempts = list(range(len(calls))), {}, [0] * len(calls)
    try:
        while pending or running:
            while pending and len(running) < executor.workers:
                index = pending.pop(0)
                attempts[index] += 1
                running[executor.submit(*calls[index])] = index
            for handle in executor.wait(list(running), timeout=None):
                index = running.pop(handle)
                try:
                    values[index] = executor.outcome(handle)["value"]
                except WorkerLost as exc:
                    if executor.retries_on_its_own or attempts[index] > executor.retries:
                        errors.append(f"{function_name(calls[index][0])}: {exc}")
                    else:
                        pending.insert(0, index)
                except TaskFailed as exc:
                    errors.append(f"{function_name(calls[index][0])}: {exc}")
    except BaseException:
        executor.close()  # Ctrl-C: stop the calls under way
        raise
    if errors:
        raise TaskFailed("; ".join(errors))
    return values


def summary(records: list[dict]) -> dict:
    """Counts and the failed runs (name, key, error) of a batch's records."""
    failed = [{"name": r["name"], "key": r["key"], "error": r.get("error")}
              for r in records if r["status"] != "done"]
    return {"runs": len(records), "done": len(records) - len(failed), "failed": failed}
