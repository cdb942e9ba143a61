"""bgn.laws.terms: the formula fitter on known laws."""

from __future__ import annotations

import numpy as np
import pytest
import sympy

from bgn.laws.terms import fit_formula
from tests.laws.conftest import KNOWN, SOFTENING


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("law", sorted(KNOWN))
def test_the_fitter_recovers_known_laws_from_noisy_points(law, seed):
    f, (lo, hi), terms, values = KNOWN[law]
    r = np.geomspace(lo, hi, 200)
    rng = np.random.default_rng(seed)
    y = f(r)
    # 1 % noise relative to the law's size (at the spring's zero crossing: to its slope)
    y = y + 0.01 * np.sqrt(y**2 + (0.1 * r * np.gradient(y, r)) ** 2) * rng.standard_normal(
        len(r))
    formula = fit_formula(r, y, n_boot=20)
    order = sorted(range(len(terms)), key=lambda k: (terms[k].kind, terms[k].power))
    found = sorted(range(len(formula.terms)),
                   key=lambda k: (formula.terms[k].kind, formula.terms[k].power))
    assert [formula.terms[k] for k in found] == [terms[k] for k in order], formula.text
    np.testing.assert_allclose(formula.values, values, rtol=0.05, err_msg=formula.text)
    # the errors the fit states cover its actual error (3 standard errors)
    assert (np.abs(formula.values - values) < 3 * formula.stderr).all(), (
        formula.text, formula.stderr)


def test_the_fit_is_relative_and_weighted():
    """Scaling a law scales its amplitudes only; points of weight 0 do not count."""
    r = np.geomspace(0.05, 5, 120)
    y = 1 / (r + SOFTENING) ** 2 + 0.3 / r
    base = fit_formula(r, y, n_boot=0)
    scaled = fit_formula(r, -1e3 * y, n_boot=0)
    assert scaled.terms == base.terms
    k = len(base.terms)
    np.testing.assert_allclose(scaled.values[:k], -1e3 * base.values[:k], rtol=1e-6)
    np.testing.assert_allclose(scaled.values[k:], base.values[k:], rtol=1e-6)
    inside = r < 1
    alone = fit_formula(r[inside], y[inside], n_boot=0)
    masked = fit_formula(r, np.where(inside, y, 1e4 * np.sin(r)), inside * 1.0, n_boot=0)
    assert masked.terms == alone.terms
    np.testing.assert_allclose(masked.values, alone.values, rtol=1e-4)


def test_the_formula_prints_and_evaluates_as_sympy_reads_it():
    r = np.geomspace(0.05, 5, 100)
    formula = fit_formula(r, 3 / (r**2 + 0.2**2) ** 1.5 - 0.5 * np.log(r), n_boot=0)
    expr = sympy.sympify(formula.text)
    again = sympy.lambdify(sympy.Symbol("r"), expr, "numpy")(r)
    np.testing.assert_allclose(again, formula(r), rtol=1e-3)
    np.testing.assert_allclose(formula(r), 3 / (r**2 + 0.04) ** 1.5 - 0.5 * np.log(r),
                               rtol=1e-6)


def test_bad_points_are_refused_in_one_line():
    with pytest.raises(ValueError, match="8 finite points"):
        fit_formula(np.array([1.0, 2.0]), np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="weights"):
        fit_formula(np.geomspace(1, 2, 20), np.ones(20), weight=-np.ones(20))
