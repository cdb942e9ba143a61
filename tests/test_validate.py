"""Bad input is refused before any work, with one line naming the key, the value and what is
accepted, and exit code 2 (bgn.training.validate, the schemas of bgn.training.config)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra.core.global_hydra import GlobalHydra

from bgn.training.validate import ConfigError, validate_generate, validate_train
from tests.conftest import compose_config

ROOT = Path(__file__).resolve().parents[1]


def refused(config: str, *overrides: str) -> str:
    """The ConfigError message of composing and validating ``config`` with ``overrides``."""
    cfg = compose_config(config, list(overrides))
    check = validate_train if config == "train" else validate_generate
    with pytest.raises(ConfigError) as err:
        check(cfg)
    message = str(err.value)
    assert "\n" not in message
    return message


@pytest.mark.parametrize("overrides, expected", [
    (["fps=1e9"], ["fps=1000000000.0", "too high for spring", "use fps <= "]),
    (["fps=0"], ["fps=0.0", "> 0"]),
    (["dataset.n_frames=3"], ["dataset.n_frames=3", ">= dataset.history + 3 = 8"]),
    (["dataset.n_frames=4"], ["dataset.n_frames=4", ">= dataset.history + 3 = 8"]),
    (["dataset.n_frames=7"], ["dataset.n_frames=7", "= 8"]),
    (["optimizer.lr=-1"], ["optimizer.lr=-1", "> 0"]),
    (["optimizer.lr=0"], ["optimizer.lr=0", "> 0"]),
    (["model.hidden=0"], ["model.hidden=0", "positive integer"]),
    (["model=gns", "model.latent=0"], ["model.latent=0", "positive integer"]),
    (["dataset.history=0"], ["dataset.history=0", "model.target_prior=none"]),
    (["dataset.history=-1"], ["dataset.history=-1", ">= 0"]),
    (["dataset.n_particles=1"], ["dataset.n_particles", ">= 2"]),
    (["dataset.dim=0"], ["dataset.dim=0", ">= 1"]),
    (["dataset.n_sims=0"], ["dataset.n_sims=0", ">= 1"]),
    (["dataset.batch_size=0"], ["dataset.batch_size=0", ">= 1"]),
    (["dataset.val_samples=0"], ["dataset.val_samples=0", ">= 1"]),
    (["+dataset.train_sims=201"], ["dataset.train_sims=201", "1..200"]),
    (["dataset.seed=-1"], ["dataset.seed=-1"]),
    (["seed=-3"], ["seed=-3"]),
    (["rollout_steps=-1"], ["rollout_steps=-1", ">= 0"]),
    (["scheduler.factor=2"], ["scheduler.factor=2", "< 1"]),
    (["dataset=collisions", "dataset.box=-1"], ["dataset.box", "> 0"]),
    (["model.dynamics=foo"], ["model.dynamics='foo'",
                              "'decoder', 'newton', 'soft_contact', 'auto'"]),
    (["dataset=collisions", "model.dynamics=soft_contact"],
     ["model.dynamics='soft_contact'", "acceleration target", "velocity target"]),
    (["model.dynamics=soft_contact", "model.contact_energy=foo"],
     ["model.contact_energy='foo'", "'lose', 'any'"]),
    (["model.dynamics=soft_contact", "model.contact_substeps=0"], ["contact_substeps=0"]),
    (["model.dynamics=soft_contact", "model.contact_calibration=yes"],
     ["model.contact_calibration='yes'", "'rollout', 'none'"]),
])
def test_train_config_refused_with_one_line(overrides, expected):
    message = refused("train", *overrides)
    for part in expected:
        assert part in message, message


def test_history_zero_suggests_what_works():
    # spring (acceleration target): a window of history 0 has no observed target at all
    message = refused("train", "dataset.history=0")
    assert "set model.target_prior=none" in message and "target_prior=last" not in message
    # with none the same window is fine
    validate_train(compose_config("train", ["dataset.history=0", "model.target_prior=none"]))
    # linear needs two: history 1 gives one, so last is what fits
    assert "set model.target_prior=last" in refused(
        "train", "dataset.history=1", "model.target_prior=linear")


@pytest.mark.parametrize("scene", ["gravity_r1", "gravity_r2"])
def test_a_decoder_whose_dynamics_loss_weighs_nothing_is_refused(scene):
    """The gravity scenes train the pair-force law alone (dynamics weight 0): with the decoder
    that trap trains no dynamics at all; the message names the fixes, which pass."""
    base = [f"dataset={scene}", "model=bgn"]
    message = refused("train", *base, "model.dynamics=decoder")
    assert "model.loss_weights.dynamics=0" in message and "model=bgn_decoder" in message
    assert "model.loss_weights.dynamics=1" in message
    for fixed in (["model=bgn_decoder"], [*base, "model.dynamics=decoder",
                                          "model.loss_weights.dynamics=1"],
                  base, [*base, "model.dynamics=auto"]):   # the head's law loss, auto's own
        validate_train(compose_config("train", [f"dataset={scene}", *fixed]))
    assert "model.loss_weights.dynamics=0" in refused(
        "train", "model.loss_weights.dynamics=0")                 # spring, the decoder


def test_generate_config_refused():
    assert "workers=0" in refused("generate", "workers=0")
    assert "dataset.n_frames=4" in refused("generate", "dataset.n_frames=4")
    assert "fps=1000000000.0" in refused("generate", "fps=1e9")


def test_defaults_and_the_study_frame_rates_pass():
    for scene in ("spring", "gravity_r1", "gravity_r2", "collisions"):
        for fps in (10, 200):
            validate_train(compose_config("train", [f"dataset={scene}", f"fps={fps}"]))
            validate_generate(compose_config("generate", [f"dataset={scene}", f"fps={fps}"]))


def test_typed_schema_refuses_wrong_types_at_composition():
    from hydra.errors import ConfigCompositionException

    for bad in ("fps=abc", "dataset.n_frames=x", "seed=1.5", "dataset.history=abc"):
        with pytest.raises(ConfigCompositionException):
            compose_config("train", [bad])
    with pytest.raises(ConfigCompositionException):
        compose_config("train", ["dataset=collisions", "dataset.types.0.radius=big"])
    with pytest.raises(ConfigCompositionException):  # a typo in a scene parameter
        compose_config("train", ["dataset.softenin=0.1"])


def run_app(monkeypatch, capsys, tmp_path, module: str, *overrides: str) -> tuple[int, str]:
    """Run an entry point's Hydra app in this process; (exit code, stderr)."""
    import importlib

    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.delenv("BGN_FULL_ERROR", raising=False)
    monkeypatch.setattr(sys, "argv", [module, *overrides, f"hydra.run.dir={tmp_path / 'run'}",
                                      f"paths.data_dir={tmp_path / 'data'}"])
    main = importlib.import_module(module).main
    with pytest.raises(SystemExit) as exit_:
        main()
    GlobalHydra.instance().clear()
    assert os.environ.get("HYDRA_FULL_ERROR") is None  # the user's setting is restored
    return exit_.value.code, capsys.readouterr().err


