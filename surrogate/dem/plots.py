"""PNG pictures of a DEM pile coloured by grade, residence time and speed."""

from __future__ import annotations

from pathlib import Path

import numpy as np

PICTURES = {
    "grade": ("grade", 100.0, "grade [%]", "viridis"),
    "residence_time": ("residence_time", 1.0, "residence time [s]", "magma"),
    "speed": (None, 1.0, "speed [m/s]", "plasma"),
}
"""File stem -> (snapshot key or None for |velocity|, factor from the snapshot's SI
value to the one shown (grade: fraction to %), colour-bar label, colour map)."""


def pile_pictures(snapshot: dict, out_dir, run: str | None = None) -> list[Path]:
    """Write ``pile_<stem>.png`` for each entry of ``PICTURES``; return the paths.

    ``run`` names the run in the titles (``cosim.plotstyle.run_label``)."""
    from matplotlib.collections import EllipseCollection

    from cosim import plotstyle

    plt = plotstyle.pyplot()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    pos = snapshot["position"]
    diameter = 2.0 * snapshot["radius"]
    paths = []
    for stem, (key, factor, label, cmap) in PICTURES.items():
        values = factor * (np.hypot(snapshot["velocity"][:, 0], snapshot["velocity"][:, 1])
                           if key is None else np.asarray(snapshot[key], dtype=float))
        fig, ax = plt.subplots(figsize=(12, 5))
        if pos.shape[0]:
            disks = EllipseCollection(diameter, diameter, 0.0, units="x", offsets=pos,
                                      offset_transform=ax.transData, cmap=cmap,
                                      linewidths=0)
            disks.set_array(np.asarray(values, dtype=float))
            ax.add_collection(disks)
            fig.colorbar(disks, ax=ax, label=label, shrink=0.8)
            pad = float(diameter.max())
            ax.set_xlim(pos[:, 0].min() - pad, pos[:, 0].max() + pad)
            ax.set_ylim(0.0, pos[:, 1].max() + pad)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.grid(False)
        plotstyle.title(fig, f"DEM pile at t = {float(snapshot['time']):.1f} s: "
                        f"{pos.shape[0]} particles coloured by {label}", run)
        paths.append(plotstyle.save(fig, out_dir / f"pile_{stem}.png", bbox_inches="tight"))
    return paths
