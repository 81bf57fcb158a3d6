"""Read-only REST interface of a storage asset (the stockpile's virtual sensors).

Source: paper section "Integration test": the monitoring service "receives
virtual sensor information from the stockpile asset using a REST interface":
the total mass in the storage, the average grade, the spatial distributions of
these quantities and the predicted velocity field in the bulk of the pile.
Every average is the paper's eq. (observation), mass-weighted over the
particles of the storage (``cosim.sensors.observe``), without time window.

Two parts:

``StorageView(particles, storage, clock, discharge_rate)``
    serves the *stockpile protocol* for any ``cosim.storage.StorageModel``
    bound to a ``ParticleStore`` (FIFO, mixing, ROM, DEM): ``time``,
    ``discharge_rate``, ``totals()``, ``history(since)``, ``fields(nx, ny)``,
    ``particle_table(limit, offset)``, ``predicted_feed(horizon_s)``,
    ``predicted_feeds(horizons_s)``, ``events(since)``, ``layout`` and
    ``origin_names()``. The owner of the storage calls ``record()`` after each
    step to extend the time series;
    ``record`` also compares the particles held with the previous call's to
    find the lots in and out (``surrogate.lots``) and the actual discharge
    rate (mass that left over the trailing 30 s, ``surrogate.lots.DischargeRate``).
``RestComponent.attach(master, particles, storage, discharge_rate)``
    serves a storage asset of a running co-simulation master (the mine
    simulator), optionally paced to real time.
``create_app(asset)`` / ``start_rest(asset, host, port)``
    the aiohttp application serving any object with that protocol
    (``StorageView`` or the stockpile asset), read-only, on 127.0.0.1 by
    default, with its OpenAPI 3.0 document at ``/openapi.json``.
    ``serve_in_thread`` runs it beside a synchronous simulator.

Units: SI (kg, m, s, kg/s); grade and hardness dimensionless. What is shown
(totals, fields, particles, feed, layout, ``origin`` = source index) is
``cosim.stockpile_view``, the same for the mine simulator's stockpile and the
OPC UA stockpile asset. Bad query parameters get HTTP 400 with
``{"error": "FIELD: must be ...", "field": FIELD}``.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time as wallclock
from collections import deque

import numpy as np
from aiohttp import web

from cosim import stockpile_view as view
from cosim.errors import ValidationError
from cosim.jsonio import plain as to_json
from cosim.master import Component
from surrogate.lots import ACTUAL_RATE_WINDOW_S, DischargeRate, LotLog

TOTALS_KEYS = ("time_s", "held_mass_kg", "grade", "hardness", "d80_m", "particle_count",
               "discharge_rate_kg_s", "discharge_actual_kg_s")
"""Fields of a totals row (``/totals`` and each ``/history`` row)."""

FIELD_NAMES = ("mass", "grade", "hardness", "residence_time", "velocity")
"""Spatial fields ``/fields`` can return (``velocity`` gives ``vx`` and ``vy``)."""

FIELD_PATTERN = "^({0})(,({0}))*$".format("|".join(FIELD_NAMES))
"""What the ``field`` parameter of ``/fields`` accepts."""

MAX_HISTORY_ROWS = 100_000
"""Largest number of rows ``/history`` returns (the latest ones)."""

MAX_GRID = 200
"""Largest grid side (cells) of ``/fields``."""

MAX_PARTICLES_PAGE = 50_000
"""Largest page of ``/particles``."""

MAX_STRIDE = 1000
"""Largest thinning step of ``/particles``."""

MAX_EVENTS_PAGE = 5000
"""Largest number of events ``/events`` returns (the oldest after ``since``)."""

MAX_HORIZON_S = 3600.0
"""Longest feed prediction [s]."""

EXCHANGE_WAIT_S = 0.5
"""Longest time [s] a request waits for the owner's exchange cycle to end."""

FEED_PROFILE_INTERVALS = 30
"""``/feed`` also gives the prediction per interval: horizon / 30 each."""


