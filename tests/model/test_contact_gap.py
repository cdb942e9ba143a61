"""The window's time-of-impact rule (``encoder.approach_gap``) and BGN's option to give it to
the contact head (``contact_gap``)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from bgn.model import BGN, ModelConfig
from bgn.model.encoder import approach_gap
from tests.model.conftest import permute_graph


def pair(dx: float, dv: float, dt: float = 0.1, radius: float = 0.1):
    """Two discs on a line, 2*radius + dx apart, closing at speed dv (newest velocity)."""
    pos = torch.tensor([[0.0, 0.0], [2 * radius + dx, 0.0]], dtype=torch.float64)
    vel = torch.zeros(2, 2, 2, dtype=torch.float64)
    vel[1, 0, 0] = -dv
    return pos, vel, torch.tensor([[0, 1], [1, 0]]), dt, radius


def gap_of(dx: float, dv: float, dt: float = 0.1, radius: float = 0.1, graph=None) -> torch.Tensor:
    pos, vel, edges, dt, radius = pair(dx, dv, dt, radius)
    g = replace(graph(2, history=1), pos=pos, vel=vel, edge_index=edges,
                radius=torch.full((2,), radius, dtype=torch.float64),
                dt=torch.tensor([dt], dtype=torch.float64))
    return approach_gap(g)


@pytest.mark.parametrize(("dx", "dv", "touch"), [
    (0.05, 1.0, True),     # closes 0.1 in the frame, 0.05 apart: touches
    (0.05, 0.4, False),    # closes only 0.04
    (0.05, -1.0, False),   # moving apart
    (0.0, 0.0, True),      # resting in contact
    (0.3, 10.0, True),     # fast: passes through the contact within the frame
])
def test_the_rule_says_whether_a_pair_touches_within_the_frame(graph, dx, dv, touch):
    gap = gap_of(dx, dv, graph=graph)
    assert ((gap <= 1e-6).tolist() == [touch, touch])
    assert torch.allclose(gap[0], gap[1])  # the same for both directions of the edge


def test_the_gap_is_the_closest_approach_over_the_contact_distance(graph):
    # 0.3 apart (gap 0.3 / 0.2 = 1.5 contact distances) closing 1.0 in dt=0.1: 0.2 left
    assert gap_of(0.3, 1.0, graph=graph)[0].item() == pytest.approx(1.0, rel=1e-6)


def test_gap_is_permutation_equivariant(graph):
    g = graph(7, history=2, kind="radius", contact=True, box=4.0)
    h, _, edge_perm = permute_graph(g)
    torch.testing.assert_close(approach_gap(h), approach_gap(g)[edge_perm])


def test_contact_gap_feeds_the_contact_edge_term(meta, stats, graph):
    torch.manual_seed(0)
    scene = meta(7, 2, "contact", "radius", box=4.0)
    small = dict(hidden=16, decoder_hidden=16, flow_hidden=16)
    plain = BGN(scene, stats(), 2, ModelConfig(**small)).double()
    with_gap = BGN(scene, stats(), 2, ModelConfig(**small, contact_gap=True)).double()
    width = plain.processor.contact.edge_term.in_features
    assert with_gap.processor.contact.edge_term.in_features == width + 2
    g = graph(7, history=2, kind="radius", contact=True, box=4.0)
    out = with_gap(g)
    loss = with_gap.total_loss(with_gap.loss_terms(g, out))
    loss.backward()
    assert torch.isfinite(loss)
    # moving the particles' newest velocities changes the gap, hence the contact logits
    faster = replace(g, vel=g.vel * 3)
    assert not torch.allclose(with_gap(faster).contact, out.contact)
    with pytest.raises(ValueError, match="contact_edge_term"):
        BGN(scene, stats(), 2, ModelConfig(**small, contact_gap=True, contact_edge_term=False))
