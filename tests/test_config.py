"""The composed training config: model defaults from the dataclasses, scene-specific model
defaults (conf/dataset_model/), the optimiser and scheduler partials, and what wins."""

from __future__ import annotations

import logging
from dataclasses import asdict
from functools import partial

import pytest
import torch
from hydra.errors import ConfigCompositionException
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import OmegaConf

from bgn.data.spec import DatasetSpec
from bgn.model.registry import MODELS
from bgn.training.module import PhysicsModule
from bgn.training.run import build_module, info, plain_stats
from tests.conftest import CONF_DIR, compose_config
from tests.model.conftest import fake_stats

SCENES = ["collisions", "spring", "gravity_r2", "gravity_r1"]
AUX = ("contact", "type", "mass_nll", "relmass")


def composed(*overrides: str):
    return compose_config("train", list(overrides))


def model_of(*overrides: str) -> dict:
    return OmegaConf.to_container(composed(*overrides).model, resolve=True)


def test_collisions_gives_bgn_its_measured_defaults():
    cfg = composed("dataset=collisions", "model=bgn")
    model = OmegaConf.to_container(cfg.model, resolve=True)
    assert model["contact_message"] == "vector"
    assert model["contact_pos_weight"] == 1
    assert cfg.optimizer.lr == 1e-3  # every model's (3e-3 lost on validation)
    assert model["loss_weights"] == {"dynamics": 1.0, "unroll": 1.0, "impulse_mass": 1.0,
                                     "law": 0.0, **dict.fromkeys(AUX, 1.0)}  # the paper's
    assert model["target_prior"] == "auto"


@pytest.mark.parametrize("scene", ["gravity_r1", "gravity_r2"])
def test_gravity_trains_the_structured_law_on_the_recorded_masses(scene):
    model = model_of(f"dataset={scene}", "model=bgn")
    assert (model["dynamics"], model["mass_law"]) == ("newton", "source")
    assert (model["loss_weights"]["dynamics"], model["loss_weights"]["law"]) == (0.0, 1.0)
    assert model["mass_context"] == "fit"


@pytest.mark.parametrize("scene", ["spring", "gravity_r1", "gravity_r2"])
def test_pair_force_scenes_hold_the_first_windows_masses_and_read_their_law_as_a_formula(scene):
    model = model_of(f"dataset={scene}")
    assert (model["rollout_masses"], model["law"]) == ("held", "auto")
    assert model_of(f"dataset={scene}", "model=newton")["rollout_masses"] == "window"


def test_every_scene_gives_bgn_the_structured_head_and_the_command_line_wins():
    assert model_of("dataset=spring", "model=bgn")["dynamics"] == "newton"
    assert model_of("dataset=spring", "model=bgn", "model.dynamics=decoder")["dynamics"] == \
        "decoder"
    assert model_of("dataset=collisions", "model=bgn")["dynamics"] == "newton"
    assert model_of("dataset=gravity_r1", "model=bgn")["dynamics"] == "newton"


@pytest.mark.parametrize("name", ["gns", "cranmer_gn"])
def test_collisions_leaves_the_baselines_alone(name):
    cfg = composed("dataset=collisions", f"model={name}")
    assert cfg.optimizer.lr == 1e-3  # the published-comparison lr, as on every other scene
    assert "contact_message" not in cfg.model and "loss_weights" not in cfg.model
    assert cfg.model.target_prior == "auto"


# (scene, model) where validation rollouts chose the paper's target over the schema's auto
PAPERS_TARGET = {("spring", m) for m in ("gns", "gns_given", "cranmer_gn", "cranmer_gn_given")} \
    | {("gravity_r1", m) for m in ("gns", "gns_given", "cranmer_gn", "cranmer_gn_given")} \
    | {("collisions", "gns_given")}


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("name", sorted(MODELS))
def test_target_prior_is_the_papers_where_validation_chose_it(scene, name):
    """The paper's target on gravity_r2 for every model, for spring's and gravity_r1's
    baselines and collisions' GNS given radii and types (chosen on validation
    rollouts, docs/results.md); the schema's auto elsewhere."""
    model = model_of(f"dataset={scene}", f"model={name}")
    papers = scene == "gravity_r2" or (scene, name) in PAPERS_TARGET
    assert model["target_prior"] == ("none" if papers else "auto")


