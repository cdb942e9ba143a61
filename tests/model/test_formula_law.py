"""The formula law (bgn.model.formula_law): the torch twin of bgn.laws.terms' Formula, and the
pair-force head with ``law=formula`` on the true law of spring frames."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from bgn.laws.terms import Formula, Term, default_library
from bgn.model import build_model
from bgn.model.formula_law import FormulaLaw, check_law
from bgn.model.references import FrameOracle
from tests.model.test_newton import frames


def spec_of(terms: list[Term], amplitudes, cs) -> str:
    cs = iter(cs)
    return json.dumps([{"types": [0, 0], "terms": [
        {"kind": t.kind, "power": t.power, "a": float(a),
         "c": float(next(cs)) if t.nonlinear else None} for t, a in zip(terms, amplitudes)]}])


@pytest.mark.parametrize("seed", range(5))
def test_the_formula_law_evaluates_the_fitted_formula(seed):
    """Any three terms of the library with random amplitudes and constants: the module gives
    the Formula's numpy values to float64 precision, down to r = 1e-6."""
    rng = np.random.default_rng(seed)
    library = default_library()
    terms = [library[k] for k in rng.choice(len(library), 3, replace=False)]
    amplitudes = rng.normal(size=3)
    cs = np.exp(rng.uniform(-4, 1, sum(t.nonlinear for t in terms)))
    formula = Formula(terms, np.concatenate([amplitudes, cs]), np.zeros(1), np.zeros(1), 0.0, 1)
    r = np.geomspace(1e-6, 10, 200)
    law = FormulaLaw(spec_of(terms, amplitudes, cs))
    got = law(torch.tensor(r)[:, None])[:, 0].detach().numpy()
    np.testing.assert_allclose(got, formula(r), rtol=1e-12, atol=0)
    # float32 in, float32 out, the float64 values rounded once
    got32 = law(torch.tensor(r, dtype=torch.float32)[:, None])
    assert got32.dtype == torch.float32
    # the spec it writes back is the one it was built from
    again = FormulaLaw(law.spec())(torch.tensor(r)[:, None])[:, 0].detach().numpy()
    np.testing.assert_allclose(again, got, rtol=1e-14)


def test_its_gradients_are_finite_at_small_distances():
    library = default_library()
    spec = spec_of(library, np.ones(len(library)),
                   np.full(sum(t.nonlinear for t in library), 0.01))
    law = FormulaLaw(spec)
    # every term of the library at once (r^-13 included), in float64 distances
    r = torch.tensor([1e-6, 1e-4, 1e-2, 1.0], dtype=torch.float64, requires_grad=True)
    law(r[:, None]).sum().backward()
    grads = [law.amplitude.grad, law.log_c.grad, r.grad]
    assert all(torch.isfinite(g).all() for g in grads), grads
    # float32 distances: the softened terms alone (the plain powers overflow float32 there)
    soft = [t for t in library if t.kind in ("shifted", "plummer", "exp", "log", "const")]
    law = FormulaLaw(spec_of(soft, np.ones(len(soft)),
                             np.full(sum(t.nonlinear for t in soft), 0.01)))
    r = torch.tensor([1e-6, 1e-4, 1e-2, 1.0], requires_grad=True)
    law(r[:, None]).sum().backward()
    grads = [law.amplitude.grad, law.log_c.grad, r.grad]
    assert all(torch.isfinite(g).all() for g in grads), grads
    # constants stay positive whatever their parameter
    with torch.no_grad():
        law.log_c.fill_(-50.0)
    assert json.loads(law.spec())[0]["terms"][-1]["c"] > 0


@pytest.mark.parametrize("bad", ["", "[]", "{", '[{"types": [0, 0], "terms": []}]',
                                 '[{"types": [0, 0], "terms": [{"kind": "sin", "a": 1}]}]',
                                 '[{"types": [0, 0], "terms": [{"kind": "exp", "a": 1}]}]'])
