"""The SLURM launcher config (``hydra/launcher=slurm``, hydra-submitit-launcher) composes, and
the sbatch script submitit would submit carries our parameters: no cluster needed."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from bgn.training.config import register_configs
from tests.conftest import CONF_DIR

pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
submitit = pytest.importorskip("submitit")


def sbatch_script(launcher_params: dict, monkeypatch) -> str:
    """What ``SlurmLauncher.launch`` builds from its parameters (the same mapping), as the
    sbatch file text; submitit's check for ``srun`` is stubbed."""
    from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf

    monkeypatch.setattr(submitit.SlurmExecutor, "affinity", classmethod(lambda cls: 1))
    params = dict(launcher_params)
    executor = submitit.AutoExecutor(folder=params.pop("submitit_folder"), cluster="slurm",
                                     slurm_max_num_timeout=params.pop("max_num_timeout"))
    base = set(OmegaConf.structured(BaseQueueConf).keys())
    executor.update_parameters(**{k if k in base else f"slurm_{k}": v
                                  for k, v in params.items()})
    assert executor._executor.max_num_timeout == launcher_params["max_num_timeout"]
    return executor._executor._make_submission_file_text("python -m bgn.train", "uid")


def test_slurm_launcher_composes_a_multi_node_gpu_job(tmp_path: Path, monkeypatch):
    register_configs()
    overrides = ["hydra/launcher=slurm", "hydra.launcher.partition=gpu",
                 f"hydra.sweep.dir={tmp_path / 'sweep'}", "hydra.launcher.nodes=2",
                 "hydra.launcher.tasks_per_node=4", "hydra.launcher.gpus_per_node=4",
                 "trainer=ddp", "+trainer.num_nodes=2", "trainer.devices=4", "ckpt_path=last"]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides, return_hydra_config=True)
    node = cfg.hydra.launcher
    assert node._target_.endswith("submitit_launcher.SlurmLauncher")
    assert node.max_num_timeout > 0 and node.signal_delay_s > 0  # requeued at the time limit
    assert cfg.trainer.num_nodes == node.nodes and cfg.trainer.devices == node.tasks_per_node
    params = OmegaConf.to_container(node, resolve=False)
    params.update(submitit_folder=str(tmp_path / "sweep" / ".submitit" / "%j"), name="train")
    launcher = instantiate(params)
    script = sbatch_script(launcher.params, monkeypatch)
    for line in ("#SBATCH --partition=gpu", "#SBATCH --nodes=2", "#SBATCH --ntasks-per-node=4",
                 "#SBATCH --gpus-per-node=4", "#SBATCH --cpus-per-task=8",
                 "#SBATCH --time=240", "#SBATCH --signal=USR2@120"):
        assert line in script, (line, script)