@pytest.mark.parametrize("scene", ["spring", "gravity_r2", "gravity_r1"])
def test_other_scenes_keep_the_papers_bgn(scene):
    cfg = composed(f"dataset={scene}")
    assert cfg.model.contact_message == "linear" and cfg.optimizer.lr == 1e-3
    weights = dict(cfg.model.loss_weights)
    # the paper's weights of 1; gravity trains its structured law alone (test above)
    law_only = scene.startswith("gravity")
    assert weights.pop("law") == (1.0 if law_only else 0.0)
    assert weights.pop("dynamics") == (0.0 if law_only else 1.0)
    assert set(weights.values()) == {1.0}


def test_the_command_line_and_the_ablation_group_win():
    cfg = composed("dataset=collisions", "model.contact_message=linear", "optimizer.lr=0.01",
                   "model.loss_weights.type=0.5", "ablation=no_contact")
    assert (cfg.model.contact_message, cfg.optimizer.lr, cfg.model.loss_weights.type) == \
        ("linear", 0.01, 0.5)
    assert cfg.model.contact is False and cfg.model.loss_weights.contact == 1.0
    assert composed("dataset=gravity_r2", "model=gns",
                    "model.target_prior=linear").model.target_prior == "linear"


def test_model_options_are_typed_by_the_dataclass():
    assert composed("model.hidden=64").model.hidden == 64
    assert composed("model=gns", "model.latent=8").model.latent == 8
    for typo in (["model.hiden=3"], ["model=gns", "model.hidden=3"], ["model.hidden=abc"]):
        with pytest.raises(ConfigCompositionException):
            composed(*typo)
    # Any-typed: a number or "balanced", checked by ModelConfig.__post_init__
    assert composed("model.contact_pos_weight=1").model.contact_pos_weight == 1


@pytest.mark.parametrize("name", sorted(MODELS))
def test_the_dataclass_is_the_one_source_of_model_defaults(name):
    """conf/model/<name>.yaml only names its schema; the composed node is the dataclass."""
    raw = OmegaConf.load(CONF_DIR / "model" / f"{name}.yaml")
    assert set(raw) == {"defaults", "name"} and raw.name == name
    # without the scene-specific defaults (conf/dataset_model/)
    model = model_of("dataset=spring", f"model={name}", "~dataset_model")
    assert model.pop("name") == name
    assert model == asdict(MODELS[name].config_class())


def test_dataset_configs_hold_data_only_and_their_cache_key_ignores_the_model():
    for scene in SCENES:
        dataset = OmegaConf.load(CONF_DIR / "dataset" / f"{scene}.yaml")
        assert not {"target_prior", "bgn_defaults", "contact_message", "lr"} & set(dataset)
        keys = {DatasetSpec.from_config(composed(f"dataset={scene}", f"model={name}").dataset,
                                        50, "train").key() for name in MODELS}
        assert len(keys) == 1, scene


def built(*overrides: str) -> tuple[PhysicsModule, dict]:
    cfg = composed(*overrides)
    meta = DatasetSpec.from_config(cfg.dataset, 50, "train").build_scene().meta
    module = build_module(cfg, dict(vars(meta)), plain_stats(fake_stats(meta.dim)),
                          int(cfg.dataset.history))
    return module, module.configure_optimizers()


def check_today(conf: dict, lr: float) -> None:
    """AdamW(lr, weight_decay 0) and ReduceLROnPlateau(min, 0.5, 5, 0.01 lr) on val/nmse."""
    opt, sched = conf["optimizer"], conf["lr_scheduler"]["scheduler"]
    assert type(opt) is torch.optim.AdamW
    assert opt.defaults["lr"] == lr and opt.defaults["weight_decay"] == 0.0
    assert tuple(opt.defaults["betas"]) == (0.9, 0.999) and opt.defaults["eps"] == 1e-8
    assert type(sched) is torch.optim.lr_scheduler.ReduceLROnPlateau
    assert (sched.mode, sched.factor, sched.patience) == ("min", 0.5, 5)
    assert sched.min_lrs == [pytest.approx(0.01 * lr)]
    assert {k: v for k, v in conf["lr_scheduler"].items() if k != "scheduler"} == \
        {"monitor": "val/nmse", "interval": "epoch", "frequency": 1, "strict": False}


@pytest.mark.parametrize(("scene", "name", "lr"), [("collisions", "bgn", 1e-3),
                                                   ("collisions", "gns", 1e-3),
                                                   ("spring", "bgn", 1e-3),
                                                   ("gravity_r2", "cranmer_gn", 1e-3)])
