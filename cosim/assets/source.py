"""Ore source: a blasted ore body from which loads are taken.

Source: paper section "Simulator": "At the sources, each particle is
assigned an identity and a location of origin"; the left source has grade
0.2 and the right 0.8; the right source has hardness 1.0 and the left a
hardness function h(x) (constant, step 1 -> 2, or quadratic); after-blast
size distribution of figure "size_distribution"; pseudo-particles of
12-160 kg (about 100 kg). Section "Digital twin as a distributed particle
simulation": the block model of cells i with a priori properties.

Model. The ore body is a row of blocks along the mining direction (local
coordinate x [m], 0 at the initial face). Taking a mass M advances the
loading face by M / (rho * A) [m] (in-situ density rho [kg/m^3], face area
A [m^2]). Each new particle n gets origin x_n at the mass centre of its
slice of the advance, so the hardness h(x_n) follows the ore body exactly;
y and z are drawn uniformly over the face. Grade is the source's grade
c [-]; the size distribution is ``cosim.sizes.blasted_fractions`` (Swebrec
with a log-normally spread median). An "appear" event records the new
particles at the loading point.
"""

from __future__ import annotations

import numpy as np
from pydantic import model_validator

from cosim.assets import Asset, Plant
from cosim.blockmodel import BlockModel
from cosim.errors import ValidationError, check_finite_range
from cosim.kinds import AssetKind
from cosim.master import CosimulationError
from cosim.params import MAX_BLOCKS, MAX_LENGTH_M, Parameters, Position, number, refuse
from cosim.sizes import blasted_fractions


class Source(Asset):
    """A loading point in a blasted ore body (loaded by the trucks whose route names it).

    Parameters
    ----------
    name : str
        Source name ("left", "right").
    plant : Plant
        The shared plant.
    loading_point : (3,) array_like
        World position of the loading point [m] (trucks drive here).
    origin : (3,) array_like
        World position of the ore body's local origin [m] (initial face,
        lower corner); particle origins are ``origin + local``.
    hardness : callable
        h(x) [-] of the local coordinate x [m] (``cosim.blockmodel``).
    grade : float
        Mineral concentration [-] in [0, 1].
    length : float
        Ore body length along the mining direction [m].
    face_width, face_height : float
        Face size [m]; the face area is their product [m^2].
    block_length : float
        Block-model cell length [m].
    density : float
        In-situ density [kg/m^3] (default 2700).
    particle_mass : float
        Mean pseudo-particle mass [kg] (default 100).
    particle_mass_spread : float
        Relative half-width of the uniform particle-mass distribution [-]
        (default 0.5: 50-150 kg).
    blast : dict
        Keyword arguments of ``blasted_fractions`` (x50 [m], x_max [m], b,
        x50_spread).
    """

    inlets = ()
    outlets = ()
    output_names = ("face_m", "hardness_at_face", "mass_taken_kg")

    def __init__(self, name: str, plant: Plant, *, loading_point, origin, hardness,
                 grade: float, length: float, face_width: float, face_height: float,
                 block_length: float = 1.0, density: float = 2700.0,
                 particle_mass: float = 100.0, particle_mass_spread: float = 0.5,
                 blast: dict | None = None):
        super().__init__(name, plant, location=loading_point)
        self.origin = np.asarray(origin, dtype=float).reshape(3)
        self.hardness = hardness
        self.grade = float(check_finite_range(f"{name}.grade", grade, 0.0, 1.0))
        self.face_width = float(face_width)
        self.face_height = float(face_height)
        self.density = float(density)
        self.particle_mass = float(check_finite_range(f"{name}.particle_mass", particle_mass,
                                                      0.0, low_open=True, unit="kg"))
        self.particle_mass_spread = float(check_finite_range(
            f"{name}.particle_mass_spread", particle_mass_spread, 0.0, 0.99))
        self.blast = dict(blast or {})
        self.block_model = BlockModel.along(0.0, length, block_length, width=face_width,
                                            height=face_height, hardness=hardness,
                                            grade=self.grade, density=density)
        self.length = float(length)
        self.face = 0.0
        """Local coordinate of the loading face [m]; advances as mass is taken."""
        self.mass_taken = 0.0
        self._update_outputs()

    def _update_outputs(self) -> None:
        # the signals change only when a load is taken: computed then, not every step
        self._outputs = {"face_m": self.face, "hardness_at_face": float(self.hardness(self.face)),
                         "mass_taken_kg": self.mass_taken}

    @property
    def mass_per_metre(self) -> float:
        """Ore mass per metre of face advance [kg/m]."""
        return self.density * self.face_width * self.face_height

    def take(self, mass: float, t: float) -> np.ndarray:
        """Blast-fragmented particles worth ``mass`` [kg] appear at the face; their ids.

        The particle count is ``round(mass / particle_mass)`` (at least one);
        masses are drawn uniformly within the spread and scaled to sum to
        ``mass`` exactly, so the face advance per load is exact.
        """
        if not (np.isfinite(mass) and mass > 0):
            raise ValidationError(f"{self.name}.take.mass", "finite and > 0 kg", f"got {mass!r}")
        rng = self.plant.rng
        count = max(int(round(mass / self.particle_mass)), 1)
        spread = self.particle_mass_spread
        masses = rng.uniform(1.0 - spread, 1.0 + spread, count)
        masses *= mass / masses.sum()
        advance = masses / self.mass_per_metre
        ends = self.face + np.cumsum(advance)
        if ends[-1] > self.length:
            raise CosimulationError(f"source {self.name}: ore body exhausted at t = {t:g} s "
                                    f"(face at {self.face:.2f} m of {self.length:g} m)")
        local = np.empty((count, 3))
        local[:, 0] = ends - advance / 2.0
        local[:, 1] = rng.uniform(0.0, self.face_width, count)
        local[:, 2] = rng.uniform(0.0, self.face_height, count)
        self.face = float(ends[-1])
        self.mass_taken += float(mass)
        self._update_outputs()
        f = blasted_fractions(rng, count, **self.blast)
        ids = self.particles.add(
            mass=masses, f=f, grade=self.grade, hardness=self.hardness(local[:, 0]),
            position=self.location, origin=self.origin + local,
            origin_block=self.block_model.cell_of(local), owner=self.owner, time=t,
            source=self.owner)
        self.plant.mass_in += float(masses.sum())
        self.plant.particles_created += count
        self.plant.record("appear", self.name, t, self.particles.slots(ids), self.location)
        return ids

    def step(self, t: float, dt: float) -> None:
        """The face does not move by itself: loads are taken by the trucks."""

    def outputs(self) -> dict[str, float]:
        return self._outputs


