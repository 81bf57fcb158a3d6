"""Security of the mock 800xA server: certificates, trust list, users, roles.

asyncua's defaults are unsafe (anonymous sessions may write, any password is
accepted, a user called ``admin`` becomes Admin). This module replaces them:

* Certificates: a self-signed application certificate and key are generated
  on first start in ``STATE/pki/own/`` (``cert.der``, ``key.pem``); client
  certificates are trusted only if a copy is in ``STATE/pki/trusted/``
  (DER or PEM; read at server start).
* Users: ``STATE/users.toml`` lists ``[users.NAME]`` with ``role`` and
  ``password_hash`` (scrypt, n=2**14, r=8, p=1, 16-byte salt;
  ``scrypt$<salt hex>$<hash hex>``). Passwords are never stored in clear.
* Roles: ``operator`` may write setpoints and belt speeds; ``surrogate``
  may acknowledge inbound records, report outflow, write the stockpile's
  reported values and advance time in lockstep; ``viewer`` may only read,
  browse and subscribe. Nobody gets asyncua's Admin role, so nobody may
  add or delete nodes over the network. Anonymous sessions are refused.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import shutil
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from asyncua import ua
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole

from cosim.errors import ValidationError

ROLES = ("operator", "surrogate", "viewer")

_SCRYPT = {"n": 2**14, "r": 8, "p": 1, "dklen": 32}


def hash_password(password: str, salt: bytes | None = None) -> str:
    """``scrypt$salt$hash`` of ``password`` (hex)."""
    salt = salt if salt is not None else secrets.token_bytes(16)
    digest = hashlib.scrypt(password.encode("utf-8"), salt=salt, **_SCRYPT)
    return f"scrypt${salt.hex()}${digest.hex()}"


def verify_password(password: str, stored: str) -> bool:
    """Constant-time check of ``password`` against a ``hash_password`` string."""
    try:
        scheme, salt_hex, digest_hex = stored.split("$")
    except ValueError:
        return False
    if scheme != "scrypt":
        return False
    digest = hashlib.scrypt(password.encode("utf-8"), salt=bytes.fromhex(salt_hex), **_SCRYPT)
    return hmac.compare_digest(digest.hex(), digest_hex)


def write_users(path: Path, users: dict[str, tuple[str, str]]) -> None:
    """Write ``users.toml`` from ``{name: (role, password)}`` (hashed here), mode 0600."""
    lines = ["# users of the mock 800xA server: role and scrypt password hash\n"]
    for name, (role, password) in users.items():
        if role not in ROLES:
            raise ValidationError("role", f"one of {ROLES}", f"got {role!r} for {name!r}")
        if not name.isidentifier():
            raise ValidationError("user", "a name of letters, digits and _", f"got {name!r}")
        lines.append(f'\n[users.{name}]\nrole = "{role}"\npassword_hash = "{hash_password(password)}"\n')
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text("".join(lines))
    os.chmod(tmp, 0o600)
    os.replace(tmp, path)


def load_users(path: Path) -> dict[str, dict]:
    """``{name: {"role", "password_hash"}}`` from ``users.toml``, validated."""
    import tomllib

    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ValidationError("users", "an existing users.toml", f"{path} not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValidationError("users", "valid TOML", f"{path}: {exc}") from None
    users = data.get("users", {})
    for name, entry in users.items():
        if entry.get("role") not in ROLES:
            raise ValidationError(f"users.{name}.role", f"one of {ROLES}", f"got {entry.get('role')!r}")
        if not str(entry.get("password_hash", "")).startswith("scrypt$"):
            raise ValidationError(f"users.{name}.password_hash", "an scrypt hash (scrypt$salt$hash)")
    return users


def ensure_users(path: Path) -> str | None:
    """Create ``users.toml`` with random passwords if it is missing.

    Returns the path of the file holding the initial passwords (mode 0600)
    when one was created, else ``None``.
    """
    if path.exists():
        return None
    passwords = {role: secrets.token_urlsafe(12) for role in ROLES}
    write_users(path, {role: (role, pw) for role, pw in passwords.items()})
    initial = path.with_name("initial-passwords.txt")
    initial.write_text("".join(f"{name} {pw}\n" for name, pw in passwords.items()))
    os.chmod(initial, 0o600)
    return str(initial)


@dataclass
class PlantUser(User):
    """An authenticated user with a plant role (operator, surrogate, viewer)."""

    plant_role: str = "viewer"


class PlantUserManager:
    """Username/password check against hashed passwords; no anonymous, no admin.

    ``check`` does the scrypt work (the session processor runs it in an
    executor, off the event loop) and leaves its verdict in ``verdicts``;
    asyncua's ``get_user``, called inside the event loop, takes that verdict
    and hashes only when there is none (a password never checked before).
    """

    def __init__(self, users: dict[str, dict]):
        self.users = users
        self.verdicts: dict[tuple, PlantUser | None] = {}

    def check(self, username, password) -> PlantUser | None:
        entry = self.users.get(username or "")
        if entry is None or password is None:
            return None
        if isinstance(password, bytes):
            password = password.decode("utf-8", errors="replace")
        if not verify_password(password, entry["password_hash"]):
            return None
        return PlantUser(role=UserRole.User, name=username, plant_role=entry["role"])

    def get_user(self, iserver, username=None, password=None, certificate=None):
        key = (username, password)
        if key in self.verdicts:
            return self.verdicts.pop(key)
        return self.check(username, password)


_WRITE = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
_CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
_USER_REQUESTS = frozenset(ua.NodeId(t) for t in USER_TYPES)


class PlantPermissions(PermissionRuleset):
    """Which service requests a plant role may make.

    Viewers may not write or call methods at all. For method calls the
    request body is decoded and every method id checked against the role's
    methods; writes are checked node by node in the attribute service
    (``opcua_server.server``), which also validates the values.
    """

    def __init__(self, methods_by_role: dict[str, set]):
        self.methods_by_role = methods_by_role

    def check_validity(self, user, action_type_id, body) -> bool:
        role = getattr(user, "plant_role", None)
        if role is None or action_type_id not in _USER_REQUESTS:
            return False
        if action_type_id == _WRITE:
            return role in ("operator", "surrogate")
        if action_type_id == _CALL:
            allowed = self.methods_by_role.get(role, set())
            from asyncua.ua.ua_binary import struct_from_binary

            try:
                params = struct_from_binary(ua.CallParameters, body.copy())
            except Exception:
                return False
            return all(m.MethodId in allowed for m in params.MethodsToCall)
        return True


# ---------------------------------------------------------------- certificates
def pki_paths(state_dir: Path) -> dict[str, Path]:
    pki = Path(state_dir) / "pki"
    return {"own": pki / "own", "trusted": pki / "trusted",
            "cert": pki / "own" / "cert.der", "key": pki / "own" / "key.pem"}


SERVER_IP_ADDRESSES = ("127.0.0.1",)
"""IP addresses every server certificate's subjectAltName holds (the default endpoint's host)."""


def server_host_names(endpoint_host: str) -> tuple[list, list[str]]:
    """The IP addresses and DNS names a server certificate's subjectAltName must
    hold (OPC UA Part 6, 6.2.2: the names clients reach the host by): 127.0.0.1
    and localhost, the machine's host name, and the endpoint's host (an address
    or a name; not a wildcard bind address such as 0.0.0.0)."""
    import ipaddress
    import socket

    ips = [ipaddress.ip_address(a) for a in SERVER_IP_ADDRESSES]
    names = ["localhost", socket.gethostname()]
    try:
        ip = ipaddress.ip_address(endpoint_host)
    except ValueError:
        names.append(endpoint_host)
    else:
        if not ip.is_unspecified:
            ips.append(ip)
    return list(dict.fromkeys(ips)), list(dict.fromkeys(names))


async def ensure_certificate(key_file: Path, cert_file: Path, app_uri: str, client: bool,
                             endpoint_host: str = "127.0.0.1") -> bool:
    """Generate a self-signed key and certificate if missing; True if generated.

    subjectAltName: the application URI and DNS ``localhost``; a server's also
    holds ``server_host_names(endpoint_host)``. An expired certificate, or a server
    certificate that lacks one of those names (made by an earlier version, or
    before the server moved to another host), is replaced (same key).
    """
    from asyncua.crypto.cert_gen import (dump_private_key_as_pem, generate_private_key,
                                         generate_self_signed_app_certificate)
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding, load_pem_private_key
    from cryptography.x509.oid import ExtendedKeyUsageOID

    ips, dns_names = ([], ["localhost"]) if client else server_host_names(endpoint_host)
    if key_file.exists() and cert_file.exists():
        cert = x509.load_der_x509_certificate(cert_file.read_bytes())
        try:
            names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
            has_names = (set(ips) <= set(names.get_values_for_type(x509.IPAddress))
                         and set(dns_names) <= set(names.get_values_for_type(x509.DNSName)))
        except x509.ExtensionNotFound:
            has_names = False
        expired = cert.not_valid_after_utc <= datetime.now(timezone.utc)
        if has_names and not expired:
            return False
        key = load_pem_private_key(key_file.read_bytes(), password=None)
    else:
        key_file.parent.mkdir(parents=True, exist_ok=True)
        key = generate_private_key()
        key_file.write_bytes(dump_private_key_as_pem(key))
    os.chmod(key_file, 0o600)
    use = [ExtendedKeyUsageOID.CLIENT_AUTH] if client else [ExtendedKeyUsageOID.SERVER_AUTH,
                                                            ExtendedKeyUsageOID.CLIENT_AUTH]
    alt_names = [x509.UniformResourceIdentifier(app_uri)]
    alt_names += [x509.DNSName(name) for name in dns_names] + [x509.IPAddress(ip) for ip in ips]
    cert = generate_self_signed_app_certificate(
        key, app_uri, {"organizationName": "MineTwin", "commonName": app_uri}, alt_names,
        extended=use, days=365)
    cert_file.write_bytes(cert.public_bytes(encoding=Encoding.DER))
    return True


def trust_certificate(state_dir: Path, certificate: Path) -> Path:
    """Copy a client certificate into the server's trust list folder."""
    trusted = pki_paths(state_dir)["trusted"]
    trusted.mkdir(parents=True, exist_ok=True)
    target = trusted / Path(certificate).name
    shutil.copyfile(certificate, target)
    return target
