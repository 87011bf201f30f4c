"""Where the ``stereo`` step's timing is taken: one :class:`Timer` per reference and pass.

A pass times each of its steps with ``with timer.step("network"): ...``; :attr:`Timer.steps` is what
:attr:`~colmap_pvs.stereo.context.RefOutcome.timings` reports (the writer thread adds ``writes`` and
``previews`` to it later), and :func:`sum_steps` adds them up per step over a run for
:attr:`~colmap_pvs.stereo.context.StereoResult.timings`. The backends time their passes with a
:class:`Timer` too (``StereoResult.pass_seconds``).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager


class Timer:
    """Seconds per named step (:attr:`steps`) and since this timer was made (:meth:`elapsed`)."""

    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.steps: dict[str, float] = {}

    @contextmanager
    def step(self, key: str) -> Iterator[None]:
        """Time the ``with`` block as ``steps[key]`` (a step timed again replaces its seconds; a block
        left by an exception records nothing)."""
        t0 = time.perf_counter()
        yield
        self.steps[key] = time.perf_counter() - t0

    def elapsed(self) -> float:
        """Seconds since this timer was made."""
        return time.perf_counter() - self.start

    def add(self, other: Timer, prefix: str = "") -> None:
        """``other``'s steps as ``PREFIX + key`` (a nested run, e.g. the geometric pass's re-estimate)."""
        self.steps.update({f"{prefix}{k}": v for k, v in other.steps.items()})


def sum_steps(outcomes: Iterable, into: dict[str, float]) -> dict[str, float]:
    """Add each outcome's step seconds (``RefOutcome.timings``) to ``into``: the photometric pass's as
    ``STEP``, a later pass's as ``PASS.STEP``; returns ``into``."""
    for out in outcomes:
        for step, sec in out.timings.items():
            key = step if out.stage == "photometric" else f"{out.stage}.{step}"
            into[key] = into.get(key, 0.0) + sec
    return into