class StorageView:
    """The stockpile protocol over a storage model bound to a particle store.

    Parameters
    ----------
    particles : cosim.particles.ParticleStore
        The scenario's store.
    storage : cosim.storage.StorageModel
        A bound storage model; its ``owner`` selects the particles held.
    clock : callable () -> float
        Current simulation time [s].
    discharge_rate : callable () -> float
        Current feeder rate [kg/s] (used for ``totals`` and the prediction).
    history_limit : int
        Rows of the time series kept (oldest dropped first), default 100,000.
    display_radius_m : float
        Radius [m] of the schematic pile of a storage without geometry, default 10.
    source_names : dict or None
        Display name per source index (``origin``), default "source N".
    """

    def __init__(self, particles, storage, clock, discharge_rate, history_limit: int = 100_000,
                 display_radius_m: float = 10.0, source_names: dict | None = None):
        self.particles = particles
        self.storage = storage
        self._clock = clock
        self._rate = discharge_rate
        self._history: deque = deque(maxlen=int(history_limit))
        self.display_radius_m = float(display_radius_m)
        self.source_names = {int(k): str(v) for k, v in (source_names or {}).items()}
        self.lots = LotLog()
        self.discharge_actual = 0.0
        self._held = None  # (time, sorted ids, mass, grade, tracking) at the last record
        self._actual = None

    @property
    def time(self) -> float:
        """Simulation time [s]."""
        return float(self._clock())

    @property
    def discharge_rate(self) -> float:
        """Feeder rate [kg/s]."""
        return float(self._rate())

    def _held_slots(self) -> np.ndarray:
        return view.held_slots(self.storage)

    @property
    def layout(self) -> str:
        """``particles`` (the model's own positions) or ``schematic``."""
        return view.layout(self.storage)

    def origin_names(self) -> dict:
        """Display name per origin (source index, ``cosim.stockpile_view``) held."""
        return view.origin_names(self.storage, self.source_names)

    def events(self, since: int = 0) -> list[dict]:
        """Lots in and out with ``seq > since`` (``surrogate.lots``)."""
        return self.lots.since(since)

    def _track_lots(self, time_s: float) -> None:
        """Lots in and out since the last call, and the actual discharge rate:
        the particles held now against those held then. A lot is the
        particles of one tracking id (the ``tracking_id`` attribute), or of
        one step when the store has none."""
        store = self.particles
        slots = self._held_slots()
        order = np.argsort(store.id[slots], kind="stable")
        slots = slots[order]
        tracking = (store.attribute("tracking_id")[slots].astype(np.int64)
                    if "tracking_id" in store.attribute_names else None)
        now = (time_s, store.id[slots], store.mass[slots], store.grade[slots], tracking)
        before, self._held = self._held, now
        if before is None:
            self._actual = DischargeRate(time_s)
            return
        ids0, mass0 = before[1], before[2]
        left = ~np.isin(ids0, now[1], assume_unique=True)
        entered = ~np.isin(now[1], ids0, assume_unique=True)
        self.discharge_actual = self._actual.add(time_s, float(mass0[left].sum()))
        for kind, mask, (_, _, mass, grade, tid) in (("in", entered, now),
                                                     ("out", left, before)):
            if not mask.any():
                continue
            if tid is None:
                keys, inverse = np.array([None]), np.zeros(int(mask.sum()), dtype=np.int64)
            else:
                keys, inverse = np.unique(tid[mask], return_inverse=True)
            lot_mass = np.bincount(inverse, weights=mass[mask], minlength=keys.size)
            lot_grade = np.bincount(inverse, weights=mass[mask] * grade[mask],
                                    minlength=keys.size) / np.maximum(lot_mass, 1e-300)
            self.lots.add(kind, time_s, keys, lot_mass, lot_grade, [None] * keys.size,
                          np.bincount(inverse, minlength=keys.size))

    def totals(self) -> dict:
        """The totals row (``cosim.stockpile_view.totals``)."""
        return view.totals(self.storage, time=self.time, discharge_rate=self.discharge_rate,
                           discharge_actual=self.discharge_actual)

    def record(self) -> dict:
        """Append the current totals to the time series (call after each step)."""
        time_s = self.time
        if self._history and time_s < self._history[-1]["time_s"]:
            self._history.clear()  # the clock went back: a new run
            self._held = None
        self._track_lots(time_s)
        row = self.totals()
        self._history.append(row)
        return row

    def history(self, since: float = -math.inf) -> list[dict]:
        """Totals rows recorded at times > ``since`` [s], oldest first."""
        return [row for row in self._history if row["time_s"] > since]

    def fields(self, nx: int, ny: int) -> dict:
        """Spatial fields on an ny x nx grid (``cosim.stockpile_view.fields``)."""
        return view.fields(self.storage, nx, ny, time=self.time,
                           discharge_rate=self.discharge_rate, radius=self.display_radius_m)

    def particle_table(self, limit: int, offset: int) -> dict:
        """A page of held particles by id (``cosim.stockpile_view.particle_table``)."""
        return view.particle_table(self.storage, limit, offset, time=self.time,
                                   discharge_rate=self.discharge_rate,
                                   radius=self.display_radius_m)

    def predicted_feed(self, horizon_s: float) -> dict:
        """The feed predicted for the next ``horizon_s`` [s] at the current rate
        (``cosim.stockpile_view.predicted_feed``)."""
        return view.predicted_feed(self.storage, horizon_s, self.discharge_rate)

    def predicted_feeds(self, horizons_s) -> list[dict]:
        """``predicted_feed`` for each of ``horizons_s`` [s], from one forecast
        (``cosim.stockpile_view.predicted_feeds``)."""
        return view.predicted_feeds(self.storage, horizons_s, self.discharge_rate)


