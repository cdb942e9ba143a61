"""A ReLU edge MLP over blocks of edges with its backward written out (the baselines, CPU).

``ops.EdgeMLP.blocks`` leaves the backward to autograd, block by block. Two costs of that grow
with the number of blocks: each block's gathers ``p[rcv]`` get a node-sized (N, F) gradient of
their own (zeroed, filled, then added to the others), and each weight gradient is a fresh
matrix added to the last. So blocks had to stay large (16 384 edges, 8 MB per activation),
larger than the caches. Here one ``autograd.Function`` runs every block of one edge MLP: the
gradients of the node products and of every weight are accumulated in one buffer each across
the blocks, so blocks can be small enough (``edge_block``) for a block's chain of products and
element-wise work to stay in cache. The arithmetic is autograd's; the tests check both against
the plain concatenated MLP in float64.

The function computes, for the edges ``j -> i`` of each block,
``z_1 = relu((W_r x + b)_i + (W_s x)_j + W_e e_ji)`` (the factored first layer, ``p_r, p_s``
computed per node by the caller), then ``z_{k+1} = act_k(W_k z_k + b_k)`` (``act_k`` ReLU or
none), then an optional LayerNorm: ``y``. It returns ``sum_{j -> i} y_ji`` per node and, when
asked, ``y`` (or ``e + y``, the residual update of GNS's edge latents) per block.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch.autograd.function import once_differentiable


@dataclass(frozen=True)
class Plan:
    """What one call runs: the blocks and the layers' shape (no tensors)."""

    slices: tuple[slice, ...]
    n_nodes: int
    relu: tuple[bool, ...]       # per linear layer after the first: a ReLU after it
    layer_norm_eps: float | None  # a LayerNorm (with weight and bias) at the end, or none
    residual: bool               # also return e + y per block (GNS's edge update)
    save: bool                   # gradients are on: keep what the backward pass needs
    recompute: bool              # keep only the inputs; recompute activations in backward


def first_layer(e: torch.Tensor, rcv: torch.Tensor, snd: torch.Tensor, p_r: torch.Tensor,
                p_s: torch.Tensor, w_e: torch.Tensor) -> torch.Tensor:
    """The factored first layer of an edge MLP, ``(W_r x + b)_i + (W_s x)_j + W_e e``, in one
    (E, F) buffer: no temporaries for the sums. ``index_select``: its backward is
    ``index_add_``, several times faster on a CPU than the accumulating ``index_put_`` behind
    ``x[idx]``."""
    z = p_r.index_select(0, rcv)
    z += p_s.index_select(0, snd)
    return z.addmm_(e, w_e.t())


def _unpack(plan: Plan, tensors: Sequence[torch.Tensor]):
    """``(*weights_and_biases, *norm, *e_blocks)`` -> (layers, norm or None, e_blocks)."""
    n = 2 * len(plan.relu)
    layers = list(zip(tensors[0:n:2], tensors[1:n:2], strict=True))
    n_norm = 2 if plan.layer_norm_eps is not None else 0
    norm = tuple(tensors[n:n + n_norm]) or None
    return layers, norm, tensors[n + n_norm:]


def _block(plan: Plan, e: torch.Tensor, rcv: torch.Tensor, snd: torch.Tensor,
           p_r: torch.Tensor, p_s: torch.Tensor, w_e: torch.Tensor,
           layers: Sequence[tuple[torch.Tensor, torch.Tensor]],
           norm: tuple[torch.Tensor, torch.Tensor] | None):
    """Activations of one block: ``acts`` (post-ReLU ``z_1`` and every later layer's output),
    the LayerNorm's statistics (or None) and the block's output ``y``."""
    z = first_layer(e, rcv, snd, p_r, p_s, w_e).relu_()
    acts = [z]
    for (weight, bias), relu in zip(layers, plan.relu, strict=True):
        z = torch.addmm(bias, z, weight.t())
        if relu:
            z.relu_()
        acts.append(z)
    if norm is None:
        return acts, None, z
    y, mean, rstd = torch.native_layer_norm(z, (z.shape[1],), norm[0], norm[1],
                                            plan.layer_norm_eps)
    return acts, (mean, rstd), y


