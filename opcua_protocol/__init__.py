"""What the plant's OPC UA server and the stockpile client agree on.

The mock 800xA process simulator (``opcua_server``) and the stockpile client
(``surrogate.client``) never import each other; they meet here: the
applications' URIs (which the certificates carry and the server checks), the
plant's namespace URI, and the node map through which the client addresses
every node it uses (``nodemap.toml``: logical name -> node id), so that the
same client can be pointed at a real plant server with the same layout.
"""

from __future__ import annotations

from pathlib import Path

from cosim.errors import ValidationError
from cosim.tomlfile import read_toml

APPLICATION_URI_SERVER = "urn:minetwin:mock800xa:server"
APPLICATION_URI_CLIENT = "urn:minetwin:stockpile:client"
NAMESPACE_URI = "urn:minetwin:mock800xa"
"""The plant's namespace (``server.namespace_uri`` of the simulator's default configuration)."""

DEFAULT_NODEMAP = Path(__file__).with_name("nodemap.toml")

REQUIRED_NODES = (
    "simulation_time", "discharge_rate_setpoint", "held_mass", "average_grade", "heartbeat",
    "surrogate_time", "sp201", "inbound_last_sequence", "inbound_acknowledged_sequence",
    "pending_sequence", "pending_tracking_ids", "pending_masses", "pending_grades",
    "pending_hardness", "pending_sources", "pending_times", "acknowledge", "outbound",
    "report_outflow", "outbound_last_sequence", "plant", "advance_time",
    "bin_discharged_event_type",
)
"""Logical names the stockpile client needs in the node map."""


def load_nodemap(path: str | Path | None = None) -> dict[str, str]:
    """Logical name -> node id string (``nsu=URI;s=ID`` or ``ns=N;s=ID``) from the
    TOML file at ``path`` (default: the simulator's layout, ``nodemap.toml``)."""
    data = read_toml(Path(path) if path else DEFAULT_NODEMAP, "node_map")
    nodes = data.get("nodes", {})
    missing = [name for name in REQUIRED_NODES if name not in nodes]
    if missing:
        raise ValidationError("node_map", f"an entry for each of {REQUIRED_NODES}",
                              f"missing {missing}")
    return {name: str(value) for name, value in nodes.items()}
