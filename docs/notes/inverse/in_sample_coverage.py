"""The law posterior scored on the very validation simulations its spread, shift and prior
share are chosen on (docs/results.md, "With a heavy tail on the likelihood"): where the
pipeline is consistent its coverage there is near 0.5 / 0.9, so a test split that reads
otherwise differs in its simulations, not in the method. ``bgn.evaluate`` with its own keys,
the law posterior handed the validation split (read with the test's frames per simulation) as
the split scored; the other sections of the report are the test split's as usual.

    python docs/notes/inverse/in_sample_coverage.py outputs/gravity_r2_s0 sims=40 \\
        mass_frames=1600 rollout.max_sims=2 calibration_sims=40 out_dir=<dir>
"""

from __future__ import annotations

import sys
from typing import Any

import bgn.eval.evaluate as evaluate

_reference = evaluate._law_posterior_reference


def _on_validation(module: Any, dataset: Any, validation: Any, prior: Any, indices: list[int],
                   *rest: Any) -> dict[str, Any]:
    frames = evaluate.matched_frames(dataset, validation, indices)
    return _reference(module, validation, validation, prior, frames, *rest)


if __name__ == "__main__":
    evaluate._law_posterior_reference = _on_validation
    sys.argv = ["bgn.evaluate", *sys.argv[1:]]
    evaluate.main()