class BlockedEdgeMLP(torch.autograd.Function):
    """``apply(plan, rcv, snd, p_r, p_s, w_e, *layer_weights_and_biases, *norm, *e_blocks)``
    -> ``(sums, *per_block_outputs)`` (the outputs ``e + y`` only with ``plan.residual``)."""

    @staticmethod
    def forward(ctx, plan: Plan, rcv: torch.Tensor, snd: torch.Tensor, p_r: torch.Tensor,
                p_s: torch.Tensor, w_e: torch.Tensor, *tensors: torch.Tensor):
        layers, norm, e_blocks = _unpack(plan, tensors)
        sums: torch.Tensor | None = None
        outputs, saved = [], []
        for s, e in zip(plan.slices, e_blocks, strict=True):
            acts, stats, y = _block(plan, e, rcv[s], snd[s], p_r, p_s, w_e, layers, norm)
            if sums is None:
                sums = y.new_zeros(plan.n_nodes, y.shape[1])
            sums.index_add_(0, rcv[s], y)
            if plan.residual:  # y is this block's own buffer unless it is a saved activation
                outputs.append(y + e if y is acts[-1] else y.add_(e))
            if plan.save and not plan.recompute:
                saved.append((acts, stats))
        assert sums is not None  # edge_blocks gives at least one (maybe empty) block
        ctx.plan, ctx.activations = plan, saved
        if plan.save:
            ctx.save_for_backward(rcv, snd, p_r, p_s, w_e, *tensors)
        return (sums, *outputs)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_sums: torch.Tensor | None, *grad_blocks: torch.Tensor | None):
        plan: Plan = ctx.plan
        rcv, snd, p_r, p_s, w_e, *tensors = ctx.saved_tensors
        layers, norm, e_blocks = _unpack(plan, tensors)
        n_layers = len(layers)
        need_e = any(ctx.needs_input_grad[len(ctx.needs_input_grad) - len(e_blocks):])

        grad_p_r, grad_p_s = torch.zeros_like(p_r), torch.zeros_like(p_s)
        grad_w_e = torch.zeros_like(w_e)
        grad_layers = [(torch.zeros_like(w), torch.zeros_like(b)) for w, b in layers]
        grad_norm = [torch.zeros_like(t) for t in norm] if norm is not None else []
        grad_e: list[torch.Tensor | None] = []
        for k, (s, e) in enumerate(zip(plan.slices, e_blocks, strict=True)):
            r, sn = rcv[s], snd[s]
            if plan.recompute:
                acts, stats, _ = _block(plan, e, r, sn, p_r, p_s, w_e, layers, norm)
            else:
                acts, stats = ctx.activations[k]
            grad_out = grad_blocks[k] if plan.residual else None
            # the gradient of y: through the sums (a gather) and through the block's output
            g = grad_sums.index_select(0, r) if grad_sums is not None \
                else acts[-1].new_zeros(acts[-1].shape)
            if grad_out is not None:
                g += grad_out
            if norm is not None:
                mean, rstd = stats
                g, gw, gb = torch.ops.aten.native_layer_norm_backward(
                    g, acts[-1], (g.shape[1],), mean, rstd, norm[0], norm[1],
                    [True, True, True])
                grad_norm[0] += gw
                grad_norm[1] += gb
            for i in range(n_layers - 1, -1, -1):
                if plan.relu[i]:  # the saved output is post-ReLU: > 0 exactly where it passed
                    g = torch.ops.aten.threshold_backward(g, acts[i + 1], 0)
                (weight, _), (grad_w, grad_b) = layers[i], grad_layers[i]
                grad_w.addmm_(g.t(), acts[i])
                grad_b += g.sum(0)
                g = g @ weight
            g = torch.ops.aten.threshold_backward(g, acts[0], 0)
            grad_w_e.addmm_(g.t(), e)
            grad_p_r.index_add_(0, r, g)
            grad_p_s.index_add_(0, sn, g)
            if need_e:  # e's own gradient: through the first layer (and the residual)
                grad_e.append(g @ w_e if grad_out is None else torch.addmm(grad_out, g, w_e))
            else:
                grad_e.append(None)
            if not plan.recompute:
                ctx.activations[k] = None  # free each block's activations once used
        flat_layers = [t for pair in grad_layers for t in pair]
        return (None, None, None, grad_p_r, grad_p_s, grad_w_e, *flat_layers, *grad_norm,
                *grad_e)
