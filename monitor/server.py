"""The monitor web server: one page, its script and style, and a proxy to the stockpile.

Source: paper section "Integration test": "A monitoring service is created
as a stand-alone web application. It receives virtual sensor information
from the stockpile asset using a REST interface" (``surrogate.rest``).

The monitor is its own process. The page talks only to the monitor (same
origin, nothing from the network): ``/api/ENDPOINT`` is forwarded to
``STOCKPILE/ENDPOINT`` with its query string. When the stockpile cannot be
reached the proxy answers 503 ``{"error": "stockpile unreachable", ...}``
and the page says so; the monitor keeps serving and the page recovers as
soon as the stockpile answers again (the page polls every second).

Parameters (``create_monitor_app``)
-----------------------------------
stockpile_url : str
    Base URL of the stockpile's REST interface, e.g. ``http://127.0.0.1:8081``.
timeout_s : float
    Time [s] the proxy waits for the stockpile before calling it
    unreachable, default 3; for ``/feed`` (a forecast of the pile's flow, the
    slowest answer) ``FEED_TIMEOUT_S``.
config : dict or None
    Capacity and alarm limits (``monitor.config``), served to the page at
    ``/monitor/config``; default ``monitor.config.DEFAULTS``.

Alarms are kept here, not in the page (``monitor.alarms``): every
``alarms.check_interval_s`` the server reads the stockpile's new
``/history`` rows and checks each one. ``GET /monitor/alarms`` serves the
occurrences; ``POST /monitor/alarms/ack`` with ``{"seq": N or "all",
"operator": NAME}`` acknowledges (400 naming the field for a bad request,
404 for an unknown seq, 409 for one already acknowledged). The operator's
name is what the page sends: the monitor has no login, and binds to
127.0.0.1 unless told otherwise.

The page draws its trends with uPlot (MIT licence,
``static/vendor/uPlot.LICENSE``), served from ``/static/vendor/`` like the
page's own files; ``make monitor-vendor`` copies it there from the version
pinned in ``monitor/package.json``.
"""

from __future__ import annotations

import asyncio
import importlib.resources
from urllib.parse import urlsplit

import aiohttp
from aiohttp import web

from cosim.errors import ValidationError
from monitor.alarms import AlarmBook
from monitor.config import load_monitor_config

PROXIED_ENDPOINTS = ("health", "totals", "history", "fields", "particles", "feed",
                     "events", "openapi.json")
"""Stockpile endpoints the page may read through the monitor."""

FEED_TIMEOUT_S = 15.0
"""Time [s] the proxy waits for ``/feed``, the stockpile's slowest answer (the
page reads it apart from the other values, with the same time-out)."""

STATIC_FILES = {"monitor.js": "application/javascript", "monitor.css": "text/css",
                "vendor/uPlot.iife.min.js": "application/javascript",
                "vendor/uPlot.min.css": "text/css",
                "vendor/uPlot.LICENSE": "text/plain"}
"""Files served under ``/static/`` (all the page needs: no external network)."""


