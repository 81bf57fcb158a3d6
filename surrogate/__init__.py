"""Granular surrogate of the stockpile: DEM (numba), reduced-order model, the
stockpile asset and its OPC UA client process (paper sections "Digital twin
as a distributed particle simulation" and "Integration test")."""