# ----------------------------------------------------------- query parameters
def _query_number(request, field, default, low, high, *, integer=False, low_open=False):
    """A query parameter as a number in [low, high] (or (low, high]), else a
    ValidationError naming ``field``."""
    raw = request.query.get(field)
    unit = "an integer" if integer else "a finite number"
    allowed = f"{unit} {'>' if low_open else '>='} {low:g} and <= {high:g}"
    if raw is None:
        return default
    try:
        value = int(raw) if integer else float(raw)
    except ValueError:
        raise ValidationError(field, allowed, f"got {raw!r}") from None
    if not math.isfinite(value) or value > high or value < low or (low_open and value == low):
        raise ValidationError(field, allowed, f"got {raw!r}")
    return value


# ------------------------------------------------------------------ the server
def create_app(asset, lock=None, exchange_idle=None) -> web.Application:
    """aiohttp application serving ``asset`` read-only.

    ``asset`` has the stockpile protocol (see ``StorageView``). ``lock`` (a
    ``threading.Lock``) is held while reading the asset when the simulation
    runs in another thread (``serve_in_thread``). ``exchange_idle`` (an
    ``asyncio.Event`` of the same loop, set between the owner's exchange cycles)
    holds each request until it is set, at most ``EXCHANGE_WAIT_S``: a request
    answered inside a cycle would stretch it (the stockpile client's lag).
    """
    middlewares = [_errors_as_json]
    if exchange_idle is not None:
        middlewares.append(_between_cycles(exchange_idle))
    app = web.Application(middlewares=middlewares)

    def read(method, *args):
        if lock is None:
            return method(*args)
        with lock:
            return method(*args)

    async def health(request):
        return web.json_response({"status": "ok", "time_s": to_json(read(lambda: asset.time))})

    async def totals(request):
        return web.json_response(to_json(read(asset.totals)))

    async def history(request):
        since = _query_number(request, "since", -math.inf, -1e12, 1e12)
        limit = _query_number(request, "limit", MAX_HISTORY_ROWS, 1, MAX_HISTORY_ROWS,
                              integer=True)
        rows = read(asset.history, since)[-limit:]
        return web.json_response({"since": to_json(since), "rows": to_json(rows)})

    async def fields(request):
        nx = _query_number(request, "nx", 40, 1, MAX_GRID, integer=True)
        ny = _query_number(request, "ny", 20, 1, MAX_GRID, integer=True)
        wanted = _field_list(request.query.get("field"))
        grid = read(asset.fields, nx, ny)
        out = {"nx": nx, "ny": ny, "time_s": read(lambda: asset.time),
               "layout": read(lambda: asset.layout),
               "x_edges": grid["x_edges"], "y_edges": grid["y_edges"]}
        for name in wanted:
            for key in (("vx", "vy") if name == "velocity" else (name,)):
                out[key] = grid[key]
        return web.json_response(to_json(out))

    async def particles(request):
        limit = _query_number(request, "limit", 5000, 1, MAX_PARTICLES_PAGE, integer=True)
        offset = _query_number(request, "offset", 0, 0, 2**31 - 1, integer=True)
        stride = _query_number(request, "stride", 1, 1, MAX_STRIDE, integer=True)
        table = read(asset.particle_table, limit * stride, offset)
        if stride > 1:  # thinned: every stride-th row of the page
            table = {key: value[::stride] if isinstance(value, np.ndarray) else value
                     for key, value in table.items()}
        names = read(asset.origin_names)
        return web.json_response(to_json({
            "limit": limit, "offset": offset, "stride": stride,
            "time_s": read(lambda: asset.time), "layout": read(lambda: asset.layout),
            "origin_names": [{"origin": value, "name": name} for value, name in names.items()],
            **table}))

    async def events(request):
        since = _query_number(request, "since", 0, 0, 2**53, integer=True)
        limit = _query_number(request, "limit", MAX_EVENTS_PAGE, 1, MAX_EVENTS_PAGE,
                              integer=True)
        rows, last = read(lambda: (asset.events(since), asset.lots.last_seq))
        return web.json_response(to_json({"since": since, "last_seq": last,
                                          "events": rows[:limit]}))

    async def feed(request):
        horizon = _query_number(request, "horizon", 30.0, 0.0, MAX_HORIZON_S, low_open=True)
        summary, profile = read(_feed_with_profile, asset, horizon)
        return web.json_response(to_json({**summary, "horizon_s": horizon,
                                          "profile": profile}))

    async def openapi(request):
        return web.json_response(OPENAPI)

    for path, handler in (("/health", health), ("/totals", totals), ("/history", history),
                          ("/fields", fields), ("/particles", particles), ("/feed", feed),
                          ("/events", events), ("/openapi.json", openapi)):
        app.router.add_get(path, handler)
    return app


