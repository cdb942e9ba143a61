"""The law's report: its markdown (``markdown``, ``law_section`` for an evaluation report),
its figure (``law_figure``), ``write_report``'s files (report.md, law.csv, law.json,
law.png) and the fine-tuning's section (``finetune_markdown``). Each pair of types' formula is
``PairLaw.formula`` (the law search's member chosen, or where no formula fits its most
accurate member, said not chosen), beside the search's front (``front_table``).
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import sympy
import torch

from bgn.laws.compare import MASS_TEXT, SCALE_TEXT, LawReport, PairLaw, read_law, relative_error
from bgn.laws.options import DEFAULTS
from bgn.laws.search import SearchResult, expression_spec


def truth_markdown(truth: dict[str, Any], truth_text: str | None) -> list[str]:
    """``against_truth``'s figures as a paragraph (none where the truth is unknown)."""
    if not truth:
        return []
    laws = [(k, name) for k, name in (("network", "the network's"),
                                      ("read_back", "the formula read back from it"),
                                      ("tuned", "the fine-tuned formula"))
            if f"{k}_max" in truth]
    text = ("Against the scene's true law `" + str(truth_text) + "`, the largest relative "
            "error over the training distances (between their 1st and 99th percentiles in "
            "brackets): " + "; ".join(f"{name} {_g(truth[f'{k}_max'], 2)} "
                                       f"({_g(truth[f'{k}_max_1_99'], 2)})" for k, name in laws)
            + ".")
    for k, name in (("read_back", "The formula read back"), ("tuned", "The fine-tuned formula")):
        if f"{k}_form_is_truth" in truth:
            text += (f" {name} has the truth's form (the same up to constants), its constants "
                     f"within {_g(truth[f'{k}_constants_vs_truth'], 2)} of the truth's."
                     if truth[f"{k}_form_is_truth"] else f" {name} does NOT have the truth's form.")
    return [text, ""]


def _g(x: float, digits: int = 3) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def _pair_name(report: LawReport, types: tuple[int, int]) -> str:
    return "" if len(report.pairs) == 1 else f" (types {types[0]}-{types[1]})"


def outcome_sentence(pair: PairLaw) -> str:
    """The search's outcome in one sentence: the member chosen, or "no formula fits"."""
    found = pair.search
    if pair.chosen:
        return (f"The simplest member of the front within the tolerance {_g(found.tolerance)} "
                f"(RMS relative error against the learned law): complexity "
                f"{pair.formula.complexity}, error {_g(pair.formula.error)}.")
    return (f"**No formula fits**: no member of the front is within the tolerance "
            f"{_g(found.tolerance)} of the learned law both as fitted and on held-out "
            f"distances (the most accurate, above, has error {_g(pair.formula.error)}, held "
            f"out {_g(pair.formula.holdout)}, and is NOT chosen); the network law is kept "
            f"unless a member fitted to the frames explains them better (the fine-tuning's "
            f"frames check).")


def front_table(found: SearchResult) -> list[str]:
    """The search's front as a markdown table: complexity, error as fitted and held out,
    formula, its tree (a force or a potential), the member chosen marked."""
    lines = ["| complexity | error | held out | formula | tree | chosen |",
             "|---|---|---|---|---|---|"]
    for m in found.front:
        lines.append(f"| {m.complexity} | {_g(m.error)} | {_g(m.holdout)} | `{m.text}` | "
                     f"{'potential' if m.potential is not None else 'force'} | "
                     f"{'yes' if m is found.chosen else ''} |")
    return lines


