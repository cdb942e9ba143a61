"""One command style (``bgn.training.validate.cli``): every ``python -m bgn.*`` command's
``--help`` names its argument and each key with its default, the same ``paths.data_dir=`` and
run folder (or ``.ckpt``) work for train, import, evaluate, render, laws and stability, and a
refused run leaves no run folder behind."""

from __future__ import annotations

import importlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from bgn.training.validate import positional_override
from tests.conftest import CONF_DIR, NETWORK_LAW, SMALL

ROOT = Path(__file__).resolve().parents[1]
ENV = {**{k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "BGN_FULL_ERROR")},
       "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}

# command -> (config folder, config name, the positional argument's key or None, the keys
# that are config groups (named by --help as group=option, their keys not listed one by one))
COMMANDS = {
    "bgn.train": (CONF_DIR, "train", None, ("dataset", "model", "optimizer", "scheduler",
                                           "trainer", "logger", "callbacks", "ablation",
                                           "experiment")),
    "bgn.train.generate": (CONF_DIR, "generate", None, ("dataset",)),
    "bgn.data.import": (CONF_DIR, "import", "path", ()),
    "bgn.evaluate": (CONF_DIR, "evaluate", "ckpt", ()),
    "bgn.render": (CONF_DIR, "render", "ckpt", ()),
    "bgn.laws": (CONF_DIR, "laws", "ckpt", ()),
    "bgn.stability": (CONF_DIR / "stability", "stability", None, ("preset",)),
    "bgn.experiments": (CONF_DIR, "experiments", None, ("preset",)),
    "bgn.data.balance": (CONF_DIR, "balance", "files", ()),
    **{f"bgn.benchmarks.{name}": (CONF_DIR / "benchmarks", name, None, ())
       for name in ("neighbours", "scaling", "flow", "shooting")},
}
# keys that are not arguments: where Hydra writes (paths.output_dir) and the root the data
# folder's default builds on
NOT_ARGUMENTS = ("paths.output_dir", "paths.root_dir")

# A tiny BGN on spring: its pair-force head's law stays a network (no formula stage), one
# epoch of two batches; a checkpoint is written (last.ckpt)
TINY_TRAIN = ["dataset=spring", *SMALL["spring"], NETWORK_LAW, "model.hidden=8",
              "model.decoder_hidden=8", "model.flow_hidden=8", "figures=false",
              "val_rollout_steps=0", "test_rollouts=false", "callbacks.progress_bar=null",
              "trainer.max_epochs=1", "+trainer.limit_train_batches=2",
              "trainer.limit_val_batches=1", "trainer.enable_model_summary=false"]
FAST_EVALUATE = ["rollout.steps=5", "rollout.max_sims=1", "max_frames=4", "mass_frames=2",
                 "mass_samples=4", "batch_size=2", "progress=false", "figures=false"]
FAST_LAWS = ["max_terms=1"]
FAST_STABILITY = ["preset=tiny", "preset.cases=[spring_offset_1e4]"]


def composed(command: str) -> Any:
    """The command's config as ``--help`` sees it (Hydra's node included)."""
    from bgn.training.config import register_configs

    folder, name, _, _ = COMMANDS[command]
    register_configs()
    with initialize_config_dir(config_dir=str(folder), version_base="1.3"):
        return compose(config_name=name, return_hydra_config=True)


