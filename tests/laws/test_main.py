"""python -m bgn.laws (bgn.laws.__main__): its files and its refusals."""

from __future__ import annotations

import csv
import json

import pytest
from omegaconf import OmegaConf

from bgn.laws.__main__ import main
from tests.laws.conftest import laws_cli, tiny_run


def test_the_command_writes_the_four_files(tmp_path, shared_data_dir):
    ckpt = tiny_run(tmp_path, shared_data_dir, "newton", "model.hidden=16")
    out = tmp_path / "laws"
    assert main([str(ckpt), f"out_dir={out}"]) == out / "report.md"  # in-process: faster
    assert sorted(p.name for p in out.iterdir()) == ["law.csv", "law.json", "law.png",
                                                      "report.md"]
    record = json.loads((out / "law.json").read_text())
    rows = list(csv.DictReader((out / "law.csv").open()))
    assert len(rows) == len(record["pairs"][0]["r"]) and rows[0]["truth"]
    assert record["pairs"][0]["formula"] in (out / "report.md").read_text()


def test_a_model_without_a_pair_force_head_is_refused_in_one_line(tmp_path, shared_data_dir):
    ckpt = tiny_run(tmp_path, shared_data_dir, "gns", "model.latent=16", "model.mlp_hidden=16",
                    "model.mlp_layers=1", "model.message_passing_steps=2")
    done = laws_cli(str(ckpt), f"out_dir={tmp_path / 'laws'}")
    assert done.returncode != 0
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "no pair-force head" in done.stderr and "model=newton" in done.stderr
    assert not (tmp_path / "laws").exists()


@pytest.mark.parametrize("option", ["colour=blue", "max_terms=x", "max_terms=9", "max_terms=4",
                                    "tolerance=-1", "parsimony=0.5"])


def test_bad_options_are_refused_in_one_line(option, capsys, tmp_path):
    with pytest.raises(SystemExit) as done:
        main([str(tmp_path / "x.ckpt"), option])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and option.split("=")[0] in err


# ----------------------------------------------------------------------------- formula law


def test_the_command_fine_tunes_with_finetune_true(tmp_path, shared_data_dir):
    ckpt = tiny_run(tmp_path, shared_data_dir, "newton", "model.hidden=16")
    out = tmp_path / "laws"
    # (tolerance=1: the simplest member is chosen, so the tiny run's law has a formula to tune)
    main([str(ckpt), f"out_dir={out}", "finetune=true", "finetune_steps=3",
          "finetune_substeps=2", "finetune_horizon=10", "tolerance=1", "max_terms=1"])
    assert {"formula.ckpt", "formula.json", "report.md", "train_config.yaml"} <= {
        p.name for p in out.iterdir()}
    record = json.loads((out / "formula.json").read_text())
    # beside the checkpoint, the run's config with the formula model's options (bgn.eval.evaluate)
    model = OmegaConf.load(out / "train_config.yaml").model
    assert model.law == "formula" and json.loads(model.law_formula) == record["model_tuned"]
    text = (out / "report.md").read_text()
    assert "The formula as the law, fine-tuned" in text and f"**{record['choice']}**" in text


@pytest.mark.parametrize("option", ["finetune=maybe", "finetune_steps=0",
                                    "finetune_substeps=x"])


def test_bad_finetune_options_are_refused_in_one_line(option, capsys, tmp_path):
    with pytest.raises(SystemExit) as done:
        main([str(tmp_path / "x.ckpt"), option])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and option.split("=")[0] in err
