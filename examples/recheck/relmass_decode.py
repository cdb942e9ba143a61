"""Re-check on validation the point the mass flow hands to Eq. 9-10 when relative masses are
scored: the posterior's median (the default, ``relmass_decode=median``) against a random
posterior draw (``draw``).

    python examples/recheck/relmass_decode.py <run or cell directory> ... \
        [--results-md docs/results.md] [--block recheck_relmass_decode_val]

Each run is evaluated twice by ``python -m bgn.evaluate``'s own code on the validation split
(``evaluate_option``), one-step frames only (rollouts cut to one step of one simulation: the
decode does not enter them); the table gives, per scene and decode, ``relmass_r2``,
``relmass_r2_estimate`` and the information gain. Every evaluation writes its own report
under ``<run>/eval/val_relmass_decode_<decode>/``.
"""

from __future__ import annotations

import evaluate_option

from bgn.eval.evaluate import RELMASS_DECODES

COLUMNS = ["relmass_r2", "relmass_r2_estimate", "info_gain"]
BLOCK = "recheck_relmass_decode_val"


def main(argv: list[str] | None = None) -> str:
    return evaluate_option.main("relmass_decode.py", __doc__, "relmass_decode", RELMASS_DECODES,
                                COLUMNS, ["rollout.steps=1", "rollout.max_sims=1"], BLOCK,
                                argv)


if __name__ == "__main__":
    main()