def shown(value: Any) -> str:
    """A default as the help writes it (YAML's spelling)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list):
        return "[" + ", ".join(map(shown, value)) + "]"
    return str(value)


def arguments(command: str) -> list[tuple[str, str | None]]:
    """(key, its default as written, or None where the default is an interpolation) of every
    key a user sets on the command line, groups aside."""
    cfg = composed(command)
    _, _, positional, groups = COMMANDS[command]
    out = []

    def walk(node: Any, prefix: str) -> None:
        for key in node:
            name = f"{prefix}{key}"
            if name in ("hydra", positional, *groups, *NOT_ARGUMENTS):
                continue
            value = node._get_node(key)
            if OmegaConf.is_dict(value):
                walk(value, f"{name}.")
                continue
            raw = value._value()
            out.append((name, None if OmegaConf.is_interpolation(node, key) or raw == "???"
                        else shown(OmegaConf.to_container(node, resolve=False)[key])))

    walk(cfg, "")
    return out


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_names_the_argument_and_every_key_with_its_default(command):
    """The help template (what ``--help`` prints) names the positional argument with its key,
    and every key of the composed config with its default, so a key added without a line in
    the help fails here."""
    template = composed(command).hydra.help.template
    assert template.startswith(f"python -m {command} "), template[:80]
    _, _, positional, groups = COMMANDS[command]
    if positional:
        assert f"({positional}=)" in template
    for group in groups:
        assert f"{group}=" in template or f"{group}." in template, group
    keys = arguments(command)
    assert keys, command
    for key, default in keys:
        if default is None:
            assert f"{key}=" in template, key
        else:
            assert re.search(rf"(^|\s){re.escape(key)}={re.escape(default)}(\s|$)", template), \
                (key, default)


def test_the_help_lists_only_options_that_exist():
    """Every option the train help lists for a group is a config of that group."""
    template = composed("bgn.train").hydra.help.template
    for group in ("dataset", "model", "ablation", "trainer"):
        line = re.search(rf"{group}=\w+ +(.+)", template).group(1)
        for option in re.findall(r"[a-z_0-9]+", line.split("(")[0]):
            assert (CONF_DIR / group / f"{option}.yaml").is_file(), (group, option)


def test_an_option_is_refused_with_its_key_value_spelling(capsys):
    from bgn.studies.render import main

    with pytest.raises(SystemExit) as done:
        main(["outputs/x", "--split", "test"])
    assert done.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--split" in err and "split=<value>" in err


@pytest.mark.parametrize("command, key, close", [
    ("bgn.evaluate", "data_dir", "paths.data_dir"),   # evaluate's key before one style
    ("bgn.laws", "config", "run_config"),
    ("bgn.laws", "finetune.steps", "finetune_steps"),
    ("bgn.render", "stpes", "steps"),
])
def test_a_key_the_command_lacks_is_refused_naming_the_closest(capsys, command, key, close):
    """Not Hydra's "to append use +key=...": the key, the closest the command has, --help."""
    main = importlib.import_module({"bgn.evaluate": "bgn.eval.evaluate", "bgn.laws":
                                    "bgn.laws.__main__", "bgn.render": "bgn.studies.render"}[
                                        command]).main
    with pytest.raises(SystemExit) as done:
        main(["some/run", f"{key}=1"])
    assert done.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "+" not in err
    assert f"{key} is not a key of python -m {command}; did you mean {close}" in err, err


@pytest.mark.parametrize("argv", [["a"], ["a", "b=1"], ["x=1", "a b", "--cfg", "job"],
                                  ["-cn", "evaluate", "r"], ["'q'", "c=2"], []])
def test_only_the_first_positional_argument_becomes_the_key(argv):
    out = positional_override(argv, "ckpt")
    positional = [a for i, a in enumerate(argv) if "=" not in a and not a.startswith("-")
                  and (i == 0 or argv[i - 1] not in ("-cn", "--cfg"))]
    assert len(out) == len(argv)
    assert sum(a.startswith("ckpt=") for a in out) == min(1, len(positional))
    assert [a for a in out if not a.startswith("ckpt=")] == [a for a in argv
                                                              if a not in positional[:1]]


# ----------------------------------------------------------------- one run, every command
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> tuple[Path, Path]:
    """(run folder, data folder): one tiny training through ``python -m bgn.train``'s own
    function (composed in this process), with the config Hydra would have saved."""
    main = importlib.import_module("bgn.train.__main__").main
    root = tmp_path_factory.mktemp("commands")
    run, data = root / "run", root / "data"
    overrides = [*TINY_TRAIN, f"paths.data_dir={data}", f"paths.output_dir={run}"]
    main(overrides)
    (run / ".hydra").mkdir()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides)
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")
    return run, data


