"""The monitor's configuration: the stockpile's capacity and the alarm limits.

A TOML file (``minetwin monitor --config FILE``) overrides any of the
defaults below; the page reads the result from ``/monitor/config``. The
monitor server raises an alarm when a limit is passed and clears it once
the value is back inside by the dead band (``monitor.alarms``):

```toml
[stockpile]
capacity_t = 2000.0        # storage capacity [t]: fill level = held mass / capacity
[alarms]
level_high_pct = 90.0      # LEVEL HIGH above this fill level [% of capacity]
level_low_pct = 10.0       # LEVEL LOW below this fill level [% of capacity]
level_deadband_pct = 2.0   # a level alarm clears this far back inside [% of capacity]
grade_low_pct = 0.0        # GRADE LOW below this grade of the pile [%] (0: off)
grade_high_pct = 100.0     # GRADE HIGH above this grade of the pile [%] (100: off)
grade_deadband_pct = 0.05  # a grade alarm clears this far back inside [percentage points]
check_interval_s = 1.0     # how often the monitor reads the stockpile for alarms [s, wall]
[trends]
window_s = 0.0             # time range the trends open with [s]; 0: the whole run
```

The default capacity of 2,000 t is the paper's stockpile ("The stockpile
holds up to 2,000 tons", section "Integration test"). The grade alarms are
off by default (0-100 %): a grade band belongs to an ore (a porphyry copper
ore's might be 0.5-1.5 %, as the integration test's feed lots of 0.6 and
1.2 %; the example mine's ore bodies carry 20 and 80 %), so set it for yours.
The level's default dead band is EEMUA 191's starting value (2 %,
``monitor.alarms``); the grade's is 0.05 percentage points; a dead band must be smaller than the distance
between its low and high limits. Bad values raise ``ValidationError`` naming
the key, e.g. ``alarms.level_high_pct``.
"""

from __future__ import annotations

import copy
import math

from cosim.errors import ValidationError
from cosim.tomlfile import read_toml

DEFAULTS = {
    "stockpile": {"capacity_t": 2000.0},
    "alarms": {"level_high_pct": 90.0, "level_low_pct": 10.0, "level_deadband_pct": 2.0,
               "grade_low_pct": 0.0, "grade_high_pct": 100.0, "grade_deadband_pct": 0.05,
               "check_interval_s": 1.0},
    "trends": {"window_s": 0.0},
}
"""Default configuration (units in the key names: t, % and s)."""

_RANGES = {
    ("stockpile", "capacity_t"): (0.0, 1e7, True),
    ("alarms", "level_high_pct"): (0.0, 100.0, False),
    ("alarms", "level_low_pct"): (0.0, 100.0, False),
    ("alarms", "grade_low_pct"): (0.0, 100.0, False),
    ("alarms", "grade_high_pct"): (0.0, 100.0, False),
    ("alarms", "level_deadband_pct"): (0.0, 100.0, False),
    ("alarms", "grade_deadband_pct"): (0.0, 100.0, False),
    ("alarms", "check_interval_s"): (0.0, 60.0, True),
    ("trends", "window_s"): (0.0, 1e7, False),
}
"""(low, high, low is exclusive) of every key."""


def load_monitor_config(path=None) -> dict:
    """The defaults overridden by the TOML file at ``path`` (None: defaults)."""
    config = copy.deepcopy(DEFAULTS)
    if path is None:
        return config
    document = read_toml(path, "config")
    for section, values in document.items():
        if section not in DEFAULTS or not isinstance(values, dict):
            raise ValidationError(section, f"a table among {sorted(DEFAULTS)}",
                                  f"got {section!r} in {path}")
        for key, value in values.items():
            field = f"{section}.{key}"
            if key not in DEFAULTS[section]:
                raise ValidationError(field, f"one of {sorted(DEFAULTS[section])}",
                                      f"unknown key in {path}")
            low, high, low_open = _RANGES[(section, key)]
            allowed = f"a number {'>' if low_open else '>='} {low:g} and <= {high:g}"
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValidationError(field, allowed, f"got {value!r}")
            if not (math.isfinite(value) and value <= high
                    and (value > low if low_open else value >= low)):
                raise ValidationError(field, allowed, f"got {value!r}")
            config[section][key] = float(value)
    alarms = config["alarms"]
    for low_key, high_key, band_key in (
            ("level_low_pct", "level_high_pct", "level_deadband_pct"),
            ("grade_low_pct", "grade_high_pct", "grade_deadband_pct")):
        if not alarms[low_key] < alarms[high_key]:
            raise ValidationError(f"alarms.{low_key}", f"< alarms.{high_key} "
                                  f"({alarms[high_key]:g})", f"got {alarms[low_key]:g}")
        # a wider band would clear a high alarm only below the low limit
        span = alarms[high_key] - alarms[low_key]
        if not alarms[band_key] < span:
            raise ValidationError(f"alarms.{band_key}", f"< alarms.{high_key} - "
                                  f"alarms.{low_key} ({span:g})", f"got {alarms[band_key]:g}")
    return config