def markdown(report: LawReport, figure: str | None = None, level: int = 2) -> str:
    """The law as a markdown section (``level``: its heading level): formula, constants,
    masses, scale, band errors and the truth where known."""
    h = "#" * level
    lines = [f"{h} The learned pair law ({report.model} on {report.scene})", ""]
    scale = SCALE_TEXT[report.scale].format(_g(report.scale_factor, 4))
    lines += [f"- Convention: the force on particle i from j is f(r) u_ij, u_ij the unit vector "
              "from j to i (f > 0: repulsive); r in the data's length units (the head reads r / "
              f"{_g(report.length_scale, 4)}); f is the force between unit masses.",
              f"- Masses (the head's mass_law={report.mass_law}): {MASS_TEXT[report.mass_law]}."
              + ("" if report.truth_masses is None else
                 f" The scene's own law: {report.truth_masses}"
                 + (" (the same)." if report.truth_masses == report.mass_law else
                    " (DIFFERENT: the learned law is not comparable with the truth).")),
              f"- Scale: {scale}; relative squared error of the targets then "
              f"{_g(report.calibration_error)}.",
              ""]
    if figure:
        lines += [f"![learned law, formula and truth]({figure})", ""]
    for pair in report.pairs:
        f = pair.formula
        lines += [f"{h}# Formula{_pair_name(report, pair.types)}", "",
                  f"    f(r) = {f.text}", "", outcome_sentence(pair), "",
                  f"Searched on {len(pair.r)} log-spaced distances over the "
                  f"{pair.n_distances} training pair distances (r = {_g(pair.r[0])} to "
                  f"{_g(pair.r[-1])}), each weighted by the data's density of log r: a "
                  "member's error is its RMS relative residual over the training pairs. The "
                  "search's front (simplest first; a potential's member is written "
                  "-d/dr[U], its complexity that of U's tree):", "",
                  *front_table(pair.search), ""]
        if report.truth_text is not None:
            lines += [f"Truth (bgn.sim): f(r) = {report.truth_text}."]
            if pair.truth_in_form is not None:
                lines += [("The formula has the truth's form (the same up to constants), its "
                           "constants within "
                           f"{_g(pair.truth_in_form['constants_vs_truth'], 2)} of the truth's "
                           "in its family." if pair.truth_in_form["same_form"]
                           else "The formula does NOT have the truth's form.")]
            lines += [""]
        lines += [f"The formula with its constants named: `f(r) = {sympy.sstr(f.template)}`" + (
            f" (the force of U(r) = `{sympy.sstr(sympy.N(f.potential, DEFAULTS.significant))}`)"
            if f.potential is not None else "") + ":", "",
            "| constant | value |", "|---|---|"]
        lines += [f"| {name} | {_g(value, 5)} |" for name, value in f.constants.items()]
        lines += ["", "Relative errors (|a - b| / |b|, |b| floored near a zero crossing) in "
                  "bands of the training distances (median / max):", ""]
        cols = ["formula_vs_learned"] + (["learned_vs_truth", "formula_vs_truth"]
                                         if pair.truth is not None else [])
        lines += ["| data quantiles | r | " + " | ".join(c.replace("_", " ") for c in cols)
                  + " |", "|---|---|" + "---|" * len(cols)]
        for band in pair.bands:
            lines.append(f"| {band['quantiles'][0]:g}-{band['quantiles'][1]:g} | "
                         f"{_g(band['r'][0])}-{_g(band['r'][1])} | "
                         + " | ".join(f"{_g(band[c]['median'], 2)} / {_g(band[c]['max'], 2)}"
                                      for c in cols) + " |")
        lines.append("")
    return "\n".join(lines)


def law_section(module: Any, dataset: Any, level: int = 2) -> str:
    """The markdown section of the learned law of ``module`` over ``dataset``'s distances
    (the training split), for an evaluation report (``bgn.eval.evaluate``): models with a
    pair-force head only (``pair_force_head`` refuses the others)."""
    return markdown(read_law(module, dataset), level=level)


