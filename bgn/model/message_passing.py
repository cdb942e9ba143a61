"""Message passing as sparse matrix products on edges sorted by receiver
(docs/design.md#graphs, docs/design.md#performance-choices).

An edge list ``(senders, receivers)`` of N nodes is the sparse N x N matrix ``A`` with
``A[i, j] = w_ji`` for each edge j -> i. The two operations the models need without a wide
per-edge tensor are its product with node features and its sampled dual:

- ``spmm(h, edge_index, w)``: ``out_i = sum over edges j -> i of w_ji h_j`` (``A H``);
- ``edge_dot(a, b, edge_index)``: ``c_ji = <a_i, b_j>`` on every edge (``A ⊙ (a bᵀ)``).

Each one's backward is the other (the gradient of ``A H`` with respect to the weights is the
sampled product, and the gradient of the sampled product is a product with ``A``), so neither
direction gathers an (E, F) tensor, multiplies it and scatters it back, and neither goes
through the accumulating ``index_put_`` behind ``x[index]``. Both run as CSR kernels
(``torch.sparse.mm``, ``torch.sparse.sampled_addmm``): faster than a gather and ``index_add_``
on large graphs, with no (E, F) memory
(docs/notes/2026-11-26-results-history.md, "Moved here from code comments and configs").

CSR needs the edges sorted by receiver, which every graph builder here already returns
(``bgn.data.edges``) and a batch keeps (``bgn.graph.collate``); other orders are sorted once
per edge list. The structure (row pointers, the transpose's order) is built once per edge-list
tensor and reused by every layer of a forward and backward pass.
"""

from __future__ import annotations

import warnings
import weakref
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch.utils.checkpoint import checkpoint

from bgn.graph import Graph
from bgn.metrics import minimum_image


@dataclass(frozen=True)
class Adjacency:
    """The CSR layout of one edge list: ``A`` (rows = receivers) and ``Aᵀ`` (rows = senders).

    ``order`` sorts the edges by (receiver, sender) (None when they already are); ``order_t``
    sorts them by (sender, receiver). Edge values are permuted by them on the way in and out,
    so callers keep their own edge order.
    """

    n: int
    crow: torch.Tensor             # (N+1,) row pointers of A
    col: torch.Tensor              # (E,) senders in CSR order
    order: torch.Tensor | None     # CSR position -> edge (None: identity)
    crow_t: torch.Tensor           # (N+1,) row pointers of Aᵀ
    col_t: torch.Tensor            # (E,) receivers in Aᵀ's CSR order
    order_t: torch.Tensor          # Aᵀ's CSR position -> edge

    def matrix(self, values: torch.Tensor, transpose: bool = False) -> torch.Tensor:
        """``A`` (or ``Aᵀ``) as a CSR tensor with per-edge ``values`` in the caller's order."""
        if transpose:
            crow, col, v = self.crow_t, self.col_t, values[self.order_t]
        else:
            crow, col = self.crow, self.col
            v = values if self.order is None else values[self.order]
        # CSR tensors are "beta" in torch 2.x (a warning); mm and sampled_addmm are stable. The
        # layout is valid by construction, so torch's invariant checks are off.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return torch.sparse_csr_tensor(crow, col, v, (self.n, self.n), check_invariants=False)

    def to_edges(self, csr_values: torch.Tensor) -> torch.Tensor:
        """Values in A's CSR order -> the caller's edge order."""
        if self.order is None:
            return csr_values
        return csr_values.new_empty(csr_values.shape).index_copy_(0, self.order, csr_values)


def _row_pointers(rows: torch.Tensor, n: int) -> torch.Tensor:
    crow = torch.zeros(n + 1, dtype=torch.int64, device=rows.device)
    crow[1:] = torch.bincount(rows, minlength=n).cumsum(0)
    return crow


