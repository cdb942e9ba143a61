"""bgn.rollout's start frames: what the validation scores (auto's and the formula stage's)
roll out from."""

from types import SimpleNamespace

import pytest

from bgn.rollout import REFERENCE_START, rollout_starts, scoring_starts


def frames(n_frames: int, history: int = 5) -> SimpleNamespace:
    return SimpleNamespace(history=history, file=SimpleNamespace(n_frames=n_frames, path="x.h5"))


@pytest.mark.parametrize("n_sims", [1, 3, 10, 33, 99, 100, 200])
def test_scoring_starts_give_the_rollouts_asked_for_from_distinct_frames(n_sims):
    """At least 100 rollouts where the file has the frames, frame 100 among the starts, every
    start leaving the horizon after it; a split that alone gives them keeps one start."""
    ds, n_steps = frames(1000), 50
    starts = scoring_starts(ds, n_steps, n_sims, 100)
    assert n_sims * len(starts) >= 100
    assert len(set(starts)) == len(starts) and REFERENCE_START in starts
    assert min(starts) >= ds.history + 1 and max(starts) + n_steps <= ds.file.n_frames - 1
    if n_sims >= 100:
        assert starts == rollout_starts(ds, n_steps) == [REFERENCE_START]


def test_scoring_starts_stop_at_what_a_short_file_holds():
    ds, n_steps = frames(40), 20
    starts = scoring_starts(ds, n_steps, 2, 100)
    assert starts == list(range(ds.history + 1, ds.file.n_frames - n_steps))
