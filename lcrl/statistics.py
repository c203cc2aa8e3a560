"""Success rates with their 95% Wilson intervals (policies and captioners alike)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from lcrl.errors import LcrlError

#: z of a two-sided 95% normal interval.
Z95 = 1.959963984540054


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion.

    Args:
        successes: number of successes ``k``.
        n: number of trials.
        z: normal quantile (1.96 for 95%).

    Returns:
        ``(low, high)``; ``(0.0, 1.0)`` when ``n`` is 0.

    Raises:
        LcrlError: ``successes`` outside ``[0, n]``.
    """
    if n < 0 or not 0 <= successes <= max(n, 0):
        raise LcrlError(f"need 0 <= successes <= n, got successes={successes}, n={n}")
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / denom
    half = z / denom * math.sqrt(p * (1.0 - p) / n + z2 / (4 * n * n))
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return (low, high)


def rate_stats(successes: Sequence[bool], steps: Sequence[int] = ()) -> dict[str, Any]:
    """Success rate, its 95% Wilson interval, counts and mean steps to success.

    Args:
        successes: one bool per attempt.
        steps: steps to success of the successful attempts.
    """
    n, k = len(successes), int(sum(bool(s) for s in successes))
    low, high = wilson_interval(k, n)
    return {
        "success": k / n if n else None,
        "ci": [low, high],
        "episodes": n,
        "successes": k,
        "mean_steps_to_success": float(np.mean(steps)) if len(steps) else None,
    }