def _build(edge_index: torch.Tensor, n: int) -> Adjacency:
    snd, rcv = edge_index[0], edge_index[1]
    key = rcv * n + snd
    order = None
    if key.numel() > 1 and not bool((key[1:] >= key[:-1]).all()):
        order = torch.argsort(key)
    col = snd if order is None else snd[order]
    order_t = torch.argsort(snd * n + rcv)
    return Adjacency(n, _row_pointers(rcv, n), col.contiguous(), order,
                     _row_pointers(snd, n), rcv[order_t].contiguous(), order_t)


# One entry: every layer of a forward (and its backward) passes the same edge_index tensor.
_last: tuple[weakref.ref, int, Adjacency] | None = None


def adjacency(edge_index: torch.Tensor, n: int) -> Adjacency:
    """The CSR layout of ``edge_index`` over ``n`` nodes, built once per edge-list tensor."""
    global _last
    if _last is not None and _last[0]() is edge_index and _last[1] == n:
        return _last[2]
    adj = _build(edge_index, n)
    _last = (weakref.ref(edge_index), n, adj)
    return adj


class _SpMM(torch.autograd.Function):
    """``A H`` with per-edge weights ``w``; backward: ``Aᵀ G`` and ``<G_i, H_j>`` per edge."""

    @staticmethod
    def forward(ctx, h: torch.Tensor, w: torch.Tensor, adj: Adjacency) -> torch.Tensor:
        ctx.save_for_backward(h, w)
        ctx.adj = adj
        return torch.sparse.mm(adj.matrix(w), h)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        h, w = ctx.saved_tensors
        adj = ctx.adj
        grad = grad.contiguous()
        grad_h = torch.sparse.mm(adj.matrix(w, transpose=True), grad) \
            if ctx.needs_input_grad[0] else None
        grad_w = _sampled(grad, h, adj) if ctx.needs_input_grad[1] else None
        return grad_h, grad_w, None


class _EdgeDot(torch.autograd.Function):
    """``c_ji = <a_i, b_j>`` per edge; backward: ``A_g b`` and ``A_gᵀ a`` (g: the gradient)."""

    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor, adj: Adjacency) -> torch.Tensor:
        ctx.save_for_backward(a, b)
        ctx.adj = adj
        return _sampled(a, b, adj)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        a, b = ctx.saved_tensors
        adj = ctx.adj
        grad_a = torch.sparse.mm(adj.matrix(grad), b) if ctx.needs_input_grad[0] else None
        grad_b = torch.sparse.mm(adj.matrix(grad, transpose=True), a) \
            if ctx.needs_input_grad[1] else None
        return grad_a, grad_b, None


def _sampled(a: torch.Tensor, b: torch.Tensor, adj: Adjacency) -> torch.Tensor:
    """``<a_rcv, b_snd>`` per edge, in the caller's edge order."""
    pattern = adj.matrix(a.new_zeros(adj.col.shape[0]))
    values = torch.sparse.sampled_addmm(pattern, a.contiguous(), b.t(), beta=0.0).values()
    return adj.to_edges(values)


def spmm(h: torch.Tensor, edge_index: torch.Tensor,
         edge_weight: torch.Tensor | None = None) -> torch.Tensor:
    """``out_i = sum over edges j -> i of w_ji h_j`` (N, F); ``w = 1`` when ``edge_weight`` is
    None. Differentiable in ``h`` and ``edge_weight``."""
    adj = adjacency(edge_index, h.shape[0])
    if edge_weight is None:
        edge_weight = h.new_ones(edge_index.shape[1])
    return _SpMM.apply(h.contiguous(), edge_weight.to(h.dtype), adj)


