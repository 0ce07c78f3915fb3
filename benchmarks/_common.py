"""Helpers shared by the benchmark scripts: timing and the one-line JSON result."""

from __future__ import annotations

import json
import time
from collections.abc import Callable


def best_time(fn: Callable[[], object], repeat: int = 3) -> float:
    """Best wall time of ``repeat`` calls, seconds."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def emit(name: str, **fields: object) -> None:
    """Print the benchmark's result as one JSON line."""
    print(json.dumps({"benchmark": name, **fields}, default=float))
