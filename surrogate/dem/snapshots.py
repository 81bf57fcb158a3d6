"""Snapshots of the DEM state to compressed files, for ROM training and plots.

A snapshot is ``Dem.snapshot()`` (dict of arrays) written as one compressed
``.npz`` file ``snapshot_NNNNNN.npz`` in a directory; ``SnapshotWriter``
writes one every ``interval`` seconds of simulated time and
``read_snapshots`` reads a directory back in time order.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cosim.errors import ValidationError


def write_snapshot(path, snapshot: dict) -> None:
    """Write one snapshot dict to ``path`` (compressed .npz)."""
    with open(path, "wb") as handle:
        np.savez_compressed(handle, **snapshot)


def read_snapshot(path) -> dict:
    """Read one snapshot file back into a dict of arrays (``time`` as float)."""
    with np.load(path, allow_pickle=False) as data:
        out = {k: data[k].copy() for k in data.files}
    out["time"] = float(out["time"])
    return out


def read_snapshots(directory):
    """Yield the snapshots of ``directory`` in time order."""
    for path in sorted(Path(directory).glob("snapshot_*.npz")):
        yield read_snapshot(path)


class SnapshotWriter:
    """Writes ``dem.snapshot()`` to ``directory`` every ``interval`` [s] of DEM time.

    Call ``maybe_write(dem)`` as often as convenient (e.g. after each
    ``advance``): it writes when the DEM time has reached the next multiple
    of ``interval`` and returns the path written, else ``None``.
    """

    def __init__(self, directory, interval: float):
        interval = float(interval)
        if not math.isfinite(interval) or interval <= 0:
            raise ValidationError("snapshot_interval", "finite and > 0 s", f"got {interval!r}")
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.interval = interval
        self.count = len(list(self.directory.glob("snapshot_*.npz")))
        self.next_time = None

    def maybe_write(self, dem):
        if self.next_time is None:
            self.next_time = dem.time
        if dem.time + 1e-12 < self.next_time:
            return None
        path = self.directory / f"snapshot_{self.count:06d}.npz"
        write_snapshot(path, dem.snapshot())
        self.count += 1
        self.next_time = dem.time + self.interval
        return path
