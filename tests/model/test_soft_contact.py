"""The soft-contact head (bgn.model.soft_contact): free fall exact, momentum exchanged in equal
and opposite pairs, a contact's restitution as its damping says, walls, invariances, and the
contact distances measured from data where no radii are given."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from bgn.graph import window_graph
from bgn.model.soft_contact import SoftContactHead
from tests.model.conftest import make_meta

DT = 0.01


def head(n: int = 2, n_types: int = 2, box: float | None = 1.0, substeps: int = 10,
         replay: int = 2, energy: str = "lose") -> SoftContactHead:
    meta = replace(make_meta(n=n, n_types=n_types, graph="radius", box=box))
    return SoftContactHead(meta, substeps, replay, energy).double()


def graph(window: torch.Tensor, radii: list[float], types: list[int],
          box: float | None = 1.0):
    """One frame's graph from positions (k+2, N, D), every pair an edge."""
    n = window.shape[1]
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    edges = torch.stack([j[i != j], i[i != j]])
    return window_graph(window[None].double(), DT, edges, torch.ones(1, n),
                        torch.tensor([radii], dtype=torch.float64),
                        torch.tensor([types]), box, torch.tensor([0]), torch.tensor([0]),
                        dtype=torch.float64)


def free_fall(x0: list[list[float]], v0: list[list[float]], g: list[float],
              frames: int = 5) -> torch.Tensor:
    """(frames, N, D) exact positions under a uniform acceleration."""
    t = torch.arange(frames, dtype=torch.float64)[:, None, None] * DT
    return (torch.tensor(x0, dtype=torch.float64) + torch.tensor(v0, dtype=torch.float64) * t
            + 0.5 * torch.tensor(g, dtype=torch.float64) * t * t)


def test_free_fall_is_exact_with_the_field_learned():
    h = head()
    with torch.no_grad():
        h.field.copy_(torch.tensor([0.3, -1.0]) * DT * DT / 1e-3)   # g = (0.3, -1) per s^2
    window = free_fall([[0.3, 0.5], [0.7, 0.6]], [[0.2, 0.1], [-0.1, 0.3]], [0.3, -1.0])
    acc, logits = h(graph(window, [0.02, 0.03], [0, 1]))
    assert logits is None
    torch.testing.assert_close(acc, torch.tensor([[0.3, -1.0]] * 2, dtype=torch.float64))


def test_a_pair_contact_conserves_momentum_with_the_learned_masses():
    h = head()
    with torch.no_grad():
        h.log_mass.copy_(torch.tensor([0.0, math.log(3.0)]))
        h.pair.friction.fill_(1.0)
    # overlapping and sliding past each other: normal and tangential forces both act
    window = free_fall([[0.40, 0.50], [0.44, 0.51]], [[0.5, 0.2], [-0.5, -0.3]], [0.0, 0.0])
    acc, _ = h(graph(window, [0.02, 0.03], [0, 1]))
    assert acc.abs().max() > 1.0                               # they push each other
    mass = torch.exp(h.log_mass.detach())
    momentum = acc[0] * mass[0] + acc[1] * mass[1]
    torch.testing.assert_close(momentum, torch.zeros(2, dtype=torch.float64), atol=1e-9, rtol=0)