def test_a_bad_spec_is_refused_in_one_line(bad):
    with pytest.raises(ValueError, match="law_formula") as err:
        check_law("formula", bad)
    assert "\n" not in str(err.value)


def test_the_law_option_is_checked():
    with pytest.raises(ValueError, match="law="):
        check_law("spline", "")
    with pytest.raises(ValueError, match="law=formula"):
        check_law("mlp", '[{"types": [0, 0], "terms": [{"kind": "const", "a": 1}]}]')


# the spring's law, f = -2 (s - 1) with s = r + 0.01 (bgn.laws.compare.TRUE_LAWS)
SPRING = json.dumps([{"types": [0, 0], "terms": [{"kind": "const", "power": 0, "a": 1.98},
                                                  {"kind": "power", "power": 1, "a": -2.0}]}])


@pytest.mark.parametrize("bad", [0.0, float("nan"), float("inf")])
def test_a_bad_law_scale_is_refused_in_one_line(bad):
    with pytest.raises(ValueError, match="law_scale") as err:
        check_law("formula", SPRING, bad)
    assert "\n" not in str(err.value)


def test_the_label_gives_the_formula_in_physical_units_and_law_scale_changes_no_prediction(
        small_cfg):
    """The formula stage keeps an inertial-mass head's formula in the network law's scale (k
    times the physical law, k of either sign: the window's mass fit absorbs it) and sets
    law_scale = 1 / k: the model's physics label then prints the physical law; its
    predictions are not law_scale's."""
    ds, g = frames(small_cfg, "spring")
    k = -1.43  # spring's README job: about -1.4
    scaled = json.dumps([{"types": [0, 0], "terms": [{**t, "a": k * t["a"]} for t in
                                                      json.loads(SPRING)[0]["terms"]]}])
    models = []
    for law_scale in (1.0, 1 / k):
        torch.manual_seed(0)
        models.append(build_model({"name": "newton", "mass_law": "inertial", "law": "formula",
                                   "law_formula": scaled, "law_scale": law_scale}, ds.meta,
                                  ds.file.stats(), ds.history).double())
    assert models[1].physics.endswith("the pair law a fitted formula 1.98 + -2*r**1")
    assert models[0].physics.endswith("the pair law a fitted formula -2.831 + 2.86*r**1")
    torch.testing.assert_close(models[0].predict(g), models[1].predict(g), rtol=0, atol=0)


def test_the_label_prints_an_expression_pair(small_cfg):
    """A law the search writes as an expression (no term kinds) is printed in the model's
    physics label with its constants' values, times law_scale."""
    ds, _ = frames(small_cfg, "spring")
    spec = json.dumps([{"types": [0, 0], "expr": "a1*exp(k1*r)/r**2",
                        "constants": {"a1": 1.5, "k1": -0.5}}])
    model = build_model({"name": "newton", "mass_law": "inertial", "law": "formula",
                         "law_formula": spec, "law_scale": 2.0}, ds.meta, ds.file.stats(),
                        ds.history)
    assert model.physics.endswith("the pair law a fitted formula 3.0*exp(-0.5*r)/r**2")


@pytest.mark.parametrize("config", [{"name": "newton"}, {"name": "bgn", "dynamics": "newton"}])
def test_a_head_with_the_true_formula_predicts_the_frame_oracles_targets(small_cfg, config):
    """Same law, same masses, same substeps: the head with law=formula and the FrameOracle
    (the true law and masses) predict the same accelerations of recorded spring frames."""
    ds, g = frames(small_cfg, "spring")  # recorded frames in float64
    model = build_model({**config, "mass_law": "inertial", "law": "formula",
                         "law_formula": SPRING, "substeps": 8}, ds.meta, ds.file.stats(),
                        ds.history).double()
    head = model.head if config["name"] == "newton" else model.force_head
    assert isinstance(head.force_law, FormulaLaw)
    oracle = FrameOracle(ds.scene, ds.history, substeps=8).predict(g)
    known = head(g, known_masses=True)[0]
    assert float(((known - oracle).norm(dim=1) / oracle.norm(dim=1)).max()) < 1e-9
    # the window's own mass fit: the recorded targets within the frame rate's error
    relative = (model.predict(g) - g.target).norm(dim=1) / g.target.norm(dim=1)
    assert float(relative.median()) < 1e-3


