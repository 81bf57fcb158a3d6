"""A third-party package adds an asset kind, an FMU role and an FMU file through the
``minetwin.assets``, ``minetwin.fmu_roles`` and ``minetwin.fmus`` entry points.

tests/plugins/minetwin_example_asset is installed with pip into a folder of its own
(``pip install --target``: a real wheel with its dist-info, nothing added to the
project's environment) and put on PYTHONPATH; ``minetwin simulate`` then finds its
kind by ``importlib.metadata`` entry points, as it finds the built-in ones, and runs a
scenario that puts a surge bin between the crusher's belt and the stockpile, and one
whose crusher steps the FMU the package ships.
"""

import json
import os
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PLUGIN = ROOT / "tests" / "plugins" / "minetwin_example_asset"
MINETWIN = str(Path(sys.executable).with_name("minetwin"))


def _scenario(path: Path) -> Path:
    text = (ROOT / "examples" / "step_response.toml").read_text()
    belt_to_pile = 'from = "conveyor_crusher_stockpile.out"\nto = "stockpile.top"'
    assert belt_to_pile in text
    text = text.replace(belt_to_pile, 'from = "conveyor_crusher_stockpile.out"\n'
                        'to = "surge_bin.feed"\n[[flows]]\nfrom = "surge_bin.out"\n'
                        'to = "stockpile.top"')
    text += ('\n[assets.surge_bin]\nkind = "surge_bin"\nposition_m = [100.0, 0.0, 62.0]\n'
             'residence_s = 20.0\n')
    path.write_text(text)
    return path


def _install_plugin(tmp_path: Path) -> dict:
    """Install the plug-in into a folder of its own; the environment that sees it."""
    site = tmp_path / "site"
    source = shutil.copytree(PLUGIN, tmp_path / "plugin")    # the build writes beside it
    # the package's crusher FMU: a copy of the built cone crusher (package data)
    shutil.copyfile(ROOT / "fmus" / "build" / "cone_crusher.fmu",
                    source / "minetwin_example_asset" / "pebble_crusher.fmu")
    # the plug-in's build backend (setuptools) comes from pip's cache, as for the project
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                    "--target", str(site), str(source)], check=True, capture_output=True,
                   timeout=300)
    assert list(site.glob("minetwin_example_asset-*.dist-info/entry_points.txt"))
    return {**os.environ, "PYTHONPATH": str(site)}


def _simulate(scenario: Path, out: Path, env: dict) -> dict:
    """``minetwin simulate`` 120 s with the plug-in seen; its summary (mass balanced)."""
    result = subprocess.run([MINETWIN, "simulate", str(scenario), "--until", "120",
                             "--out", str(out), "--quiet"], capture_output=True, text=True,
                            env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mass_balance_rel_error"] < 1e-12
    return summary


def test_a_plugin_asset_kind_runs_in_a_scenario(tmp_path):
    scenario = _scenario(tmp_path / "with_surge_bin.toml")
    refused = subprocess.run([MINETWIN, "simulate", str(scenario), "--until", "120",
                              "--out", str(tmp_path / "refused"), "--quiet"],
                             capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2
    assert "assets.surge_bin.kind: must be one of ['belt', 'crusher', 'mill', 'screen', " \
           "'source', 'stockpile', 'truck_fleet']" in refused.stderr

    out = tmp_path / "run"
    summary = _simulate(scenario, out, _install_plugin(tmp_path))
    with sqlite3.connect(out / "events.sqlite") as db:
        times = dict(db.execute(
            "SELECT e.asset, MIN(e.time) FROM events e WHERE e.asset IN ('surge_bin', "
            "'stockpile') AND e.type = 'enter' GROUP BY e.asset").fetchall())
        exits = db.execute("SELECT COUNT(*) FROM events WHERE asset = 'surge_bin' AND "
                           "type = 'exit'").fetchone()[0]
    assert exits > 0
    # every parcel waits its 20 s in the bin (within one 0.5 s step) before the pile
    assert 20.0 <= times["stockpile"] - times["surge_bin"] <= 20.5


def _roles(env=None) -> dict:
    result = subprocess.run([MINETWIN, "fmus", "roles", "--json"], capture_output=True,
                            text=True, env=env, timeout=120)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def test_a_plugin_fmu_role_and_fmu_file_are_found_and_used(tmp_path):
    scenario = tmp_path / "pebble.toml"
    text = (ROOT / "examples" / "step_response.toml").read_text()
    assert 'fmu = "crusher" ' in text
    scenario.write_text(text.replace('fmu = "crusher" ', 'fmu = "pebble_crusher" ', 1))
    counter = str(ROOT / "fmus" / "build" / "test" / "counter.fmu")

    # without the package: its role and its FMU are unknown, and both are refused by name
    assert sorted(_roles()["roles"]) == ["crusher", "mill"]
    refused = subprocess.run([MINETWIN, "simulate", str(scenario), "--until", "60",
                              "--out", str(tmp_path / "refused"), "--quiet"],
                             capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2
    assert "assets.crusher.fmu: must be an existing .fmu file or an FMU name" in refused.stderr
    assert "got 'pebble_crusher'" in refused.stderr
    unknown = subprocess.run([MINETWIN, "fmus", "validate", "--interface", "stair_counter",
                              counter], capture_output=True, text=True, timeout=120)
    assert unknown.returncode == 2 and "--interface: must be one of" in unknown.stderr

    env = _install_plugin(tmp_path)
    listed = _roles(env)
    assert sorted(listed["roles"]) == ["crusher", "mill", "stair_counter"]
    assert [v["name"] for v in listed["roles"]["stair_counter"]] == \
        ["increment", "counter", "elapsed"]
    assert Path(listed["fmus"]["pebble_crusher"]).name == "pebble_crusher.fmu"
    # the package's role checks an FMU: the counter fits it, the mill does not
    fits = subprocess.run([MINETWIN, "fmus", "validate", "--interface", "stair_counter",
                           counter], capture_output=True, text=True, env=env, timeout=120)
    assert fits.returncode == 0, fits.stderr
    misfit = subprocess.run([MINETWIN, "fmus", "validate", "--interface", "stair_counter",
                             str(ROOT / "fmus" / "build" / "mill.fmu")], capture_output=True,
                            text=True, env=env, timeout=120)
    assert misfit.returncode == 1 and "variable 'increment'" in misfit.stderr

    summary = _simulate(scenario, tmp_path / "run", env)
    assert summary["fmus"]["crusher_fmu"].endswith("pebble_crusher.fmu")