def _feed_with_profile(asset, horizon: float) -> tuple[dict, dict]:
    """The asset's predicted feed for ``horizon`` [s], and per interval of
    horizon / FEED_PROFILE_INTERVALS the mass [kg], grade and hardness
    predicted to leave in it, and its mass [kg] from each origin (``origins``: the
    source indices; ``origin_mass_kg``: one row per origin), all differences of the
    cumulative predictions, which are one forecast read at every interval's end."""
    ends = np.linspace(0.0, horizon, FEED_PROFILE_INTERVALS + 1)[1:]
    cumulative = asset.predicted_feeds([float(h) for h in ends])
    by_origin = [feed.pop("mass_by_origin") for feed in cumulative]
    sources = sorted(set().union(*by_origin))
    mass = np.array([feed["mass_kg"] for feed in cumulative])
    interval_mass = np.diff(mass, prepend=0.0)
    profile = {"t_s": ends, "mass_kg": interval_mass}
    for name in ("grade", "hardness"):
        weighted = np.array([feed["mass_kg"] * feed[name] if feed["mass_kg"] > 0 else 0.0
                             for feed in cumulative])
        with np.errstate(invalid="ignore", divide="ignore"):
            profile[name] = np.where(interval_mass > 1e-9 * max(mass[-1], 1.0),
                                     np.diff(weighted, prepend=0.0) / interval_mass, np.nan)
    profile["grade"] = np.clip(profile["grade"], 0.0, 1.0)
    profile["origins"] = sources
    profile["origin_mass_kg"] = [np.diff([masses.get(k, 0.0) for masses in by_origin],
                                         prepend=0.0) for k in sources]
    return cumulative[-1], profile


