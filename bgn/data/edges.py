"""Sparse edge lists: complete graphs, radius (collision-candidate) graphs, disjoint unions.

An edge list is an ``int64`` array of shape ``(2, E)``: row 0 holds senders, row 1 receivers.
Every builder here returns both directions of every pair, no self-loops, sorted by
``(receiver, sender)`` so that the output is deterministic whatever the search order was.
The dense matrices of the paper are the special case :func:`full_graph` (docs/design.md#graphs).

Neighbour search uses :class:`scipy.spatial.cKDTree`, so it costs ``O(N log N + E)`` and never
builds an ``N x N`` distance matrix, caps neighbours, or drops one. Membership is decided by one
float64 formula, :func:`pair_distance`, so the same pair is always in or out whoever asks.
A scene with periodic boundaries (``SceneMeta.period``) passes its box lengths: neighbours are
then found on the torus (``cKDTree(boxsize=...)``) and distances follow the minimum image
(:func:`minimum_image`), as the engine that made the data saw them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from bgn.coerce import as_float, as_int, as_real_array
from bgn.metrics import minimum_image  # noqa: F401 (here too: the graphs' rule)

__all__ = [
    "batch_edges",
    "contact_margin",
    "full_graph",
    "minimum_image",
    "pair_distance",
    "radius_graph",
]

# The tree compares its own distance arithmetic (e.g. squared distance against r**2) with the
# query radius; that can round differently from pair_distance. Query a slightly larger ball and
# decide membership exactly afterwards, so a pair exactly at the cut-off is never lost.
_QUERY_RELATIVE_SLACK = 1e-9
_QUERY_ABSOLUTE_SLACK = 1e-300  # only matters when the reach is 0 (identical points)


def _empty_edges() -> np.ndarray:
    return np.zeros((2, 0), dtype=np.int64)


def _as_positions(positions: np.ndarray) -> np.ndarray:
    pos = np.asarray(positions)
    if pos.ndim != 2:
        raise ValueError(
            f"positions must have shape (N, D), got shape {pos.shape}"
            + ("; for 1-D points use positions.reshape(-1, 1)" if pos.ndim == 1 else "")
        )
    if pos.shape[1] < 1:
        raise ValueError(f"positions must have at least one coordinate (D >= 1), got {pos.shape}")
    return as_real_array(pos, "positions")


def full_graph(n: int) -> np.ndarray:
    """Every ordered pair ``(sender, receiver)`` with ``sender != receiver``: ``n (n - 1)`` edges.

    Sorted by receiver, then sender.
    """
    n = as_int(n, "n")
    if n < 2:
        return _empty_edges()
    receivers = np.repeat(np.arange(n, dtype=np.int64), n - 1)
    # Row r lists 0..n-2; shifting the entries >= r by one skips r itself and keeps them sorted.
    senders = np.tile(np.arange(n - 1, dtype=np.int64), (n, 1))
    senders += senders >= np.arange(n, dtype=np.int64)[:, None]
    return np.stack([senders.reshape(-1), receivers])


def _as_period(period: Sequence[float] | np.ndarray | None, dim: int) -> np.ndarray | None:
    """(D,) float64 box lengths (0: not periodic), or None where no dimension is periodic."""
    if period is None:
        return None
    p = np.asarray(period, dtype=np.float64).reshape(-1)
    if p.shape != (dim,) or not (np.isfinite(p).all() and (p >= 0).all()):
        raise ValueError(f"period must be one finite length >= 0 per dimension (0: not "
                         f"periodic), shape ({dim},); got {np.asarray(period).tolist()}")
    return p if p.any() else None


def pair_distance(positions: np.ndarray, senders: np.ndarray, receivers: np.ndarray,
                  period: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """Euclidean distance ``|x_receiver - x_sender|`` for each pair, in float64; with
    ``period`` (D,) the minimum-image distance (each periodic coordinate difference moved by
    whole box lengths into ``[-L/2, L/2]``).

    This is the one distance formula of the package: the square root of the squared coordinate
    differences summed in coordinate order. Every neighbour decision (and every test oracle) uses
    it, so a pair at exactly the cut-off is judged the same way everywhere. It is symmetric bit for
    bit (negating a difference is exact), and translation does not change it when the
    coordinate differences are exact.
    """
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2:
        raise ValueError(f"positions must have shape (N, D), got shape {pos.shape}")
    s = np.asarray(senders)
    r = np.asarray(receivers)
    if s.shape != r.shape or s.ndim != 1:
        raise ValueError(
            f"senders and receivers must be 1-D and of equal length, got {s.shape} and {r.shape}"
        )
    p = _as_period(period, pos.shape[1])
    total = np.zeros(s.shape[0], dtype=np.float64)
    # One column at a time: gathers from contiguous columns are several times faster than
    # gathering rows and reducing, and the summation order is fixed (no pairwise summation).
    for d, column in enumerate(np.ascontiguousarray(pos.T)):
        diff = column[r] - column[s]
        if p is not None and p[d] > 0:
            diff -= p[d] * np.rint(diff / p[d])
        diff *= diff
        total += diff
    return np.sqrt(total, out=total)


def _symmetric_sorted(i: np.ndarray, j: np.ndarray, n: int) -> np.ndarray:
    """Both directions of the undirected pairs ``(i, j)``, sorted by (receiver, sender)."""
    if i.size == 0:
        return _empty_edges()
    # int32 halves the memory traffic of the steps below, and scipy would copy to int32 anyway.
    index_dtype = np.int32 if n <= np.iinfo(np.int32).max else np.int64
    m = i.size
    senders = np.empty(2 * m, dtype=index_dtype)
    receivers = np.empty(2 * m, dtype=index_dtype)
    senders[:m], senders[m:] = i, j
    receivers[:m], receivers[m:] = j, i
    # COO -> CSR is a counting sort by receiver (linear in E); rows then hold about the mean
    # degree each, so sorting senders within rows is cheap (scipy does it while canonicalising;
    # sort_indices() below makes that explicit and costs nothing then); faster than sorting a
    # combined int64 key or np.lexsort
    # (docs/notes/2026-11-26-results-history.md, "Measurements behind the defaults").
    adjacency = sp.csr_matrix(
        (np.ones(senders.size, dtype=np.int8), (receivers, senders)), shape=(n, n)
    )
    del senders, receivers
    adjacency.sort_indices()
    out = np.empty((2, adjacency.indices.size), dtype=np.int64)
    out[0] = adjacency.indices
    out[1] = np.repeat(np.arange(n, dtype=index_dtype), np.diff(adjacency.indptr))
    return out


def radius_graph(
    positions: np.ndarray,
    radii: np.ndarray | None = None,
    margin: float = 0.0,
    cutoff: float | None = None,
    period: Sequence[float] | np.ndarray | None = None,
) -> np.ndarray:
    """All pairs of distinct points within a distance, both directions, sorted by receiver.

    Edges are sorted by (receiver, sender). Exactly one mode:

    - ``radii`` given (shape ``(N,)``, finite, >= 0): pairs with
      ``|x_i - x_j| <= (r_i + r_j) + margin``, the collision candidates of
      docs/design.md#graphs.
    - ``cutoff`` given (finite, >= 0): pairs with ``|x_i - x_j| <= cutoff``; ``margin`` must be 0.

    Distances come from :func:`pair_distance`; the comparison is inclusive, so points exactly at
    the threshold are neighbours. Cost is ``O(N log N + candidates)`` with a KD-tree queried at the
    largest possible pair threshold (``2 max(r) + margin`` or ``cutoff``). With very uneven radii
    the candidates outnumber the final edges; the result is still exact.

    Args:
        positions: ``(N, D)`` array, ``D >= 1``, finite.
        radii: per-point radii, or None for cutoff mode.
        margin: added to ``r_i + r_j`` in radii mode (see :func:`contact_margin`), finite, >= 0.
        cutoff: a single distance threshold, or None for radii mode.
        period: ``(D,)`` box lengths of periodic boundaries (0: that dimension is not
            periodic), or None. Distances are then minimum-image ones; the points may lie
            anywhere (unwrapped), and the largest pair threshold must be below half of every
            periodic length (a pair then meets within it through one image at most).

    Returns:
        ``int64`` array of shape ``(2, E)``: senders, receivers. ``(2, 0)`` when ``N < 2``.
    """
    pos = _as_positions(positions)
    n = pos.shape[0]
    if (radii is None) == (cutoff is None):
        raise ValueError("give exactly one of radii (with an optional margin) or cutoff")
    margin = as_float(margin, "margin", minimum=0.0)

    rad: np.ndarray | None = None
    if radii is not None:
        rad = np.asarray(radii)
        if rad.shape != (n,):
            raise ValueError(f"radii must have shape (N,) = ({n},), got {rad.shape}")
        rad = as_real_array(rad, "radii")
        if n and rad.min() < 0:
            raise ValueError(f"radii must be >= 0, found {rad.min()}")
        reach = 2.0 * float(rad.max()) + margin if n else 0.0
    else:
        cut = as_float(cutoff, "cutoff", minimum=0.0)
        if margin != 0.0:
            raise ValueError("margin applies only with radii; fold it into cutoff instead")
        reach = cut

    box = _as_period(period, pos.shape[1])
    if box is not None and reach >= 0.5 * box[box > 0].min():
        raise ValueError(f"the radius graph's reach {reach:g} must be below half the periodic "
                         f"box length {box[box > 0].min():g}: a pair would meet within it "
                         "through two images; use a smaller connectivity radius or a larger box")
    if n < 2:
        return _empty_edges()

    query_radius = reach * (1.0 + _QUERY_RELATIVE_SLACK) + _QUERY_ABSOLUTE_SLACK
    if box is None:
        tree = cKDTree(pos)
    else:  # the tree's torus wants coordinates in [0, L) (any origin: a torus has none)
        wrapped = np.array(pos, dtype=np.float64)
        periodic = box > 0
        wrapped[:, periodic] = np.mod(wrapped[:, periodic], box[periodic])
        # mod of a tiny negative value rounds to L itself
        wrapped[:, periodic] = np.where(wrapped[:, periodic] >= box[periodic], 0.0,
                                        wrapped[:, periodic])
        tree = cKDTree(wrapped, boxsize=box)
    pairs = tree.query_pairs(query_radius, output_type="ndarray")
    if pairs.size == 0:
        return _empty_edges()
    i = pairs[:, 0].astype(np.int64, copy=False)
    j = pairs[:, 1].astype(np.int64, copy=False)

    distance = pair_distance(pos, i, j, box)
    if rad is not None:
        keep = distance <= (rad[i] + rad[j]) + margin
    else:
        keep = distance <= reach
    if not keep.all():  # in cutoff mode the slack adds almost no candidates: skip a copy
        i, j = i[keep], j[keep]
    return _symmetric_sorted(i, j, n)


def contact_margin(max_relative_speed: float, dt: float, safety: float = 1.5) -> float:
    """Margin for :func:`radius_graph` that makes every contact before the next frame a candidate.

    Two particles close their gap by at most ``relative speed x dt`` between frames, so pairs
    within ``r_i + r_j + v_rel dt`` now contain every pair that can touch before the next graph is
    built. The safety factor (default 1.5) covers what that bound leaves out: the relative speed
    can grow during the step (forces, gravity, a collision that sends a third particle faster),
    the largest speed is usually estimated from the current frame only, and integrator substeps
    can overshoot. Too large a margin only adds candidate edges; too small silently misses
    collisions, so the factor errs on the large side.

    Args:
        max_relative_speed: an upper bound on ``|v_i - v_j|`` over pairs (e.g. twice the largest
            speed), finite, >= 0.
        dt: time until the next frame, finite, > 0.
        safety: multiplier >= 1.

    Returns:
        ``safety * max_relative_speed * dt``.
    """
    speed = as_float(max_relative_speed, "max_relative_speed", minimum=0.0)
    step = as_float(dt, "dt", minimum=0.0)
    if step == 0.0:
        raise ValueError("dt must be > 0")
    factor = as_float(safety, "safety", minimum=1.0)
    return factor * speed * step


def batch_edges(edge_lists: Sequence[np.ndarray], n_nodes: Sequence[int]) -> np.ndarray:
    """Disjoint union of graphs: each graph's indices offset by the node count before it.

    Node ``k`` of graph ``g`` becomes node ``sum(n_nodes[:g]) + k`` of the batch. If every input is
    sorted by (receiver, sender), so is the output.

    Args:
        edge_lists: one ``(2, E_g)`` integer array per graph, indices in ``[0, n_nodes[g])``.
        n_nodes: node count of each graph.

    Returns:
        ``int64`` array of shape ``(2, sum E_g)``.
    """
    if len(edge_lists) != len(n_nodes):
        raise ValueError(
            f"got {len(edge_lists)} edge lists but {len(n_nodes)} node counts; one per graph"
        )
    pieces = []
    offset = 0
    for g, (edges, count) in enumerate(zip(edge_lists, n_nodes, strict=True)):
        count = as_int(count, f"n_nodes[{g}]")
        e = np.asarray(edges)
        if e.ndim != 2 or e.shape[0] != 2:
            raise ValueError(f"edge_lists[{g}] must have shape (2, E), got {e.shape}")
        if e.size and not np.issubdtype(e.dtype, np.integer):
            raise ValueError(f"edge_lists[{g}] must hold integers, got dtype {e.dtype}")
        e = e.astype(np.int64, copy=False)
        if e.size and (e.min() < 0 or e.max() >= count):
            raise ValueError(
                f"edge_lists[{g}] has node indices in [{e.min()}, {e.max()}], "
                f"outside [0, {count}) for a graph of {count} nodes"
            )
        pieces.append(e + offset)
        offset += count
    if not pieces:
        return _empty_edges()
    return np.concatenate(pieces, axis=1)


def scene_edges(graph: str, positions: np.ndarray, radii: np.ndarray, margin: float,
                period: Sequence[float] | None = None) -> np.ndarray:
    """The edges a scene asks for (``SceneMeta.graph``): complete, or pairs closer than
    ``r_i + r_j + margin`` (minimum-image distances where ``period``, ``SceneMeta.period``,
    is given)."""
    if graph == "full":
        return full_graph(len(positions))
    if graph == "radius":
        return radius_graph(positions, radii=radii, margin=margin, period=period)
    raise ValueError(f"unknown graph kind {graph!r}; use 'full' or 'radius'")


def pair_codes(i: np.ndarray, j: np.ndarray, n: int) -> np.ndarray:
    """One integer per unordered pair {i, j} of n nodes (``min * n + max``): edges in both
    directions and recorded contacts ``(i < j)`` compare with ``np.isin``."""
    i, j = np.asarray(i, dtype=np.int64), np.asarray(j, dtype=np.int64)
    return np.minimum(i, j) * n + np.maximum(i, j)
