"""Model only what the scene needs; loss keys; the dense ablation; building from a dict."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bgn.graph import collate
from bgn.model import BGN, LOSS_KEYS, ModelConfig, build_model
from bgn.model.encoder import edge_input_dim


def names(model: BGN) -> list[str]:
    return [name for name, _ in model.named_parameters()]


def small(**overrides) -> ModelConfig:
    return ModelConfig(hidden=16, decoder_hidden=16, flow_hidden=8, flow_transforms=2,
                       **overrides)


def test_full_model_has_every_head(meta, stats, graph):
    model = BGN(meta(6, 3), stats(), 2, small()).double()
    # every task head of the paper; "unroll" comes from the data (dataset.unroll), and
    # "impulse_mass" and "law" with the structured head (tests/model/test_newton.py)
    paper = frozenset(LOSS_KEYS) - {"unroll", "impulse_mass", "law"}
    assert model.heads == paper
    assert any(n.startswith("processor.classifier") for n in names(model))
    assert any(n.startswith("processor.contact") for n in names(model))
    assert any(n.startswith("inverse.flow") for n in names(model))
    g = graph(6, n_types=3)
    terms = model.loss_terms(g, model(g))
    assert set(terms) == paper
    assert all(t.ndim == 0 and torch.isfinite(t) for t in terms.values())
    total = model.total_loss(terms)
    torch.testing.assert_close(total, sum(terms.values()))


def test_loss_weights(meta, stats, graph):
    model = BGN(meta(6, 3), stats(), 2, small(loss_weights={"dynamics": 2.0, "type": 0.0}))
    model = model.double()
    g = graph(6, n_types=3)
    terms = model.loss_terms(g, model(g))
    expected = 2 * terms["dynamics"] + terms["contact"] + terms["mass_nll"] + terms["relmass"]
    torch.testing.assert_close(model.total_loss(terms), expected)
    with pytest.raises(ValueError, match="unknown loss weights"):
        ModelConfig(loss_weights={"dynamic": 1.0})


def test_one_type_has_no_classifier(meta, stats, graph):
    model = BGN(meta(6, 1), stats(), 2, small(classifier=True)).double()
    assert model.processor.classifier is None
    assert not any("classifier" in n for n in names(model))
    g = graph(6, n_types=1)
    out = model(g)
    assert out.type_logits is None and "type" not in model.loss_terms(g, out)


def test_classifier_off(meta, stats):
    model = BGN(meta(6, 3), stats(), 2, small(classifier=False))
    assert not any("classifier" in n for n in names(model)) and "type" not in model.heads


def test_no_contact_head(meta, stats, graph):
    model = BGN(meta(6, 2), stats(), 2, small(contact=False)).double()
    assert model.processor.contact is None
    assert not any(n.startswith("processor.contact") for n in names(model))
    g = graph(6)
    out = model(g)
    assert out.contact is None and "contact" not in model.loss_terms(g, out)


def test_no_inverse(meta, stats, graph):
    model = BGN(meta(6, 2), stats(), 2, small(inverse=False)).double()
    assert model.inverse is None
    assert not any("inverse" in n or "flow" in n for n in names(model))
    g = graph(6)
    out = model(g)
    assert out.mass_nll is None and out.relmass is None
    assert not {"mass_nll", "relmass"} & set(model.loss_terms(g, out))
    with pytest.raises(RuntimeError, match="no inverse head"):
        model.sample_mass(g, 2)


def test_contact_scene_uses_probabilities(meta, stats, graph):
    """Contact scenes: logits out, BCE-with-logits against 0/1 targets."""
    model = BGN(meta(6, 2, "contact"), stats(), 2, small()).double()
    g = graph(6, contact=True)
    out = model(g)
    expected = torch.nn.functional.binary_cross_entropy_with_logits(out.contact, g.edge_contact)
    torch.testing.assert_close(model.loss_terms(g, out)["contact"], expected)


def test_contact_bce_balances_rare_contacts(meta, stats, graph):
    """About 1 % of candidate edges touch: with ``balanced`` the positive class weighs
    (1 - p) / p; the default is the paper's plain BCE."""
    rare = stats()
    rare["contact"] = {**rare["contact"], "mean": np.array([0.01])}
    model = BGN(meta(6, 2, "contact"), rare, 2, small(contact_pos_weight="balanced")).double()
    assert float(model.contact_pos_weight) == pytest.approx(99.0)
    g = graph(6, contact=True)
    out = model(g)
    expected = torch.nn.functional.binary_cross_entropy_with_logits(
        out.contact, g.edge_contact, pos_weight=torch.tensor(99.0, dtype=torch.float64))
    torch.testing.assert_close(model.loss_terms(g, out)["contact"], expected)
    plain = BGN(meta(6, 2, "contact"), rare, 2, small())
    assert float(plain.contact_pos_weight) == 1.0
    assert "contact_pos_weight" not in model.state_dict()  # rebuilt from the statistics
    with pytest.raises(ValueError, match="contact_pos_weight"):
        small(contact_pos_weight=-1.0)


