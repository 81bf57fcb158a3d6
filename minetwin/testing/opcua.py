"""A lockstep OPC UA integration for tests: mock 800xA server process + stockpile client.

Source: paper section "Integration test" (mock process simulator, stockpile
surrogate as OPC UA client, tracking exchange). The
server and client are the real ones (``opcua_server``, ``surrogate.client``)
over Basic256Sha256 SignAndEncrypt with credentials and certificates made
for the test (``minetwin.harness.prepare_state``). In lockstep the
server's clock advances only when the client calls ``Plant.AdvanceTime``,
so a run is deterministic and as fast as the machine allows.

The server runs as its own process (as in a plant); the client runs in the
test's process, so a test can read the stockpile asset directly and can
substitute a client class (e.g. a test double that misbehaves).
"""

from __future__ import annotations

import asyncio
import json
import signal
import time
from dataclasses import dataclass
from pathlib import Path

from minetwin.testing.assertions import assert_ids_accounted, assert_mass_balance

LEDGER_TIMEOUT_S = 20.0
"""Wall seconds to wait for the server to write its ledger."""


class MockPlantServer:
    """The mock 800xA server (``minetwin serve-800xa --lockstep``) on a free 127.0.0.1 port.

    Attributes after ``start()``: ``url``, ``passwords`` (role -> password of
    the test users ``operator``, ``surrogate``, ``viewer``), ``client_cert``
    and ``client_key`` (a client certificate the server trusts).

    Parameters
    ----------
    workdir : Path
        Folder for the server's state, log and ledger.
    config : Path, optional
        Plant configuration TOML merged over the defaults (belts, feed lots).
    lockstep : bool
        Advance only on ``AdvanceTime`` calls (default True).
    """

    def __init__(self, workdir, *, config=None, lockstep: bool = True):
        self.workdir = Path(workdir)
        self.config = config
        self.lockstep = lockstep
        self.process = None

    def start(self) -> "MockPlantServer":
        from minetwin.harness import ServerProcess, prepare_state

        self.workdir.mkdir(parents=True, exist_ok=True)
        self.state = prepare_state(self.workdir / "state")
        self.passwords = self.state["passwords"]
        self.client_cert, self.client_key = self.state["client_cert"], self.state["client_key"]
        self.process = ServerProcess(self.workdir, self.state, lockstep=self.lockstep,
                                     config=self.config)
        self.url = self.process.url
        return self

    def ledger(self) -> dict:
        """The server's exchange ledger now (entered / left mass per tracking id, counters)."""
        path = self.process.ledger
        path.unlink(missing_ok=True)
        self.process.proc.send_signal(signal.SIGUSR1)  # the server writes its ledger
        end = time.monotonic() + LEDGER_TIMEOUT_S
        while time.monotonic() < end:
            if path.exists():
                return json.loads(path.read_text())
            if self.process.proc.poll() is not None:
                break
            time.sleep(0.05)
        raise RuntimeError(f"the mock 800xA server wrote no ledger within {LEDGER_TIMEOUT_S:g} s; "
                           f"see {self.process.log_path}")

    def stop(self) -> None:
        if self.process is not None:
            self.process.stop()


