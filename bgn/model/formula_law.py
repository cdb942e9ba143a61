"""A pair law given as a formula: the torch twin of ``bgn.laws.terms``' fitted ``Formula``.

``FormulaLaw(spec)`` evaluates ``f(r) = sum_k a_k term_k(r; c_k)`` at physical distances r with
the term kinds of ``bgn.laws.terms.default_library`` (``const``, ``power`` r^p, ``log`` log r,
``exp`` exp(-r/c), ``shifted`` (r + c)^p, ``plummer`` (r^2 + c^2)^(p/2)). The amplitudes
``a_k`` and the constants ``c_k`` are parameters (``c = exp(log_c)``: positive whatever an
optimiser does); the powers are the formula's form and stay fixed. It is evaluated in float64
(a power of a tiny r, or ``(r + c)^p`` near r = 0, loses every digit in float32) and returned
in the input's dtype.

The spec (``bgn.laws.finetune.formula_spec`` writes it; a plain JSON string so that a checkpoint's
hyper-parameters stay ``weights_only``-loadable and Hydra-typed) is a list of pairs of particle
types, each ``{"types": [a, b], "terms": [{"kind", "power", "a", "c"}, ...]}`` (``c`` null for
a term without one), or a general expression ``{"types": [a, b], "expr": "<sympy text in r and
the constants>", "constants": {"k1": ..., ...}}`` (``bgn.laws.search.expression_spec`` writes
one from the law search): the expression is evaluated in torch float64 through
``sympy.lambdify`` (``EXPRESSION_FUNCTIONS``), each constant a parameter relative to its spec
value (of either sign: a general tree has no positive-only constant). A pair of types the spec
does not name feels no force.
"""

from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Callable
from typing import Any

import sympy
import torch
from torch import nn

KINDS = ("const", "power", "log", "exp", "shifted", "plummer")
NONLINEAR = ("exp", "shifted", "plummer")
# the functions an expression pair may use, and their torch twins (powers, sums, products and
# quotients are Python's operators); pi and E are numbers
EXPRESSION_FUNCTIONS: dict[str, Callable[..., Any]] = {
    "exp": torch.exp, "log": torch.log, "sqrt": torch.sqrt, "sin": torch.sin, "cos": torch.cos,
    "tanh": torch.tanh, "Abs": torch.abs}
_NUMBERS = {"pi": math.pi, "E": math.e}
_R = sympy.Symbol("r", positive=True)


def parse_expression(expr: Any, constants: Any) -> sympy.Expr:
    """An expression pair's ``expr`` (text in r and the names of ``constants``) as sympy,
    refused in one line where it is not one: other characters or names than numbers,
    ``+ - * / ** ( )``, r, the constants, ``EXPRESSION_FUNCTIONS`` and pi, E (the text is
    checked before sympy reads it), a constant not a finite number or not in the expression."""
    if not isinstance(expr, str) or not expr.strip():
        raise ValueError(f"model.law_formula: an expression pair's 'expr' must be a non-empty "
                         f"string, got {expr!r}")
    if not isinstance(constants, dict):
        raise ValueError(f"model.law_formula: an expression pair's 'constants' must be a "
                         f"mapping of names to numbers, got {constants!r}")
    for name, value in constants.items():
        if (not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", str(name)) or name in ("r", *_NUMBERS)
                or name in EXPRESSION_FUNCTIONS):
            raise ValueError(f"model.law_formula: constant name {name!r} must be an identifier "
                             "other than r, pi, E and the functions")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(
                value):
            raise ValueError(f"model.law_formula: constant {name} = {value!r} must be a "
                             "finite number")
    if re.search(r"[^\w\s.+\-*/()]|\.\s*[A-Za-z_]|__", expr):
        raise ValueError(f"model.law_formula: expression {expr!r} may hold only numbers, names, "
                         "+ - * / ** and parentheses")
    allowed = {"r", *constants, *EXPRESSION_FUNCTIONS, *_NUMBERS}
    for name in re.findall(r"(?<![\w.])[A-Za-z_][A-Za-z0-9_]*", expr):
        if name not in allowed:
            raise ValueError(f"model.law_formula: expression {expr!r} names {name!r}: use r, "
                             f"the constants {sorted(constants)}, "
                             f"{sorted(EXPRESSION_FUNCTIONS)}, pi and E")
    local = {"r": _R, **{n: sympy.Symbol(n, real=True) for n in constants}}
    try:
        parsed = sympy.sympify(expr, locals=local)
    except (sympy.SympifyError, SyntaxError, TypeError, ValueError, AttributeError) as err:
        raise ValueError(f"model.law_formula: expression {expr!r} does not parse "
                         f"({type(err).__name__})") from None
    if not isinstance(parsed, sympy.Expr):
        raise ValueError(f"model.law_formula: expression {expr!r} is not a formula")
    unused = sorted(set(constants) - {str(s) for s in parsed.free_symbols})
    if unused:
        raise ValueError(f"model.law_formula: constant {unused[0]!r} is not in the expression "
                         f"{expr!r}")
    return parsed