def moved_data(run: Path, data: Path, tmp_path: Path) -> Path:
    """The run's data under another folder, so a command finds them only through
    ``paths.data_dir=`` (the run's config names the old one, removed from its reach)."""
    import shutil

    moved = tmp_path / "moved"
    shutil.copytree(data, moved)
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    cfg.paths.data_dir = str(tmp_path / "nowhere")  # the run's own data_dir: not there
    (run / ".hydra" / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    return moved


def test_evaluate_render_laws_and_stability_take_the_run_folder_and_paths_data_dir(
        tiny_run, tmp_path):
    """The same run folder and ``paths.data_dir=`` for evaluate, render, laws and stability
    (in this process: the argument list each command's console entry parses)."""
    from bgn.eval.evaluate import main as evaluate
    from bgn.laws.__main__ import main as laws
    from bgn.studies.render import main as render
    from bgn.studies.stability import main as stability
    from bgn.training.checkpoints import chosen_checkpoint

    run, data = tiny_run
    config = (run / ".hydra" / "config.yaml").read_text()
    try:
        moved = moved_data(run, data, tmp_path)
        given = f"paths.data_dir={moved}"
        out = evaluate([str(run), given, f"out_dir={tmp_path / 'eval'}", *FAST_EVALUATE])
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["provenance"]["checkpoint"].startswith(str(run.resolve()))
        assert metrics["provenance"]["command"].startswith(f"python -m bgn.evaluate {run}")
        gif = render([str(run), given, "steps=3", f"out={tmp_path / 'r.gif'}"])
        assert gif.is_file()
        report = laws([str(run), given, f"out_dir={tmp_path / 'laws'}", *FAST_LAWS])
        assert "f(r) = " in report.read_text()
        stability([*FAST_STABILITY, f"checkpoints.spring={run}", given,
                   f"report_dir={tmp_path / 'stability'}"])
        rows = (tmp_path / "stability" / "model.csv").read_text()
        chosen = chosen_checkpoint(run).name  # the run's checkpoint, as evaluate's
        assert f"spring_offset_1e4,spring,{chosen}," in rows
        # without paths.data_dir the run's own (missing) data folder is used: not found
        # there, the data would be generated again, so the moved copy was what was read
        assert not (tmp_path / "nowhere").exists()
    finally:
        (run / ".hydra" / "config.yaml").write_text(config)


def test_a_checkpoint_file_is_taken_where_a_run_folder_is(tiny_run, tmp_path):
    from bgn.laws.__main__ import main as laws
    from bgn.studies.render import main as render

    run, data = tiny_run
    ckpt = run / "checkpoints" / "last.ckpt"
    given = f"paths.data_dir={data}"
    assert render([str(ckpt), given, "steps=2", f"out={tmp_path / 'c.gif'}"]).is_file()
    assert laws([str(ckpt), given, f"out_dir={tmp_path / 'laws'}", *FAST_LAWS]).is_file()


def test_the_import_takes_paths_data_dir(tmp_path):
    """``python -m bgn.data.import <path> name=<name> paths.data_dir=<folder>`` writes there,
    and training reads it there with the same key."""
    from bgn.training.validate import validate_train
    from tests.conftest import compose_config

    rng = np.random.default_rng(0)
    x = np.cumsum(rng.normal(scale=0.01, size=(20, 30, 3, 2)), axis=1) + rng.normal(
        size=(20, 1, 3, 2))
    np.savez(tmp_path / "walk.npz", positions=x, dt=0.02)
    command = importlib.import_module("bgn.train.import").command
    paths = command([str(tmp_path / "walk.npz"), "name=walk",
                     f"paths.data_dir={tmp_path / 'mine'}"])
    assert paths["train"].is_relative_to(tmp_path / "mine" / "imported" / "walk")
    spec = validate_train(compose_config("train", [
        "dataset=imported", "dataset.name=walk", f"paths.data_dir={tmp_path / 'mine'}"]))
    assert spec.n_sims >= 1


def test_a_run_folder_of_the_formula_stage_gives_the_formula_checkpoint(tmp_path):
    """The resolver every command shares: a run whose formula stage kept the formula gives
    laws/formula.ckpt (with the formula's config), one that kept the network its best."""
    from bgn.training.checkpoints import resolve_run

    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "best.ckpt").write_bytes(b"")
    (tmp_path / ".hydra").mkdir()
    (tmp_path / ".hydra" / "config.yaml").write_text("{}")
    (tmp_path / "laws").mkdir()
    (tmp_path / "laws" / "formula.ckpt").write_bytes(b"")
    (tmp_path / "laws" / "train_config.yaml").write_text("{}")
    for choice, ckpt, config in (
            ("formula", "laws/formula.ckpt", "laws/train_config.yaml"),
            ("network", "checkpoints/best.ckpt", ".hydra/config.yaml")):
        (tmp_path / "laws" / "formula.json").write_text(json.dumps({"choice": choice}))
        found, _, found_config = resolve_run(str(tmp_path))
        assert (found, found_config) == (tmp_path / ckpt, tmp_path / config)


