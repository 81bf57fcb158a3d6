"""``minetwin serve-800xa``: the mock 800xA process simulator (OPC UA server)."""

from __future__ import annotations

import sys
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "serve-800xa", help="run the mock 800xA process simulator (OPC UA server)",
        description="Run the mock 800xA process simulator: conveyors CV101/CV301 in bins and the "
                    "stockpile SP201's setpoint, served over OPC UA (Basic256Sha256/Aes "
                    "SignAndEncrypt, users from STATE/users.toml). Stops on SIGINT/SIGTERM.")
    parser.add_argument("--config", type=Path, help="TOML file merged over the defaults "
                        "(opcua_server/config/default.toml)")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="simulation seconds per wall-clock second (default 1: real time)")
    parser.add_argument("--lockstep", action="store_true",
                        help="advance only when the surrogate calls Plant.AdvanceTime")
    parser.add_argument("--insecure", action="store_true",
                        help="ALSO offer the unencrypted None endpoint (local development only)")
    parser.add_argument("--host", help="address to bind (default from config: 127.0.0.1)")
    parser.add_argument("--port", type=int, help="TCP port (default from config: 4840)")
    parser.add_argument("--state-dir", type=Path,
                        help="folder of certificates, trust list and users.toml")
    parser.add_argument("--ledger", type=Path, help="write the exchange ledger JSON here at exit")
    parser.add_argument("--until", type=float, metavar="S",
                        help="freeze the clock at S s of simulation time and write the ledger "
                             "(as SIGUSR1 does), so a run ends at a known plant time")
    parser.add_argument("--ready-file", type=Path,
                        help="write the endpoint URL here once the server listens")
    parser.add_argument("--add-user", metavar="NAME:ROLE",
                        help="add or replace a user (role operator|surrogate|viewer) with the "
                             "password read from stdin, then exit")
    parser.set_defaults(handler=run)


def run(args) -> int:
    import asyncio

    from cosim.errors import ValidationError
    from opcua_server.config import load_config

    overrides: dict = {"server": {}}
    if args.host:
        overrides["server"]["host"] = args.host
    if args.port is not None:
        if not 0 < args.port < 65536:
            raise ValidationError("port", "in [1, 65535]", f"got {args.port}")
        overrides["server"]["port"] = args.port
    if args.state_dir:
        overrides["server"]["state_dir"] = str(args.state_dir)
    config = load_config(args.config, overrides)
    if args.add_user:
        return _add_user(Path(config["server"]["state_dir"]), args.add_user)
    if not (args.speed > 0 and args.speed < 1e6):
        raise ValidationError("speed", "in (0, 1e6)", f"got {args.speed}")
    if args.until is not None and not 0 < args.until < 1e9:
        raise ValidationError("until", "in (0, 1e9) s", f"got {args.until}")
    from opcua_server.server import serve

    return asyncio.run(serve(config, speed=args.speed, insecure=args.insecure,
                             lockstep=args.lockstep, ledger_path=args.ledger,
                             ready_file=args.ready_file, until_s=args.until))


def _add_user(state_dir: Path, spec: str) -> int:
    from cosim.errors import ValidationError
    from opcua_server.security import ROLES, hash_password, load_users

    name, _, role = spec.partition(":")
    if role not in ROLES:
        raise ValidationError("add_user", f"NAME:ROLE with ROLE one of {ROLES}", f"got {spec!r}")
    password = sys.stdin.readline().rstrip("\n")
    if len(password) < 8:
        raise ValidationError("password", "at least 8 characters (read from stdin)")
    path = state_dir / "users.toml"
    users = load_users(path) if path.exists() else {}
    # keep the other users' hashes as they are
    lines = ["# users of the mock 800xA server: role and scrypt password hash\n"]
    for other, entry in users.items():
        if other != name:
            lines.append(f'\n[users.{other}]\nrole = "{entry["role"]}"\n'
                         f'password_hash = "{entry["password_hash"]}"\n')
    if not name.isidentifier():
        raise ValidationError("add_user", "a NAME of letters, digits and _", f"got {name!r}")
    lines.append(f'\n[users.{name}]\nrole = "{role}"\npassword_hash = "{hash_password(password)}"\n')
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(lines))
    path.chmod(0o600)
    print(f"serve-800xa: user {name!r} ({role}) written to {path}", file=sys.stderr)
    return 0