def test_force_scene_contact_target_is_compressed(meta, stats, graph):
    model = BGN(meta(6, 2), stats(), 2, small()).double()
    g = graph(6)
    c = model.contact_target(g)
    torch.testing.assert_close(c, torch.log1p(g.edge_contact / 0.8))
    linear = BGN(meta(6, 2), stats(), 2, small(force_transform="linear")).double()
    torch.testing.assert_close(linear.contact_target(g), g.edge_contact / 0.8)


def test_graph_without_edges(meta, stats, graph):
    """A radius graph may have no edges at all: losses stay finite."""
    model = BGN(meta(4, 2, "contact", "radius"), stats(), 2, small()).double()
    g = graph(4, kind="radius", contact=True, cutoff=1e-9)
    assert g.edge_index.shape[1] == 0
    terms = model.loss_terms(g, model(g))
    assert all(torch.isfinite(t) for t in terms.values())
    model.total_loss(terms).backward()


def test_dense_contact_mode_on_full_graph(meta, stats, graph):
    model = BGN(meta(6, 2), stats(), 2, small(contact_mode="dense")).double()
    assert model.processor.contact.message is None          # no message map in this mode
    assert model.processor.out_features == 16 + 2 + 6       # H_V ‖ Ŷ ‖ row of Ĉ
    batch = collate([graph(6, seed=0), graph(6, seed=1)])
    out = model(batch)
    assert out.target.shape == (12, 2)
    model.total_loss(model.loss_terms(batch, out)).backward()


def test_dense_contact_mode_rejects_radius_graphs(meta, stats, graph):
    with pytest.raises(ValueError, match="full graph"):
        BGN(meta(6, 2, "contact", "radius"), stats(), 2, small(contact_mode="dense"))
    model = BGN(meta(6, 2), stats(), 2, small(contact_mode="dense")).double()
    with pytest.raises(ValueError, match="contact_mode='dense'.*N=6"):
        model(graph(5))                                      # another N
    with pytest.raises(ValueError, match="contact_mode='dense'"):
        model(graph(6, kind="radius", cutoff=1.0))           # not complete


def test_history_mismatch_is_clear(meta, stats, graph):
    model = BGN(meta(6, 2), stats(), 3, small())
    with pytest.raises(ValueError, match="velocity window"):
        model(graph(6, history=2, dtype=torch.float32))


def test_build_model_from_config_dict(meta, stats):
    config = {"name": "bgn", "hidden": 16, "flow": "naf",
              "loss_weights": {"dynamics": 1.0, "contact": 0.5, "type": 1.0, "mass_nll": 1.0,
                               "relmass": 1.0}}
    model = build_model(config, meta(6, 2), stats(), 2)
    assert isinstance(model, BGN) and model.cfg.flow == "naf"
    assert model.loss_weights["contact"] == 0.5
    with pytest.raises(ValueError, match="unknown bgn model options.*hiden"):
        build_model({"name": "bgn", "hiden": 16}, meta(6, 2), stats(), 2)
    with pytest.raises(ValueError, match="unknown model"):
        build_model({"name": "nope"}, meta(6, 2), stats(), 2)


