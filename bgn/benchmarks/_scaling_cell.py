"""One cell of ``bgn.benchmarks.scaling`` (one model, one frame), in a process of its own.

Run as a script by path, with ``PYTHONPATH`` at the checkout to measure, so the same file times
this checkout or another one (``--against``): it imports only what every checkout has
(``build_model``, the ``Graph`` dataclass, ``SceneMeta``, the Hydra configs under ``conf/``).
The frame, its statistics and the scene record come in a ``torch.save`` file written by the
parent; one JSON line goes out on stdout (two with training: the timings, then the same with the
FLOP count). A process per cell keeps the peak resident memory
(``VmHWM``, reset at the cell's start) that cell's alone::

    python bgn/benchmarks/_scaling_cell.py PAYLOAD MODEL [--repeats 2] [--device cpu]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import bgn  # noqa: F401  (first: a checkout may set allocator variables before torch loads)

# isort: split
import torch
from torch.utils.flop_counter import FlopCounterMode


def graph_class() -> type:
    """The checkout's Graph dataclass (``bgn.graph`` now, ``bgn.data.batch`` before)."""
    try:
        from bgn.graph import Graph
    except ImportError:
        from bgn.data.batch import Graph
    return Graph


def train_config(overrides: list[str]):
    """The checkout's own training config (``conf/train.yaml``) with ``overrides``."""
    from hydra import compose, initialize_config_dir

    try:
        from bgn.training.config import register_configs
        register_configs()
    except ImportError:  # older checkouts had untyped configs
        pass
    conf = Path(bgn.__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        return compose("train", overrides=overrides)


def model_config(model: str) -> tuple[dict, float]:
    """The checkout's own config for ``model`` on collisions: (model options, learning rate)."""
    from omegaconf import OmegaConf

    cfg = train_config(["dataset=collisions", f"model={model}"])
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


def addmm_flop(self_shape: Any, a_shape: Any, b_shape: Any, out_shape: Any = None,
               **kwargs: Any) -> int:
    """FLOPs of the in-place ``addmm_``, which ``FlopCounterMode`` does not count by itself
    (the edge MLPs' first layer and weight gradients accumulate in place)."""
    return 2 * a_shape[0] * a_shape[1] * b_shape[1]


def train_step(model: Any, opt: torch.optim.Optimizer, g: Any) -> None:
    """One training step: forward, every loss term, backward, optimiser."""
    opt.zero_grad(set_to_none=True)
    model.total_loss(model.loss_terms(g, model(g))).backward()
    opt.step()


def training_throughput(overrides: list[str], steps: int, device: str = "cpu") -> dict:
    """Samples/s of a real training run's parts (``bgn.training.run.build``): the data loader alone,
    the model step alone (forward, backward, AdamW on batches already loaded), and Lightning's
    fit loop for ``steps`` steps (loader, step, logging, metrics, clipping; no validation),
    all on ``device``."""
    import lightning as L
    from hydra.utils import instantiate

    from bgn.training.run import build

    cfg = train_config(["dataset=collisions", "figures=false", *overrides])
    datamodule, module = build(cfg)
    batch = int(cfg.dataset.batch_size)

    def rate(seconds: float, n_steps: int) -> float:
        return n_steps * batch / seconds

    loader = iter(datamodule.train_dataloader())
    batches = [next(loader) for _ in range(steps)]            # the first pays for file opening
    start = time.perf_counter()
    for _ in range(steps):
        next(loader)
    result = {"loader_samples_s": rate(time.perf_counter() - start, steps)}

    cuda = torch.device(device).type == "cuda"
    model = module.model.to(device)
    batches = [g.to(device) for g in batches]
    opt = instantiate(cfg.optimizer, _convert_="all")(model.parameters()) \
        if "optimizer" in cfg else torch.optim.AdamW(model.parameters(), lr=1e-3)
    times = []
    for g in batches:
        start = time.perf_counter()
        train_step(model, opt, g)
        if cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    result["step_samples_s"] = rate(sum(times[1:]), steps - 1)

    class Clock(L.Callback):
        def on_train_batch_start(self, trainer, *_) -> None:
            if trainer.global_step == 1:                       # after the first (warm-up) step
                self.start = time.perf_counter()

    clock = Clock()
    trainer = L.Trainer(max_steps=steps + 1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        limit_val_batches=0, num_sanity_val_steps=0, callbacks=[clock],
                        gradient_clip_val=cfg.trainer.get("gradient_clip_val"),
                        accelerator="gpu" if cuda else "cpu", devices=1)
    trainer.fit(module, datamodule=datamodule)
    result["fit_samples_s"] = rate(time.perf_counter() - clock.start, steps)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("payload", type=Path, help="the frame (or, with --training, unused)")
    parser.add_argument("model")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--skip-train", action="store_true")
    parser.add_argument("--training", nargs="*", default=None, metavar="OVERRIDE",
                        help="measure the default collisions training instead (with overrides)")
    args = parser.parse_args(argv)
    if args.training is not None:
        json.dump(training_throughput([f"model={args.model}", *args.training], args.repeats,
                                      args.device), sys.stdout)
        print()
        return 0

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
        """Median of ``repeats`` timed calls (after a warm-up call by the caller)."""
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
        model.predict(g)                                       # warm-up
        result["infer_s"] = timed(lambda: model.predict(g))
    result["infer_peak_bytes"] = max(peak() - base, 0)

    if not args.skip_train:
        model.train()
        opt = torch.optim.AdamW(model.parameters(), lr=lr)
        train_step(model, opt, g)                              # warm-up
        result["train_s"] = timed(lambda: train_step(model, opt, g))
        result["train_peak_bytes"] = max(peak() - base, 0)
        # the timings out first: the FLOP count's dispatch keeps more alive than a plain
        # step (docs/notes/2026-11-26-results-history.md,
        # "The baselines' edge MLPs with their backward written out"), and a process killed
        # there keeps its timings
        json.dump(result, sys.stdout)
        print(flush=True)
        counter = FlopCounterMode(display=False,
                                  custom_mapping={torch.ops.aten.addmm_: addmm_flop})
        with counter:
            train_step(model, opt, g)
        result["train_flop"] = counter.get_total_flops()
    json.dump(result, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
