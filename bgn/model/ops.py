"""Sparse graph operations on edge lists (docs/design.md#graphs): O(E) time and memory.

Edges are ``edge_index = (senders, receivers)``; a receiver aggregates its senders' features.
The paper's dense matrix products ``Â H`` are the special case of a complete edge list.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from itertools import pairwise

import torch
from torch import nn
from torch.nn import functional as F
from torch.utils.checkpoint import checkpoint

from bgn.model.fused_edges import BlockedEdgeMLP, Plan, first_layer
from bgn.model.message_passing import (
    MAX_EDGE_BLOCKS,
    CheckpointEdges,
    checkpointed,
    edge_blocks,
    edge_chunks,
    spmm,
)

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "silu": nn.SiLU,
    "relu": nn.ReLU,
    "gelu": nn.GELU,
    "tanh": nn.Tanh,
    "softplus": nn.Softplus,
}


# Activations that can overwrite their input: their backward reads the output only. Not
# SiLU: its backward reads the input, so autograd clones the input of an in-place SiLU (a copy
# of every (E, F) activation, no memory saved).
IN_PLACE = frozenset({"relu"})
# Hidden widths of the edge MLPs are padded with zero weights to a multiple of this inside the
# matrix products: MKL's float32 kernels run faster on such widths than on cranmer_gn's 300
# (docs/notes/2026-11-25-history.md, "Earlier runs"); the padded channels stay exactly zero.
PAD_WIDTH = 16


def activation(name: str, inplace: bool = False) -> nn.Module:
    """A fresh activation module by name (``silu``, ``relu``, ``gelu``, ``tanh``, ``softplus``).

    ``inplace=True`` overwrites the input where the activation allows it (``IN_PLACE``): one
    (E, F) buffer less per layer on a big graph. Only for inputs nothing else reads (the output
    of a Linear layer inside an MLP)."""
    try:
        cls = ACTIVATIONS[name]
    except KeyError:
        raise ValueError(f"unknown activation {name!r}; choose one of {sorted(ACTIVATIONS)}")\
            from None
    return cls(inplace=True) if inplace and name in IN_PLACE else cls()


def scatter_sum(src: torch.Tensor, index: torch.Tensor, dim_size: int) -> torch.Tensor:
    """``out[n] = sum of src[e] over e with index[e] == n``; shape (dim_size, ...)."""
    out = src.new_zeros((dim_size, *src.shape[1:]))
    return out.index_add_(0, index, src)


def gcn_aggregate(h: torch.Tensor, edge_index: torch.Tensor,
                  edge_weight: torch.Tensor | None = None,
                  normalize: bool = False) -> torch.Tensor:
    """``Â H`` with ``Â = A + I`` (paper Eq. 1) on an edge list.

    ``out_i = h_i + sum over edges j -> i of w_ji h_j`` (``w = 1`` when ``edge_weight`` is None).
    ``normalize=True`` uses the symmetric ``D^-1/2 Â D^-1/2`` with ``D`` the weighted in-degree
    plus one (the self loop), as in Kipf & Welling's GCN. The neighbour sum is a sparse product
    (``message_passing.spmm``): no (E, F) tensor forward or backward.
    """
    senders, receivers = edge_index[0], edge_index[1]
    n = h.shape[0]
    if not normalize:
        return h + spmm(h, edge_index, edge_weight)
    if edge_weight is None:
        edge_weight = h.new_ones(senders.shape[0])
    deg = 1.0 + scatter_sum(edge_weight, receivers, n)
    inv_sqrt = deg.rsqrt()
    edge_weight = inv_sqrt.index_select(0, receivers) * edge_weight \
        * inv_sqrt.index_select(0, senders)
    return (inv_sqrt * inv_sqrt)[:, None] * h + spmm(h, edge_index, edge_weight)


def pad_features(x: torch.Tensor, width: int) -> torch.Tensor:
    """Fixed (parameter-free) projection to ``width`` channels: zero-pad or truncate.

    Used for the raw-residual path when a layer changes width. A *learned* projection ``P``
    would be pointless there: ``Â H W + Â H P = Â H (W + P)`` is just another linear map, so
    the raw input would no longer pass through unchanged. Padding keeps the raw features in
    the first channels, which is what the raw residual is for.
    """
    f = x.shape[-1]
    if f == width:
        return x
    if f > width:
        return x[..., :width]
    return torch.nn.functional.pad(x, (0, width - f))


# Below this many input features a Linear layer's weight gradient is computed as
# ``(xᵀ g)ᵀ`` instead of autograd's ``gᵀ x``: MKL's single-thread kernel for the latter is far
# slower when x is that narrow (docs/notes/2026-11-25-history.md, "Earlier runs").
NARROW_INPUT = 16


class _NarrowLinear(torch.autograd.Function):
    """``x Wᵀ + b`` for narrow ``x`` (..., K), K < ``NARROW_INPUT``; backward as autograd's,
    with the weight gradient's product in the orientation MKL runs fast."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor,
                bias: torch.Tensor | None) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        return F.linear(x, weight, bias)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, weight = ctx.saved_tensors
        grad_x = grad @ weight if ctx.needs_input_grad[0] else None
        g2 = grad.reshape(-1, grad.shape[-1])
        grad_w = (x.reshape(-1, x.shape[-1]).t() @ g2).t() if ctx.needs_input_grad[1] else None
        grad_b = g2.sum(0) if ctx.has_bias and ctx.needs_input_grad[2] else None
        return grad_x, grad_w, grad_b


