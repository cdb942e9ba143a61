"""One cell of ``bgn.benchmarks.scaling`` (one model, one frame), in a process of its own.

Run as a script by path, with ``PYTHONPATH`` at the checkout to measure, so the same file times
this checkout or another one (``--against``): it imports only what every checkout has
(``build_model``, the ``Graph`` dataclass, ``SceneMeta``, the Hydra configs under ``conf/``).
The frame, its statistics and the scene record come in a ``torch.save`` file written by the
parent; one JSON line goes out on stdout. A process per cell makes the peak resident memory
(``ru_maxrss``) that cell's alone::

    python bgn/benchmarks/_scaling_cell.py PAYLOAD MODEL [--repeats 2] [--device cpu]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import bgn  # noqa: F401  (first: a checkout may set allocator variables before torch loads)
import torch
from torch.utils.flop_counter import FlopCounterMode


def graph_class() -> type:
    """The checkout's Graph dataclass (``bgn.graph`` now, ``bgn.data.batch`` before)."""
    try:
        from bgn.graph import Graph
    except ImportError:
        from bgn.data.batch import Graph
    return Graph


def model_config(model: str) -> tuple[dict, float]:
    """The checkout's own config for ``model`` on collisions: (model options, learning rate)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    try:
        from bgn.config import register_configs
        register_configs()
    except ImportError:  # older checkouts had untyped configs
        pass
    conf = Path(bgn.__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose("train", overrides=["dataset=collisions", f"model={model}"])
    params = OmegaConf.to_container(cfg.model, resolve=True)
    lr = OmegaConf.select(cfg, "optimizer.lr", default=None) or params.get("lr", 1e-3)
    return params, float(lr)


def rss_bytes(field: str = "VmRSS") -> int:
    """Resident memory now (``VmRSS``) or its peak (``VmHWM``), from Linux /proc; 0 elsewhere.
    Not ``ru_maxrss``: that survives ``exec`` and so starts at the forking parent's size."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def reset_peak() -> None:
    """Restart the peak (``VmHWM``) from the current resident size (Linux 4.0+)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("payload", type=Path)
    parser.add_argument("model")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--skip-train", action="store_true")
    args = parser.parse_args(argv)

    from bgn.model.registry import build_model
    from bgn.sim.scene import SceneMeta

    payload = torch.load(args.payload, weights_only=False)
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    Graph = graph_class()
    known = {f.name for f in dataclasses.fields(Graph)}
    g = Graph(**{k: v for k, v in payload["graph"].items() if k in known}).to(device)
    meta = SceneMeta(**payload["meta"])
    params, lr = model_config(args.model)
    torch.manual_seed(0)
    model = build_model(params, meta, payload["stats"], payload["history"]).to(device)

    def sync() -> None:
        if cuda:
            torch.cuda.synchronize()

    def peak() -> int:
        return torch.cuda.max_memory_allocated() if cuda else rss_bytes("VmHWM")

    def timed(step) -> float:
        """Median of ``repeats`` timed calls after one untimed warm-up."""
        step()
        times = []
        for _ in range(args.repeats):
            sync()
            start = time.perf_counter()
            step()
            sync()
            times.append(time.perf_counter() - start)
        return sorted(times)[len(times) // 2]

    result: dict = {"edges": int(g.edge_index.shape[1]), "nodes": int(g.pos.shape[0])}
    base = torch.cuda.memory_allocated() if cuda else rss_bytes()
    torch.cuda.reset_peak_memory_stats() if cuda else reset_peak()
    # inference first: the peak of the training step would hide its smaller one
    model.eval()
    with torch.no_grad():
        result["infer_s"] = timed(lambda: model.predict(g))
    result["infer_peak_bytes"] = max(peak() - base, 0)

    if not args.skip_train:
        model.train()
        opt = torch.optim.AdamW(model.parameters(), lr=lr)

        def train_step() -> None:
            opt.zero_grad(set_to_none=True)
            loss = model.total_loss(model.loss_terms(g, model(g)))
            loss.backward()
            opt.step()

        # the FLOP count rides on an extra untimed step (it slows the dispatch a little)
        counter = FlopCounterMode(display=False)
        with counter:
            train_step()
        result["train_flop"] = counter.get_total_flops()
        result["train_s"] = timed(train_step)
        result["train_peak_bytes"] = max(peak() - base, 0)
    json.dump(result, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