def test_complete_graph_node_features_need_self_weight(meta, stats, graph):
    """Eq. 1 on a complete graph: Â = 11ᵀ, so H_V is one row repeated; ``self_weight`` fixes it."""
    g = graph(6)
    for self_weight, identical in ((False, True), (True, False)):
        model = BGN(meta(6, 2), stats(), 2,
                    small(self_weight=self_weight, velocity_increments=False)).double()
        x = model.normalizer.velocity(g.vel).flatten(1)
        h_v = model.node_encoder(x, g.edge_index)
        assert torch.allclose(h_v, h_v[:1].expand_as(h_v)) == identical


def test_contact_message_mlp_reads_both_particles(meta, stats, graph):
    """An elastic impulse depends on both masses: the MLP message sees H̃_V of both ends, the
    linear message only the edge features. Both are weighted by the contact estimate."""
    g = graph(6, contact=True)
    for message, reads_nodes in (("linear", False), ("mlp", True)):
        model = BGN(meta(6, 2, "contact"), stats(), 2, small(contact_message=message)).double()
        head = model.processor.contact
        e = torch.randn(g.edge_index.shape[1], edge_input_dim(2, 2), dtype=torch.float64)
        c = torch.randn(e.shape[0], dtype=torch.float64)
        h = torch.randn(6, model.processor.tilde_v_features, dtype=torch.float64)
        a = head.aggregate(c, e, g.edge_index, h)
        assert a.shape == (6, model.cfg.hidden)
        assert torch.allclose(a, head.aggregate(c, e, g.edge_index, h + 1.0)) != reads_nodes
        # no contact anywhere (probabilities -> 0): nothing is aggregated
        none = head.aggregate(torch.full_like(c, -1e4), e, g.edge_index, h)
        torch.testing.assert_close(none, torch.zeros_like(none))


def test_unknown_contact_message_is_clear(meta, stats):
    with pytest.raises(ValueError, match="contact_message='conv'"):
        small(contact_message="conv")


def test_vector_message_is_an_impulse_in_the_pairs_plane(meta, stats, graph):
    """An elastic impulse acts along the contact normal, which within a frame lies in the
    plane of x_i - x_j and v_i - v_j. In 3D with a one-step window the vector message of an
    isolated pair must stay in that plane, whatever the network's weights; with no contact it
    vanishes and the forward target is the decoder's alone."""
    torch.manual_seed(0)
    model = BGN(meta(2, 2, "contact", "radius", dim=3), stats(3), 0,
                small(contact_message="vector")).double()
    g = graph(2, dim=3, history=0, kind="radius", contact=True, cutoff=10.0, seed=3)
    assert g.edge_index.shape[1] == 2
    p, _, x = model._process(g)
    assert p.impulse is not None and p.impulse.shape == (2, 3)
    assert p.impulse.abs().max() > 1e-6
    normal = torch.linalg.cross(g.pos[0] - g.pos[1], g.vel[0, 0] - g.vel[1, 0])
    cosine = (p.impulse @ normal) / (p.impulse.norm(dim=-1) * normal.norm())
    torch.testing.assert_close(cosine, torch.zeros_like(cosine), atol=1e-10, rtol=0)
    head = model.processor.contact
    e = torch.randn(2, edge_input_dim(3, 0), dtype=torch.float64)
    h = torch.randn(2, model.processor.tilde_v_features, dtype=torch.float64)
    none = head.aggregate(torch.full((2,), -1e4, dtype=torch.float64), e, g.edge_index, h)
    torch.testing.assert_close(none, torch.zeros_like(none))
    # the impulse is added to the decoded target (Eq. 5 + sum_j ĉ_ij m_ij)
    decoded = model.decoder(torch.cat([p.h_cv, x], -1))
    torch.testing.assert_close(model(g).target, decoded + p.impulse)