def _field_list(raw: str | None) -> list[str]:
    if raw is None:
        return list(FIELD_NAMES)
    names = raw.split(",")
    unknown = [name for name in names if name not in FIELD_NAMES]
    if unknown:
        raise ValidationError("field", f"a comma-separated list of {list(FIELD_NAMES)}",
                              f"got {unknown[0]!r}")
    return list(dict.fromkeys(names))


@web.middleware
async def _errors_as_json(request, handler):
    """Errors as JSON: 400 naming the parameter, 404/405 with a message."""
    try:
        return await handler(request)
    except ValidationError as exc:
        return web.json_response({"error": str(exc), "field": exc.field}, status=400)
    except web.HTTPException as exc:
        if exc.status < 400:
            raise
        allow = {"Allow": exc.headers["Allow"]} if "Allow" in exc.headers else None
        return web.json_response({"error": exc.reason, "field": None}, status=exc.status,
                                 headers=allow)


def _between_cycles(exchange_idle: asyncio.Event):
    """Middleware: the handler runs once ``exchange_idle`` is set (a handler reads
    the asset without yielding, so no cycle starts before it has answered), or
    after ``EXCHANGE_WAIT_S`` anyway, so that back-to-back cycles (catching up,
    lockstep) never starve a reader."""
    @web.middleware
    async def after_the_cycle(request, handler):
        loop = asyncio.get_running_loop()
        deadline = loop.time() + EXCHANGE_WAIT_S
        # woken when the cycle ends, a request may find the next already begun
        while not exchange_idle.is_set() and (left := deadline - loop.time()) > 0:
            try:
                await asyncio.wait_for(exchange_idle.wait(), left)
            except TimeoutError:
                break
        return await handler(request)

    return after_the_cycle


async def start_rest(asset, host: str = "127.0.0.1", port: int = 0, lock=None,
                     exchange_idle=None):
    """Serve ``asset`` on ``host:port`` (0: a free port) in the running loop,
    between the owner's exchange cycles if it gives ``exchange_idle``
    (``create_app``).

    Returns ``(runner, actual_port)``; stop with ``await runner.cleanup()``.
    """
    runner = web.AppRunner(create_app(asset, lock, exchange_idle), access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    await site.start()
    actual_port = site._server.sockets[0].getsockname()[1]
    return runner, actual_port


class RestThread:
    """The REST server in a background thread, beside a synchronous simulator.

    The simulator holds ``lock`` while it steps; the server holds it while it
    reads. ``port`` is the bound port; ``stop()`` shuts the server down.
    """

    def __init__(self, asset, host: str = "127.0.0.1", port: int = 0, lock=None):
        self.lock = lock if lock is not None else threading.Lock()
        self._loop = asyncio.new_event_loop()
        started = threading.Event()
        failure: list[BaseException] = []

        def run():
            asyncio.set_event_loop(self._loop)
            try:
                self._runner, self.port = self._loop.run_until_complete(
                    start_rest(asset, host, port, self.lock))
            except BaseException as exc:  # reported to the caller below
                failure.append(exc)
                started.set()
                return
            started.set()
            self._loop.run_forever()
            self._loop.run_until_complete(self._runner.cleanup())
            self._loop.close()

        self._thread = threading.Thread(target=run, name="rest-server", daemon=True)
        self._thread.start()
        started.wait()
        if failure:
            raise failure[0]

    def stop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10)


def serve_in_thread(asset, host: str = "127.0.0.1", port: int = 0, lock=None) -> RestThread:
    """Start the REST server for ``asset`` in a background thread."""
    return RestThread(asset, host, port, lock)