# ----------------------------------------------------------------------------- refused runs
def run_app(monkeypatch, module: str, *args: str) -> int:
    """``python -m <module> <args>`` through its Hydra app, in this process (the logging set-up
    Hydra makes, handlers on this test's captured streams, undone after)."""
    import logging

    monkeypatch.setattr(sys, "argv", [module, *args])
    main = getattr(importlib.import_module(module), "command", None) or \
        importlib.import_module(module).main
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    try:
        with pytest.raises(SystemExit) as done:
            main()
    finally:
        GlobalHydra.instance().clear()
        for handler in root.handlers[:]:
            if handler not in handlers:
                root.removeHandler(handler)
                handler.close()
        root.handlers[:] = handlers
        root.setLevel(level)
    return done.value.code


@pytest.mark.parametrize("module, args", [
    ("bgn.train.__main__", ["optimizer.lr=-1"]),          # refused by the validation
    ("bgn.train.__main__", ["dataset=imported", "dataset.name=none_such"]),
    ("bgn.train.import", ["/no/such/file.npz", "name=x"]),  # a refused import (exit 1)
])
def test_a_refused_run_leaves_no_run_folder(monkeypatch, capsys, tmp_path, module, args):
    run = tmp_path / "outputs" / "run"
    code = run_app(monkeypatch, module, *args, f"paths.data_dir={tmp_path / 'data'}",
                   f"hydra.run.dir={run}")
    assert code in (1, 2)
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not run.exists() and (tmp_path / "outputs").is_dir()  # only the run's own folder
    assert not (tmp_path / "data").exists()


def test_a_refused_run_keeps_a_folder_that_holds_anything_else(monkeypatch, capsys, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "notes.txt").write_text("mine")
    code = run_app(monkeypatch, "bgn.train.__main__", "optimizer.lr=-1",
                   f"paths.data_dir={tmp_path / 'data'}", f"hydra.run.dir={run}")
    assert code == 2 and (run / "notes.txt").read_text() == "mine"
    capsys.readouterr()


# ----------------------------------------------------------------------------- the console
def console(*args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True,
                          env=ENV, cwd=ROOT, timeout=timeout)


@pytest.mark.slow
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_on_the_console(command):
    done = console(command, "--help")
    assert done.returncode == 0, done.stderr
    _, _, positional, _ = COMMANDS[command]
    assert done.stdout.startswith(f"python -m {command} ")
    for key, _ in arguments(command):
        assert f"{key}=" in done.stdout, key
    if positional:
        assert f"({positional}=)" in done.stdout


@pytest.mark.slow
def test_one_run_folder_and_data_dir_through_every_console_command(tmp_path):
    """On the console: ``python -m bgn.train`` into a run folder, then evaluate, render,
    laws and stability on that folder, all with the same ``paths.data_dir=``; Lightning's log
    lines once each, without its advertisement."""
    run, data = tmp_path / "run", tmp_path / "data"
    given = f"paths.data_dir={data}"
    done = console("bgn.train", *TINY_TRAIN, given, f"hydra.run.dir={run}")
    assert done.returncode == 0, done.stderr[-3000:]
    log = done.stdout + done.stderr
    assert "litlogger" not in log and "litmodels" not in log and "Tip:" not in log
    assert "INFO: GPU available" not in log  # Lightning's own handler: gone
    assert log.count("GPU available") == 1
    assert "LeafSpec" not in log
    for args in (["bgn.evaluate", str(run), *FAST_EVALUATE],
                 ["bgn.render", str(run), "steps=2", f"out={tmp_path / 'r.gif'}"],
                 ["bgn.laws", str(run), f"out_dir={tmp_path / 'laws'}", *FAST_LAWS],
                 ["bgn.stability", *FAST_STABILITY, f"checkpoints.spring={run}",
                  f"report_dir={tmp_path / 'stability'}", f"hydra.run.dir={tmp_path / 'st'}"]):
        done = console(*args, given)
        assert done.returncode == 0, (args[0], done.stderr[-3000:])
    assert (run / "eval" / "test" / "report.md").is_file()
    assert (tmp_path / "r.gif").is_file() and (tmp_path / "laws" / "report.md").is_file()
    assert (tmp_path / "stability" / "report.md").is_file()
