import numpy as np
import pytest

from bgn.data.targets import backward_velocities, step, targets


@pytest.mark.parametrize("kind", ["velocity", "acceleration"])
def test_targets_step_recorded_frames_forward(kind):
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.normal(size=(50, 7, 3)), axis=0)
    dt = 0.02
    v = backward_velocities(x, dt)  # v[j] is the input velocity of frame j + 1
    y = targets(x, dt, kind)        # y[j] is the target of frame j + 1
    for t in range(1, 49):
        nxt, _ = step(x[t], v[t - 1], y[t - 1], dt, kind)
        np.testing.assert_allclose(nxt, x[t + 1], rtol=0, atol=1e-12 * np.abs(x).max())


def test_rollout_of_targets_reproduces_trajectory():
    rng = np.random.default_rng(1)
    x = np.cumsum(np.cumsum(rng.normal(size=(200, 4, 2)), axis=0), axis=0) * 1e-3
    dt = 0.1
    y = targets(x, dt, "acceleration")
    pos, vel = x[1], backward_velocities(x[:2], dt)[0]
    for t in range(1, 199):
        pos, vel = step(pos, vel, y[t - 1], dt, "acceleration")
        np.testing.assert_allclose(pos, x[t + 1], atol=1e-9)


def test_unknown_kind():
    with pytest.raises(ValueError, match="unknown target kind"):
        targets(np.zeros((5, 2, 2)), 0.1, "jerk")
