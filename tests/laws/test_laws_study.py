"""bgn.studies.laws_study with the law search's outcomes: a cell where no formula fits is a
row of its own (no fitted formula, no rollouts), and the findings count it."""

from __future__ import annotations

import json
import math


def test_a_cell_where_no_formula_fits_is_a_row_and_a_finding(tmp_path):
    from bgn.studies.laws_study import findings, law_row

    (tmp_path / "law.json").write_text(json.dumps({"pairs": [{"formula": "-0.5*exp(-r)"}]}))
    record = {"outcome": "no formula fits", "choice": "network", "tuned": None,
              "validation": {}, "truth": "-2*r + 99/50", "report": str(tmp_path / "report.md"),
              "against_truth": {"network_max": 0.3, "network_max_1_99": 0.02,
                                "read_back_max": 0.4, "read_back_max_1_99": 0.1,
                                "read_back_form_is_truth": 0.0,
                                "read_back_constants_vs_truth": math.nan}}
    row = law_row(record)
    assert row["fitted to the frames"] == "no formula fits" and row["horizon"] is None
    assert row["read back from the network"] == "-0.5*exp(-r)"
    assert row["formula chosen"] == 0.0 and row["network vs truth"] == 0.3
    assert all(math.isnan(row[k]) for k in ("network val error", "formula val error",
                                            "network failed", "formula failed",
                                            "form is the truth's", "fitted vs truth"))
    text = "\n".join(findings([{"scene": "spring", **row}], "50"))
    assert "No formula fit the learned law (within the search's tolerance) in 1 of 1" in text
    assert "formula 0, network 0" in text  # no rollouts: no failures counted
