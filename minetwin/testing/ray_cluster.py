"""A real Ray cluster on 127.0.0.1 for tests and benchmarks: a head node and
worker nodes, each started with ``ray start`` as its own processes, on free
ports, with their own ``--temp-dir``, a fixed number of CPUs and bounded
memory; stopped by ending exactly the processes they started (``ray stop``
would end every Ray process of the machine, other users' too).

    with LocalRayCluster(workers=1, cpus_per_node=1) as cluster:
        executor = RayExecutor(cluster.address)
        ...
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from minetwin.ports import free_port

MEMORY_BYTES = 1_500_000_000
"""Memory each node offers its tasks [bytes] (Ray's --memory)."""
OBJECT_STORE_BYTES = 100_000_000
"""Object store of each node [bytes] (Ray's minimum is about 75 MB)."""


def _ray_command() -> str:
    """The ``ray`` script beside this Python (its workers run this Python)."""
    return str(Path(sys.executable).with_name("ray"))


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(
            errors="replace")
    except OSError:
        return ""


def _parent(pid: int) -> int | None:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return None


class LocalRayCluster:
    """Head plus ``workers`` worker nodes with ``cpus_per_node`` CPUs each."""

    def __init__(self, workers: int = 1, cpus_per_node: int = 1):
        self.workers = workers
        self.cpus_per_node = cpus_per_node
        self.temp_dir = None
        self.address = None

    def _start(self, *options: str) -> None:
        env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
        node = [_ray_command(), "start", "--node-ip-address=127.0.0.1",
                f"--num-cpus={self.cpus_per_node}", "--num-gpus=0",
                f"--memory={MEMORY_BYTES}", f"--object-store-memory={OBJECT_STORE_BYTES}",
                f"--node-manager-port={free_port()}", f"--object-manager-port={free_port()}",
                f"--dashboard-agent-listen-port={free_port()}",
                f"--dashboard-agent-grpc-port={free_port()}",
                f"--metrics-export-port={free_port()}",
                f"--runtime-env-agent-port={free_port()}", "--disable-usage-stats", *options]
        done = subprocess.run(node, env=env, capture_output=True, text=True, timeout=180)
        if done.returncode != 0:
            raise RuntimeError(f"ray start failed ({done.returncode}): "
                               f"{(done.stdout + done.stderr)[-3000:]}")

    def start(self) -> "LocalRayCluster":
        # short: Ray's Unix sockets live under it (a path is limited to 107 bytes)
        self.temp_dir = tempfile.mkdtemp(prefix="mtray", dir="/tmp")
        port = free_port()
        self.address = f"127.0.0.1:{port}"
        try:
            self._start("--head", f"--port={port}", f"--temp-dir={self.temp_dir}",
                        "--include-dashboard=false")
            for _ in range(self.workers):
                self._start(f"--address={self.address}")
        except BaseException:
            self.stop()
            raise
        return self

    def processes(self) -> list[int]:
        """The pids of this cluster: every process whose command line names its
        temp dir or its head's address, and their descendants (the workers)."""
        pids = [int(p) for p in os.listdir("/proc") if p.isdigit()]
        mine = {pid for pid in pids
                if self.temp_dir in _cmdline(pid) or (self.address in _cmdline(pid)
                                                      and "ray" in _cmdline(pid))}
        mine.discard(os.getpid())
        grown = True
        while grown:
            extra = {pid for pid in pids if pid not in mine and _parent(pid) in mine}
            mine |= extra
            grown = bool(extra)
        return sorted(mine)

    def task_workers(self, function_name: str) -> list[int]:
        """Worker processes running a task of ``function_name`` (proctitle ``ray::name``)."""
        return [pid for pid in self.processes()
                if _cmdline(pid).startswith(f"ray::{function_name}")]

    def stop(self) -> None:
        if self.temp_dir is None:
            return
        for sig, wait_s in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
            pids = self.processes()
            for pid in pids:
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait_s
            while pids and time.monotonic() < deadline:
                pids = [pid for pid in pids if Path(f"/proc/{pid}").exists()
                        and "zombie" not in _state(pid)]
                time.sleep(0.2)
        shutil.rmtree(self.temp_dir, ignore_errors=True)
        self.temp_dir = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:", 1)[1].split("\n")[0]
    except (OSError, IndexError):
        return "zombie"