@dataclass
class ExchangeResult:
    """What crossed the OPC UA exchange, per tracking id, after a lockstep run.

    ``entered``: mass [kg] per tracking id discharged onto the stockpile
    (server ledger); ``left``: mass reported onto the outgoing belt (server
    ledger); ``held``: mass still in the stockpile (client asset);
    ``report``: the integration report's counts (``opcua_server.audit``).
    """

    time_s: float
    entered: dict[int, float]
    left: dict[int, float]
    held: dict[int, float]
    report: dict
    ledger: dict
    summary: dict

    def assert_mass_balance(self, rtol: float = 1e-9) -> float:
        """Mass discharged onto the stockpile = mass held + mass reported out."""
        __tracebackhide__ = True
        return assert_mass_balance(self.report, rtol=rtol, where="the OPC UA stockpile exchange")

    def assert_ids_accounted(self, rtol: float = 1e-9):
        """Every tracking id that entered is held or has left, with all its mass, once."""
        __tracebackhide__ = True
        pending = self.ledger.get("pending", 0)
        where = "the OPC UA stockpile exchange" + (
            f" ({pending} inbound record(s) still unacknowledged on the server)" if pending
            else "")
        entered = list(self.entered)
        return assert_ids_accounted(
            entered, held=list(self.held), left=list(self.left),
            entered_mass=[self.entered[k] for k in entered],
            held_mass=list(self.held.values()), left_mass=list(self.left.values()),
            split_allowed=True, rtol=rtol, kind="tracking id", where=where,
            hint="Compare the client's outflow reports for these ids with the server "
                 "ledger's outflow_log (ExchangeResult.ledger).")

    def fingerprint(self) -> str:
        """Everything a run's outcome is, without wall-clock figures, as canonical JSON
        (NaN written as NaN, so two identical runs give equal strings)."""
        return json.dumps({"time_s": self.time_s, "entered": self.entered, "left": self.left,
                           "held": self.held, "outflow_log": self.ledger.get("outflow_log"),
                           "history": self.summary.get("history")}, sort_keys=True)


class LockstepStockpile:
    """The stockpile asset as an OPC UA client of ``server``, advancing in lockstep.

    Parameters
    ----------
    server : MockPlantServer
        A started lockstep server.
    model : str
        Storage model name (``fifo``, ``mixing``, ``rom``, ...), default ``fifo``.
    seed : int
        Seed of the asset (default 0).
    period : float
        Simulated seconds per ``AdvanceTime`` call (default 1.0).
    dt : float
        Largest asset step [s] (default 0.5).
    client_class : type
        ``surrogate.client.StockpileClient`` or a subclass (test doubles).
    wall_timeout : float
        Wall seconds a ``run`` may take before it fails (default 120).
    """

    def __init__(self, server: MockPlantServer, model: str = "fifo", *, seed: int = 0,
                 period: float = 1.0, dt: float = 0.5, client_class=None,
                 particle_mass_kg: float = 100.0, wall_timeout: float = 120.0):
        from surrogate.client import ClientOptions, StockpileClient

        self.server = server
        self.wall_timeout = float(wall_timeout)
        self.options = ClientOptions(
            server_url=server.url, username="surrogate", password=server.passwords["surrogate"],
            certificate=server.client_cert, private_key=server.client_key, model=model,
            seed=seed, particle_mass_kg=particle_mass_kg, dt_s=dt, lockstep=True,
            period_s=period)
        self.client = (client_class or StockpileClient)(self.options)
        self._ran = False

    @property
    def asset(self):
        """The ``StockpileAsset`` (particles, storage model, totals)."""
        return self.client.asset

    def run(self, until: float) -> ExchangeResult:
        """Advance server and client together to ``until`` [s]; return what crossed."""
        if self._ran:
            raise RuntimeError("a LockstepStockpile runs once; attach another client "
                               "(stockpile_client(...)) to a fresh mock_800xa for a second run")
        self._ran = True
        self.options.duration_s = float(until)
        try:
            code = asyncio.run(asyncio.wait_for(self.client.run(), self.wall_timeout))
        except TimeoutError:
            raise AssertionError(
                f"the lockstep exchange did not reach t = {until:g} s within "
                f"{self.wall_timeout:g} s wall (client at t = {self.asset.time:g} s, "
                f"{self.client.reconnects} reconnect(s)); see {self.server.process.log_path}"
            ) from None
        if code != 0:
            raise AssertionError(f"the stockpile client was refused by the server (exit {code}); "
                                 f"see {self.server.process.log_path}")
        return self.result()

    def result(self) -> ExchangeResult:
        from opcua_server.audit import audit

        ledger = self.server.ledger()
        summary = self.client.write_summary()
        return ExchangeResult(
            time_s=float(ledger["time_s"]),
            entered={int(k): float(v) for k, v in ledger["entered"].items()},
            left={int(k): float(v) for k, v in ledger["left"].items()},
            held={int(k): float(v) for k, v in summary["held"].items()},
            report=audit(ledger, summary), ledger=ledger, summary=summary)

    def close(self) -> None:
        self.client.stop()
