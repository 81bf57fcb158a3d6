"""Automated co-simulation tests for MineTwin users.

``minetwin.testing.plugin`` is a pytest plugin (installed with the package as
the ``pytest11`` entry point ``minetwin``) with fixtures that run scenarios,
load and validate FMUs and start a lockstep OPC UA integration. The
assertions and the reference machinery are importable from here::

    from minetwin.testing import assert_mass_balance, assert_ids_accounted
"""

from minetwin.testing.assertions import (
    assert_ids_accounted, assert_mass_balance, assert_matches_reference,
    assert_signal_within_band, assert_step_response, measure_step_response, signal_from)
from minetwin.testing.bands import Tolerance, compare_signal
from minetwin.testing.reference import ReferenceResult, ReferenceSpec, compare

__all__ = [
    "assert_ids_accounted", "assert_mass_balance", "assert_matches_reference",
    "assert_signal_within_band", "assert_step_response", "measure_step_response",
    "signal_from", "Tolerance", "compare_signal", "ReferenceResult", "ReferenceSpec", "compare",
]
