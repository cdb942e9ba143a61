"""What a checkout must not carry: the folders runs write (``data/``, ``outputs/``) hold nothing
tracked, so a clone, a checkout or a merge never replaces a user's data or runs (a link to a
data folder once committed from a worktree replaced the folder of every checkout)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def tracked(*paths: str) -> list[str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    out = subprocess.run(["git", "ls-files", "--", *paths], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout
    return out.split()


def test_the_data_and_outputs_folders_track_nothing_but_a_placeholder():
    assert tracked("data") == []
    assert set(tracked("outputs")) <= {"outputs/.gitkeep"}
