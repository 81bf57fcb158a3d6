"""Configuration of the mock 800xA process simulator (TOML).

The default file ``opcua_server/config/default.toml`` documents every key
and its unit. A user's file is merged over the defaults key by key, so it
only needs the keys it changes. Every value is validated at load; a bad one
is a ``ValidationError`` naming the key and its allowed range.
"""

from __future__ import annotations

from pathlib import Path

from cosim.errors import ValidationError, check_finite_range
from cosim.tomlfile import read_toml

DEFAULT_CONFIG = Path(__file__).with_name("config") / "default.toml"


def _merge(base: dict, override: dict) -> dict:
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _read(path: Path, field: str) -> dict:
    return read_toml(path, field)


def _positive(section: dict, name: str, where: str) -> float:
    if name not in section:
        raise ValidationError(f"{where}.{name}", "present", "missing key")
    return float(check_finite_range(f"{where}.{name}", section[name], 0.0, low_open=True))


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> dict:
    """Defaults, merged with the file at ``path`` and then ``overrides``; validated."""
    config = _read(DEFAULT_CONFIG, "config")
    if path is not None:
        config = _merge(config, _read(Path(path), "config"))
    if overrides:
        config = _merge(config, overrides)
    for belt in ("cv101", "cv301"):
        section = config[belt]
        for key in ("length_m", "bin_length_m", "max_belt_speed_m_s"):
            _positive(section, key, belt)
        if section["bin_length_m"] > section["length_m"]:
            raise ValidationError(f"{belt}.bin_length_m", f"<= {belt}.length_m",
                                  f"got {section['bin_length_m']}")
        check_finite_range(f"{belt}.belt_speed_m_s", section["belt_speed_m_s"], 0.0,
                           section["max_belt_speed_m_s"], unit="m/s")
    sp = config["sp201"]
    _positive(sp, "max_discharge_rate_kg_s", "sp201")
    check_finite_range("sp201.discharge_rate_kg_s", sp["discharge_rate_kg_s"], 0.0,
                       sp["max_discharge_rate_kg_s"], unit="kg/s")
    check_finite_range("sp201.discharge_start_s", sp.get("discharge_start_s", 0.0), 0.0,
                       unit="s")
    check_finite_range("sp201.initial_inventory_kg", sp.get("initial_inventory_kg", 0.0), 0.0,
                       5.0e6, unit="kg")
    check_finite_range("sp201.initial_lot_kg", sp.get("initial_lot_kg", 15000.0), 0.0,
                       5.0e6, low_open=True, unit="kg")
    _positive(config["server"], "tick_s", "server")
    lots = config["feed"].get("lots", [])
    if not lots:
        raise ValidationError("feed.lots", "a non-empty list of lots")
    for k, lot in enumerate(lots):
        where = f"feed.lots[{k}]"
        _positive(lot, "duration_s", where)
        _positive(lot, "feed_rate_kg_s", where)
        _positive(lot, "hardness", where)
        check_finite_range(f"{where}.grade", lot.get("grade", float("nan")), 0.0, 1.0)
        if int(lot.get("source", -1)) < 0:
            raise ValidationError(f"{where}.source", "an integer >= 0", f"got {lot.get('source')}")
        if "name" in lot and not (isinstance(lot["name"], str) and lot["name"].strip()):
            raise ValidationError(f"{where}.name", "a non-empty string", f"got {lot['name']!r}")
    source_names(config)  # one name per source
    first = int(config["feed"].get("first_tracking_id", 1))
    if not 0 <= first < 2**63:
        raise ValidationError("feed.first_tracking_id", "in [0, 2**63)", f"got {first}")
    return config



def source_names(config: dict) -> dict[int, str]:
    """Display name of each source that a feed lot names (``feed.lots[k].name``),
    e.g. ``{0: "left source"}``; a source whose lots name it twice differently
    is a ``ValidationError``. The stockpile and the integration test's figures
    show these names instead of the source's index."""
    names: dict[int, str] = {}
    for k, lot in enumerate(config["feed"].get("lots", [])):
        if "name" not in lot:
            continue
        source, name = int(lot["source"]), str(lot["name"]).strip()
        if names.setdefault(source, name) != name:
            raise ValidationError(f"feed.lots[{k}].name", f"{names[source]!r} (the name an "
                                  f"earlier lot gives source {source})", f"got {name!r}")
    return names