@pytest.mark.parametrize("override, expected", [
    ("fps=abc", "fps=abc"),                      # refused by the schema, at composition
    ("optimizer.lr=-1", "optimizer.lr=-1"),      # refused by the validation
    ("dataset.n_frames=4", "dataset.n_frames=4"),
    ("dataset=nope", "dataset/nope"),            # an unknown config
])
def test_train_app_exits_2_with_one_line(monkeypatch, capsys, tmp_path, override, expected):
    code, err = run_app(monkeypatch, capsys, tmp_path, "bgn.train.__main__", override)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0] and "BGN_FULL_ERROR=1" in lines[0], err
    assert "Traceback" not in err
    assert not (tmp_path / "data").exists()  # nothing generated


@pytest.mark.slow
@pytest.mark.parametrize("args", [["fps=abc"], ["model.hidden=0"], ["dataset.history=0"]])
def test_train_command_exits_2_without_traceback(tmp_path, args):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("HYDRA_FULL_ERROR", None)
    env.pop("BGN_FULL_ERROR", None)
    cmd = [sys.executable, "-m", "bgn.train", *args, f"paths.data_dir={tmp_path / 'data'}",
           f"hydra.run.dir={tmp_path / 'run'}"]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert args[0].split("=")[0] in done.stderr
    # the full trace on request
    full = subprocess.run(cmd, capture_output=True, text=True, timeout=120,
                          env={**env, "BGN_FULL_ERROR": "1"})
    assert full.returncode != 0 and "Traceback" in full.stderr


