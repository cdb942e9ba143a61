"""Edge-list operations against dense matrices."""

from __future__ import annotations

import pytest
import torch

from bgn.model.ops import activation, gcn_aggregate, mlp, pad_features, scatter_sum


def test_scatter_sum_matches_loop():
    src = torch.arange(12.0).reshape(6, 2)
    index = torch.tensor([0, 2, 0, 1, 2, 2])
    out = scatter_sum(src, index, 4)
    expected = torch.zeros(4, 2)
    for s, i in zip(src, index, strict=True):
        expected[i] += s
    torch.testing.assert_close(out, expected)


def test_scatter_sum_empty():
    out = scatter_sum(torch.zeros(0, 3), torch.zeros(0, dtype=torch.long), 5)
    assert out.shape == (5, 3) and not out.any()


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("normalize", [False, True])
def test_gcn_aggregate_is_a_hat_h(weighted, normalize):
    """Â H with Â = A + I, A[i, j] = weight of edge j -> i; optional D^-1/2 Â D^-1/2."""
    gen = torch.Generator().manual_seed(0)
    n = 7
    adj = (torch.rand(n, n, generator=gen) < 0.4).double() * (1 - torch.eye(n))
    if weighted:
        adj = adj * torch.rand(n, n, generator=gen).double()
    rcv, snd = adj.nonzero(as_tuple=True)
    edge_index = torch.stack([snd, rcv])
    h = torch.randn(n, 5, generator=gen).double()
    w = adj[rcv, snd] if weighted else None
    a_hat = (adj != 0).double() * (adj if weighted else 1.0) + torch.eye(n)
    if normalize:
        d = a_hat.sum(1).rsqrt()
        a_hat = d[:, None] * a_hat * d[None, :]
    torch.testing.assert_close(gcn_aggregate(h, edge_index, w, normalize), a_hat @ h)


def test_pad_features_is_fixed_projection():
    x = torch.randn(3, 4)
    assert torch.equal(pad_features(x, 4), x)
    assert torch.equal(pad_features(x, 6)[:, :4], x) and not pad_features(x, 6)[:, 4:].any()
    assert torch.equal(pad_features(x, 2), x[:, :2])


def test_mlp_and_activation():
    net = mlp([3, 8, 2], "silu", layer_norm=True)
    assert net(torch.randn(5, 3)).shape == (5, 2)
    with pytest.raises(ValueError, match="unknown activation"):
        activation("swishy")
