"""Re-check on validation the mass fit of the pair-force head along a rollout: refitted to
every step's window (``model.rollout_masses=window``, the default) against fitted once, to
the rollout's first window, and held (``held``).

    python examples/recheck/rollout_masses.py <run or cell directory> ... \
        [--results-md docs/results.md] [--block recheck_rollout_masses_val]

Each run (BGN or ``model=newton`` with the pair-force head) is evaluated twice by ``python -m
bgn.evaluate``'s own code on the validation split (``evaluate_option``, ``rollout.masses``):
100 steps from frame 100 of 10 validation simulations, as the ``recheck`` preset scores its
cells; one-step and inverse metrics do not depend on the option, so they are cut to a few
frames. The table gives, per scene, model and option, the rollout errors after 10, 50 and
100 steps (mean over all rollouts, failures at the cap), the median after 100, the energy
error and the failed share. Every evaluation writes its own report under
``<run>/eval/val_masses_<value>/``.
"""

from __future__ import annotations

import evaluate_option

from bgn.model.newton import ROLLOUT_MASSES

COLUMNS = ["rollout/pos_err_mean@10", "rollout/pos_err_mean@50", "rollout/pos_err_mean@100",
           "rollout/pos_err_median@100", "rollout/energy_err@100", "rollout/failed_share"]
EVALUATION = ["rollout.steps=100", "rollout.max_sims=10", "max_frames=16", "mass_frames=4",
              "mass_samples=4"]
BLOCK = "recheck_rollout_masses_val"


def main(argv: list[str] | None = None) -> str:
    return evaluate_option.main("rollout_masses.py", __doc__, "rollout.masses", ROLLOUT_MASSES,
                                COLUMNS, EVALUATION, BLOCK, argv)


if __name__ == "__main__":
    main()
