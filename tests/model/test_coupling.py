"""The coupling fit ``a_i = k_i sum_j c_j X_ij`` (bgn.model.coupling): charges of either sign and
inertial masses, both hidden, recovered from frames made with them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bgn.model.coupling import (
    coupling_errors,
    fit_couplings,
    levenberg_marquardt,
    lifted_start,
    relative_weights,
    residual,
    sign_patterns,
)
from bgn.sim.nbody import NBodyScene
from bgn.sim.scene import State

SCENE = NBodyScene("r2")
DT = 0.02


def system(seed: int, frames: np.ndarray, n: int = 4) -> tuple[np.ndarray, np.ndarray, dict]:
    """The pair terms (n, M, n) of the true law 1/s^2 and the recorded accelerations (n, M) at
    ``frames`` of one charged simulation, and its truth."""
    scene = NBodyScene("r2", n_particles=n)
    rng = np.random.default_rng(seed)
    state = scene.draw_state(rng)
    charges = rng.choice([-1.0, 1.0], n) * np.exp(0.5 * rng.standard_normal(n))
    traj = scene.simulate_from(State(state.positions, state.velocities, state.masses,
                                     charges=charges), np.arange(0, frames.max() + 1) * DT)
    x = traj.positions[frames]                                               # (F, n, D)
    diff = x[:, :, None] - x[:, None]                                        # x_i - x_j
    r = np.linalg.norm(diff, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        # force on i from j per unit coupling (like charges repel: F = q_i q_j X)
        terms = diff / ((r + scene.softening) ** 2 * r)[..., None]
    terms[:, np.arange(n), np.arange(n)] = 0.0
    f, _, _, d = terms.shape
    design = terms.transpose(1, 0, 3, 2).reshape(n, f * d, n)
    target = traj.accelerations[frames].transpose(1, 0, 2).reshape(n, f * d)
    return design, target, {"masses": state.masses, "charges": charges}


def batch(systems: list[tuple[np.ndarray, np.ndarray, dict]]):
    n = max(s[0].shape[0] for s in systems)
    m = max(s[0].shape[1] for s in systems)
    design = torch.zeros(len(systems), n, m, n, dtype=torch.float64)
    target = torch.zeros(len(systems), n, m, dtype=torch.float64)
    real = torch.zeros(len(systems), n, dtype=torch.bool)
    for b, (d, t, _) in enumerate(systems):
        k = d.shape[0]
        design[b, :k, :d.shape[1], :k] = torch.from_numpy(d)
        target[b, :k, :t.shape[1]] = torch.from_numpy(t)
        real[b, :k] = True
    return design, target, real


def relative_mass_error(k: torch.Tensor, c: torch.Tensor, masses: np.ndarray) -> float:
    """Largest error of the log-masses c / k against the truth, both centred (free scale)."""
    fitted = np.log((c / k).numpy())
    return float(np.abs((fitted - fitted.mean()) - (np.log(masses) - np.log(masses).mean()))
                 .max())


def charge_error(c: torch.Tensor, charges: np.ndarray) -> float:
    """Largest error of c against the charges of unit rms, up to the global sign."""
    truth = charges / np.sqrt((charges**2).mean())
    return float(min(np.abs(c.numpy() - truth).max(), np.abs(c.numpy() + truth).max()))


def test_sign_patterns_cover_every_pattern_of_a_few_particles_and_fix_the_first() -> None:
    assert sign_patterns(4).shape == (8, 4)
    assert (sign_patterns(4)[:, 0] == 1).all()
    assert len({tuple(row.tolist()) for row in sign_patterns(4)}) == 8
    many = sign_patterns(12)
    assert many.shape == (16, 12) and (many[0] == 1).all()
    assert torch.equal(many, sign_patterns(12))  # the same on every call


def test_the_frames_of_a_simulation_give_its_masses_and_charges_of_either_sign() -> None:
    """Pooled over frames spread along each simulation, with the true law: the masses up to
    one scale, the charges (signs included) up to one scale and one sign."""
    systems = [system(seed, np.arange(10, 400, 12)) for seed in range(6)]
    design, target, real = batch(systems)
    k, c = fit_couplings(design, target, real)
    assert sum((s[2]["charges"] > 0).any() and (s[2]["charges"] < 0).any()
               for s in systems) >= 3  # both signs within most simulations
    for b, (_, _, truth) in enumerate(systems):
        assert relative_mass_error(k[b], c[b], truth["masses"]) < 1e-6
        assert charge_error(c[b], truth["charges"]) < 1e-6
    # the gauge: c of unit rms, its largest entry positive
    torch.testing.assert_close(c.pow(2).mean(1), torch.ones(6, dtype=c.dtype))
    assert (c.gather(1, c.abs().argmax(1, keepdim=True)) > 0).all()
    assert residual(design, target, k, c).abs().max() < 1e-6 * target.abs().max()


def test_the_lifted_start_lies_in_the_truths_basin_where_many_frames_pin_every_coupling(
        ) -> None:
    """From the lifted start alone (no sign patterns), Levenberg-Marquardt reaches the truth."""
    systems = [system(seed, np.arange(10, 400, 12)) for seed in range(6)]
    design, target, real = batch(systems)
    w = relative_weights(target, real)
    d, t = design * w[..., None], target * w
    k, c, _ = levenberg_marquardt(d, t, *lifted_start(d, t, real), real)
    for b, (_, _, truth) in enumerate(systems):
        assert relative_mass_error(k[b], c[b], truth["masses"]) < 1e-6


def test_one_window_of_four_frames_with_exact_accelerations_is_enough() -> None:
    """Eight equations per frame for seven unknowns: a window's few frames identify the
    couplings where the accelerations are exact (the fit finds the optimum from several
    starts, where one start from charges of one sign ends in a wrong minimum)."""
    systems = [system(seed, np.arange(100, 104)) for seed in range(8)]
    design, target, real = batch(systems)
    k, c = fit_couplings(design, target, real)
    errors = [relative_mass_error(k[b], c[b], s[2]["masses"]) for b, s in enumerate(systems)]
    assert max(errors) < 1e-4, errors


def test_padded_particles_change_nothing_and_get_no_coupling() -> None:
    frames = np.arange(10, 300, 15)
    three, four = system(11, frames, n=3), system(12, frames, n=4)
    together = fit_couplings(*batch([three, four]))
    alone = [fit_couplings(*batch([s])) for s in (three, four)]
    torch.testing.assert_close(together[0][0, :3], alone[0][0][0])
    torch.testing.assert_close(together[1][1], alone[1][1][0])
    assert together[0][0, 3] == 0 and together[1][0, 3] == 0


def test_the_fit_carries_the_laws_gradient_and_reports_its_errors() -> None:
    systems = [system(seed, np.arange(10, 200, 10)) for seed in range(2)]
    design, target, real = batch(systems)
    design = design.float().requires_grad_()
    k, c = fit_couplings(design, target.float(), real)
    assert k.dtype == torch.float32
    (k.sum() + c.pow(3).sum()).backward()
    assert design.grad is not None and torch.isfinite(design.grad).all()
    assert design.grad.abs().sum() > 0
    k_err, c_err = coupling_errors(design.detach(), target.float(), real, k.detach(),
                                   c.detach())
    assert k_err.shape == c_err.shape == (2, 4)
    assert torch.isfinite(k_err).all() and torch.isfinite(c_err).all()
    # exact data: the errors are tiny against the couplings themselves
    assert (k_err / k.detach().abs()).max() < 1e-3 and (c_err / c.detach().abs()).max() < 1e-3


@pytest.mark.parametrize("seed", [0, 1])
def test_a_noisy_window_fits_no_worse_than_the_truth(seed: int) -> None:
    """Accelerations with 1 % noise: the fit's residual is at most the truth's (it is a least
    squares optimum over the starts, not a wrong minimum)."""
    design, target, truth = system(seed, np.arange(50, 58))
    rng = np.random.default_rng(seed)
    noisy = target * (1 + 0.01 * rng.standard_normal(target.shape))
    d, t, real = batch([(design, noisy, truth)])
    k, c = fit_couplings(d, t, real)
    w = relative_weights(t, real)
    q, m = truth["charges"], truth["masses"]
    true_k, true_c = torch.tensor(q / m)[None], torch.tensor(q)[None]
    fitted = residual(d * w[..., None], t * w, k, c).pow(2).sum()
    exact = residual(d * w[..., None], t * w, true_k, true_c).pow(2).sum()
    assert fitted <= exact * 1.0001
