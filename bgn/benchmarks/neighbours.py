"""Benchmark of :func:`bgn.data.edges.radius_graph`: does neighbour search scale linearly in N?

Uniform random points in 2-D at a density giving about ``neighbours`` neighbours per point
within a cut-off of 1. Writes ``neighbours.md``, ``neighbours.csv`` and ``neighbours.png`` (time
against N, log-log, with a linear reference line) under ``report_dir``::

    python -m bgn.benchmarks.neighbours [sizes=[2000,20000,200000]] [neighbours=20]
        [report_dir=outputs/benchmarks]      # --help: every key (conf/benchmarks/neighbours.yaml)

The scaling ratio is ``(t(N_b) / t(N_a)) / (N_b / N_a)`` for the two largest sizes, so with the
defaults ``t(200k) / t(20k) / 10``: 1 is linear, above 1 is worse than linear.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy

from bgn.benchmarks._report import command, console, need_ints, options, print_table
from bgn.data.edges import radius_graph
from bgn.provenance import machine
from bgn.tables import markdown_table, write_csv
from bgn.training.validate import ConfigError, need_int

CUTOFF = 1.0
# Single runs above this size: the largest case is slow enough that noise matters less.
BEST_OF_3_BELOW = 100_000


@dataclass(frozen=True)
class Row:
    n: int
    edges: int
    repeats: int
    seconds: float  # best of `repeats` timed calls, after the first call
    first_call: float  # the first call at this size, untimed in `seconds`

    @property
    def mean_degree(self) -> float:
        return self.edges / self.n

    @property
    def edges_per_second(self) -> float:
        return self.edges / self.seconds

    @property
    def us_per_particle(self) -> float:
        return 1e6 * self.seconds / self.n


def box_side(n: int, neighbours: float, dim: int = 2) -> float:
    """Side of the square holding n uniform points with `neighbours` expected within CUTOFF.

    Expected neighbours = density x area of the cut-off disc = n / L^2 x pi r^2 (fewer near the
    box edges, so the measured mean degree is slightly below the target).
    """
    assert dim == 2
    return math.sqrt(n * math.pi * CUTOFF**2 / neighbours)


def time_one(n: int, neighbours: float, repeats: int, rng: np.random.Generator) -> Row:
    positions = rng.uniform(0.0, box_side(n, neighbours), size=(n, 2))
    # The first call at a new size pays for first-touch page faults on memory the process (in a
    # VM, even the guest) never used before: at 200k about as much as the search
    # (docs/notes/2026-11-26-results-history.md, "Moved here from code comments and configs").
    # Report it separately, and time the steady state a training loop sees.
    start = time.perf_counter()
    radius_graph(positions, cutoff=CUTOFF)
    first_call = time.perf_counter() - start
    best = math.inf
    edges = 0
    for _ in range(repeats):
        start = time.perf_counter()
        out = radius_graph(positions, cutoff=CUTOFF)
        best = min(best, time.perf_counter() - start)
        edges = out.shape[1]
        del out
    return Row(n=n, edges=edges, repeats=repeats, seconds=best, first_call=first_call)


def scaling_ratio(rows: list[Row]) -> tuple[Row, Row, float, float] | None:
    """(t_b / t_a) / (N_b / N_a) for the two largest sizes, steady state and first call.

    None with fewer than two sizes.
    """
    ordered = sorted(rows, key=lambda r: r.n)
    if len(ordered) < 2:
        return None
    a, b = ordered[-2], ordered[-1]
    growth = b.n / a.n
    return a, b, (b.seconds / a.seconds) / growth, (b.first_call / a.first_call) / growth


HEADERS = [
    "N",
    "edges",
    "mean degree",
    "seconds",
    "edges / s",
    "us / particle",
    "runs",
    "first call s",
]


def formatted(row: Row) -> list[str]:
    return [
        f"{row.n:,}",
        f"{row.edges:,}",
        f"{row.mean_degree:.2f}",
        f"{row.seconds:.4f}",
        f"{row.edges_per_second / 1e6:.2f} M",
        f"{row.us_per_particle:.3f}",
        ("best of " if row.repeats > 1 else "") + str(row.repeats),
        f"{row.first_call:.4f}",
    ]


CSV_HEADER = [
    "n",
    "edges",
    "mean_degree",
    "seconds",
    "edges_per_second",
    "us_per_particle",
    "runs",
    "first_call_seconds",
]


def csv_row(r: Row) -> list:
    return [
        r.n,
        r.edges,
        f"{r.mean_degree:.4f}",
        f"{r.seconds:.6f}",
        f"{r.edges_per_second:.1f}",
        f"{r.us_per_particle:.4f}",
        r.repeats,
        f"{r.first_call:.6f}",
    ]


def write_markdown(
    rows: list[Row],
    ratio: tuple[Row, Row, float, float] | None,
    neighbours: float,
    retained: bool,
    path: Path,
) -> None:
    lines = [
        "# Neighbour search benchmark (`radius_graph`)",
        "",
        f"Uniform random points in 2-D, cut-off {CUTOFF}, density for about {neighbours:g} "
        "neighbours per point (fewer near the box edges). Edges are directed (both directions).",
        "Time is one `radius_graph` call: KD-tree build, pair query, exact distance filter, "
        "sort by (receiver, sender). `seconds` is the best of the timed runs after one untimed "
        "first call at that size; `first call s` is that first call, which also pays for "
        "first-touch page faults on fresh memory.",
        "",
        f"Machine: {machine(scipy=scipy.__version__)}",
        "",
        "Allocator: "
        + (
            "freed memory retained in the process (`retain_memory=true`)."
            if retained
            else "default glibc malloc (arrays over 32 MiB are page-faulted again on every call; "
            "`retain_memory=true` measures without that)."
        ),
        "",
        markdown_table(HEADERS, [dict(zip(HEADERS, formatted(r))) for r in rows]),
    ]
    lines.append("")
    if ratio is not None:
        a, b, value, cold = ratio
        lines.append(
            f"Linear-scaling ratio (t({b.n:,}) / t({a.n:,})) / ({b.n:,} / {a.n:,}) = "
            f"**{value:.2f}** (1 = linear); from the first calls: {cold:.2f}."
        )
        lines.append("")
    lines.append("![time against N](neighbours.png)")
    path.write_text("\n".join(lines) + "\n")


def write_plot(rows: list[Row], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ordered = sorted(rows, key=lambda r: r.n)
    n = np.array([r.n for r in ordered], dtype=float)
    t = np.array([r.seconds for r in ordered])
    fig, ax = plt.subplots(figsize=(5.5, 4.0), dpi=120)
    first = np.array([r.first_call for r in ordered])
    ax.loglog(n, t, "o-", label="radius_graph (steady state)")
    ax.loglog(n, first, "s:", alpha=0.7, label="first call at that size")
    # Linear reference through the largest size, where fixed overheads matter least.
    reference = t[-1] * n / n[-1]
    ax.loglog(n, reference, "--", color="grey", label="linear (slope 1)")
    ax.set_xlabel("particles N")
    ax.set_ylabel("seconds")
    ax.set_title(f"Neighbour search, 2-D, mean degree {rows[-1].mean_degree:.1f}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def retain_freed_memory() -> bool:
    """Ask glibc malloc to keep freed memory instead of returning it to the kernel.

    Large arrays (over 32 MiB) are otherwise mmap-ed and unmapped on every call, so each call
    page-faults its whole working set again; in this VM that costs more than the search itself
    at 2 M points. Returns False where this is not glibc.
    """
    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_max = -1, -4  # from glibc's malloc.h
    return bool(mallopt(m_mmap_max, 0)) and bool(mallopt(m_trim_threshold, 2**31 - 1))


def check(cfg: Any) -> None:
    """Everything ``python -m bgn.benchmarks.neighbours`` is given, before any work."""
    from bgn.coerce import need_float

    need_ints(cfg.sizes, "sizes", 2, why=" (particles)")
    need_float(cfg.neighbours, "neighbours", 0, why=" (the target mean degree)")
    need_int(cfg.seed, "seed", 0)
    if not isinstance(cfg.retain_memory, bool):
        raise ConfigError("retain_memory", cfg.retain_memory, "true or false")


@command("neighbours", check)  # key=value; bad input: one line, exit 2
def main(cfg: Any) -> int:
    """Time the search at each size and write the report under ``report_dir``."""
    args = options(cfg)
    out = console()
    retained = args.retain_memory and retain_freed_memory()
    if args.retain_memory and not retained:
        out.print("[yellow]retain_memory=true: not glibc, ignored[/yellow]")
    rng = np.random.default_rng(args.seed)
    # Warm-up: first calls pay for lazy imports and page faults, not for the search.
    radius_graph(rng.uniform(size=(1000, 2)), cutoff=0.05)

    rows = []
    for n in sorted(set(args.sizes)):
        repeats = 3 if n < BEST_OF_3_BELOW else 1
        rows.append(time_one(n, args.neighbours, repeats, rng))
        out.log(f"N = {n:,}: {rows[-1].seconds:.4f} s (first call {rows[-1].first_call:.4f} s)")

    print_table(out, f"radius_graph, 2-D uniform, ~{args.neighbours:g} neighbours", HEADERS,
                [formatted(r) for r in rows])
    ratio = scaling_ratio(rows)
    if ratio is not None:
        a, b, value, cold = ratio
        out.print(
            f"linear-scaling ratio (t({b.n:,}) / t({a.n:,})) / {b.n / a.n:g} = "
            f"[bold]{value:.2f}[/bold] (1 = linear); from the first calls: {cold:.2f}"
        )

    args.report_dir.mkdir(parents=True, exist_ok=True)
    write_csv(args.report_dir / "neighbours.csv", CSV_HEADER,
              [dict(zip(CSV_HEADER, csv_row(r))) for r in rows])
    write_markdown(rows, ratio, args.neighbours, retained, args.report_dir / "neighbours.md")
    write_plot(rows, args.report_dir / "neighbours.png")
    out.print(f"wrote {args.report_dir / 'neighbours.md'}, .csv, .png")
    return 0


if __name__ == "__main__":
    main()
