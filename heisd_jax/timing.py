"""Wall-clock helpers shared by the benchmark scripts and the cost-model calibration."""

from __future__ import annotations

import time

import jax
import numpy as np


def wall_seconds(fn, reps: int) -> list[float]:
    """Wall-clock of each of `reps` calls of fn() (results blocked on), after one untimed
    call (compilation and warm-up excluded)."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return times


def median_seconds(fn, reps: int) -> float:
    """Median of `wall_seconds`."""
    return float(np.median(wall_seconds(fn, reps)))