def edge_dot(a: torch.Tensor, b: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
    """``<a_i, b_j>`` for every edge j -> i, (E,). Differentiable in ``a`` and ``b``."""
    return _EdgeDot.apply(a.contiguous(), b.contiguous(), adjacency(edge_index, a.shape[0]))


def edge_difference(x: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
    """``x_i - x_j`` for every edge j -> i (receiver minus sender), (E, ...). ``index_select``
    rather than ``x[index]``: its backward is ``index_add_``, not the slower accumulating
    ``index_put_``."""
    return x.index_select(0, edge_index[1]) - x.index_select(0, edge_index[0])


def edge_period(g: Graph, receivers: torch.Tensor | None = None) -> torch.Tensor | None:
    """(E, D) the box lengths of the graph each edge's receiver belongs to (``Graph.period``;
    ``receivers`` (E,): those of a subset of edges), or None for a graph without periodic
    boundaries (or a stand-in without the field, e.g. ``bgn.laws.sample.sample_law``'s two
    particles)."""
    period = getattr(g, "period", None)
    if period is None:
        return None
    rcv = g.edge_index[1] if receivers is None else receivers
    return period.index_select(0, g.batch.index_select(0, rcv))


def edge_vector(x: torch.Tensor, g: Graph) -> torch.Tensor:
    """The relative position ``x_i - x_j`` on every edge j -> i of ``g`` (E, ..., D) from
    positions ``x`` (N, ..., D) of its nodes: ``edge_difference``, by the minimum image in a
    periodic scene. Every relative position a model makes on an edge goes through here."""
    dx = edge_difference(x, g.edge_index)
    period = edge_period(g)
    if period is None:
        return dx
    return minimum_image(dx, period.reshape(period.shape[0], *[1] * (dx.ndim - 2), -1))


class CheckpointEdges(NamedTuple):
    """The edge counts above which a module checkpoints its edge work (``edge_chunks``), on
    the CPU and on a GPU; None: from the chunk size alone. Set by ``PhysicsModel`` from its
    config (``checkpoint_edges``, ``checkpoint_edges_gpu``)."""

    cpu: int | None = None
    gpu: int | None = None

    def above(self, x: torch.Tensor) -> int | None:
        """The threshold for work on ``x``'s device."""
        return self.gpu if x.is_cuda else self.cpu


def checkpointed(n_edges: int, chunk: int | None, above: int | None) -> bool:
    """Whether edge work on ``n_edges`` edges runs in checkpointed chunks: a chunk size is
    set and the graph is larger than both it and the threshold ``above``
    (``CheckpointEdges.above``). With gradients off nothing is recomputed."""
    return bool(chunk) and n_edges > max(chunk, above or 0)


def edge_chunks(fn: Callable[..., torch.Tensor], chunk: int | None,
                per_edge: tuple[torch.Tensor, ...], shared: tuple[torch.Tensor, ...] = (),
                above: int | None = None) -> torch.Tensor:
    """``fn(*per_edge, *shared)`` with the per-edge arguments (first dimension E) split into
    chunks of ``chunk`` edges when E is larger than both ``chunk`` and ``above``; with
    gradients on, each chunk's intermediates are recomputed in the backward pass (activation
    checkpointing). Memory for ``fn``'s intermediates is then O(chunk) instead of O(E), for one
    more forward of ``fn``: ``above`` keeps that recompute off graphs small enough to hold."""
    n_edges = per_edge[0].shape[0]
    if not checkpointed(n_edges, chunk, above):
        return fn(*per_edge, *shared)
    parts = []
    for start in range(0, n_edges, chunk):
        args = (*(a[start:start + chunk] for a in per_edge), *shared)
        parts.append(checkpoint(fn, *args, use_reentrant=False) if torch.is_grad_enabled()
                     else fn(*args))
    return torch.cat(parts)


# At most this many blocks per graph, larger blocks beyond: the backward of each block's
# gathers makes node-sized gradients (N, F) of its own, so a fixed block size would cost
# O(N E / block), quadratic in N
# (docs/notes/2026-11-26-results-history.md, "Edge blocks for the baselines").
MAX_EDGE_BLOCKS = 32


def edge_blocks(n_edges: int, block: int | None,
                max_blocks: int | None = MAX_EDGE_BLOCKS) -> list[slice]:
    """Consecutive slices of at most ``block`` edges that cover ``n_edges`` (larger ones where
    that would make more than ``max_blocks``): one slice when ``block`` is None or the
    graph is no larger (an empty one for a graph without edges).

    Edge work run block by block, with each block's outputs summed or kept per block, never
    makes a per-edge tensor of the whole graph. On a CPU that is faster, not only smaller: a
    block's (8 192, 128) float32 tensors are 4 MB, which malloc recycles within the process
    and the caches hold between consecutive operations, where a (300 000, 128) tensor is
    150 MB of fresh pages that the kernel zeroes at every allocation
    (docs/notes/2026-11-26-results-history.md, "Edge blocks")."""
    if not block or n_edges <= block:
        return [slice(0, n_edges)]
    if max_blocks:
        block = max(block, -(-n_edges // max_blocks))
    return [slice(start, min(start + block, n_edges)) for start in range(0, n_edges, block)]


class _EdgeSums(torch.autograd.Function):
    """``out[0, i] = sum over edges e with receiver i of phi(x_e)``, ``out[1, j]`` the same over
    senders, in chunks of edges; the backward recomputes each chunk's ``phi`` and returns the
    gradients of its parameters (``x`` is data: no gradient). No per-edge tensor of the whole
    graph exists in either pass, and no node-sized tensor per chunk."""

    @staticmethod
    def forward(ctx, phi: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
                rcv: torch.Tensor, snd: torch.Tensor, n: int, chunk: int,
                *params: torch.Tensor) -> torch.Tensor:
        ctx.phi, ctx.chunk = phi, chunk
        ctx.save_for_backward(x, rcv, snd, *params)
        out = None
        for start in range(0, x.shape[0], chunk):
            y = phi(x[start:start + chunk])
            if out is None:
                out = y.new_zeros(2, n, *y.shape[1:])
            out[0].index_add_(0, rcv[start:start + chunk], y)
            out[1].index_add_(0, snd[start:start + chunk], y)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, rcv, snd, *params = ctx.saved_tensors
        grads = [torch.zeros_like(p) for p in params]
        for start in range(0, x.shape[0], ctx.chunk):
            r, s = rcv[start:start + ctx.chunk], snd[start:start + ctx.chunk]
            with torch.enable_grad():
                y = ctx.phi(x[start:start + ctx.chunk])
            g = grad[0].index_select(0, r) + grad[1].index_select(0, s)
            for total, part in zip(grads, torch.autograd.grad(y, params, g, allow_unused=True),
                                   strict=True):
                if part is not None:
                    total += part
        return (None, None, None, None, None, None, *grads)


def edge_sums(phi: Callable[[torch.Tensor], torch.Tensor], params: Iterable[torch.Tensor],
              x: torch.Tensor, edge_index: torch.Tensor, n: int, chunk: int | None = None,
              above: int | None = None) -> torch.Tensor:
    """(2, N, ...) ``phi`` of every edge's data ``x`` (E, ...) summed at the receivers and at
    the senders; ``params``: the parameters ``phi`` uses. On graphs of more than ``chunk`` and
    ``above`` edges, in chunks (``_EdgeSums``): the memory of ``phi``'s activations is
    O(chunk), for one more forward of ``phi``. ``_EdgeSums`` returns no gradient for ``x``, so
    an ``x`` that needs one (data made by the model itself, an unrolled loss) takes the plain
    path."""
    snd, rcv = edge_index[0], edge_index[1]
    if not checkpointed(x.shape[0], chunk, above) or x.requires_grad:
        y = phi(x)
        zeros = y.new_zeros(n, *y.shape[1:])
        return torch.stack([zeros.index_add(0, rcv, y), zeros.index_add(0, snd, y)])
    return _EdgeSums.apply(phi, x, rcv, snd, n, chunk,
                           *(p for p in params if p.requires_grad))