# ------------------------------------------------------------------ scenario kind


class BlastParameters(Parameters):
    """After-blast size distribution (Swebrec, ``cosim.sizes.blasted_fractions``)."""

    x50_m: number(1e-5, 10.0, low_open=True, unit="m") = 0.1
    x_max_m: number(1e-4, 10.0, unit="m") = 1.0
    b: number(0.0, 20.0, low_open=True) = 2.0
    x50_spread: number(0.0, 2.0) = 0.15

    @model_validator(mode="after")
    def _median_below_largest(self):
        if self.x50_m > self.x_max_m:
            raise refuse("x50_m", f"finite and > 1e-05 and <= {self.x_max_m:g} m",
                         f"got {self.x50_m!r}")
        return self


class SourceParameters(Parameters):
    """``[assets.NAME] kind = "source"``: see ``Source`` for each parameter's meaning."""

    loading_point_m: Position
    ore_body_origin_m: Position | None = None
    """[m]; default: the loading point."""
    grade: number(0.0, 1.0)
    hardness: dict
    """Table ``kind = "constant" | "step" | "quadratic"`` and its parameters
    (``cosim.blockmodel.hardness_function``)."""
    length_m: number(0.0, MAX_LENGTH_M, low_open=True, unit="m")
    face_width_m: number(0.0, MAX_LENGTH_M, low_open=True, unit="m")
    face_height_m: number(0.0, MAX_LENGTH_M, low_open=True, unit="m")
    block_length_m: number(0.0, MAX_LENGTH_M, low_open=True, unit="m") = 1.0
    density_kg_m3: number(100.0, 20000.0, unit="kg/m^3") = 2700.0
    particle_mass_kg: number(0.0, 1e5, low_open=True, unit="kg") = 100.0
    particle_mass_spread: number(0.0, 0.99) = 0.5
    blast: BlastParameters = BlastParameters()

    @model_validator(mode="after")
    def _complete(self):
        if self.ore_body_origin_m is None:
            self.ore_body_origin_m = list(self.loading_point_m)
        smallest_block = self.length_m / MAX_BLOCKS
        if self.block_length_m < smallest_block:
            raise refuse("block_length_m",
                         f">= {smallest_block:g} m (length_m / {MAX_BLOCKS:,} blocks)",
                         f"got {self.block_length_m!r}")
        self.hardness = _checked_hardness(self.hardness)
        return self


def _checked_hardness(spec: dict) -> dict:
    import math

    from cosim.blockmodel import hardness_function

    for key, value in spec.items():
        if key != "kind" and (isinstance(value, bool) or not isinstance(value, (int, float))
                              or not math.isfinite(value)):
            raise refuse(f"hardness.{key}", "a finite number", f"got {value!r}")
    try:
        profile = hardness_function(spec)
    except ValidationError as exc:
        raise refuse(f"hardness.{exc.field.split('.')[-1]}", exc.allowed) from None
    probe = profile(np.linspace(0.0, 1000.0, 101))
    if not np.all(probe > 0):
        raise refuse("hardness", "a profile with hardness > 0 everywhere",
                     f"min {probe.min():g}")
    return dict(spec)


class SourceKind(AssetKind):
    """An ore source (``Source``): loaded by the trucks whose route names it; no ports."""

    Parameters = SourceParameters
    component = Source
    loadable = True

    def location(self, parameters, inlet):
        return list(parameters.loading_point_m)

    def build(self, name, p, context):
        from cosim.blockmodel import hardness_function

        source = Source(
            name, context.plant, loading_point=p.loading_point_m, origin=p.ore_body_origin_m,
            hardness=hardness_function(p.hardness), grade=p.grade, length=p.length_m,
            face_width=p.face_width_m, face_height=p.face_height_m,
            block_length=p.block_length_m, density=p.density_kg_m3,
            particle_mass=p.particle_mass_kg, particle_mass_spread=p.particle_mass_spread,
            blast={"x50": p.blast.x50_m, "x_max": p.blast.x_max_m, "b": p.blast.b,
                   "x50_spread": p.blast.x50_spread})
        context.add(source)
        return [source]