def law_figure(report: LawReport, tuned: str | None = None) -> Any:
    """Learned law, formula and truth against r, their relative errors, and the histogram of
    the training distances underneath; one column per pair of types. ``tuned``: a
    ``model.law_formula`` spec drawn too (the formula fitted to the frames)."""
    from matplotlib.ticker import FormatStrFormatter, FuncFormatter, NullFormatter

    from bgn.figures import plt

    n = len(report.pairs)
    fig, axes = plt.subplots(3, n, figsize=(6 * n, 8.5), sharex="col", squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1.4, 1.2]})
    for col, pair in enumerate(report.pairs):
        law_ax, err_ax, hist_ax = axes[:, col]
        curves = {"learned": pair.learned, "formula": pair.formula(pair.r)}
        if tuned is not None:
            curves["formula fitted to the frames"] = spec_values(tuned, pair.types, pair.r)
        if pair.truth is not None:
            curves["truth"] = pair.truth
        signs = {np.sign(c[np.abs(c) > 0]).mean() for c in curves.values()}
        one_sign = all(abs(s) == 1 for s in signs) and len(signs) == 1
        flip = -1.0 if one_sign and signs.pop() < 0 else 1.0
        styles = {"learned": "-", "formula": "--", "formula fitted to the frames": "-.",
                  "truth": ":"}
        for name, c in curves.items():
            law_ax.plot(pair.r, flip * c, styles[name], label=name, lw=2 if name == "learned"
                        else 1.5)
        law_ax.set_xscale("log")
        if one_sign:
            law_ax.set_yscale("log")
        law_ax.set_ylabel(("-f(r)" if flip < 0 else "f(r)") + " (force between unit masses)")
        law_ax.legend(fontsize=8)
        law_ax.set_title(f"{report.scene}{_pair_name(report, pair.types)}: "
                         f"f = {pair.formula.text}"
                         + ("" if pair.chosen else " (no formula fits: most accurate)"),
                         fontsize=9)
        err_ax.plot(pair.r, relative_error(curves["formula"], pair.learned, pair.r),
                    label="formula vs learned")
        if pair.truth is not None:
            err_ax.plot(pair.r, relative_error(pair.learned, pair.truth, pair.r),
                        label="learned vs truth")
            err_ax.plot(pair.r, relative_error(curves["formula"], pair.truth, pair.r), "--",
                        label="formula vs truth")
            if tuned is not None:
                err_ax.plot(pair.r, relative_error(curves["formula fitted to the frames"],
                                               pair.truth, pair.r), "-.",
                            label="fitted to the frames vs truth")
        err_ax.set_yscale("log")
        err_ax.set_ylabel("relative error")
        err_ax.legend(fontsize=8)
        hist_ax.stairs(pair.hist_counts, pair.hist_edges, fill=True, color="0.6")
        hist_ax.set_yscale("log")
        hist_ax.set_xlabel("r (distance between the pair)")
        hist_ax.xaxis.set_major_formatter(FormatStrFormatter("%g"))
        # within two decades also 2 and 5 times a power of ten (else the decades alone)
        if pair.r[-1] / pair.r[0] < 100:
            hist_ax.xaxis.set_minor_formatter(FuncFormatter(
                lambda x, _: f"{x:g}" if f"{x:.0e}"[0] in "25" else ""))
        else:
            hist_ax.xaxis.set_minor_formatter(NullFormatter())
        hist_ax.set_ylabel("training pairs")
    fig.tight_layout()
    return fig


def spec_values(spec: str, types: tuple[int, int], r: np.ndarray) -> np.ndarray:
    """The law of a ``model.law_formula`` spec between ``types`` at distances ``r``."""
    from bgn.model.formula_law import FormulaLaw

    n_types = 1 + max(max(p["types"]) for p in json.loads(spec))
    law = FormulaLaw(spec, max(n_types, max(types) + 1))
    pair = torch.full((len(r),), min(types) * law.n_types + max(types))
    with torch.no_grad():
        return law(torch.as_tensor(r, dtype=torch.float64), pair).numpy()