def test_a_constant_driven_to_zero_still_writes_a_valid_spec():
    """A fit can drive a shifted term's c below what a double holds (exp(log_c) = 0): the spec
    written back must still parse (the formula stage rebuilds every tuned law from it)."""
    law = FormulaLaw(json.dumps([{"types": [0, 0], "terms": [
        {"kind": "shifted", "power": -1.0, "a": 1.0, "c": 0.5}]}]))
    with torch.no_grad():
        law.log_c.fill_(-1000.0)
    again = FormulaLaw(law.spec())  # refused before: c = 0.0
    r = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)
    torch.testing.assert_close(again.values(r), law.values(r))


# ----------------------------------------------------------------------------- expression pairs

EXPR = {"types": [0, 0], "expr": "a1*exp(k1*r)/Abs(r + k2)**(3/2) + a2*sin(k3*r) + a3*log(r)",
        "constants": {"a1": 1.7, "k1": -0.8, "k2": 0.3, "a2": -0.4, "k3": 2.1, "a3": 0.05}}


def numpy_law(pair: dict, r: np.ndarray) -> np.ndarray:
    import sympy

    rs = sympy.Symbol("r", positive=True)
    expr = sympy.sympify(pair["expr"], locals={"r": rs}).subs(
        {sympy.Symbol(k): v for k, v in pair["constants"].items()})
    return np.asarray(sympy.lambdify(rs, expr, "numpy")(r), np.float64) * np.ones_like(r)


def test_an_expression_pair_gives_numpys_values_and_writes_its_spec_back():
    law = FormulaLaw(json.dumps([EXPR]))
    r = np.geomspace(1e-3, 10, 200)
    got = law(torch.tensor(r)[:, None])[:, 0].detach().numpy()
    np.testing.assert_allclose(got, numpy_law(EXPR, r), rtol=1e-12, atol=0)
    assert law(torch.tensor(r, dtype=torch.float32)[:, None]).dtype == torch.float32
    assert json.loads(law.spec()) == [EXPR]
    # changed constants are written back; the spec rebuilds the same law
    with torch.no_grad():
        law.constant.mul_(1.1)
    spec = json.loads(law.spec())[0]
    assert spec["constants"]["k1"] == pytest.approx(-0.88)
    again = FormulaLaw(law.spec())(torch.tensor(r)[:, None])
    torch.testing.assert_close(again, law(torch.tensor(r)[:, None]), rtol=1e-14, atol=0)


def test_gradients_reach_an_expressions_constants():
    law = FormulaLaw(json.dumps([EXPR]))
    r = torch.logspace(-1, 0.7, 50, dtype=torch.float64)
    law(r[:, None]).sum().backward()
    assert law.constant.grad is not None and torch.isfinite(law.constant.grad).all()
    assert (law.constant.grad != 0).all()


def test_expression_and_term_pairs_mix_per_pair_of_types():
    """Types (0, 0) a term-kind law, (0, 1) an expression: each pair of types feels its own;
    a term-kind law keeps the state a checkpoint holds (no expression parameters)."""
    terms = json.loads(SPRING)[0]
    spec = json.dumps([terms, {**EXPR, "types": [0, 1]}])
    law = FormulaLaw(spec, n_types=2)
    r = torch.tensor([[0.5], [1.0], [2.0]], dtype=torch.float64)
    same = law(r, torch.zeros(3, dtype=torch.long))[:, 0].detach().numpy()
    other = law(r, torch.ones(3, dtype=torch.long))[:, 0].detach().numpy()
    np.testing.assert_allclose(same, 1.98 - 2.0 * r[:, 0].numpy(), rtol=1e-14)
    np.testing.assert_allclose(other, numpy_law(EXPR, r[:, 0].numpy()), rtol=1e-12)
    assert [p.get("expr") for p in json.loads(law.spec())] == [None, EXPR["expr"]]
    assert set(FormulaLaw(SPRING).state_dict()) == {"amplitude", "amplitude_scale", "log_c"}


