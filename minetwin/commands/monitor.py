"""``minetwin monitor``: the stand-alone monitoring web application."""

from __future__ import annotations


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "monitor", help="serve the stockpile monitor web page",
        description="Serve the monitoring web page for a stockpile's REST interface (paper "
                    "section 'Integration test'): pile coloured by grade, hardness, residence "
                    "time or origin, velocity arrows, totals, time series, the predicted "
                    "feed, and alarms with a dead band that an operator acknowledges (kept "
                    "by this server: GET /monitor/alarms, POST /monitor/alarms/ack). The page reads the stockpile through this server and shows "
                    "'stockpile unreachable' while it is down. Runs until interrupted.")
    parser.add_argument("--stockpile", required=True, metavar="URL",
                        help="base URL of the stockpile REST interface, e.g. "
                             "http://127.0.0.1:8081")
    parser.add_argument("--port", type=int, default=8050, metavar="P",
                        help="port to serve on (8050; 0 picks a free one)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to bind (127.0.0.1)")
    parser.add_argument("--config", metavar="FILE",
                        help="TOML with the stockpile capacity, alarm limits and dead "
                             "bands (see monitor/config.py; default capacity 2000 t, level "
                             "10-90 %% with a 2 %% dead band, grade 25-75 %% with 1 point)")
    parser.set_defaults(handler=run)


def run(args) -> int:
    import asyncio
    import signal
    import sys

    from cosim.errors import ValidationError
    from monitor.config import load_monitor_config
    from monitor.server import check_stockpile_url, serve_monitor

    check_stockpile_url(args.stockpile)
    config = load_monitor_config(args.config)
    if not 0 <= args.port <= 65535:
        raise ValidationError("port", "an integer in [0, 65535]", f"got {args.port}")

    async def serve() -> int:
        try:
            runner, port = await serve_monitor(args.stockpile, args.host, args.port, config)
        except OSError as exc:
            print(f"minetwin monitor: error: cannot serve on {args.host}:{args.port}: {exc}",
                  file=sys.stderr)
            return 1
        print(f"minetwin monitor: serving http://{args.host}:{port}/ "
              f"(stockpile {args.stockpile})", file=sys.stderr, flush=True)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await stop.wait()
        await runner.cleanup()
        return 0

    return asyncio.run(serve())
