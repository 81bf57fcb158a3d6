import numpy as np
import pytest
from hypothesis import given, strategies as st
from hypothesis.extra.numpy import arrays

from cosim import sizes
from cosim.errors import ValidationError

fractions = arrays(np.float64, sizes.N_CLASSES,
                   elements=st.floats(0.0, 1.0, allow_nan=False)).filter(
    lambda a: a.sum() > 1e-6).map(lambda a: a / a.sum())


def test_class_diameters_follow_design():
    assert sizes.DIAMETERS[6] == pytest.approx(1e-3)
    assert sizes.DIAMETERS[15] == pytest.approx(1.0)
    assert sizes.DIAMETERS[0] == pytest.approx(1e-5)
    assert sizes.class_of(1e-3) == 6
    assert sizes.class_of(0.25) == 14


def test_retained_is_the_papers_F():
    f = sizes.swebrec()
    F = sizes.retained(f)
    assert F[0] == pytest.approx(1.0)
    assert F[15] == pytest.approx(f[15])
    assert np.allclose(sizes.passing(f)[:-1] + F[1:], 1.0)


@given(fractions, st.floats(0.01, 0.99), st.floats(0.01, 0.99))
def test_d_passing_is_monotone_in_F(f, a, b):
    lo, hi = sorted((a, b))
    assert sizes.d_passing(f, lo) <= sizes.d_passing(f, hi) * (1 + 1e-12)


def test_d_passing_matches_the_swebrec_median():
    f = sizes.swebrec(x50=0.1)
    assert sizes.d_passing(f, 0.5) == pytest.approx(0.1, rel=1e-6)


def test_d_passing_vectorised_equals_rowwise():
    rng = np.random.default_rng(1)
    many = sizes.blasted_fractions(rng, 50)
    assert np.allclose(sizes.d_passing(many, 0.8),
                       [sizes.d_passing(row, 0.8) for row in many])


@given(st.floats(0.01, 0.5), st.floats(0.5, 5.0))
def test_blast_curves_are_distributions(x50, b):
    for f in (sizes.swebrec(x50, 1.0, b), sizes.rosin_rammler(x50, b)):
        assert np.all((f >= 0) & (f <= 1))
        assert f.sum() == pytest.approx(1.0, abs=1e-12)


def test_blasted_fractions_are_seeded():
    a = sizes.blasted_fractions(np.random.default_rng(3), 10)
    b = sizes.blasted_fractions(np.random.default_rng(3), 10)
    assert np.array_equal(a, b)
    assert np.allclose(a.sum(axis=1), 1.0)


@pytest.mark.parametrize("bad, field", [
    (np.full(15, 1 / 15), "f"),
    (np.full(16, 0.1), "f"),
    (np.r_[-0.1, 1.1, np.zeros(14)], "f"),
])
def test_check_fractions_refuses(bad, field):
    with pytest.raises(ValidationError, match=f"^{field}: must be"):
        sizes.check_fractions(bad)