def test_pair_text_reads_both_kinds():
    from bgn.model.formula_law import pair_text

    assert pair_text(json.loads(SPRING)[0]) == "1.98 + -2*r**1"
    assert pair_text({"types": [0, 0], "expr": "a*r**(-2)", "constants": {"a": -1.5}},
                     scale=2.0) == "-3.0/r**2"


@pytest.mark.parametrize("bad", [
    {"types": [0, 0], "expr": 3, "constants": {}},
    {"types": [0, 0], "expr": "a*r +", "constants": {"a": 1.0}},
    {"types": [0, 0], "expr": "__import__('os').getcwd()", "constants": {}},
    {"types": [0, 0], "expr": "r.conjugate()", "constants": {}},
    {"types": [0, 0], "expr": "a*gamma(r)", "constants": {"a": 1.0}},
    {"types": [0, 0], "expr": "a*r", "constants": {"a": float("nan")}},
    {"types": [0, 0], "expr": "a*r", "constants": {"a": 1.0, "b": 2.0}},
    {"types": [0, 0], "expr": "r*r", "constants": {"r": 1.0}},
    {"types": [0, 0], "expr": "a*r", "constants": [1.0]},
    {"types": [0], "expr": "a*r", "constants": {"a": 1.0}},
    {"types": [0, 0], "expr": "a*r", "constants": {"a": 1.0}, "terms": []},
    {"types": [0, 0], "expr": "Piecewise((a, r < 1), (0, True))", "constants": {"a": 1.0}},
], ids=lambda b: str(b.get("expr"))[:20])
def test_a_bad_expression_pair_is_refused_in_one_line(bad):
    with pytest.raises(ValueError, match="law_formula") as err:
        check_law("formula", json.dumps([bad]))
    assert "\n" not in str(err.value)


def test_scaling_a_law_scales_its_terms_and_its_expressions_amplitudes():
    """``scale_`` puts a law read in a free scale into physical units: terms and expression
    pairs alike (a search member is linear in its a's); an expression that is not is refused,
    unchanged."""
    spec = json.dumps([
        {"types": [0, 0], "terms": [{"kind": "power", "power": -2.0, "a": 1.5, "c": None}]},
        {"types": [0, 1], "expr": "-(a1*k1*r**(-k1 - 1) + a2*exp(-k2*r))",
         "constants": {"a1": 0.7, "k1": 2.0, "a2": -0.2, "k2": 1.3}}])
    law = FormulaLaw(spec, n_types=2)
    r = torch.linspace(0.2, 4.0, 9, dtype=torch.float64)
    pairs = torch.tensor([0, 1] * 4 + [1])
    before = law(r, pairs).detach()
    law.scale_(-3.5)
    assert torch.allclose(law(r, pairs).detach(), -3.5 * before)
    again = FormulaLaw(law.spec(), n_types=2)  # the spec written back carries the scale
    assert torch.allclose(again(r, pairs).detach(), -3.5 * before)
    bad = FormulaLaw(json.dumps([{"types": [0, 0], "expr": "b*exp(-k*r)",
                                  "constants": {"b": 2.0, "k": 1.0}}]))
    with pytest.raises(ValueError, match="not linear in its amplitudes"):
        bad.scale_(2.0)
    assert json.loads(bad.spec())[0]["constants"] == {"b": 2.0, "k": 1.0}