def _jsonable(report: LawReport) -> dict[str, Any]:
    out = {f.name: getattr(report, f.name) for f in fields(report) if f.name != "pairs"}
    out["outcome"] = report.outcome
    out["pairs"] = []
    for pair in report.pairs:
        f, found = pair.formula, pair.search
        out["pairs"].append({
            "types": list(pair.types), "formula": f.text, "chosen": pair.chosen,
            "outcome": found.outcome, "tolerance": found.tolerance,
            "complexity": f.complexity, "relative_rms": f.error,
            "expression": sympy.sstr(f.template), "constants": f.constants,
            "spec": expression_spec(f, pair.types),
            "front": [{"complexity": m.complexity, "error": m.error,
                       "holdout_error": m.holdout, "formula": m.text,
                       "tree": "potential" if m.potential is not None else "force",
                       "chosen": m is found.chosen} for m in found.front],
            "search_seconds": found.timings.get("total_s"),
            "r": pair.r.tolist(), "density": pair.density.tolist(),
            "n_distances": pair.n_distances,
            "bands": pair.bands, "truth_in_form": pair.truth_in_form,
            "histogram": {"edges": pair.hist_edges.tolist(),
                          "counts": pair.hist_counts.tolist()}})
    return out


def write_report(report: LawReport, out_dir: str | Path, title: str | None = None) -> Path:
    """report.md, law.csv (r, learned, formula, truth per pair of types), law.json and
    law.png in ``out_dir``; each file written whole or not at all."""
    from bgn.figures import save
    from bgn.training.checkpoints import write_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = [["type_a", "type_b", "r", "learned", "formula", "truth"]]
    for pair in report.pairs:
        fitted = pair.formula(pair.r)
        for k, r in enumerate(pair.r):
            rows.append([*pair.types, f"{r:.9g}", f"{pair.learned[k]:.9g}", f"{fitted[k]:.9g}",
                         "" if pair.truth is None else f"{pair.truth[k]:.9g}"])
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerows(rows)
    record = json.dumps(_jsonable(report), indent=2)
    body = (f"# {title}\n\n" if title else "") + markdown(report, "law.png", level=2) + "\n"
    tmp = out / "law.tmp.png"
    try:  # the figure first: the step most likely to fail, and nothing is written before it
        save(law_figure(report), tmp)
    except Exception:
        tmp.unlink(missing_ok=True)
        raise
    write_atomic(out / "law.csv", text.getvalue())
    write_atomic(out / "law.json", record)
    write_atomic(out / "report.md", body)
    tmp.replace(out / "law.png")
    return out / "report.md"