class RestComponent(Component):
    """Serve a storage asset of a running co-simulation (``cosim.master``).

    ``RestComponent.attach(master, ...)`` adds it as the master's last
    component and its ``gate`` as the first: the gate takes ``lock`` at the
    start of every step, this component records the totals row at the end,
    paces the run to ``realtime_factor`` simulated seconds per wall second
    (None: as fast as possible, pausing ``READ_WINDOW_S`` per step) and
    gives the lock back. So the REST thread reads only between steps, a
    consistent state, and freely once the run has returned.

    Parameters
    ----------
    particles, storage : the plant's ParticleStore and the bound storage model
    discharge_rate : callable () -> float
        Current feeder rate [kg/s].
    host, port : where to serve (127.0.0.1, 0: a free port; ``self.port``)
    realtime_factor : float or None
        Simulated seconds per wall second, default None.
    display_radius_m : float
        Schematic pile radius [m] for models without geometry, default 10.
    source_names : dict or None
        Display name per source index (``origin``), default "source N".
    """

    name = "rest"
    READ_WINDOW_S = 0.002
    """Wall time [s] the REST thread gets per step when the run is not paced."""

    def __init__(self, particles, storage, discharge_rate, *, host: str = "127.0.0.1",
                 port: int = 0, realtime_factor: float | None = None,
                 display_radius_m: float = 10.0, source_names: dict | None = None):
        super().__init__()
        if realtime_factor is not None and not realtime_factor > 0:
            raise ValidationError("realtime_factor", "> 0 or None", f"got {realtime_factor!r}")
        self.time = 0.0
        self.realtime_factor = realtime_factor
        self.view = StorageView(particles, storage, lambda: self.time, discharge_rate,
                                display_radius_m=display_radius_m, source_names=source_names)
        self.view.record()
        self.lock = threading.Lock()
        self.gate = _LockGate(self.lock)
        self.server = serve_in_thread(self.view, host, port, self.lock)
        self.port = self.server.port
        self._start = None

    @classmethod
    def attach(cls, master, particles, storage, discharge_rate, **options) -> "RestComponent":
        """Build one, add it last to ``master`` and its gate first; return it."""
        rest = master.add(cls(particles, storage, discharge_rate, **options))
        master.components.insert(0, rest.gate)
        return rest

    def step(self, t: float, dt: float) -> None:
        self.time = t + dt
        self.view.record()
        now = wallclock.monotonic()
        if self._start is None:
            self._start = now - t / self.realtime_factor if self.realtime_factor else now
        pause = (self._start + self.time / self.realtime_factor - now
                 if self.realtime_factor else 0.0)
        if self.lock.locked():
            self.lock.release()
        wallclock.sleep(max(pause, self.READ_WINDOW_S))

    def finish(self) -> None:
        if self.lock.locked():  # a component failed mid-step
            self.lock.release()
        self.server.stop()


def serve_simulation(simulation, *, asset: str = "stockpile", **options) -> RestComponent:
    """Serve the storage asset ``asset`` of a built mine-simulator ``Simulation``.

    ``options`` go to ``RestComponent`` (host, port, realtime_factor,
    display_radius_m). The origins are named after the plant's sources (their
    owner indices, ``cosim.stockpile_view``). Call before the simulation runs.
    """
    from cosim.assets.source import Source

    pile = simulation.assets[asset]
    names = {a.owner: f"source {a.name}" for a in simulation.assets.values()
             if isinstance(a, Source)}
    return RestComponent.attach(simulation.master, simulation.plant.particles, pile.model,
                                lambda: pile.outputs()["discharge_rate_kg_s"],
                                source_names=names, **options)


class _LockGate(Component):
    """First component of the master: takes the REST lock for the step."""

    name = "rest_gate"

    def __init__(self, lock):
        super().__init__()
        self.lock = lock

    def step(self, t: float, dt: float) -> None:
        self.lock.acquire()


# ------------------------------------------------------------ OpenAPI document
_NUM = {"type": "number", "nullable": True}
_NUM_LIST = {"type": "array", "items": _NUM}
_GRID = {"type": "array", "items": _NUM_LIST}
_INT_LIST = {"type": "array", "items": {"type": "integer", "minimum": 0}}
_TOTALS = {
    "type": "object",
    "required": list(TOTALS_KEYS),
    "properties": {
        "time_s": {"type": "number", "description": "simulation time [s]"},
        "held_mass_kg": {"type": "number", "minimum": 0, "description": "mass held [kg]"},
        "grade": {**_NUM, "description": "mass-weighted grade [-]; null when empty"},
        "hardness": {**_NUM, "description": "mass-weighted relative hardness [-]"},
        "d80_m": {**_NUM, "description": "80 % passing size [m]"},
        "particle_count": {"type": "integer", "minimum": 0},
        "discharge_rate_kg_s": {"type": "number", "minimum": 0,
                                "description": "feeder rate setpoint [kg/s]"},
        "discharge_actual_kg_s": {"type": "number", "minimum": 0,
                                  "description": "actual discharge rate [kg/s]: mass that left "
                                                 f"in the trailing {ACTUAL_RATE_WINDOW_S:g} s "
                                                 "over that window (over the run while it is "
                                                 "younger)"},
    },
}
_LAYOUT = {"type": "string", "enum": ["schematic", "particles"],
           "description": "schematic: positions show the order of leaving of a storage "
                          "without geometry (FIFO, mixing); particles: the model's positions"}
