"""Start the plant server and the stockpile client as real processes (tests, demo).

Used by ``minetwin integration-test``, the tests and the benchmark, and meant
for a pytest plugin: ``prepare_state`` makes throw-away credentials and
certificates for one run; ``ServerProcess`` and ``StockpileProcess`` start
``minetwin serve-800xa`` / ``minetwin stockpile`` on 127.0.0.1 and a free
port and stop them (SIGTERM, then SIGKILL) in ``stop()``.
"""

from __future__ import annotations

import asyncio
import math
import os
import secrets
import signal
import subprocess
import sys
import time
from pathlib import Path

from minetwin.ports import free_port
from opcua_protocol import APPLICATION_URI_CLIENT, NAMESPACE_URI
from opcua_server.security import (ROLES, ensure_certificate, pki_paths, trust_certificate,
                                   write_users)


def prepare_state(root: Path) -> dict:
    """Users with fresh random passwords, a trusted client certificate, no ledger
    and no history.

    Returns ``{"server_state", "client_state", "passwords": {role: pw},
    "client_cert", "client_key", "password_files": {role: path}}``.
    """
    root = Path(root)
    server_state, client_state = root / "server", root / "client"
    for stem in ("ledger", "history"):
        for suffix in (".sqlite", ".sqlite-wal", ".sqlite-shm"):
            (server_state / f"{stem}{suffix}").unlink(missing_ok=True)  # a new run: a new plant
    passwords = {role: secrets.token_urlsafe(12) for role in ROLES}
    write_users(server_state / "users.toml", {r: (r, pw) for r, pw in passwords.items()})
    files = {}
    for role, pw in passwords.items():
        path = root / f"{role}.password"
        path.write_text(pw + "\n")
        os.chmod(path, 0o600)
        files[role] = path
    pki = pki_paths(client_state)
    asyncio.run(ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_CLIENT, client=True))
    trust_certificate(server_state, pki["cert"])
    return {"server_state": server_state, "client_state": client_state, "passwords": passwords,
            "password_files": files, "client_cert": pki["cert"], "client_key": pki["key"]}


def minetwin_command() -> list[str]:
    """The `minetwin` command line of this interpreter (works without the console script)."""
    return [sys.executable, "-m", "minetwin.cli"]


