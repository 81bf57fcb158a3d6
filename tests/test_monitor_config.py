"""The monitor's configuration (capacity and alarm limits): defaults, overrides, refusals."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from cosim.errors import ValidationError
from monitor.config import DEFAULTS, load_monitor_config

MINETWIN = str(Path(sys.executable).with_name("minetwin"))


def test_defaults_and_overrides(tmp_path):
    assert load_monitor_config() == DEFAULTS
    path = tmp_path / "monitor.toml"
    path.write_text("[stockpile]\ncapacity_t = 500\n[alarms]\nlevel_high_pct = 80.5\n")
    config = load_monitor_config(path)
    assert config["stockpile"]["capacity_t"] == 500.0
    assert config["alarms"]["level_high_pct"] == 80.5
    assert config["alarms"]["level_low_pct"] == DEFAULTS["alarms"]["level_low_pct"]


@pytest.mark.parametrize("text, field", [
    ("[stockpile]\ncapacity_t = 0\n", "stockpile.capacity_t"),
    ("[stockpile]\ncapacity_t = 'big'\n", "stockpile.capacity_t"),
    ("[stockpile]\ncapacity_t = nan\n", "stockpile.capacity_t"),
    ("[alarms]\nlevel_high_pct = 101\n", "alarms.level_high_pct"),
    ("[alarms]\nlevel_low_pct = 95\n", "alarms.level_low_pct"),
    ("[alarms]\ngrade_low_pct = 80\ngrade_high_pct = 70\n", "alarms.grade_low_pct"),
    ("[alarms]\nsiren = true\n", "alarms.siren"),
    ("[screen]\nwidth = 3\n", "screen"),
    ("[trends]\nwindow_s = -1\n", "trends.window_s"),
    ("[alarms]\nlevel_deadband_pct = 80\n", "alarms.level_deadband_pct"),  # = 90 - 10
    ("[alarms]\ngrade_deadband_pct = -1\n", "alarms.grade_deadband_pct"),
    ("[alarms]\ncheck_interval_s = 0\n", "alarms.check_interval_s"),
])
def test_bad_values_name_the_key(tmp_path, text, field):
    path = tmp_path / "monitor.toml"
    path.write_text(text)
    with pytest.raises(ValidationError) as refused:
        load_monitor_config(path)
    assert refused.value.field == field


def test_monitor_command_refuses_a_bad_config(tmp_path):
    path = tmp_path / "monitor.toml"
    path.write_text("[alarms]\nlevel_high_pct = 150\n")
    done = subprocess.run([MINETWIN, "monitor", "--stockpile", "http://127.0.0.1:9", "--port", "0",
                           "--config", str(path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "alarms.level_high_pct" in done.stderr and "Traceback" not in done.stderr