_EVENT = {
    "type": "object",
    "required": ["seq", "time_s", "kind", "tracking_id", "mass_kg", "grade", "source",
                 "particle_count"],
    "properties": {
        "seq": {"type": "integer", "minimum": 1, "description": "event number, 1, 2, ..."},
        "time_s": {"type": "number", "description": "simulation time [s]"},
        "kind": {"type": "string", "enum": ["in", "out"],
                 "description": "in: a lot received; out: (part of) a lot discharged"},
        "tracking_id": {"type": "integer", "nullable": True, "minimum": 0},
        "mass_kg": {"type": "number", "minimum": 0, "description": "mass [kg]"},
        "grade": {**_NUM, "description": "mass-weighted grade [-]"},
        "source": {"type": "integer", "nullable": True, "minimum": 0},
        "particle_count": {"type": "integer", "minimum": 0},
    },
}
_ERROR = {
    "description": "bad query parameter",
    "content": {"application/json": {"schema": {
        "type": "object", "required": ["error", "field"],
        "properties": {"error": {"type": "string"},
                       "field": {"type": "string", "nullable": True}}}}},
}


def _param(name, schema, description):
    return {"name": name, "in": "query", "required": False, "schema": schema,
            "description": description}


def _get(summary, schema, parameters=()):
    responses = {"200": {"description": "OK",
                         "content": {"application/json": {"schema": schema}}}}
    if parameters:
        responses["400"] = _ERROR
    return {"get": {"summary": summary, "parameters": list(parameters),
                    "responses": responses}}


