"""A job's budget and its signals: what every long fit checks (docs/design.md#budgets).

A job is bounded by work (``trainer.max_steps``: the same command and seed give the same model
on any machine) and capped by wall time over the whole job (``trainer.max_time``: candidates,
force matching, the formula stage and the test together). The cap is a :class:`Deadline`
made once when the job starts and handed down; a loop that can run for more than a few
seconds calls :func:`check` between its iterations, which raises :class:`OutOfTime` past the
deadline and Lightning's ``SIGTERMException`` (a ``SystemExit``) once SIGTERM has arrived,
so a signal is acted on within seconds wherever the job is.

SIGTERM: :func:`watch_signals` installs a handler that records the signal and, outside a
:func:`deferred` section, raises at once. Inside one (``trainer.fit``, whose loop and the
fits it calls check the flag at safe points: between optimiser steps, between iterations)
it only records it, so no optimiser step is cut in half. SIGINT keeps Python's
``KeyboardInterrupt``.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import FrameType

# Lightning's SIGTERMException is imported where it is raised: this module is imported by
# the commands before their input is checked, which must not wait for Lightning to load


class OutOfTime(RuntimeError):
    """The job's wall-clock cap (``trainer.max_time``) was reached."""


_received: list[str] = []   # the signals recorded since watch_signals()
_defer_depth = 0            # > 0: inside a section that checks the flag at safe points


def received() -> str | None:
    """The name of the first signal recorded (``"SIGTERM"``), or None."""
    return _received[0] if _received else None


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    if not _received:
        _received.append("SIGTERM")
    if _defer_depth == 0:
        from lightning.pytorch.utilities.exceptions import SIGTERMException

        raise SIGTERMException()


def watch_signals() -> None:
    """Record SIGTERM (and raise it outside :func:`deferred` sections). Idempotent; only
    from the main thread (signal handlers can only be set there)."""
    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGTERM) is not _on_sigterm:
        signal.signal(signal.SIGTERM, _on_sigterm)


def reset_signals() -> None:
    """Forget recorded signals (tests; a new job in the same process)."""
    _received.clear()


@contextmanager
def deferred() -> Iterator[None]:
    """Inside, SIGTERM is only recorded; the code inside checks it (:func:`check`, or
    Lightning's loop through its own handler, which composes with ours)."""
    global _defer_depth
    _defer_depth += 1
    try:
        yield
    finally:
        _defer_depth -= 1


@dataclass(frozen=True)
class Deadline:
    """The wall-clock end of a job (``time.monotonic()`` seconds), or none."""

    end: float | None = None

    @classmethod
    def after(cls, seconds: float | None) -> Deadline:
        """A deadline ``seconds`` from now (None: no cap)."""
        return cls(None if seconds is None else time.monotonic() + float(seconds))

    def left(self) -> float | None:
        """Seconds left (never negative), or None without a cap."""
        return None if self.end is None else max(0.0, self.end - time.monotonic())

    def passed(self) -> bool:
        return self.end is not None and time.monotonic() >= self.end

    def sooner(self, seconds: float | None) -> Deadline:
        """The earlier of this deadline and ``seconds`` from now (None: this one)."""
        if seconds is None:
            return self
        other = time.monotonic() + float(seconds)
        return Deadline(other if self.end is None else min(self.end, other))

    def less(self, seconds: float) -> Deadline:
        """This deadline moved ``seconds`` earlier (a reserve kept for what comes after)."""
        return self if self.end is None else Deadline(self.end - float(seconds))


NO_DEADLINE = Deadline()


def check(deadline: Deadline | None = None, what: str = "the job") -> None:
    """Between iterations of a long loop: raise ``SIGTERMException`` once SIGTERM arrived,
    :class:`OutOfTime` once ``deadline`` has passed (naming ``what`` was cut short)."""
    if _received:
        from lightning.pytorch.utilities.exceptions import SIGTERMException

        raise SIGTERMException()
    if deadline is not None and deadline.passed():
        raise OutOfTime(f"{what} reached the job's wall-clock cap (trainer.max_time)")


def clock_text(seconds: float) -> str:
    """``seconds`` as a reader says it: ``"42 s"``, ``"7 min 05 s"``, ``"1 h 02 min"``."""
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s // 60 % 60:02d} min"

