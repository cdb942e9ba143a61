"""What regenerates a result: the commit of the code that made it, the machine it ran on, and
the generated blocks of a results file (docs/results.md), which the commands that make the
tables rewrite in place."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path


def git_commit() -> str:
    """``git rev-parse HEAD`` of the checkout bgn runs from, 'unknown' without git; where the
    code is a copy (a cluster job's, a container's), ``$BGN_GIT_COMMIT`` as the copier set it
    wins: a copy's git metadata, if any came along, may be stale."""
    given = os.environ.get("BGN_GIT_COMMIT", "unknown")
    if given != "unknown":
        return given
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent,
                             capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return given
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else given


def machine(**versions: str) -> str:
    """One line: platform, processor, logical CPUs, Python and numpy, then ``versions``
    (library name -> version string) in the order given."""
    import numpy as np

    libs = {"numpy": np.__version__, **versions}
    return (
        f"{platform.platform()}, {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} logical CPUs, Python {platform.python_version()}, "
        + ", ".join(f"{name} {version}" for name, version in libs.items())
    )


# the libraries whose versions change trained numbers (a run on another build of one of them,
# or on another processor, is not expected to match a table to the digit)
NUMERIC_LIBRARIES = ("torch", "lightning", "zuko", "numpy", "scipy", "h5py")


def processor() -> str:
    """The processor's model name (``/proc/cpuinfo`` on Linux), else what platform says."""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def library_versions() -> str:
    """``NUMERIC_LIBRARIES`` and their installed versions, one string."""
    from importlib.metadata import PackageNotFoundError, version

    def installed(name: str) -> str:
        try:
            return version(name)
        except PackageNotFoundError:
            return "not installed"

    return ", ".join(f"{name} {installed(name)}" for name in NUMERIC_LIBRARIES)


def block_markers(name: str) -> tuple[str, str]:
    """The markers around a generated block in a results file."""
    return (f"<!-- generated:{name}:begin -->", f"<!-- generated:{name}:end -->")


def replace_block(text: str, name: str, body: str) -> str:
    """``text`` with the block between ``name``'s markers replaced by ``body`` (the markers
    kept); the block appended at the end where the markers are missing."""
    begin, end = block_markers(name)
    block = f"{begin}\n{body.strip()}\n{end}"
    start, stop = text.find(begin), text.find(end)
    if start >= 0 and stop > start:
        return text[:start] + block + text[stop + len(end):]
    return (text.rstrip("\n") + "\n\n" if text.strip() else "") + block + "\n"


def write_block(path: str | Path, name: str, body: str) -> None:
    """Rewrite ``name``'s generated block of the results file ``path`` (made if missing)."""
    results = Path(path)
    old = results.read_text() if results.exists() else ""
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text(replace_block(old, name, body))