OPENAPI = {
    "openapi": "3.0.3",
    "info": {"title": "MineTwin stockpile virtual sensors", "version": "1.0.0",
             "description": "Read-only REST interface of the stockpile asset (paper section "
                            "'Integration test'). SI units."},
    "paths": {
        "/health": _get("liveness and simulation time", {
            "type": "object", "required": ["status", "time_s"],
            "properties": {"status": {"type": "string", "enum": ["ok"]},
                           "time_s": {"type": "number"}}}),
        "/totals": _get("current totals of the stockpile", _TOTALS),
        "/history": _get("totals time series since a time (the latest rows)", {
            "type": "object", "required": ["since", "rows"],
            "properties": {"since": _NUM, "rows": {"type": "array", "items": _TOTALS}}},
            [_param("since", {"type": "number", "minimum": -1e12, "maximum": 1e12},
                    "rows recorded strictly after this time [s]; default all"),
             _param("limit", {"type": "integer", "minimum": 1, "maximum": MAX_HISTORY_ROWS},
                    f"at most this many rows, the latest (default {MAX_HISTORY_ROWS})")]),
        "/fields": _get("spatial fields on a grid over the pile (arrays ny x nx)", {
            "type": "object", "required": ["nx", "ny", "time_s", "x_edges", "y_edges"],
            "properties": {"nx": {"type": "integer"}, "ny": {"type": "integer"},
                           "time_s": {"type": "number"}, "layout": _LAYOUT,
                           "x_edges": _NUM_LIST, "y_edges": _NUM_LIST,
                           "mass": _GRID, "grade": _GRID, "hardness": _GRID,
                           "residence_time": _GRID, "vx": _GRID, "vy": _GRID}},
            [_param("nx", {"type": "integer", "minimum": 1, "maximum": MAX_GRID},
                    "cells along x (default 40)"),
             _param("ny", {"type": "integer", "minimum": 1, "maximum": MAX_GRID},
                    "cells along y (default 20)"),
             _param("field", {"type": "string", "pattern": FIELD_PATTERN},
                    f"comma-separated subset of {', '.join(FIELD_NAMES)} (default all)")]),
        "/particles": _get("a page of the particles held, optionally thinned", {
            "type": "object",
            "required": ["limit", "offset", "total", "id", "tracking_id", "x", "y", "grade",
                         "hardness", "residence_time", "origin"],
            "properties": {"limit": {"type": "integer"}, "offset": {"type": "integer"},
                           "stride": {"type": "integer"},
                           "time_s": {"type": "number"}, "layout": _LAYOUT,
                           "origin_names": {"type": "array", "items": {
                               "type": "object", "required": ["origin", "name"],
                               "properties": {"origin": {"type": "integer", "minimum": -1},
                                              "name": {"type": "string"}}}},
                           "total": {"type": "integer", "minimum": 0},
                           "id": _INT_LIST, "tracking_id": _INT_LIST,
                           "x": _NUM_LIST, "y": _NUM_LIST, "grade": _NUM_LIST,
                           "mass": _NUM_LIST, "hardness": _NUM_LIST,
                           "residence_time": _NUM_LIST,
                           "origin": {"type": "array",
                                      "items": {"type": "integer", "minimum": -1},
                                      "description": "index of the source the particle was "
                                                     "mined at (-1: unknown); names in "
                                                     "origin_names"}}},
            [_param("limit", {"type": "integer", "minimum": 1, "maximum": MAX_PARTICLES_PAGE},
                    "page size (default 5000)"),
             _param("offset", {"type": "integer", "minimum": 0, "maximum": 2**31 - 1},
                    "first row (default 0)"),
             _param("stride", {"type": "integer", "minimum": 1, "maximum": MAX_STRIDE},
                    "thinning: every stride-th row from offset, at most limit rows "
                    "(default 1)")]),
        "/feed": _get("feed predicted for the next horizon seconds", {
            "type": "object",
            "required": ["horizon_s", "mass_kg", "grade", "hardness", "d80_m", "tracking_ids"],
            "properties": {"horizon_s": {"type": "number"},
                           "mass_kg": {"type": "number", "minimum": 0},
                           "grade": _NUM, "hardness": _NUM, "d80_m": _NUM,
                           "particle_count": {"type": "integer", "minimum": 0},
                           "tracking_ids": _INT_LIST,
                           "profile": {"type": "object", "properties": {
                               "t_s": _NUM_LIST, "mass_kg": _NUM_LIST, "grade": _NUM_LIST,
                               "hardness": _NUM_LIST,
                               "origins": {"type": "array", "items": {"type": "integer"},
                                           "description": "source indices (-1: unknown)"},
                               "origin_mass_kg": {"type": "array", "items": _NUM_LIST}}}}},
            [_param("horizon", {"type": "number", "exclusiveMinimum": True, "minimum": 0,
                                "maximum": MAX_HORIZON_S},
                    "prediction horizon [s] (default 30)")]),
        "/events": _get("macro-tracking events: lots in and out with tracking ids", {
            "type": "object", "required": ["since", "last_seq", "events"],
            "properties": {"since": {"type": "integer"},
                           "last_seq": {"type": "integer", "minimum": 0,
                                        "description": "seq of the latest event (0: none)"},
                           "events": {"type": "array", "items": _EVENT}}},
            [_param("since", {"type": "integer", "minimum": 0, "maximum": 2**53},
                    "events with seq strictly greater (default 0: all kept)"),
             _param("limit", {"type": "integer", "minimum": 1, "maximum": MAX_EVENTS_PAGE},
                    f"at most this many events, the oldest (default {MAX_EVENTS_PAGE})")]),
        "/openapi.json": {"get": {"summary": "this document",
                                  "responses": {"200": {"description": "OpenAPI 3.0 document"}}}},
    },
}
"""OpenAPI 3.0 document of the API (served at ``/openapi.json``)."""
