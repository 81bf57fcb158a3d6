"""Reduced-order stockpile model (Wallin and Servin 2021; paper sections
"Digital twin as a distributed particle simulation" and "Integration test"):
fields on a grid (``grid``), POD + ridge model (``model``), design of
experiments on the DEM (``doe``), advection (``advect``), surface layer
(``surface``), the storage asset (``storage``) and accuracy metrics
(``metrics``)."""