def test_optimiser_and_scheduler_from_the_composed_config(scene, name, lr):
    module, conf = built(f"dataset={scene}", f"model={name}")
    check_today(conf, lr)
    assert "optimizer" not in module.hparams and "lr" not in module.hparams.model_config


def test_every_optimiser_and_scheduler_knob_is_config():
    _, conf = built("optimizer.lr=0.02", "optimizer.weight_decay=0.01",
                    "optimizer.betas=[0.8,0.99]", "scheduler.factor=0.2",
                    "scheduler.patience=7", "scheduler.lr_min_ratio=0.1",
                    "scheduler.monitor=val/loss", "scheduler.mode=max",
                    "+scheduler.cooldown=2")
    opt, sched = conf["optimizer"], conf["lr_scheduler"]["scheduler"]
    assert (opt.defaults["lr"], opt.defaults["weight_decay"]) == (0.02, 0.01)
    assert tuple(opt.defaults["betas"]) == (0.8, 0.99)
    assert (sched.mode, sched.factor, sched.patience, sched.cooldown) == ("max", 0.2, 7, 2)
    assert sched.min_lrs == [pytest.approx(0.002)]
    assert conf["lr_scheduler"]["monitor"] == "val/loss"
    _, conf = built("~optimizer", "~scheduler")  # no groups: the module's own defaults
    check_today(conf, 1e-3)
    _, conf = built("optimizer._target_=torch.optim.SGD", "~optimizer.betas",
                    "~optimizer.eps", "~optimizer.amsgrad")
    assert type(conf["optimizer"]) is torch.optim.SGD


def test_a_module_without_optimiser_settings_trains_as_today(tmp_path):
    """PhysicsModule.load_from_checkpoint(path) has no callables: today's AdamW and plateau.
    A checkpoint of the earlier layout (lr, weight_decay, ... as hyperparameters) loads."""
    module, _ = built("dataset=spring", "model.hidden=8", "model.decoder_hidden=8",
                      "model.flow_hidden=8")
    path = tmp_path / "old.ckpt"
    hparams = {**dict(module.hparams), "lr": 5e-4, "weight_decay": 0.0, "lr_min_ratio": 0.01,
               "lr_patience": 5}
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": hparams,
                "pytorch-lightning_version": "2.6.6"}, path)
    loaded = PhysicsModule.load_from_checkpoint(path, map_location="cpu")
    check_today(loaded.configure_optimizers(), 1e-3)
    mine = PhysicsModule(**{k: v for k, v in module.hparams.items()},
                         optimizer=partial(torch.optim.SGD, lr=0.1))
    assert type(mine.configure_optimizers()["optimizer"]) is torch.optim.SGD


def test_messages_come_from_rank_zero_only(caplog, monkeypatch):
    caplog.set_level(logging.INFO, logger="bgn.train")
    monkeypatch.setattr(rank_zero_only, "rank", 1)
    info("from rank 1")
    monkeypatch.setattr(rank_zero_only, "rank", 0)
    info("from rank 0")
    assert [r.getMessage() for r in caplog.records] == ["from rank 0"]


def test_the_more_sims_experiment_sets_the_sizes_and_nothing_else():
    plain, more = composed("dataset=gravity_r2"), composed("dataset=gravity_r2",
                                                           "experiment=more_sims")
    assert (more.dataset.n_sims, more.dataset.n_frames) == (100, 300)
    for cfg in (plain, more):
        cfg.dataset.n_sims = cfg.dataset.n_frames = 0
    assert OmegaConf.to_container(plain) == OmegaConf.to_container(more)


def test_the_presets_go_by_their_names_and_the_old_quick_names_are_gone():
    from hydra.errors import MissingConfigException

    smoke = compose_config("train", ["experiment=smoke"])
    assert (smoke.dataset.n_sims, smoke.trainer.max_time) == (3, "00:00:02:00")
    assert compose_config("experiments", ["preset=first_look"]).preset.name == "first_look"
    pareto = compose_config("experiments", ["preset=pareto_first_look"])
    assert pareto.preset.name == "pareto_first_look"
    for config, override in (("train", "experiment=quick"), ("experiments", "preset=quick"),
                             ("experiments", "preset=pareto_quick")):
        with pytest.raises(MissingConfigException):
            compose_config(config, [override])