def test_study_validates_every_cell_before_training(monkeypatch, capsys):
    """A bad preset fails before the first cell trains, naming the cell."""
    from hydra import initialize_config_dir
    from omegaconf import OmegaConf

    import bgn.studies.dispatch as dispatch
    import bgn.studies.grid as grid
    from tests.conftest import CONF_DIR

    cfg = compose_config("experiments", ["preset=tiny"])
    OmegaConf.update(cfg, "preset.scene_overrides.collisions",
                     ["dataset.n_particles=30", "dataset.box=4.0", "dataset.n_frames=5"])
    trained = []
    monkeypatch.setattr(grid, "train_cell", lambda *a: trained.append(a))
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        with pytest.raises(SystemExit) as exit_:
            dispatch.main(cfg)
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and len(err.strip().splitlines()) == 1
    assert "bgn: error: cell collisions_" in err and "dataset.n_frames=5" in err
    assert not trained


def test_the_default_rollout_sims_are_capped_at_a_small_validation_split(monkeypatch):
    """One validation simulation (an import of few trajectories): the default
    ``val_rollout_sims=2`` rolls out that one; the same value typed, or more, is refused."""
    from bgn.training import validate

    monkeypatch.setattr(validate, "ARGV", ["python -m bgn.train", "dataset.n_sims=1"])
    cfg = compose_config("train", ["dataset.n_sims=1"])
    assert validate_train(cfg).with_split("val").n_sims == 1
    assert cfg.val_rollout_sims == 1
    for given in (2, 3):
        monkeypatch.setattr(validate, "ARGV", ["python -m bgn.train", f"val_rollout_sims={given}"])
        with pytest.raises(ConfigError, match="val_rollout_sims.*validation simulations: 1"):
            validate_train(compose_config("train", ["dataset.n_sims=1",
                                                    f"val_rollout_sims={given}"]))
    cfg = compose_config("train", ["dataset.n_sims=3"])  # enough: the default stands
    validate_train(cfg)
    assert cfg.val_rollout_sims == 2


def test_the_coupling_law_beyond_its_particle_limit_is_refused_before_anything_runs():
    """Couplings are fitted densely per simulation: with more particles than
    ``coupling.MAX_PARTICLES`` the job would crawl for minutes per step, so the config is
    refused in one line naming the limit and the other mass laws; at the limit it passes."""
    from bgn.model.coupling import MAX_PARTICLES

    head = ["dataset=spring", "model.dynamics=newton", "model.mass_law=coupling"]
    message = refused("train", *head, f"dataset.n_particles={MAX_PARTICLES + 1}")
    assert f"at most {MAX_PARTICLES} particles" in message and "mass_law=inertial" in message
    assert "model.mass_law" in message
    validate_train(compose_config("train", [*head, f"dataset.n_particles={MAX_PARTICLES}"]))
    validate_train(compose_config("train", ["dataset=spring", "model.dynamics=newton",
                                            f"dataset.n_particles={MAX_PARTICLES + 1}"]))
    # a contact scene's structured head is the impulse head, which reads no mass law
    validate_train(compose_config("train", ["dataset=collisions", "model.dynamics=newton",
                                            "model.mass_law=coupling"]))
