"""``EdgeMLP.fused`` (``bgn.model.fused_edges``, the backward written out) against the plain
concatenated MLP on every edge: sums, per-block residual outputs and every gradient, in
float64, with and without recomputation; and where the fused path is taken."""

from __future__ import annotations

import pytest
import torch

from bgn.model.message_passing import MAX_EDGE_BLOCKS, CheckpointEdges
from bgn.model.ops import EdgeMLP
from tests.model.conftest import random_graph

TOL = dict(rtol=1e-5, atol=1e-5)


def plain_phi(mlp: EdgeMLP, e, x, edge_index, hidden_only=False):
    snd, rcv = edge_index
    layers = mlp.rest[:-1] if hidden_only else mlp.rest
    return layers(mlp.first(torch.cat([e, x[rcv], x[snd]], dim=1)))


def edges(n=40, seed=0):
    return random_graph(n, kind="radius", seed=seed, cutoff=1.2).edge_index


def inputs(n_edges, edge_in, n=40, node_in=4, seed=3):
    gen = torch.Generator().manual_seed(seed)
    e = torch.randn(n_edges, edge_in, generator=gen, dtype=torch.float64, requires_grad=True)
    x = torch.randn(n, node_in, generator=gen, dtype=torch.float64, requires_grad=True)
    return e, x


@pytest.mark.parametrize("recompute", [False, True])
@pytest.mark.parametrize("block", [7, 1000])
def test_fused_residual_update_equals_the_plain_interaction(recompute, block):
    """GNS's edge update: sums of ``phi`` at the receivers and ``e + phi`` per block, with a
    loss that reads the sums and only every other block's outputs (the others get no
    gradient), against the plain MLP on the concatenated edges."""
    torch.manual_seed(0)
    mlp = EdgeMLP(6, 4, [10, 12, 6], "relu", layer_norm=True).double()
    mlp.edge_block = block
    if recompute:
        mlp.edge_chunk, mlp.checkpoint_edges = 1, CheckpointEdges(0, 0)
    ei = edges()
    e, x = inputs(ei.shape[1], 6)
    slices = mlp.block_slices(e)
    assert len(slices) == -(-ei.shape[1] // block)
    weight = torch.linspace(-1, 1, 6, dtype=torch.float64)

    def loss(sums, outputs):
        return sums.square().sum() + sum((y * weight).sum() for y in outputs[::2])

    fused = mlp.fused([e[s] for s in slices], x, ei, slices, residual=True)
    assert fused is not None
    sums, outputs = fused
    phi = plain_phi(mlp, e, x, ei)
    plain_sums = phi.new_zeros(40, 6).index_add(0, ei[1], phi)
    plain_outputs = [(e + phi)[s] for s in slices]
    torch.testing.assert_close(sums, plain_sums, **TOL)
    torch.testing.assert_close(torch.cat(outputs), torch.cat(plain_outputs), **TOL)
    params = [e, x, *mlp.parameters()]
    got = torch.autograd.grad(loss(sums, outputs), params)
    want = torch.autograd.grad(loss(plain_sums, plain_outputs), params)
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, **TOL)


@pytest.mark.parametrize("hidden_only", [False, True])
def test_fused_sums_without_layer_norm_equal_the_plain_messages(hidden_only):
    """cranmer_gn's case: ReLU after every hidden layer, no LayerNorm, the sums only (of the
    last hidden layer with ``hidden_only``); the edge features need no gradient."""
    torch.manual_seed(1)
    mlp = EdgeMLP(3, 4, [10, 20, 5], "relu").double()
    mlp.edge_block = 5
    ei = edges(seed=2)
    e, x = inputs(ei.shape[1], 3)
    e = e.detach()
    slices = mlp.block_slices(e)
    sums, outputs = mlp.fused([e[s] for s in slices], x, ei, slices, hidden_only=hidden_only)
    assert outputs == []
    phi = plain_phi(mlp, e, x, ei, hidden_only)
    plain = phi.new_zeros(40, phi.shape[1]).index_add(0, ei[1], phi)
    torch.testing.assert_close(sums[:, :phi.shape[1]], plain, **TOL)
    assert torch.all(sums[:, phi.shape[1]:] == 0)  # the zero-padded hidden channels
    params = [x, *mlp.parameters()]
    got = torch.autograd.grad(sums.square().sum(), params, allow_unused=True)
    want = torch.autograd.grad(plain.square().sum(), params, allow_unused=True)
    for g, w in zip(got, want, strict=True):
        if w is None:  # the output layer, unused with hidden_only
            assert g is None or torch.all(g == 0)
        else:
            torch.testing.assert_close(g, w, **TOL)


def test_fused_path_on_an_empty_graph_and_without_gradients():
    mlp = EdgeMLP(3, 4, [8, 8], "relu", layer_norm=True).double()
    mlp.edge_block = 4
    _, x = inputs(0, 3)
    e = torch.zeros(0, 3, dtype=torch.float64)
    ei = torch.zeros(2, 0, dtype=torch.int64)
    slices = mlp.block_slices(e)
    sums, _ = mlp.fused([e[s] for s in slices], x, ei, slices)
    assert sums.shape == (40, 8) and torch.all(sums == 0)
    sums.sum().backward()                        # gradients exist and are zero
    assert torch.all(x.grad == 0)
    ei = edges()
    e, x = inputs(ei.shape[1], 3)
    slices = mlp.block_slices(e)
    with torch.no_grad():
        sums, _ = mlp.fused([e[s] for s in slices], x, ei, slices)
    assert not sums.requires_grad
    phi = plain_phi(mlp, e, x, ei)
    torch.testing.assert_close(sums, phi.new_zeros(40, 8).index_add(0, ei[1], phi), **TOL)


def test_the_fused_path_is_taken_only_where_it_applies():
    """ReLU, blocks on, a CPU: fused, and its blocks are not capped (no node-sized cost per
    block). Another activation or no blocks: None (the caller runs ``blocks``), capped."""
    ei = edges()
    n_edges = ei.shape[1]
    assert n_edges > MAX_EDGE_BLOCKS
    e, x = inputs(n_edges, 3)
    relu = EdgeMLP(3, 4, [8, 8], "relu").double()
    relu.edge_block = 1
    slices = relu.block_slices(e)
    assert len(slices) == n_edges
    assert relu.fused([e[s] for s in slices], x, ei, slices) is not None
    soft = EdgeMLP(3, 4, [8, 8], "softplus").double()
    soft.edge_block = 1
    slices = soft.block_slices(e)
    assert len(slices) <= MAX_EDGE_BLOCKS
    assert soft.fused([e[s] for s in slices], x, ei, slices) is None
    relu.edge_block = None
    assert relu.fused([e], x, ei, [slice(0, n_edges)]) is None
