"""``minetwin stockpile``: the stockpile surrogate as an OPC UA client process."""

from __future__ import annotations

import os
import sys
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "stockpile", help="run the stockpile surrogate against an 800xA (mock) OPC UA server",
        description="Run the stockpile asset as an OPC UA client: receive discharged bins, "
                    "follow the discharge-rate setpoint, report the outflow, serve the REST API "
                    "for the monitor. Resumes from --checkpoint after a restart. The password is "
                    "read from --password-file or the MINETWIN_OPCUA_PASSWORD environment "
                    "variable. Stops on SIGINT/SIGTERM.")
    parser.add_argument("--server", required=True, metavar="URL",
                        help="opc.tcp:// endpoint of the plant server")
    parser.add_argument("--model", default="rom",
                        help="storage model: rom (default: the shipped paper-scale ROM), fifo, "
                             "mixing, dem or any registered name")
    parser.add_argument("--model-option", action="append", default=[], metavar="KEY=VALUE",
                        help="keyword option of the storage model, repeatable (e.g. "
                             "model=out/rom/model.npz for rom)")
    parser.add_argument("--user", default="surrogate", help="OPC UA user (role surrogate)")
    parser.add_argument("--password-file", type=Path, help="file whose first line is the password")
    parser.add_argument("--state-dir", type=Path, default=Path("out/stockpile"),
                        help="folder of the client certificate (pki/own), generated if missing")
    parser.add_argument("--server-cert", type=Path, help="pin the server certificate (DER)")
    parser.add_argument("--insecure", action="store_true",
                        help="connect without encryption (server must run --insecure)")
    parser.add_argument("--checkpoint", type=Path, help="checkpoint file (resume from it)")
    parser.add_argument("--summary", type=Path, help="write the final summary JSON here")
    parser.add_argument("--rest-port", type=int, help="serve the REST API on 127.0.0.1:PORT "
                        "(0: a free port)")
    parser.add_argument("--rest-port-file", type=Path, help="write the REST port here")
    parser.add_argument("--node-map", type=Path, help="node map TOML (default: the mock's layout)")
    parser.add_argument("--lockstep", action="store_true",
                        help="drive the server's clock: AdvanceTime(--period) each cycle")
    parser.add_argument("--period", type=float, default=1.0,
                        help="simulation seconds per lockstep cycle (default 1)")
    parser.add_argument("--cycle", type=float, default=0.1,
                        help="wall seconds between exchange cycles in real time (default 0.1)")
    parser.add_argument("--dt", type=float, default=0.5, help="largest asset step [s] (default 0.5)")
    parser.add_argument("--slice", type=float, default=5.0,
                        help="largest step [s] of a FIFO pile catching up, one per slice of "
                             "bins (default 5)")
    parser.add_argument("--cycle-budget", type=float, default=0.25,
                        help="wall seconds a cycle may spend stepping in real time: a client "
                             "behind catches up over several cycles (default 0.25)")
    parser.add_argument("--duration", type=float, help="stop at this simulation time [s]")
    parser.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    parser.add_argument("--particle-mass", type=float, default=100.0,
                        help="pseudo-particle mass [kg] (default 100)")
    parser.add_argument("--source-name", action="append", default=[], metavar="INDEX=NAME",
                        help="display name of a source (the origin index of its ore), "
                             "repeatable, e.g. '0=left source': the REST interface's "
                             "origin_names, which the monitor shows (default: source INDEX)")
    parser.set_defaults(handler=run)


def run(args) -> int:
    import asyncio
    import signal

    from cosim.errors import ValidationError
    from cosim.storage import storage_class
    from surrogate.client import ClientOptions, StockpileClient

    storage_class(args.model, field="model")
    if not args.server.startswith("opc.tcp://"):
        raise ValidationError("server", "an opc.tcp:// URL", f"got {args.server!r}")
    for name in ("period", "cycle", "dt", "slice", "cycle_budget"):
        value = getattr(args, name)
        if not 0 < value <= 3600:
            raise ValidationError(name, "in (0, 3600] s", f"got {value}")
    storage_options = parse_model_options(args.model_option)
    source_names = parse_source_names(args.source_name)
    if args.password_file:
        if not args.password_file.is_file():
            raise ValidationError("password_file", "an existing file", f"{args.password_file}")
        password = args.password_file.read_text().splitlines()[0]
    else:
        password = os.environ.get("MINETWIN_OPCUA_PASSWORD", "")
    if not password:
        raise ValidationError("password", "given by --password-file or MINETWIN_OPCUA_PASSWORD")

    async def main() -> int:
        cert = key = None
        if not args.insecure:
            from opcua_protocol import APPLICATION_URI_CLIENT
            from opcua_server.security import ensure_certificate, pki_paths

            pki = pki_paths(args.state_dir)
            if await ensure_certificate(pki["key"], pki["cert"], APPLICATION_URI_CLIENT,
                                        client=True):
                print(f"stockpile: generated client certificate {pki['cert']}; copy it into the "
                      f"server's pki/trusted folder", file=sys.stderr)
            cert, key = pki["cert"], pki["key"]
        client = StockpileClient(ClientOptions(
            server_url=args.server, username=args.user, password=password, certificate=cert,
            private_key=key, server_certificate=args.server_cert, insecure=args.insecure,
            model=args.model, storage_options=storage_options, source_names=source_names,
            seed=args.seed,
            particle_mass_kg=args.particle_mass, dt_s=args.dt, slice_s=args.slice,
            cycle_budget_s=args.cycle_budget,
            cycle_s=args.cycle, lockstep=args.lockstep, period_s=args.period,
            duration_s=args.duration, checkpoint=args.checkpoint, summary=args.summary,
            node_map=args.node_map, rest_port=args.rest_port,
            rest_port_file=args.rest_port_file))
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, client.stop)
        print(f"stockpile: model {args.model}, server {args.server}", file=sys.stderr, flush=True)
        return await client.run()

    return asyncio.run(main())


def parse_model_options(items: list[str], field: str = "model_option") -> dict:
    """``KEY=VALUE`` strings -> storage keyword options (numbers where they parse)."""
    from cosim.errors import ValidationError

    options = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            raise ValidationError(field, "KEY=VALUE", f"got {item!r}")
        options[key] = _number_or_text(value)
    return options


def parse_source_names(items: list[str], field: str = "source_name") -> dict[int, str]:
    """``INDEX=NAME`` strings -> ``{index: name}`` (index an integer >= 0, name not empty)."""
    from cosim.errors import ValidationError

    names = {}
    for item in items:
        index, sep, name = item.partition("=")
        if not sep or not index.strip().isdigit() or not name.strip():
            raise ValidationError(field, "INDEX=NAME with INDEX an integer >= 0 and a "
                                  "non-empty NAME", f"got {item!r}")
        names[int(index)] = name.strip()
    return names


def _number_or_text(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text
