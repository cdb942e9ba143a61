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
a term without one). A pair of types the spec does not name feels no force.
"""

from __future__ import annotations

import json
import math
import sys
from typing import Any

import torch
from torch import nn

KINDS = ("const", "power", "log", "exp", "shifted", "plummer")
NONLINEAR = ("exp", "shifted", "plummer")


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
        terms = p.get("terms") if isinstance(p, dict) else None
        if not isinstance(terms, list) or not terms or len(p.get("types", ())) != 2:
            raise ValueError(f"model.law_formula: pair {p!r} needs 'types' [a, b] and a "
                             "non-empty list of 'terms'")
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
        flat = [(sorted(p["types"]), t) for p in pairs for t in p["terms"]]
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

    def values(self, r: torch.Tensor) -> torch.Tensor:
        """(..., K) each term times its amplitude at r (...), in float64."""
        r = r.double()
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
        # a constant the fit drove below exp(-745) underflows to 0, which no spec may hold:
        # the least positive double is the same law to every digit
        c = self.log_c.detach().double().exp().clamp_min(sys.float_info.min).tolist()
        a = self.amplitudes().detach().tolist()
        for k, (kind, p, pid) in enumerate(zip(self.kinds, self.powers, self.pair_ids)):
            entry = pairs.setdefault(pid, {"types": [pid // self.n_types, pid % self.n_types],
                                           "terms": []})
            entry["terms"].append({"kind": kind, "power": p,
                                   "a": a[k],
                                   "c": c[k] if kind in NONLINEAR else None})
        return json.dumps(list(pairs.values()))


def term_text(term: dict[str, Any], digits: int = 4) -> str:
    """One term of a spec as plain text, e.g. ``-1.003*(r + 0.01067)**-2`` (model labels;
    bgn.laws prints whole formulas through sympy)."""
    a, p, c = f"{term['a']:.{digits}g}", f"{term.get('power', 0.0):g}", term.get("c")
    c = None if c is None else f"{c:.{digits}g}"
    return {"const": a, "power": f"{a}*r**{p}", "log": f"{a}*log(r)",
            "exp": f"{a}*exp(-r/{c})", "shifted": f"{a}*(r + {c})**{p}",
            "plummer": f"{a}*(r**2 + {c}**2)**({p}/2)"}[term["kind"]]


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
