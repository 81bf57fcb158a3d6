"""A seeded FIFO or mixing mine run is bitwise the same on every x86-64 machine.

The digests below were recorded with
``minetwin simulate examples/step_response.toml --until 900 --seed 1 --storage-model M``
and ``_digest`` on an AMD EPYC with AVX-512; the same run with another OpenBLAS kernel
(``OPENBLAS_CORETYPE=Prescott``), numba compiling for another CPU
(``NUMBA_CPU_NAME=generic``), glibc's non-FMA maths
(``GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX2_Usable,-FMA_Usable,-AVX_Usable``) and numpy
without its AVX-512 loops (``NPY_DISABLE_CPU_FEATURES``, also with AVX2's) gives the
same digests, which is what ``cosim.numerics`` is for. (The digests recorded before
held only on CPUs without AVX-512: numpy's exp, log and power round differently there.)
A change to a model changes them on purpose: rerun ``python tests/test_reproducibility.py``
and paste its output.
"""

import hashlib
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from cosim.numerics import ANOTHER_CPU_ENV

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "examples" / "step_response.toml"
MINETWIN = str(Path(sys.executable).with_name("minetwin"))

DIGESTS = {
    "fifo": ("2d8db0d17b20a9b4033bedafb1effc4f3d4e4727245dc7caf66d3f2daeb584f6",
             "2c4d0b85ec7a89c64bf5ad12043e90fe7ff4b4e7c6a8146856dac8c79340adf9"),
    "mixing": ("2d92d4483d201a8ce31fd16f84b2969031328668cf241917d01dda9c6a09e406",
               "18b57a139abe9df9cce2c5559b4eed1ff94660224998f7aef503249839b497f2"),
}
"""(events, time series) SHA-256 digests per storage model."""



def _digest(out: Path) -> tuple[str, str]:
    """SHA-256 of every event-store row in table and row order, and of the time series."""
    events = hashlib.sha256()
    with sqlite3.connect(f"file:{out / 'events.sqlite'}?mode=ro", uri=True) as con:
        tables = [name for (name,) in con.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table' ORDER BY name")]
        for table in tables:
            for row in con.execute(f"SELECT * FROM {table} ORDER BY rowid"):
                events.update(repr(row).encode())
    series = pd.read_parquet(out / "timeseries.parquet")
    rows = pd.util.hash_pandas_object(series, index=True).to_numpy().tobytes()
    columns = "\0".join(series.columns).encode()
    return events.hexdigest(), hashlib.sha256(columns + rows).hexdigest()


def _run(model: str, out: Path, env=None) -> tuple[str, str]:
    subprocess.run([MINETWIN, "simulate", str(SCENARIO), "--until", "900", "--seed", "1",
                    "--storage-model", model, "--out", str(out), "--quiet"],
                   check=True, capture_output=True, env={**os.environ, **(env or {})})
    return _digest(out)


@pytest.mark.parametrize("model", sorted(DIGESTS))
def test_seeded_mine_run_has_the_recorded_digest_on_this_cpu_and_another(model, tmp_path):
    here = _run(model, tmp_path / "here")
    assert here == DIGESTS[model], f"{model}: {here} (rerun this file to re-record)"
    assert _run(model, tmp_path / "other", ANOTHER_CPU_ENV) == here


DEM_RUN = """
import hashlib, numpy as np
from surrogate.dem import Dem
from surrogate.dem.builders import config_for_particles, pour_pile
cfg = config_for_particles(150)
dem = Dem(cfg, seed=4)
pour_pile(dem, 150)
dem.advance(1.0)
print(hashlib.sha256(np.ascontiguousarray(dem.pos).tobytes() + dem.vel.tobytes()).hexdigest())
"""


@pytest.mark.slow
def test_reproducible_mode_makes_a_chaotic_dem_run_the_same_on_another_cpu():
    """MINETWIN_REPRODUCIBLE=1: no fastmath, generic CPU; the DEM's state after 1 s of
    pouring hashes alike here and under another CPU's numerics."""
    env = {**os.environ, "MINETWIN_REPRODUCIBLE": "1"}
    here, elsewhere = (subprocess.run([sys.executable, "-c", DEM_RUN], check=True, text=True,
                                      capture_output=True, env=extra).stdout
                       for extra in (env, {**env, **ANOTHER_CPU_ENV}))
    assert len(here.strip()) == 64 and here == elsewhere


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        for name in sorted(DIGESTS):
            print(f'    "{name}": {_run(name, Path(folder) / name)!r},')