def check_stockpile_url(url: str) -> str:
    """The stockpile base URL without a trailing slash; http(s) with a host."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValidationError("stockpile", "an http:// or https:// URL with a host",
                              f"got {url!r}")
    return url.rstrip("/")


def _asset(name: str) -> bytes:
    return importlib.resources.files("monitor").joinpath("static", *name.split("/")).read_bytes()


def create_monitor_app(stockpile_url: str, timeout_s: float = 3.0,
                       config: dict | None = None) -> web.Application:
    """aiohttp application of the monitor for the stockpile at ``stockpile_url``."""
    stockpile_url = check_stockpile_url(stockpile_url)
    config = load_monitor_config() if config is None else config
    app = web.Application()
    pages = {name: _asset(name) for name in ("index.html", *STATIC_FILES)}

    book = AlarmBook(config)

    async def check_alarms(session):
        """Read the stockpile's new history rows and check each; forever."""
        since = -1e12
        while True:
            try:
                async with session.get(f"{stockpile_url}/totals") as response:
                    totals = await response.json()
                if totals["time_s"] < since:  # a new run: check_row sees its clock go back
                    since = -1e12
                async with session.get(f"{stockpile_url}/history",
                                       params={"since": repr(since)}) as response:
                    rows = (await response.json())["rows"]
                for row in rows:
                    book.check_row(row)
                if rows:
                    since = rows[-1]["time_s"]
                book.error = None
            except (aiohttp.ClientError, asyncio.TimeoutError, ValueError, KeyError) as exc:
                # the page shows the stockpile as unreachable; alarms stay as they are
                book.error = f"{type(exc).__name__}: {exc}"
            await asyncio.sleep(config["alarms"]["check_interval_s"])

    async def open_session(app):
        app["session"] = aiohttp.ClientSession(
            timeout=aiohttp.ClientTimeout(total=timeout_s))
        checker = asyncio.create_task(check_alarms(app["session"]))
        yield
        checker.cancel()
        try:
            await checker
        except asyncio.CancelledError:
            pass
        await app["session"].close()

    app.cleanup_ctx.append(open_session)

    async def index(request):
        return web.Response(body=pages["index.html"], content_type="text/html",
                            headers={"Cache-Control": "no-store"})

    async def static(request):
        name = request.match_info["name"]
        if "vendor" in request.match_info:
            name = "vendor/" + name
        if name not in STATIC_FILES:
            raise web.HTTPNotFound()
        return web.Response(body=pages[name], content_type=STATIC_FILES[name],
                            headers={"Cache-Control": "no-store"})

    async def own_health(request):
        return web.json_response({"status": "ok", "stockpile": stockpile_url})

    async def own_config(request):
        return web.json_response(config, headers={"Cache-Control": "no-store"})

    async def alarms(request):
        return web.json_response({**book.summary(), "error": book.error},
                                 headers={"Cache-Control": "no-store"})

    async def acknowledge(request):
        try:
            body = await request.json()
        except ValueError:
            body = None
        if not isinstance(body, dict):
            return web.json_response({"error": "body: must be a JSON object with seq and "
                                      "operator", "field": "body"}, status=400)
        try:
            acknowledged = book.acknowledge(body.get("seq"), body.get("operator"))
        except ValidationError as exc:
            return web.json_response({"error": str(exc), "field": exc.field}, status=400)
        except LookupError as exc:
            return web.json_response({"error": str(exc.args[0]), "field": "seq"}, status=404)
        except ValueError as exc:
            return web.json_response({"error": str(exc), "field": "seq"}, status=409)
        return web.json_response({"acknowledged": acknowledged})

    async def proxy(request):
        endpoint = request.match_info["endpoint"]
        if endpoint not in PROXIED_ENDPOINTS:
            return web.json_response({"error": f"endpoint: must be one of "
                                      f"{list(PROXIED_ENDPOINTS)} (got {endpoint!r})",
                                      "field": "endpoint"}, status=404)
        url = f"{stockpile_url}/{endpoint}"
        wait = aiohttp.ClientTimeout(total=max(FEED_TIMEOUT_S, timeout_s)
                                     if endpoint == "feed" else timeout_s)
        try:
            async with request.app["session"].get(url, params=request.query,
                                                  timeout=wait) as upstream:
                body = await upstream.read()
                return web.Response(body=body, status=upstream.status,
                                    content_type="application/json",
                                    headers={"Cache-Control": "no-store"})
        except (aiohttp.ClientError, asyncio.TimeoutError) as exc:
            return web.json_response(
                {"error": "stockpile unreachable", "stockpile": stockpile_url,
                 "detail": type(exc).__name__}, status=503)

    app.router.add_get("/", index)
    app.router.add_get("/static/{name}", static)
    app.router.add_get("/static/{vendor:vendor}/{name}", static)
    app.router.add_get("/monitor/health", own_health)
    app.router.add_get("/monitor/config", own_config)
    app.router.add_get("/monitor/alarms", alarms)
    app.router.add_post("/monitor/alarms/ack", acknowledge)
    app.router.add_get("/api/{endpoint}", proxy)
    return app


async def serve_monitor(stockpile_url: str, host: str = "127.0.0.1", port: int = 0,
                        config: dict | None = None):
    """Start the monitor in the running loop; returns ``(runner, actual_port)``."""
    runner = web.AppRunner(create_monitor_app(stockpile_url, config=config), access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, host, port)
    await site.start()
    return runner, site._server.sockets[0].getsockname()[1]