@pytest.mark.parametrize(("energy", "zeta"), [("lose", 0.1), ("any", 0.1), ("any", -0.05)])
def test_a_head_on_contact_rebounds_with_the_restitution_of_its_damping(energy, zeta):
    h = head(box=None, substeps=40, replay=0, energy=energy)
    with torch.no_grad():          # "lose" keeps the damping ratio >= 0 through a softplus
        h.pair.damping.fill_(math.log(math.expm1(zeta)) if energy == "lose" else zeta)
        h.pair.friction.fill_(-30.0)                           # no friction
    x = torch.tensor([[0.0, 0.0], [0.0501, 0.0]], dtype=torch.float64)
    v = torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=torch.float64)
    g = graph(torch.stack([x - v * DT, x]), [0.025, 0.025], [0, 0], box=None)
    reach = h.reach(g)
    dt = torch.full((2,), DT, dtype=torch.float64)
    for _ in range(20):                                        # long past the contact
        moved, v = h.frame(g, x, v, dt, reach)
        x = x + moved
    assert v[0, 0] < 0 < v[1, 0]                               # apart
    assert float(h.pair.zeta()) == pytest.approx(zeta)
    assert float(v[1, 0].detach()) == pytest.approx(h.pair.restitution(), rel=0.03)
    assert (h.pair.restitution() > 1) == (zeta < 0)           # "any": energy may be created


def test_a_disc_resting_on_the_floor_stays_there():
    h = head(n=1, n_types=1)
    with torch.no_grad():
        h.field.copy_(torch.tensor([0.0, -1.0]) * DT * DT / 1e-3)
        h.wall.damping.fill_(0.7)
    x = torch.tensor([[0.5, 0.0199]], dtype=torch.float64)     # on the floor, radius 0.02
    window = torch.stack([x] * 4)
    for _ in range(200):
        g = graph(window[-4:], [0.02], [0], box=1.0)
        acc, _ = h(g)
        nxt = 2 * window[-1] - window[-2] + acc * DT * DT
        window = torch.cat([window, nxt[None]])
    assert abs(float(window[-1, 0, 1]) - 0.02) < 0.002       # neither sunk nor launched


def test_translation_and_permutation():
    h = head(n=3, n_types=2)
    with torch.no_grad():
        h.field.copy_(torch.tensor([0.0, -1.0]) * DT * DT / 1e-3)
    window = free_fall([[0.40, 0.50], [0.44, 0.51], [0.6, 0.3]],
                       [[0.5, 0.2], [-0.5, -0.3], [0.1, 0.0]], [0.0, -1.0])
    radii, types = [0.02, 0.03, 0.02], [0, 1, 0]
    acc, _ = h(graph(window, radii, types, box=None))
    shifted, _ = h(graph(window + torch.tensor([3.0, -2.0], dtype=torch.float64), radii, types,
                         box=None))
    torch.testing.assert_close(shifted, acc)
    perm = [2, 0, 1]
    permuted, _ = h(graph(window[:, perm], [radii[p] for p in perm], [types[p] for p in perm],
                          box=None))
    torch.testing.assert_close(permuted, acc[perm])


def test_without_radii_the_measured_distances_are_used_and_their_absence_named():
    h = head()
    window = free_fall([[0.40, 0.50], [0.44, 0.51]], [[0.5, 0.2], [-0.5, -0.3]], [0.0, 0.0])
    g = graph(window, [0.0, 0.0], [0, 1])
    with pytest.raises(ValueError, match="no contact distances"):
        h(g)
    h.set_reach([[0.04, 0.05], [0.05, 0.06]], [0.02, 0.03])
    with_radii, _ = h(graph(window, [0.02, 0.03], [0, 1]))
    measured, _ = h(g)
    torch.testing.assert_close(measured, with_radii)


def test_the_label_says_whether_radii_were_given_and_old_checkpoints_load():
    """What the model was given: radii where the data have them, else the contact distances
    it measured; a state saved before the flag (all trained on data with radii) still loads."""
    from bgn.model.newton import head_given, head_label

    h = head()
    assert head_given(h) == ("radii", "types") and "(radii, types)" in head_label(h)
    h.set_reach([[0.04, 0.05], [0.05, 0.06]], [0.02, 0.03], radii_given=False)
    assert head_given(h) == ("types",) and "contact distances measured" in head_label(h)
    state = h.state_dict()
    del state["radii_given"]
    old = head()
    old.load_state_dict(state)
    assert bool(old.radii_given)
    torch.testing.assert_close(old.pair_reach, h.pair_reach)
