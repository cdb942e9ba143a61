"""Symmetries: translation invariance, permutation equivariance, batching = graphs alone."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from bgn.graph import collate
from bgn.model import BGN, ModelConfig, ModelOutput
from tests.model.conftest import permute_graph

NODE_FIELDS = ("target", "type_logits", "mass_nll", "log_mass_sample")
EDGE_FIELDS = ("contact", "relmass", "edge_weight")
SCENES = [  # interaction, graph kind, n_types, model options
    ("pairwise", "full", 3, {}),
    ("contact", "radius", 2, {}),
    ("contact", "radius", 2, {"contact_message": "mlp"}),
    ("contact", "radius", 2, {"contact_message": "vector"}),
]


def build(meta, stats, interaction, kind, n_types, n=7, **overrides) -> BGN:
    torch.manual_seed(1)
    cfg = ModelConfig(hidden=16, decoder_hidden=16, flow_hidden=8, flow_transforms=2,
                      **overrides)
    return BGN(meta(n, n_types, interaction, kind), stats(), 2, cfg).double()


def assert_outputs_close(a: ModelOutput, b: ModelOutput, node=None, edge=None) -> None:
    for name in NODE_FIELDS + EDGE_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is None:
            continue
        index = node if name in NODE_FIELDS else edge
        torch.testing.assert_close(x if index is None else x[index], y, atol=1e-9, rtol=1e-9,
                                   msg=name)


@pytest.mark.parametrize(("interaction", "kind", "n_types", "overrides"), SCENES)
def test_translation_invariance(meta, stats, graph, interaction, kind, n_types, overrides):
    model = build(meta, stats, interaction, kind, n_types, **overrides)
    g = graph(7, n_types=n_types, kind=kind, contact=interaction == "contact", seed=2)
    assert g.edge_index.shape[1] > 0
    noise = torch.randn(7, dtype=torch.float64)
    shifted = replace(g, pos=g.pos + torch.tensor([13.25, -4.5], dtype=torch.float64))
    assert_outputs_close(model(g, noise), model(shifted, noise))
    torch.testing.assert_close(model.predict(g), model.predict(shifted))


def test_absolute_position_option_breaks_translation_invariance(meta, stats, graph):
    model = build(meta, stats, "pairwise", "full", 2, use_absolute_position=True)
    g = graph(7, seed=2)
    shifted = replace(g, pos=g.pos + 3.0)
    assert not torch.allclose(model.predict(g), model.predict(shifted))


@pytest.mark.parametrize(("interaction", "kind", "n_types", "overrides"), SCENES)
def test_permutation_equivariance(meta, stats, graph, interaction, kind, n_types, overrides):
    model = build(meta, stats, interaction, kind, n_types, **overrides)
    g = graph(7, n_types=n_types, kind=kind, contact=interaction == "contact", seed=4)
    permuted, perm, edge_perm = permute_graph(g)
    noise = torch.randn(7, dtype=torch.float64)
    assert_outputs_close(model(g, noise), model(permuted, noise[perm]), perm, edge_perm)
    a = model.loss_terms(g, model(g, noise))
    b = model.loss_terms(permuted, model(permuted, noise[perm]))
    for key in a:
        torch.testing.assert_close(a[key], b[key], msg=key)


@pytest.mark.parametrize(("interaction", "kind", "n_types", "overrides"), [
    ("pairwise", "full", 3, {}),
    ("contact", "radius", 2, {"degree_normalize": True}),
    ("contact", "radius", 2, {"contact_message": "mlp"}),
    ("contact", "radius", 2, {"contact_message": "vector"}),
    ("pairwise", "full", 2, {"contact_mode": "dense"}),
])
def test_batch_equals_graphs_alone(meta, stats, graph, interaction, kind, n_types, overrides):
    model = build(meta, stats, interaction, kind, n_types, **overrides)
    box = 6.0 if interaction == "contact" else None
    if box is not None:
        model = BGN(replace(model.meta, box=box), stats(), 2, model.cfg).double()
    graphs = [graph(7, n_types=n_types, kind=kind, contact=interaction == "contact",
                    box=box, seed=s) for s in (10, 11)]
    noises = [torch.randn(7, dtype=torch.float64) for _ in graphs]
    batch = collate(graphs)
    out = model(batch, torch.cat(noises))
    n0, e0 = 7, graphs[0].edge_index.shape[1]
    node_slices = [slice(0, n0), slice(n0, None)]
    edge_slices = [slice(0, e0), slice(e0, None)]
    for g, noise, ns, es in zip(graphs, noises, node_slices, edge_slices, strict=True):
        alone = model(g, noise)
        for name in NODE_FIELDS + EDGE_FIELDS:
            x = getattr(out, name)
            if x is not None:
                s = ns if name in NODE_FIELDS else es
                torch.testing.assert_close(x[s], getattr(alone, name), msg=name)


def test_contact_edge_term_is_symmetric(meta, stats, graph):
    """With the edge term the contact logit of j -> i still equals that of i -> j."""
    model = build(meta, stats, "contact", "full", 2, contact_edge_term=True)
    g = graph(7, contact=True, seed=6)
    out = model(g)
    snd, rcv = g.edge_index
    code = rcv * 7 + snd
    reverse = torch.argsort(code)[torch.searchsorted(code.sort().values, snd * 7 + rcv)]
    torch.testing.assert_close(out.contact, out.contact[reverse])
