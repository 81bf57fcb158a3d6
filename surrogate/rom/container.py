"""Geometry and bulk properties of the stockpile container the ROM runs in.

The ROM works in the DEM's vertical plane (x horizontal, y up) [m]. These
numbers come from the DEM configuration and the training data and travel in
the model file's header, so a trained model carries the container it knows.

Parameters
----------
x_min, x_max : float
    Side walls [m].
floor : float
    Floor height [m].
outlet_x : float
    Centre of the bottom outlet (feeder) on the floor [m].
outlet_width : float
    Width of the feeder opening [m] (default 0: a point outlet).
feeder_zone_height : float
    Height above the floor of the zone the feeder draws from [m] (default 1).
inlet_x : float
    Horizontal position where incoming material falls onto the pile [m].
areal_density : float
    Mass per unit area of the settled bulk in the plane [kg/m^2] (measured
    from the DEM piles; sets how much a deposited particle raises the surface).
repose_angle : float
    Angle of repose of the bulk [rad] (surface-layer spreading; default 0.6,
    about 34 degrees).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from cosim.errors import ValidationError


@dataclass(frozen=True)
class Container:
    x_min: float
    x_max: float
    floor: float
    outlet_x: float
    inlet_x: float
    areal_density: float
    repose_angle: float = 0.6
    outlet_width: float = 0.0
    feeder_zone_height: float = 1.0

    def __post_init__(self):
        if not self.x_max > self.x_min:
            raise ValidationError("container.x_max", f"> x_min = {self.x_min}", f"got {self.x_max}")
        for name in ("outlet_x", "inlet_x"):
            value = getattr(self, name)
            if not self.x_min <= value <= self.x_max:
                raise ValidationError(f"container.{name}", f"in [{self.x_min}, {self.x_max}] m",
                                      f"got {value}")
        if not self.areal_density > 0:
            raise ValidationError("container.areal_density", "> 0 kg/m^2",
                                  f"got {self.areal_density}")
        if not (self.outlet_width >= 0 and self.feeder_zone_height > 0):
            raise ValidationError("container.outlet_width/feeder_zone_height", ">= 0 and > 0 m",
                                  f"got {self.outlet_width}, {self.feeder_zone_height}")
        if not 0 < self.repose_angle < 1.5:
            raise ValidationError("container.repose_angle", "in (0, 1.5) rad",
                                  f"got {self.repose_angle}")

    def full_cell_mass(self, grid) -> float:
        """Mass [kg] of a full cell of ``grid``: areal_density dx dy."""
        return self.areal_density * grid.dx * grid.dy

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "Container":
        return cls(**{k: float(v) for k, v in data.items()})