def parse_spec(spec: str | list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The spec's pairs, each checked; a malformed spec is refused in one line."""
    try:
        pairs = json.loads(spec) if isinstance(spec, str) else spec
    except json.JSONDecodeError as err:
        raise ValueError(f"model.law_formula is not JSON ({err}): write it with "
                         "bgn.laws.finetune.formula_spec") from None
    if not isinstance(pairs, list) or not pairs:
        raise ValueError("model.law_formula must be a non-empty JSON list of pairs "
                         "{types, terms} (bgn.laws.finetune.formula_spec)")
    for p in pairs:
        if isinstance(p, dict) and "expr" in p:
            types = p.get("types")
            if (not isinstance(types, list) or len(types) != 2 or "terms" in p
                    or not all(isinstance(t, int) and t >= 0 for t in types)):
                raise ValueError(f"model.law_formula: expression pair {p!r} needs 'types' "
                                 "[a, b] (types >= 0), 'expr' and 'constants', no 'terms'")
            parse_expression(p["expr"], p.get("constants", {}))
            continue
        terms = p.get("terms") if isinstance(p, dict) else None
        if not isinstance(terms, list) or not terms or len(p.get("types", ())) != 2:
            raise ValueError(f"model.law_formula: pair {p!r} needs 'types' [a, b] and a "
                             "non-empty list of 'terms' (or 'expr' and 'constants')")
        for t in terms:
            if t.get("kind") not in KINDS:
                raise ValueError(f"model.law_formula: term kind {t.get('kind')!r}; choose "
                                 f"one of {KINDS}")
            if t["kind"] in NONLINEAR and not (t.get("c") or 0) > 0:
                raise ValueError(f"model.law_formula: the {t['kind']} term needs a constant "
                                 f"c > 0, got {t.get('c')!r}")
    return pairs


class FormulaLaw(nn.Module):
    """``f(r)`` of a spec (see the module doc) at physical distances, per pair of types."""

    def __init__(self, spec: str | list[dict[str, Any]], n_types: int = 1) -> None:
        super().__init__()
        pairs = parse_spec(spec)
        self.n_types = n_types
        self.pairs = pairs  # the spec's order: spec() writes the pairs back in it
        flat = [(sorted(p["types"]), t) for p in pairs if "expr" not in p for t in p["terms"]]
        self.kinds = [t["kind"] for _, t in flat]
        self.powers = [float(t.get("power", 0.0)) for _, t in flat]
        self.pair_ids = [a * n_types + b for (a, b), _ in flat]
        # amplitudes relative to the spec's (1 at the start): an optimiser's step is then a
        # relative change whatever the law's units, as log_c's is for the constants
        a = torch.tensor([float(t["a"]) for _, t in flat], dtype=torch.float64)
        self.register_buffer("amplitude_scale", torch.where(a != 0, a.abs(), torch.ones_like(a)))
        self.amplitude = nn.Parameter(a / self.amplitude_scale)
        self.log_c = nn.Parameter(torch.tensor(
            [math.log(float(t["c"])) if t["kind"] in NONLINEAR else 0.0 for _, t in flat],
            dtype=torch.float64))
        # expression pairs: one column each, after the terms'; their constants, relative to
        # the spec's values as the amplitudes are, of either sign
        exprs = [p for p in pairs if "expr" in p]
        self.expressions = [p["expr"] for p in exprs]
        self.expression_names = [list(p.get("constants", {})) for p in exprs]
        self.pair_ids += [min(p["types"]) * n_types + max(p["types"]) for p in exprs]
        self._functions = [
            sympy.lambdify([_R, *(sympy.Symbol(n, real=True) for n in names)],
                           parse_expression(p["expr"], p.get("constants", {})),
                           modules=[{**EXPRESSION_FUNCTIONS, **_NUMBERS}])
            for p, names in zip(exprs, self.expression_names)]
        if exprs:  # registered only then: a term-kind law's state is what checkpoints hold
            k = torch.tensor([float(v) for p in exprs for v in p.get("constants", {}).values()],
                             dtype=torch.float64)
            self.register_buffer("constant_scale",
                                 torch.where(k != 0, k.abs(), torch.ones_like(k)))
            self.constant = nn.Parameter(k / self.constant_scale)

    def values(self, r: torch.Tensor) -> torch.Tensor:
        """(..., K) each term times its amplitude at r (...), then each expression pair's law,
        in float64."""
        r = r.double()
        terms = self._term_values(r) if self.kinds else r.new_zeros(*r.shape, 0)
        if not self.expressions:
            return terms
        constants = self.constants()
        cols, i = [], 0
        for fn, names in zip(self._functions, self.expression_names):
            value = fn(r, *constants[i:i + len(names)])
            cols.append(torch.as_tensor(value, dtype=torch.float64,
                                        device=r.device).expand_as(r))
            i += len(names)
        return torch.cat([terms, torch.stack(cols, -1)], -1)

    def constants(self) -> torch.Tensor:
        """(C,) the expression pairs' constants in the spec's order, float64."""
        if not self.expressions:
            return self.log_c.new_zeros(0)
        return self.constant.double() * self.constant_scale.double()

    def _term_values(self, r: torch.Tensor) -> torch.Tensor:
        c = self.log_c.double().exp()
        cols = []
        for k, (kind, p) in enumerate(zip(self.kinds, self.powers)):
            if kind == "const":
                cols.append(torch.ones_like(r))
            elif kind == "power":
                cols.append(r**p)
            elif kind == "log":
                cols.append(torch.log(r))
            elif kind == "exp":
                cols.append(torch.exp(-r / c[k]))
            elif kind == "shifted":
                cols.append((r + c[k]) ** p)
            else:
                cols.append((r * r + c[k] * c[k]) ** (p / 2))
        return torch.stack(cols, -1) * self.amplitudes()

    def amplitudes(self) -> torch.Tensor:
        """(K,) the amplitudes a_k, float64."""
        return self.amplitude.double() * self.amplitude_scale.double()

    @torch.no_grad()
    def scale_(self, factor: float) -> None:
        """The whole law times ``factor``, in place: the terms' amplitudes and each expression
        pair's amplitudes (its constants named ``a1, a2, ...``, as the law search names them:
        ``bgn.laws.search.form_expression``), in which its expression is linear. An
        expression that this does not scale (checked at distances 0.1 to 10) is refused,
        unchanged (``ValueError``)."""
        r = torch.logspace(-1, 1, 17, dtype=torch.float64)
        before = self.values(r)
        self.amplitude.mul_(factor)
        if self.expressions:
            names = [n for ns in self.expression_names for n in ns]
            linear = torch.tensor([re.fullmatch(r"a\d+", n) is not None for n in names])
            saved = self.constant.detach().clone()
            self.constant[linear] *= factor
            after = self.values(r)[..., len(self.kinds):]
            want = factor * before[..., len(self.kinds):]
            ok = torch.isfinite(want)
            if not torch.allclose(after[ok], want[ok], rtol=1e-9, atol=0.0):
                self.constant.copy_(saved)
                self.amplitude.div_(factor)
                raise ValueError("model.law_formula: an expression is not linear in its "
                                 f"amplitudes a1, a2, ...: cannot scale {self.expressions}")

    def forward(self, r: torch.Tensor, pair: torch.Tensor | None = None) -> torch.Tensor:
        """``f(r)`` at distances r (E, ...) in r's dtype; ``pair`` (E,): each edge's pair of
        types as ``min * n_types + max`` (None: one type)."""
        cols = self.values(r)
        if pair is None:
            pair = torch.zeros(r.shape[0], dtype=torch.long, device=r.device)
        ids = torch.tensor(self.pair_ids, device=r.device)
        mask = (pair.view(-1, *[1] * (r.dim() - 1), 1) == ids).to(cols.dtype)
        return (cols * mask).sum(-1).to(r.dtype)

    def spec(self) -> str:
        """The spec with the current values of the constants (``bgn.laws.finetune.formula_spec``'s
        format): what a fine-tuned law is, in a form a config can carry."""
        pairs: dict[int, dict[str, Any]] = {}
        out: list[dict[str, Any]] = []
        # a constant the fit drove below exp(-745) underflows to 0, which no spec may hold:
        # the least positive double is the same law to every digit
        c = self.log_c.detach().double().exp().clamp_min(sys.float_info.min).tolist()
        a = self.amplitudes().detach().tolist()
        values = iter(self.constants().detach().tolist())
        terms = iter(enumerate(zip(self.kinds, self.powers, self.pair_ids)))
        exprs = iter(zip(self.expressions, self.expression_names,
                         self.pair_ids[len(self.kinds):]))
        for pair in self.pairs:  # the spec's order; term pairs of one pair of types merged
            if "expr" in pair:
                text, names, pid = next(exprs)
                out.append({"types": [pid // self.n_types, pid % self.n_types], "expr": text,
                            "constants": {n: next(values) for n in names}})
                continue
            for _ in pair["terms"]:
                k, (kind, p, pid) = next(terms)
                if pid not in pairs:
                    pairs[pid] = {"types": [pid // self.n_types, pid % self.n_types],
                                  "terms": []}
                    out.append(pairs[pid])
                pairs[pid]["terms"].append({"kind": kind, "power": p, "a": a[k],
                                            "c": c[k] if kind in NONLINEAR else None})
        return json.dumps(out)


def term_text(term: dict[str, Any], digits: int = 4) -> str:
    """One term of a spec as plain text, e.g. ``-1.003*(r + 0.01067)**-2`` (model labels;
    bgn.laws prints whole formulas through sympy)."""
    a, p, c = f"{term['a']:.{digits}g}", f"{term.get('power', 0.0):g}", term.get("c")
    c = None if c is None else f"{c:.{digits}g}"
    return {"const": a, "power": f"{a}*r**{p}", "log": f"{a}*log(r)",
            "exp": f"{a}*exp(-r/{c})", "shifted": f"{a}*(r + {c})**{p}",
            "plummer": f"{a}*(r**2 + {c}**2)**({p}/2)"}[term["kind"]]


def pair_text(pair: dict[str, Any], scale: float = 1.0, digits: int = 4) -> str:
    """One pair of a spec as plain text, its law times ``scale`` (a head's ``law_scale``):
    the terms joined by ``+`` (``term_text``), or an expression pair's expression with its
    constants' values."""
    if "expr" in pair:
        return sympy.sstr(sympy.N(pair_expression(pair, scale), digits))
    return " + ".join(term_text({**t, "a": t["a"] * scale}) for t in pair["terms"])


def pair_expression(pair: dict[str, Any], scale: float = 1.0) -> sympy.Expr:
    """One pair of a spec as a sympy expression in r (``positive``), its law times ``scale``:
    every constant (amplitudes, c's, an expression's constants) a float, a term's power a
    rational (the form's): ``bgn.laws.search.same_form`` reads the floats as the family's."""
    if "expr" in pair:
        expr = parse_expression(pair["expr"], pair.get("constants", {}))
        values = {sympy.Symbol(n, real=True): sympy.Float(v, 17)
                  for n, v in pair.get("constants", {}).items()}
        expr = expr.xreplace(values)
        return expr if scale == 1.0 else sympy.Float(scale, 17) * expr
    return sum((sympy.Float(t["a"] * scale, 17) * _term_expression(t) for t in pair["terms"]),
               sympy.Integer(0))


def _term_expression(term: dict[str, Any]) -> sympy.Expr:
    """One term of a spec without its amplitude (``FormulaLaw._term_values``' kinds)."""
    kind, p = term["kind"], sympy.nsimplify(float(term.get("power", 0.0)))
    c = None if term.get("c") is None else sympy.Float(term["c"], 17)
    if kind == "const":
        return sympy.Integer(1)
    if kind == "power":
        return _R**p
    if kind == "log":
        return sympy.log(_R)
    if kind == "exp":
        return sympy.exp(-_R / c)
    if kind == "shifted":
        return (_R + c) ** p
    return (_R**2 + c**2) ** (p / 2)


# auto: the network law is trained, then read back as a formula and fine-tuned after the fit,
# and the one that validates better on rollouts is kept (bgn.laws.stage.law_stage, handed to
# bgn.training.run.train); the model itself carries the network law
LAWS = ("mlp", "formula", "auto")


def check_law(law: str, law_formula: str, law_scale: float = 1.0) -> None:
    """The ``law`` / ``law_formula`` / ``law_scale`` options of a model config, refused in one
    line."""
    # the window's mass fit leaves the law's sign free as well as its size: any finite k != 0
    if not (isinstance(law_scale, (int, float)) and math.isfinite(law_scale) and law_scale != 0):
        raise ValueError(f"law_scale={law_scale!r} must be a finite non-zero number (1: the "
                         "formula is in physical units)")
    if law not in LAWS:
        raise ValueError(f"law={law!r}; choose one of {LAWS}")
    if law == "formula":
        parse_spec(law_formula)
    elif law_formula:
        raise ValueError(f"law_formula is set but law={law}: set law=formula to use it, or "
                         "leave law_formula empty")
