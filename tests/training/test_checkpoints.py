"""The atomic writers: a killed or failing writer never leaves a half-written file."""

from __future__ import annotations

import pytest
import torch

from bgn.training.checkpoints import save_atomic, write_atomic


def test_save_atomic_round_trips_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "best.ckpt"
    save_atomic({"state_dict": {"w": torch.arange(3.0)}}, path)
    assert torch.equal(torch.load(path, weights_only=True)["state_dict"]["w"], torch.arange(3.0))
    assert [p.name for p in tmp_path.iterdir()] == ["best.ckpt"]


class Unsavable:
    def __reduce__(self):
        raise RuntimeError("cannot be saved")


def test_a_failing_save_keeps_the_old_checkpoint(tmp_path):
    path = tmp_path / "best.ckpt"
    save_atomic({"step": 1}, path)
    with pytest.raises(RuntimeError, match="cannot be saved"):  # torch.save fails mid-way
        save_atomic({"step": 2, "bad": Unsavable()}, path)
    assert torch.load(path, weights_only=True) == {"step": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["best.ckpt"]


def test_write_atomic_replaces_the_text_whole(tmp_path):
    path = tmp_path / "sub" / "metrics.json"
    write_atomic(path, "{}")
    write_atomic(path, '{"a": 1}')
    assert path.read_text() == '{"a": 1}'
    assert [p.name for p in path.parent.iterdir()] == ["metrics.json"]