class ManagedProcess:
    """A child process with its output in a log file; ``stop()`` ends it."""

    def __init__(self, args: list[str], log_path: Path, env: dict | None = None):
        self.args = args
        self.log_path = Path(log_path)
        self.log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(args, stdout=self.log, stderr=subprocess.STDOUT,
                                     env={**os.environ, **(env or {})})

    def wait_for_file(self, path: Path, timeout: float = 120.0) -> str:
        """The file's text once the process wrote it; ``timeout`` [s] is generous:
        on a loaded machine a server takes more than 30 s to start (seen)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if Path(path).exists() and Path(path).read_text():
                return Path(path).read_text()
            if self.proc.poll() is not None:
                raise RuntimeError(f"{self.args[3]} exited with {self.proc.returncode}; "
                                   f"see {self.log_path}:\n{self.log_path.read_text()[-3000:]}")
            time.sleep(0.05)
        raise TimeoutError(f"{path} did not appear within {timeout} s; see {self.log_path}")

    def kill(self) -> None:
        """SIGKILL: a crash, no clean-up."""
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def stop(self, timeout: float = 15.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.log.close()
        return self.proc.returncode


PORT_ATTEMPTS = 3
"""Ports a ``ServerProcess`` tries when another process took the free port it chose
before the server bound it."""


def _size(path: Path) -> int:
    return path.stat().st_size if path.exists() else 0


def _read_from(path: Path, offset: int) -> str:
    with open(path, "rb") as log:
        log.seek(offset)
        return log.read().decode(errors="replace")


class ServerProcess(ManagedProcess):
    """``minetwin serve-800xa`` on 127.0.0.1 and a free port (another one if that
    port was taken before the server bound it, unless ``port`` is given).

    ``until``: the server's clock freezes at that simulation time (``--until``);
    ``clock_frozen()`` tells when it has.
    """

    def __init__(self, workdir: Path, state: dict, *, speed: float = 1.0, lockstep: bool = False,
                 insecure: bool = False, config: Path | None = None, port: int | None = None,
                 until: float | None = None):
        workdir = Path(workdir)
        self.state = state
        self.until, self.speed, self.lockstep = until, speed, lockstep
        self.ledger = workdir / "ledger.json"
        ready = workdir / "server.ready"
        options = ["--host", "127.0.0.1", "--state-dir", str(state["server_state"]),
                   "--speed", str(speed), "--ledger", str(self.ledger), "--ready-file", str(ready)]
        options += ["--lockstep"] if lockstep else []
        options += ["--insecure"] if insecure else []
        options += ["--config", str(config)] if config else []
        options += ["--until", str(until)] if until is not None else []
        for attempt in range(1, PORT_ATTEMPTS + 1):
            self.port = port or free_port()
            ready.unlink(missing_ok=True)
            log_start = _size(workdir / "server.log")
            super().__init__(minetwin_command() + ["serve-800xa", "--port", str(self.port), *options],
                             workdir / "server.log")
            try:
                self.url = self.wait_for_file(ready).strip()
                return
            except RuntimeError:
                self.log.close()
                taken = "address already in use" in _read_from(self.log_path, log_start)
                if port or not taken or attempt == PORT_ATTEMPTS:
                    raise


    def clock_frozen(self) -> bool:
        """True once the server has frozen its clock and written the ledger."""
        import json

        try:
            return bool(json.loads(self.ledger.read_text()).get("paused"))
        except (OSError, ValueError):
            return False


class StockpileProcess(ManagedProcess):
    """``minetwin stockpile`` connected to ``url`` as the ``surrogate`` user.

    ``model_options``: ``KEY=VALUE`` storage options, each passed as
    ``--model-option`` (e.g. ``["model=out/rom/model.npz"]`` for ``rom``).
    ``source_names``: display name per source index, each passed as
    ``--source-name`` (``opcua_server.config.source_names`` of the plant's feed).
    """

    def __init__(self, workdir: Path, state: dict, url: str, *, model: str = "fifo",
                 model_options: list[str] | None = None, lockstep: bool = False,
                 period: float = 1.0, duration: float | None = None, rest: bool = False,
                 extra: list[str] | None = None, name: str = "stockpile",
                 source_names: dict | None = None):
        workdir = Path(workdir)
        self.summary = workdir / f"{name}.summary.json"
        self.checkpoint = workdir / f"{name}.checkpoint"
        self.rest_port_file = workdir / f"{name}.rest_port"
        args = minetwin_command() + ["stockpile", "--server", url, "--model", model,
                              "--state-dir", str(state["client_state"]),
                              "--password-file", str(state["password_files"]["surrogate"]),
                              "--checkpoint", str(self.checkpoint), "--summary", str(self.summary)]
        for option in model_options or []:
            args += ["--model-option", option]
        for index, source in (source_names or {}).items():
            args += ["--source-name", f"{index}={source}"]
        args += ["--lockstep", "--period", str(period)] if lockstep else []
        args += ["--duration", str(duration)] if duration is not None else []
        if rest:
            self.rest_port_file.unlink(missing_ok=True)
            args += ["--rest-port", "0", "--rest-port-file", str(self.rest_port_file)]
        args += extra or []
        super().__init__(args, workdir / f"{name}.log")
        self.rest_url = None
        if rest:
            self.rest_url = f"http://127.0.0.1:{self.wait_for_file(self.rest_port_file).strip()}"


def drain_and_stop(server: ServerProcess, stockpile: StockpileProcess | None,
                   timeout: float = 30.0, catch_up_limit: float | None = None
                   ) -> tuple[dict, dict | None]:
    """Freeze the server's clock, let the stockpile catch up, stop both.

    A server started with ``until`` is not signalled: its clock freezes at
    ``until`` by itself, and is waited for (``timeout`` plus the wall time the
    rest of the run takes at the server's speed). Returns ``(ledger, summary)``.
    The stockpile has caught up when its time
    (REST ``/totals``) reached the frozen clock and the server then saw two
    more of its heartbeats (a whole exchange cycle after it: reports sent,
    records acknowledged). ``timeout`` [s of wall time] bounds each wait
    *without progress*: a stockpile that lags far behind (a loaded machine)
    is waited for as long as its time keeps moving, or at most
    ``catch_up_limit`` [s of wall time] in all if given (a benchmark: a
    stockpile that fell behind without bound is stopped where it is).
    """
    import json
    import urllib.request

    end = time.monotonic() + timeout
    if server.until is None:
        server.proc.send_signal(signal.SIGUSR1)
    elif not server.lockstep:
        end += server.until / server.speed
    ledger = {}
    while time.monotonic() < end:
        time.sleep(0.3)
        if server.clock_frozen():
            ledger = json.loads(server.ledger.read_text())
            break
    target = ledger.get("time_s", 0.0)
    summary = None
    if stockpile is not None:
        def stockpile_time():
            try:
                with urllib.request.urlopen(stockpile.rest_url + "/totals", timeout=2) as resp:
                    return json.loads(resp.read())["time_s"]
            except (OSError, ValueError, KeyError):
                return None

        last, stalled_since = None, time.monotonic()
        give_up = math.inf if catch_up_limit is None else time.monotonic() + catch_up_limit
        while (stockpile.rest_url and time.monotonic() - stalled_since < timeout
               and time.monotonic() < give_up):
            now = stockpile_time()
            if now is not None and now >= target - 1e-9:
                break
            if now is not None and (last is None or now > last):
                last, stalled_since = now, time.monotonic()
            time.sleep(0.2)
        if server.state is not None:
            asyncio.run(_two_more_heartbeats(server, timeout))
        else:
            time.sleep(1.0)
        stockpile.stop()
        summary = json.loads(stockpile.summary.read_text())
    server.stop()
    return json.loads(server.ledger.read_text()), summary


async def _two_more_heartbeats(server: ServerProcess, timeout: float) -> None:
    from asyncua import ua

    client = await connect(server.url, server.state, "viewer")
    try:
        idx = await client.get_namespace_index(NAMESPACE_URI)
        heartbeat = client.get_node(ua.NodeId("Plant.SP201.Heartbeat", idx))
        first, end = await heartbeat.read_value(), time.monotonic() + timeout
        while await heartbeat.read_value() < first + 2 and time.monotonic() < end:
            await asyncio.sleep(0.1)
    finally:
        await client.disconnect()


async def connect(url: str, state: dict, role: str, *, password: str | None = None,
                  certificate: Path | None = None, private_key: Path | None = None,
                  secure: bool = True, timeout: float = 4.0):
    """An asyncua client session as ``role`` (the user of that name).

    By default it uses the run's trusted client certificate over
    Basic256Sha256 SignAndEncrypt; ``password``, ``certificate`` and
    ``secure=False`` let tests try what must be refused.
    """
    from asyncua import Client, ua
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    client = Client(url, timeout=timeout)
    client.application_uri = APPLICATION_URI_CLIENT
    if role is not None:
        client.set_user(role)
        client.set_password(state["passwords"][role] if password is None else password)
    if secure:
        await client.set_security(SecurityPolicyBasic256Sha256,
                                  str(certificate or state["client_cert"]),
                                  str(private_key or state["client_key"]),
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
    await client.connect()
    return client
