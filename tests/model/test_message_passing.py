"""The fast kernels against the plain formulas they replace, in float64 (to 1e-5, in practice
round-off): the sparse products of ``bgn.model.message_passing``, the edge MLP's accumulated
first layer, its chunked checkpointing and its blocks, and every model's loss and gradients
with all of them swapped back to the gather / ``index_add_`` / concatenation forms."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from torch.nn import functional as F

import bgn.model.encoder as encoder
import bgn.model.ops as ops
import bgn.model.processor as processor
from bgn.model import build_model
from bgn.model.baselines import InteractionNetwork
from bgn.model.impulse import ContactImpulseHead
from bgn.model.message_passing import (
    MAX_EDGE_BLOCKS,
    CheckpointEdges,
    adjacency,
    edge_blocks,
    edge_chunks,
    edge_difference,
    edge_dot,
    edge_sums,
    spmm,
)
from bgn.model.ops import EdgeMLP
from tests.model.conftest import fake_stats, make_meta, random_graph

TOL = dict(rtol=1e-5, atol=1e-5)


def naive_spmm(h, edge_index, w=None):
    snd, rcv = edge_index
    msg = h[snd] if w is None else h[snd] * w[:, None]
    return torch.zeros_like(h).index_add(0, rcv, msg)


def naive_edge_dot(a, b, edge_index):
    snd, rcv = edge_index
    return (a[rcv] * b[snd]).sum(-1)


def naive_gcn_aggregate(h, edge_index, edge_weight=None, normalize=False):
    """``gcn_aggregate`` as it was: gather, weight, scatter."""
    snd, rcv = edge_index
    n = h.shape[0]
    if edge_weight is None:
        edge_weight = h.new_ones(snd.shape[0])
    self_weight = None
    if normalize:
        deg = 1.0 + torch.zeros(n, dtype=h.dtype).index_add(0, rcv, edge_weight)
        inv_sqrt = deg.rsqrt()
        edge_weight = inv_sqrt[rcv] * edge_weight * inv_sqrt[snd]
        self_weight = (inv_sqrt * inv_sqrt)[:, None]
    out = naive_spmm(h, edge_index, edge_weight)
    return (h if self_weight is None else self_weight * h) + out


def naive_edge_mlp(self, e, x, edge_index):
    """``EdgeMLP.forward`` as the plain concatenation ``phi([e, x_i, x_j])``, one chunk."""
    snd, rcv = edge_index
    return self.rest(self.first(torch.cat([e, x[rcv], x[snd]], dim=1)))


def naive_blocks(self, e_blocks, x, edge_index, slices, hidden_only=False):
    """``EdgeMLP.blocks`` as the plain concatenation on each block."""
    layers = self.rest[:-1] if hidden_only else self.rest
    for e, s in zip(e_blocks, slices, strict=True):
        snd, rcv = edge_index[:, s]
        yield layers(self.first(torch.cat([e, x[rcv], x[snd]], dim=1)))


def naive_sum_at_receivers(self, e, x, edge_index, n):
    """``EdgeMLP.sum_at_receivers`` as the plain messages of every edge, summed."""
    m = naive_edge_mlp(self, e, x, edge_index)
    return m.new_zeros(n, m.shape[1]).index_add(0, edge_index[1], m)


def naive_interaction(self, v, e, edge_index, slices):
    """GNS's ``InteractionNetwork.forward`` on the whole edge list: ``e' = e + phi_e``, nodes
    sum the updated edges."""
    e = torch.cat(e)
    de = naive_edge_mlp(self.edge, e, v, edge_index)
    summed = de.new_zeros(v.shape[0], de.shape[1]).index_add(0, edge_index[1], de)
    return v + self.node(torch.cat([v, summed], dim=1)), [e + de]


def radius_edges(n=40, seed=0, shuffle=False):
    g = random_graph(n, kind="radius", seed=seed, cutoff=1.2)
    e = g.edge_index
    if shuffle:
        e = e[:, torch.randperm(e.shape[1], generator=torch.Generator().manual_seed(seed))]
    return e


@pytest.mark.parametrize("shuffle", [False, True])
def test_spmm_and_edge_dot_match_gathers_and_their_gradients(shuffle):
    e = radius_edges(shuffle=shuffle)
    assert e.shape[1] > 50
    gen = torch.Generator().manual_seed(1)
    h = torch.randn(40, 6, generator=gen, dtype=torch.float64, requires_grad=True)
    b = torch.randn(40, 6, generator=gen, dtype=torch.float64, requires_grad=True)
    w = torch.rand(e.shape[1], generator=gen, dtype=torch.float64, requires_grad=True)
    torch.testing.assert_close(spmm(h, e, w), naive_spmm(h, e, w), **TOL)
    torch.testing.assert_close(spmm(h, e), naive_spmm(h, e), **TOL)
    torch.testing.assert_close(edge_dot(h, b, e), naive_edge_dot(h, b, e), **TOL)
    assert torch.autograd.gradcheck(lambda h, w: spmm(h, e, w), (h, w))
    assert torch.autograd.gradcheck(lambda a, b: edge_dot(a, b, e), (h, b))


def test_kernels_on_an_empty_edge_list():
    e = torch.zeros(2, 0, dtype=torch.long)
    h = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    out = spmm(h, e, torch.zeros(0, dtype=torch.float64))
    assert out.shape == (5, 3) and not out.any()
    assert edge_dot(h, h, e).shape == (0,)
    out.sum().backward()
    assert h.grad is not None and not h.grad.any()


def test_adjacency_is_built_once_per_edge_list():
    e = radius_edges()
    assert adjacency(e, 40) is adjacency(e, 40)
    assert adjacency(e.clone(), 40) is not adjacency(e, 40)


def test_edge_difference_is_receiver_minus_sender():
    e = radius_edges()
    x = torch.randn(40, 3, 2, dtype=torch.float64)
    torch.testing.assert_close(edge_difference(x, e), x[e[1]] - x[e[0]])


@pytest.mark.parametrize("weighted", [False, True])
@pytest.mark.parametrize("normalize", [False, True])
def test_gcn_aggregate_matches_the_gather_scatter_form(weighted, normalize):
    e = radius_edges(shuffle=True)
    gen = torch.Generator().manual_seed(2)
    h = torch.randn(40, 5, generator=gen, dtype=torch.float64)
    w = torch.rand(e.shape[1], generator=gen, dtype=torch.float64) if weighted else None
    torch.testing.assert_close(ops.gcn_aggregate(h, e, w, normalize),
                               naive_gcn_aggregate(h, e, w, normalize), **TOL)


@pytest.mark.parametrize("chunk", [None, 7])
@pytest.mark.parametrize("layer_norm", [False, True])
@pytest.mark.parametrize("act", ["silu", "softplus"])  # softplus(0) != 0 on padded channels
def test_edge_mlp_factored_padded_and_chunked_equals_the_concatenation(chunk, layer_norm, act):
    """Hidden widths 10 and 20 run padded to 16 and 32 (``ops.PAD_WIDTH``)."""
    torch.manual_seed(0)
    mlp = EdgeMLP(3, 4, [10, 20, 5], act, layer_norm).double()
    mlp.edge_chunk = chunk
    e = radius_edges()
    gen = torch.Generator().manual_seed(3)
    ef = torch.randn(e.shape[1], 3, generator=gen, dtype=torch.float64, requires_grad=True)
    x = torch.randn(40, 4, generator=gen, dtype=torch.float64, requires_grad=True)
    fast = mlp(ef, x, e)
    grads = torch.autograd.grad(fast.square().sum(), [ef, x, *mlp.parameters()])
    slow = naive_edge_mlp(mlp, ef, x, e)
    expected = torch.autograd.grad(slow.square().sum(), [ef, x, *mlp.parameters()])
    torch.testing.assert_close(fast, slow, **TOL)
    for got, want in zip(grads, expected, strict=True):
        torch.testing.assert_close(got, want, **TOL)


def test_edge_blocks_cover_the_edges_once():
    assert edge_blocks(10, None) == [slice(0, 10)] and edge_blocks(10, 10) == [slice(0, 10)]
    assert edge_blocks(0, 4) == [slice(0, 0)]
    blocks = edge_blocks(10, 4)
    assert blocks == [slice(0, 4), slice(4, 8), slice(8, 10)]
    # never more than MAX_EDGE_BLOCKS: their node-sized gradients would make O(N E) work
    many = edge_blocks(1000, 1)
    assert len(many) == MAX_EDGE_BLOCKS and many[0].start == 0 and many[-1].stop == 1000
    assert all(a.stop == b.start for a, b in zip(many, many[1:]))


@pytest.mark.parametrize("block", [None, 7])
@pytest.mark.parametrize("layer_norm", [False, True])   # True: no output layer after the sums
@pytest.mark.parametrize("checkpointed", [False, True])
@pytest.mark.parametrize("act", ["relu", "softplus"])    # softplus(0) != 0 on padded channels
def test_edge_mlp_in_blocks_and_summed_equals_the_plain_messages(block, layer_norm,
                                                                  checkpointed, act):
    """``sum_at_receivers`` (blocks, the output layer after the sums) and ``blocks`` against
    the concatenated MLP on every edge, values and gradients, in float64."""
    torch.manual_seed(0)
    mlp = EdgeMLP(3, 4, [10, 20, 5], act, layer_norm).double()
    mlp.edge_block = block
    if checkpointed:
        mlp.edge_chunk, mlp.checkpoint_edges = 1, CheckpointEdges(0, 0)
    e = radius_edges()
    n_edges = e.shape[1]
    gen = torch.Generator().manual_seed(3)
    ef = torch.randn(n_edges, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    x = torch.randn(40, 4, generator=gen, dtype=torch.float64, requires_grad=True)
    params = [ef, x, *mlp.parameters()]
    slices = mlp.block_slices(ef)
    assert len(slices) == (1 if block is None else -(-n_edges // block))
    fast_sum = mlp.sum_at_receivers(ef, x, e, 40)
    fast_blocks = torch.cat(list(mlp.blocks([ef[s] for s in slices], x, e, slices)))
    slow_sum = naive_sum_at_receivers(mlp, ef, x, e, 40)
    slow_blocks = naive_edge_mlp(mlp, ef, x, e)
    for fast, slow in ((fast_sum, slow_sum), (fast_blocks, slow_blocks)):
        torch.testing.assert_close(fast, slow, **TOL)
        grads = torch.autograd.grad(fast.square().sum(), params)
        expected = torch.autograd.grad(slow.square().sum(), params)
        for got, want in zip(grads, expected, strict=True):
            torch.testing.assert_close(got, want, **TOL)


def test_checkpointing_only_above_its_threshold():
    calls = []

    def fn(a):
        calls.append(a.shape[0])
        return a * 2

    a = torch.ones(100, 3)
    assert torch.equal(edge_chunks(fn, 30, (a,), above=100), a * 2) and calls == [100]
    calls.clear()
    assert torch.equal(edge_chunks(fn, 30, (a,), above=99), a * 2) and calls == [30, 30, 30, 10]


def test_a_gpu_has_its_own_checkpointing_threshold(meta, stats):
    """Every module that checkpoints gets both thresholds from the config and reads the GPU's
    for work on a GPU (there checkpointing costs more time than the memory is worth)."""
    model = build_model({"name": "bgn", "contact_message": "vector", "checkpoint_edges": 7,
                         "checkpoint_edges_gpu": 11}, meta(6, 2, "contact", "radius", box=4.0),
                        stats(), 2)
    modules = [m for m in model.modules() if hasattr(m, "checkpoint_edges")]
    assert modules
    for module in modules:
        assert module.checkpoint_edges.above(torch.ones(1)) == 7
        assert module.checkpoint_edges.above(SimpleNamespace(is_cuda=True)) == 11
    with pytest.raises(ValueError, match="checkpoint_edges_gpu=-1 must be >= 0"):
        build_model({"name": "gns", "checkpoint_edges_gpu": -1}, meta(), stats(), 2)


def loss_and_grads(model, g):
    torch.manual_seed(7)  # the same training noise and flow draws in both runs
    loss = model.total_loss(model.loss_terms(g, model(g)))
    return loss, torch.autograd.grad(loss, list(model.parameters()), allow_unused=True)


@pytest.mark.parametrize("name", ["bgn", "bgn_newton", "gns", "cranmer_gn"])
def test_every_model_equals_its_plain_form(monkeypatch, name):
    """Loss and every gradient of each model with the fast kernels against the same model
    with the kernels swapped back to gathers, index_add_ and concatenations (float64);
    ``bgn_newton`` (the collisions default) also with the impulse head's gate on every edge
    in every replayed frame."""
    small = {"bgn": {"hidden": 16, "decoder_hidden": 16, "flow_hidden": 8,
                     "contact_message": "vector", "edge_chunk": 50, "checkpoint_edges": 0},
             "bgn_newton": {"hidden": 16, "decoder_hidden": 20, "flow_hidden": 8,
                            "dynamics": "newton", "edge_chunk": 50, "checkpoint_edges": 0},
             "gns": {"latent": 16, "mlp_hidden": 16, "message_passing_steps": 3,
                     "edge_chunk": 50, "checkpoint_edges": 0, "edge_block": 40},
             "cranmer_gn": {"hidden": 20, "message_dim": 8, "edge_chunk": 50,
                            "checkpoint_edges": 0, "edge_block": 40}}[name]
    meta = make_meta(30, 2, "contact", "radius", box=4.0)
    torch.manual_seed(0)
    model = build_model({"name": name.removesuffix("_newton"), **small}, meta, fake_stats(),
                        2).double().train()
    g = random_graph(30, history=2, kind="radius", contact=True, box=4.0, seed=4, cutoff=1.5)
    assert g.edge_index.shape[1] > 50  # several chunks
    loss, grads = loss_and_grads(model, g)
    if name == "bgn_newton":
        hits = []
        fast_resolve = ContactImpulseHead.resolve

        def plain_resolve(self, g, x, v, dt, every_edge=True):
            out = fast_resolve(self, g, x, v, dt, True)
            if not every_edge:  # a replayed frame: count its impacts
                hits.append(len(out.pairs))
                out = out._replace(logits=None)
            return out

        monkeypatch.setattr(ContactImpulseHead, "resolve", plain_resolve)

    monkeypatch.setattr(ops, "spmm", naive_spmm)
    monkeypatch.setattr(encoder, "gcn_aggregate", naive_gcn_aggregate)
    monkeypatch.setattr(processor, "edge_dot", naive_edge_dot)
    monkeypatch.setattr(EdgeMLP, "forward", naive_edge_mlp)
    monkeypatch.setattr(EdgeMLP, "blocks", naive_blocks)
    monkeypatch.setattr(InteractionNetwork, "forward", naive_interaction)
    monkeypatch.setattr(EdgeMLP, "sum_at_receivers", naive_sum_at_receivers)
    monkeypatch.setattr(encoder, "edge_difference", lambda x, e: x[e[1]] - x[e[0]])
    for module in model.modules():  # and no chunks (the relative-mass decoder has them too)
        if hasattr(module, "edge_chunk"):
            module.edge_chunk = None
        if hasattr(module, "edge_block"):  # nor blocks
            module.edge_block = None
    plain_loss, plain_grads = loss_and_grads(model, g)
    if name == "bgn_newton":  # the replays met impacts (else the gate's subset is empty)
        assert len(hits) == 2 and min(hits) > 0          # history 2: two replays
    torch.testing.assert_close(loss, plain_loss, **TOL)
    for got, want in zip(grads, plain_grads, strict=True):
        if want is None:
            assert got is None
        else:
            torch.testing.assert_close(got, want, **TOL)


def test_activation_in_place_only_where_allowed():
    assert ops.activation("relu", inplace=True).inplace
    # SiLU's backward reads its input: in place, autograd would clone it (no gain)
    assert not ops.activation("silu", inplace=True).inplace
    assert not ops.activation("relu").inplace
    assert isinstance(ops.activation("tanh", inplace=True), torch.nn.Tanh)


def test_mlp_in_place_activations_leave_the_input_alone():
    net = ops.mlp([4, 8, 8, 3], "relu")
    x = torch.randn(5, 4, requires_grad=True)
    before = x.detach().clone()
    net(x).sum().backward()
    torch.testing.assert_close(x.detach(), before)
    torch.testing.assert_close(net(x), F.linear(F.relu(F.linear(F.relu(
        F.linear(x, net[0].weight, net[0].bias)), net[2].weight, net[2].bias)),
        net[4].weight, net[4].bias))


@pytest.mark.parametrize("shape", [(30, 4), (5, 6, 3)])
def test_narrow_linear_equals_f_linear_and_its_gradients(shape):
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(*shape, generator=gen, dtype=torch.float64, requires_grad=True)
    layer = ops.Linear(shape[-1], 7).double()
    assert shape[-1] < ops.NARROW_INPUT
    assert torch.autograd.gradcheck(ops.linear, (x, layer.weight, layer.bias))
    fast = layer(x)
    grads = torch.autograd.grad(fast.square().sum(), [x, layer.weight, layer.bias])
    slow = F.linear(x, layer.weight, layer.bias)
    expected = torch.autograd.grad(slow.square().sum(), [x, layer.weight, layer.bias])
    torch.testing.assert_close(fast, slow, **TOL)
    for got, want in zip(grads, expected, strict=True):
        torch.testing.assert_close(got, want, **TOL)


@pytest.mark.parametrize("frames", [1, 2])
def test_pair_context_sums_before_its_last_layer_as_the_plain_messages(frames):
    """``PairContext`` applies its edge MLP's last (linear) layer after the sums over frames
    and at the nodes: the same as summing the (E, F, 2 hidden) messages, values and gradients
    (float64)."""
    from bgn.model.inverse import _EPS, PairContext, pair_features, window_accelerations

    g = random_graph(30, history=2, kind="radius", contact=True, box=4.0, seed=4, cutoff=1.5)
    torch.manual_seed(0)
    ctx = PairContext(8, "silu", frames).double()
    fast = ctx(g)
    grads = torch.autograd.grad(fast.square().sum(), list(ctx.parameters()))

    snd, rcv = g.edge_index
    m = ctx.edge(pair_features(g, frames)).sum(1)
    n = len(g.vel)
    acc = window_accelerations(g, frames)
    plain = ctx.node(torch.cat([m.new_zeros(n, 8).index_add(0, rcv, m[:, :8]),
                                m.new_zeros(n, 8).index_add(0, snd, m[:, 8:]),
                                0.5 * torch.log((acc * acc).sum(-1) + _EPS)], -1))
    expected = torch.autograd.grad(plain.square().sum(), list(ctx.parameters()))
    torch.testing.assert_close(fast, plain, **TOL)
    for got, want in zip(grads, expected, strict=True):
        torch.testing.assert_close(got, want, **TOL)


def summed_edge_mlp(seed: int, n: int, e: int, frames: int, width: int,
                    data_grad: bool = False):
    """A random edge list of ``n`` nodes and ``e`` edges, edge data (E, frames, 5) and a
    one-layer edge MLP summed over the frames: (edge_index, x, net, phi)."""
    torch.manual_seed(seed)
    edge_index = torch.stack([torch.randint(0, n, (e,)), torch.randint(0, n, (e,))])
    x = torch.randn(e, frames, 5, dtype=torch.float64, requires_grad=data_grad)
    net = torch.nn.Sequential(torch.nn.Linear(5, width), torch.nn.SiLU()).double()
    return edge_index, x, net, lambda v: net(v).sum(1)


def test_edge_sums_in_chunks_equal_the_plain_sums_and_their_gradients():
    # an edge MLP summed at receivers and senders: chunked (custom backward) == plain
    n = 17
    edge_index, x, net, phi = summed_edge_mlp(3, n, 230, frames=3, width=8)
    weights = torch.randn(2, n, 8, dtype=torch.float64)
    results = []
    for chunk in (None, 40):
        out = edge_sums(phi, net.parameters(), x, edge_index, n, chunk)
        grads = torch.autograd.grad((out * weights).sum(), list(net.parameters()))
        results.append((out, grads))
    (plain, plain_grads), (chunked, chunked_grads) = results
    torch.testing.assert_close(chunked, plain, **TOL)
    for got, want in zip(chunked_grads, plain_grads, strict=True):
        torch.testing.assert_close(got, want, **TOL)


def test_edge_sums_keep_the_gradient_of_data_that_needs_one():
    # features made by the model itself (an unrolled loss): the chunked path would drop their
    # gradient, so they take the plain one
    n = 9
    edge_index, x, net, phi = summed_edge_mlp(4, n, 120, frames=1, width=4, data_grad=True)
    grads = [torch.autograd.grad(edge_sums(phi, net.parameters(), x, edge_index, n,
                                           chunk).sum(), x)[0]
             for chunk in (None, 30)]
    torch.testing.assert_close(grads[1], grads[0], **TOL)