def finetune_markdown(record: dict[str, Any], level: int = 2) -> str:
    """The comparison table of ``finetune_formula``'s record."""
    h = "#" * level
    v = record["validation"]
    frames = record.get("frames")
    if record.get("outcome") == "no formula fits":  # nothing chosen (no_formula_record)
        checked = ("" if not frames else
                   f" The front's members were fitted to the frames all the same: the best "
                   f"explains them less well than the network law (law loss "
                   f"{_g(frames['formula_loss'])} against {_g(frames['network_loss'])}).")
        return (f"{h} The formula as the law, fine-tuned\n\nNo formula fits the learned law "
                f"within the tolerance {_g(record['tolerance'])} (the most accurate member of "
                f"the front has error {_g(record['best_error'])}).{checked} The network law "
                "is kept.\n\n"
                + "".join(line + "\n" for line in truth_markdown(
                    record.get("against_truth") or {}, record.get("truth"))))
    if not v:  # the validation rollouts were cut (finetune_formula)
        return (f"{h} The formula as the law, fine-tuned\n\nThe fitted formula as the model's "
                f"pair law, its constants fitted in {record['steps']} evaluations: "
                f"`{spec_text(record['tuned'])}`. Not compared: the job's wall-clock cap "
                "(trainer.max_time) was reached before the validation rollouts finished "
                f"({', '.join((record.get('budget') or {}).get('cut', []))} cut), so the "
                "network law is kept.\n")
    horizons = sorted(v["network"]["errors"], key=int)
    lines = [f"{h} The formula as the law, fine-tuned",
             "",
             f"The fitted formula as the model's pair law (model.law=formula), its constants "
             f"fitted in {record['steps']} evaluations of the law's loss on "
             f"{record.get('batch_size', '?')} training frames with model.substeps="
             f"{record['substeps']}, the rest of the model the checkpoint's; both scored on "
             f"the validation split's rollouts ({v['network']['rollouts']} rollouts, a failed "
             "one at the cap): the mean error and the typical one (the geometric mean over "
             "the rollouts)." + ("" if not frames else
                                 " No formula fits the learned law within the tolerance "
                                 f"{_g(record.get('tolerance'))}; the front's members were "
                                 "fitted to the frames, and the formula below explains them "
                                 "better than the network law does (law loss "
                                 f"{_g(frames['formula_loss'])} against "
                                 f"{_g(frames['network_loss'])}): the frames, not the "
                                 "learned law, put it forward."),
             "",
             "| law | formula | " + " | ".join(f"mean @{k} | typical @{k}" for k in horizons)
             + " | failed |",
             "|---|---|" + "---|---|" * len(horizons) + "---|"]
    rows = [("network", "(MLP)", v["network"])] + [
        (f"formula, substeps {k}", spec_text(record["tuned"]), s)
        for k, s in record["formula_by_substeps"].items()]
    for name, text, s in rows:
        typical = s.get("typical", {})
        lines.append(f"| {name} | `{text}` | " + " | ".join(
            f"{_g(s['errors'][k])} | {_g(typical[k]) if k in typical else ''}"
            for k in horizons) + f" | {s['failed_share']:.0%} |")
    if record.get("forms"):
        lines += ["", "Forms tried (the law search's front: the member chosen, then the others "
                  "simplest first; each form's constants fitted to the law's loss on the "
                  "frames; the lowest loss wins, the least complex within "
                  f"{DEFAULTS.form_tolerance:.0%} of it):",
                  "", "| from | tuned | complexity | constants | loss |",
                  "|---|---|---|---|---|"]
        lines += [f"| `{spec_text(f['start'])}` | `{spec_text(f['tuned'])}` | "
                  f"{f.get('complexity', '')} | {f['constants']} | {_g(f['loss'])} |"
                  for f in record["forms"]]
    lines += ["", f"Fitted before fine-tuning: `{spec_text(record['start'])}`; the formula "
              f"rolls out with substeps {record['rollout_substeps']} (the lower mean error: "
              "substeps are for the rare close encounters).", ""]
    if record.get("polish"):
        lines += [f"The chosen form's constants then polished through "
                  f"{record['polish']['substeps']} substeps ({record['polish']['evaluations']} "
                  f"evaluations; loss {_g(record['polish']['loss'])}).", ""]
    if record.get("scale", 1.0) != 1.0:
        lines += [f"The tuned constants put in physical units by the factor {_g(record['scale'])} "
                  "(the loss through the window's mass fit leaves the law's scale free; "
                  "the forms above are before it). The model keeps the formula times "
                  f"{_g(record.get('model_scale', 1.0))}, the network law's scale, in which "
                  "its mass flow reads the window's fitted masses.", ""]
    lines += truth_markdown(record.get("against_truth") or {}, record.get("truth"))
    lines += [f"Chosen: **{record['choice']}** (the fewer failed validation rollouts, then "
              f"the lower mean error after {horizons[-1]} steps, a failed one at the cap)."]
    if record.get("path"):
        lines += ["", f"Checkpoint with the formula law: `{record['path']}`."]
    return "\n".join(lines) + "\n"


def spec_text(pairs: list[dict[str, Any]] | None) -> str:
    """A ``model.law_formula`` spec (parsed) as text: each pair of types' law in r (terms or
    expression pairs, ``bgn.model.formula_law.pair_expression``); "none" for no spec (no
    formula fits)."""
    from bgn.model.formula_law import pair_expression

    if not pairs:
        return "none"
    return "; ".join((f"{p['types'][0]}-{p['types'][1]}: " if len(pairs) > 1 else "")
                     + sympy.sstr(sympy.N(pair_expression(p), DEFAULTS.significant))
                     for p in pairs)
