"""Browse the mock 800xA server's address space and write it as Markdown.

``python -m minetwin.address_space [--out opcua_server/ADDRESS_SPACE.md]``
starts a server (lockstep, default configuration, throw-away state, on
127.0.0.1 and a free port), browses it from ``Objects`` as the ``viewer``
user, as any OPC UA client would, and writes one table row per node: node id,
browse path, node class, type definition, data type, value rank and array
dimensions, access level, engineering units, EURange and description; then
the ``BinDischargedEventType`` fields and the methods' arguments. The test
``tests/test_opcua_address_space.py`` browses a running server the same way
and fails if the file is not what it finds.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
from pathlib import Path

from asyncua import ua

from opcua_protocol import NAMESPACE_URI
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "opcua_server" / "ADDRESS_SPACE.md"
_HIERARCHY = ua.NodeId(ua.ObjectIds.HierarchicalReferences)
_ACCESS = ((1, "read"), (2, "write"), (4, "history"))
"""AccessLevel bits (CurrentRead, CurrentWrite, HistoryRead)."""


async def browse(client) -> dict:
    """``{"nodes": [row, ...], "event_fields": [...], "methods": {...}}`` of our namespace."""
    idx = await client.get_namespace_index(NAMESPACE_URI)
    rows, methods, seen = [], {}, set()

    async def visit(node, path):
        for ref in await node.get_references(_HIERARCHY, ua.BrowseDirection.Forward,
                                             includesubtypes=True):
            child = client.get_node(ref.NodeId)
            if ref.NodeId.NamespaceIndex != idx or ref.NodeId in seen:
                continue  # (SP201 is a component of Plant and also its HasNotifier target)
            seen.add(ref.NodeId)
            name = ref.BrowseName.Name
            row = await _describe(client, child, f"{path}/{name}", ref)
            rows.append(row)
            if row["class"] == "Method":
                methods[row["path"]] = await _arguments(child)
            elif row["class"] == "Object":
                await visit(child, f"{path}/{name}")

    await visit(client.nodes.objects, "Objects")
    event_type = client.get_node(ua.NodeId("BinDischargedEventType", idx))
    fields = []
    for prop in await event_type.get_properties():
        data_type = await prop.read_data_type()
        fields.append({"name": (await prop.read_browse_name()).Name,
                       "data_type": (await client.get_node(data_type).read_browse_name()).Name})
    return {"nodes": rows, "event_fields": fields, "methods": methods}


async def _describe(client, node, path, ref) -> dict:
    node_class = ref.NodeClass.name
    row = {"node_id": node.nodeid.Identifier, "path": path, "class": node_class,
           "type": "", "data_type": "", "rank": "", "access": "", "unit": "", "range": "",
           "description": (await node.read_description()).Text or ""}
    if ref.TypeDefinition and not ref.TypeDefinition.is_null():
        row["type"] = (await client.get_node(ref.TypeDefinition).read_browse_name()).Name
    if node_class != "Variable":
        return row
    row["data_type"] = (await client.get_node(await node.read_data_type()).read_browse_name()).Name
    rank = (await node.read_attribute(ua.AttributeIds.ValueRank)).Value.Value
    if rank == ua.ValueRank.Scalar:
        row["rank"] = "scalar"
    else:
        dims = (await node.read_attribute(ua.AttributeIds.ArrayDimensions)).Value.Value or []
        row["rank"] = f"array [{', '.join(str(d) if d else 'any' for d in dims)}]"
    level = (await node.read_attribute(ua.AttributeIds.AccessLevel)).Value.Value
    row["access"] = ", ".join(name for bit, name in _ACCESS if level & bit)
    for prop in await node.get_properties():
        name = (await prop.read_browse_name()).Name
        value = await prop.read_value()
        if name == "EngineeringUnits":
            row["unit"] = value.DisplayName.Text
        elif name == "EURange":
            row["range"] = f"{value.Low:g} .. {value.High:g}"
    return row


async def _arguments(method) -> dict:
    out = {}
    for prop in await method.get_properties():
        name = (await prop.read_browse_name()).Name
        out[name] = [f"{a.Name}: {_type_name(a.DataType)}{'[]' if a.ValueRank == 1 else ''}"
                     for a in await prop.read_value()]
    return out


def _type_name(node_id: ua.NodeId) -> str:
    for name in ("Double", "UInt64", "Int32", "String", "Boolean"):
        if node_id == ua.NodeId(getattr(ua.ObjectIds, name)):
            return name
    return node_id.to_string()


def render(space: dict) -> str:
    """The Markdown of ``browse``'s result (deterministic: the order of browsing)."""
    lines = [
        "# Address space of the mock 800xA server",
        "",
        "Written by `python -m minetwin.address_space` from a browse of a running server",
        "(default configuration) from `Objects`; `tests/test_opcua_address_space.py` checks it",
        f"against the server. Namespace `{NAMESPACE_URI}`, node ids `ns=<index>;s=<Id>`.",
        "Access is the node's AccessLevel; what a session may do is its UserAccessLevel",
        "(operator: setpoints and belt speeds; surrogate: the reported values; viewer: nothing).",
        "",
        "| Node id | Browse path | Class | Type | Data type | Value rank | Access | Unit | "
        "EURange | Description |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in space["nodes"]:
        lines.append(f"| `{r['node_id']}` | `{r['path']}` | {r['class']} | {r['type']} | "
                     f"{r['data_type']} | {r['rank']} | {r['access']} | {r['unit']} | "
                     f"{r['range']} | {r['description']} |")
    lines += ["", "## Methods", ""]
    for path, args in space["methods"].items():
        inputs = ", ".join(args.get("InputArguments", []))
        outputs = ", ".join(args.get("OutputArguments", []))
        lines.append(f"* `{path}({inputs})` -> `{outputs}`")
    lines += ["", "## Events", "",
              "`BinDischargedEventType` (subtype of BaseEventType), emitted by `Objects/Plant/SP201`:",
              ""]
    lines += [f"* `{f['name']}`: {f['data_type']}" for f in space["event_fields"]]
    return "\n".join(lines) + "\n"


async def browse_server(url: str, state: dict) -> dict:
    from minetwin.harness import connect

    client = await connect(url, state, "viewer")
    try:
        return await browse(client)
    finally:
        await client.disconnect()


def main(argv: list[str] | None = None) -> int:
    from minetwin.harness import ServerProcess, prepare_state

    parser = argparse.ArgumentParser(
        prog="python -m minetwin.address_space",
        description="Start the mock 800xA server, browse it from Objects and write the "
                    "address space as Markdown.")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT,
                        help=f"Markdown file to write (default {DEFAULT_OUT})")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        state = prepare_state(Path(tmp) / "state")
        server = ServerProcess(Path(tmp), state, lockstep=True)
        try:
            text = render(asyncio.run(browse_server(server.url, state)))
        finally:
            server.stop()
    args.out.write_text(text)
    print(f"address space: {text.count(chr(10) + '| `')} nodes written to {args.out}",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