def linear(x: torch.Tensor, weight: torch.Tensor,
           bias: torch.Tensor | None = None) -> torch.Tensor:
    """``F.linear`` with a fast weight gradient for narrow inputs (``NARROW_INPUT``)."""
    if weight.shape[1] < NARROW_INPUT and torch.is_grad_enabled() and weight.requires_grad:
        return _NarrowLinear.apply(x, weight, bias)
    return F.linear(x, weight, bias)


class Linear(nn.Linear):
    """``nn.Linear`` (same parameters, same state-dict keys) through ``linear``."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return linear(x, self.weight, self.bias)


def mlp(sizes: list[int], act: str = "silu", layer_norm: bool = False,
        activate_last: bool = False) -> nn.Sequential:
    """Plain MLP ``sizes[0] -> ... -> sizes[-1]``; optional LayerNorm on the output (GNS style)."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(pairwise(sizes)):
        layers.append(Linear(a, b))
        if i < len(sizes) - 2 or activate_last:
            layers.append(activation(act, inplace=True))  # on the Linear's own output
    if layer_norm:
        layers.append(nn.LayerNorm(sizes[-1]))
    return nn.Sequential(*layers)


def _padded(width: int) -> int:
    return -(-width // PAD_WIDTH) * PAD_WIDTH


def _pad_linear(weight: torch.Tensor, bias: torch.Tensor | None, rows: int, cols: int,
                ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``weight`` (out, in) and ``bias`` zero-padded to ``rows`` outputs and ``cols`` inputs
    (differentiable: the gradients of the real entries are those of the unpadded layer)."""
    out, inp = weight.shape
    if (out, inp) != (rows, cols):
        weight = F.pad(weight, (0, cols - inp, 0, rows - out))
        if bias is not None and out != rows:
            bias = F.pad(bias, (0, rows - out))
    return weight, bias


class EdgeMLP(nn.Module):
    """``phi([e_ij, x_i, x_j])`` for every edge j -> i; ``sizes`` = hidden widths + output width.

    ``factored=True`` applies the first layer's node blocks per node and gathers the products,
    ``W [e, x_i, x_j] = W_e e + (W_r x + b)[i] + (W_s x)[j]``: the same function as the plain
    concatenation (``factored=False``), with fewer FLOPs and no (E, 2F) concatenated copy when
    the node features are wide (faster forward and backward: docs/design.md#performance-choices).
    The hidden layers run at widths padded with zero weights to a multiple of ``PAD_WIDTH`` (exactly
    the same function; faster matrix products), the output at its own width.

    ``edge_chunk`` and ``checkpoint_edges`` (set by ``PhysicsModel`` from its config): on
    graphs with more edges, the edges run in chunks with activation checkpointing
    (``message_passing.edge_chunks``). ``edge_block`` (the baselines' configs): on a CPU,
    ``sum_at_receivers`` and GNS's interaction step run the edges in blocks of that many,
    without a per-edge tensor of the whole graph (``message_passing.edge_blocks``): through
    ``fused`` (the backward written out, ``bgn.model.fused_edges``) for ReLU, else ``blocks``.
    """

    def __init__(self, edge_in: int, node_in: int, sizes: list[int], act: str = "relu",
                 layer_norm: bool = False, factored: bool = True) -> None:
        super().__init__()
        self.edge_in, self.node_in, self.factored = edge_in, node_in, factored
        self.first = nn.Linear(edge_in + 2 * node_in, sizes[0])
        self.rest = nn.Sequential(activation(act, inplace=True), *mlp(sizes, act, layer_norm))
        # the output layer (None: the first layer is the only one); its columns stay unpadded
        linears = [m for m in self.rest if isinstance(m, nn.Linear)]
        self._last = linears[-1] if linears else None
        self.edge_chunk: int | None = None
        self.checkpoint_edges = CheckpointEdges()
        self.edge_block: int | None = None

    def forward(self, e: torch.Tensor, x: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
        """Edge (E, edge_in) and node (N, node_in) features -> (E, sizes[-1])."""
        snd, rcv = edge_index[0], edge_index[1]
        if not self.factored:
            return self.rest(self.first(torch.cat([e, x.index_select(0, rcv),
                                                   x.index_select(0, snd)], dim=1)))
        return edge_chunks(self._edges, self.edge_chunk, (e, rcv, snd), self.node_products(x),
                           self.checkpoint_edges.above(e))

    def node_products(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The first layer's node blocks applied per node, ``(W_r x + b, W_s x)``, and its
        edge block ``W_e``, at the padded hidden width."""
        first = self.first
        width = _padded(first.out_features) if self._last is not None else first.out_features
        weight, bias = _pad_linear(first.weight, first.bias, width, first.in_features)
        w_e, w_r, w_s = weight.split([self.edge_in, self.node_in, self.node_in], dim=1)
        return F.linear(x, w_r, bias), F.linear(x, w_s), w_e

    def _padded_weights(self, layer: nn.Linear, cols: int,
                        ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """A hidden or output layer's weight and bias for ``cols`` (padded) inputs. Every layer
        but the last writes padded columns; the next one's padded input weights are zero, so
        whatever the activation makes of them adds nothing."""
        rows = layer.out_features if layer is self._last else _padded(layer.out_features)
        return _pad_linear(layer.weight, layer.bias, rows, cols)

    def block_slices(self, e: torch.Tensor) -> list[slice]:
        """The blocks of ``e``'s edges (``edge_block`` on a CPU; one block on a GPU, whose
        caching allocator already reuses memory and whose kernels want large tensors). The
        fused path has no per-block node-sized cost, so no cap on the number of blocks."""
        if e.is_cuda:
            return edge_blocks(e.shape[0], None)
        return edge_blocks(e.shape[0], self.edge_block,
                           None if self._fused_layers(False) is not None else MAX_EDGE_BLOCKS)

    def _fused_layers(self, hidden_only: bool,
                      ) -> tuple[list[tuple[nn.Linear, bool]], nn.LayerNorm | None] | None:
        """The layers after the first as (Linear, ReLU after it) and the final LayerNorm, when
        ``fused_edges.BlockedEdgeMLP`` can run them (factored, ReLU activations, an affine
        LayerNorm or none, blocks on); None otherwise."""
        if not self.factored or self.edge_block is None or not isinstance(self.rest[0], nn.ReLU):
            return None
        layers: list[tuple[nn.Linear, bool]] = []
        norm = None
        for module in list(self.rest)[1:]:
            if isinstance(module, nn.Linear):
                if hidden_only and module is self._last:
                    break
                layers.append((module, False))
            elif isinstance(module, nn.ReLU) and layers:
                layers[-1] = (layers[-1][0], True)
            elif isinstance(module, nn.LayerNorm) and module.elementwise_affine \
                    and module.bias is not None:
                norm = module
            else:
                return None
        return layers, norm

    def fused(self, e_blocks: Sequence[torch.Tensor], x: torch.Tensor,
              edge_index: torch.Tensor, slices: Sequence[slice], hidden_only: bool = False,
              residual: bool = False) -> tuple[torch.Tensor, list[torch.Tensor]] | None:
        """Every block through ``fused_edges.BlockedEdgeMLP`` on a CPU: the (N, F) sums of
        ``phi`` at the receivers and, with ``residual``, each block's ``e + phi`` (GNS's edge
        update); ``hidden_only`` stops before the output layer. None where the fused path does
        not apply (a GPU, another activation, blocks off): the caller runs ``blocks``."""
        found = None if x.is_cuda else self._fused_layers(hidden_only)
        if found is None:
            return None
        layers, norm = found
        p_r, p_s, w_e = self.node_products(x)
        tensors: list[torch.Tensor] = []
        cols = p_r.shape[1]
        for module, _ in layers:
            weight, bias = self._padded_weights(module, cols)
            tensors += [weight, bias]
            cols = weight.shape[0]
        if norm is not None:
            tensors += [norm.weight, norm.bias]
        grad = torch.is_grad_enabled()
        plan = Plan(slices=tuple(slices), n_nodes=x.shape[0],
                    relu=tuple(relu for _, relu in layers),
                    layer_norm_eps=None if norm is None else norm.eps,
                    residual=residual, save=grad,
                    recompute=grad and checkpointed(edge_index.shape[1], self.edge_chunk,
                                                    self.checkpoint_edges.above(x)))
        sums, *outputs = BlockedEdgeMLP.apply(plan, edge_index[1], edge_index[0], p_r, p_s,
                                              w_e, *tensors, *e_blocks)
        return sums, outputs

    def blocks(self, e_blocks: Sequence[torch.Tensor], x: torch.Tensor,
               edge_index: torch.Tensor, slices: Sequence[slice],
               hidden_only: bool = False) -> Iterator[torch.Tensor]:
        """``phi`` of each block of edges, one after another: ``e_blocks[k]`` holds the edge
        features of ``edge_index[:, slices[k]]``. ``hidden_only`` stops before the output layer.
        On graphs above the checkpointing threshold each block is recomputed in the backward
        pass (as ``forward``'s chunks)."""
        products = self.node_products(x)
        n_edges = edge_index.shape[1]
        recompute = torch.is_grad_enabled() and checkpointed(
            n_edges, self.edge_chunk, self.checkpoint_edges.above(x))
        for e, s in zip(e_blocks, slices, strict=True):
            args = (e, edge_index[1, s], edge_index[0, s], *products)
            if recompute:
                yield checkpoint(self._edges, *args, hidden_only, use_reentrant=False)
            else:
                yield self._edges(*args, hidden_only)

    def sum_at_receivers(self, e: torch.Tensor, x: torch.Tensor, edge_index: torch.Tensor,
                         n: int) -> torch.Tensor:
        """(n, sizes[-1]): ``phi`` summed over each node's incoming edges, block by block.

        When the output layer is linear with nothing after it, it runs once on the sums of
        the last hidden layer, ``sum_j (W h_j + b) = W sum_j h_j + deg_i b``: the same sums
        (to round-off) without the output layer's per-edge product."""
        linear_out = self._last is not None and self.rest[-1] is self._last
        slices = self.block_slices(e)
        rcv = edge_index[1]
        e_blocks = [e[s] for s in slices]
        fused = self.fused(e_blocks, x, edge_index, slices, hidden_only=linear_out)
        total: torch.Tensor | None = None
        if fused is not None:
            total = fused[0]
        else:
            for s, y in zip(slices, self.blocks(e_blocks, x, edge_index, slices,
                                                hidden_only=linear_out), strict=True):
                if total is None:
                    total = y.new_zeros(n, y.shape[1])
                total.index_add_(0, rcv[s], y)
        assert total is not None  # edge_blocks gives at least one (maybe empty) block
        if not linear_out:
            return total
        last = self._last
        weight, _ = self._padded_weights(last, total.shape[1])
        out = total @ weight.t()
        if last.bias is not None:
            degree = torch.bincount(rcv, minlength=n).to(out.dtype)
            out = out + degree[:, None] * last.bias
        return out

    def _edges(self, e: torch.Tensor, rcv: torch.Tensor, snd: torch.Tensor, p_r: torch.Tensor,
               p_s: torch.Tensor, w_e: torch.Tensor, hidden_only: bool = False) -> torch.Tensor:
        z = first_layer(e, rcv, snd, p_r, p_s, w_e)
        for module in self.rest:
            if isinstance(module, nn.Linear):
                if hidden_only and module is self._last:
                    break
                z = F.linear(z, *self._padded_weights(module, z.shape[1]))
            else:
                z = module(z)
        return z
