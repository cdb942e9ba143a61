"""Shared fixtures: real Hydra configs composed from conf/, small sizes, a temporary data dir."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from bgn.training.config import register_configs

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"

# Small but meaningful sizes per scene, so data tests run in seconds. Data that a training
# config generates are simulated in the test's process (dataset.generate_workers=1): spawning
# a pool of workers costs more than these simulations.
IN_PROCESS = "+dataset.generate_workers=1"
SMALL = {
    "spring": ["dataset.n_sims=2", "dataset.n_frames=60", IN_PROCESS],
    "gravity_r1": ["dataset.n_sims=2", "dataset.n_frames=60", IN_PROCESS],
    "gravity_r2": ["dataset.n_sims=2", "dataset.n_frames=60", IN_PROCESS],
    "collisions": ["dataset.n_sims=2", "dataset.n_frames=40", "dataset.n_particles=30",
                   "dataset.box=4.0", IN_PROCESS],
}

# spring's and gravity_r2's BGN read their law back as a formula after training
# (model.law=auto), a stage the commands hand to bgn.training.run.train: a test of the
# training alone, calling train() itself, keeps the network law
NETWORK_LAW = "model.law=mlp"


# the provenance record report.md is written with, for tests of the report's text alone
REPORT_RECORD = {"split": "test", "command": "c", "checkpoint": "k", "run_config": "r",
                 "run_config_hash": "h", "git_commit": "g", "machine": "m", "cpu_count": 1,
                 "torch_threads": 1, "seeds": {}, "calibration_split": "val",
                 "wall_time_s": 0.0}
TINY_RUN = ["dataset=spring", *SMALL["spring"], NETWORK_LAW, "dataset.test_samples=17",
            "model.hidden=8", "model.decoder_hidden=8", "model.flow_hidden=8", "figures=false",
            "val_rollout_steps=0",
            "callbacks.progress_bar=null", "trainer.max_epochs=1",
            "+trainer.limit_train_batches=2", "trainer.limit_val_batches=1",
            "trainer.enable_model_summary=false"]


# The law search at its defaults costs tens of seconds per law (bgn.laws.search). A test of what
# reads a law back (evaluate's report, the formula stage, auto's formula candidate, the laws
# command) checks the plumbing, not the search: it gets a search of the same grammar cut to
# sums of two terms, no products, no potentials, few starts, which still finds a spring's or a
# softened power law. The search itself is tested on its own (tests/laws/test_search.py, which
# calls bgn.laws.search directly, with options of its own).
def fast_search_options():
    """The cut search of the tests (above)."""
    from bgn.laws.options import SEARCH_DEFAULTS

    return replace(SEARCH_DEFAULTS, potentials=False, max_terms=2, product_terms=1,
                   random_starts=2, random_forms=1, refine_per_size=5)


@pytest.fixture(autouse=True)
def fast_law_search(monkeypatch):
    """In-process law searches at the defaults (but for ``max_terms``, python -m bgn.laws's
    key) run with ``fast_search_options`` (see above); a search given other options keeps
    them."""
    import bgn.laws.compare as compare
    from bgn.laws.options import SEARCH_DEFAULTS

    full, fast = compare.search_law, fast_search_options()

    def search(r, y, weight=None, tolerance=compare.DEFAULTS.tolerance,
               options=SEARCH_DEFAULTS):
        if replace(options, max_terms=SEARCH_DEFAULTS.max_terms) == SEARCH_DEFAULTS:
            options = replace(fast, max_terms=min(options.max_terms, fast.max_terms))
        return full(r, y, weight, tolerance, options)

    monkeypatch.setattr(compare, "search_law", search)


def compose_config(config_name: str, overrides: list[str]) -> DictConfig:
    register_configs()  # the model schemas (conf/model/<name>.yaml build on them)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name=config_name, overrides=overrides)


@pytest.fixture
def small_cfg(tmp_path: Path):
    """``small_cfg(scene, *overrides)`` -> a composed generate config writing to tmp_path."""

    def make(scene: str, *overrides: str) -> DictConfig:
        return compose_config("generate", [f"dataset={scene}", *SMALL[scene],
                                           f"paths.data_dir={tmp_path / 'data'}", *overrides])

    return make


@pytest.fixture(scope="session")
def shared_data_dir(tmp_path_factory) -> Path:
    """One data cache for the whole session: training tests reuse the small datasets."""
    return tmp_path_factory.mktemp("data")


@pytest.fixture(scope="session")
def small_datamodules(shared_data_dir: Path) -> dict:
    """The small DataModule of every scene in ``SMALL``, data generated and set up once per
    session (shared by the tests that read every scene)."""
    from bgn.training.run import data_module

    out = {}
    for scene in SMALL:
        cfg = compose_config("train", [f"dataset={scene}", *SMALL[scene],
                                       f"paths.data_dir={shared_data_dir}"])
        dm = data_module(cfg)
        dm.prepare_data()
        dm.setup()
        out[scene] = dm
    return out


@pytest.fixture(scope="session")
def trained_run(tmp_path_factory, shared_data_dir: Path) -> tuple[Path, dict[str, float]]:
    """A tiny spring run trained by ``bgn.training.run.train`` (its test phase included), with the
    config Hydra would have saved in ``.hydra/config.yaml``; returns (run dir, its metrics).
    Shared by the session's tests (evaluate, the API): they read it, they never retrain it."""
    from omegaconf import OmegaConf

    from bgn.training.run import train

    run = tmp_path_factory.mktemp("run")
    cfg = compose_config("train", [*TINY_RUN, f"paths.data_dir={shared_data_dir}",
                                   f"paths.output_dir={run}"])
    metrics = train(cfg)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    return run, metrics
