"""The benchmarks' one timer: the median wall time of a call, after warm-up calls that do not count."""
from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def median_seconds(run: Callable[[], object], repeats: int, warmup: int = 1,
                   between: Callable[[], object] | None = None) -> float:
    """Median seconds of `repeats` calls of run() after `warmup` uncounted ones; between(), if given, runs
    after every call (counted or not) and is not timed (e.g. resetting what run() accumulates)."""
    for _ in range(warmup):
        run()
        if between is not None:
            between()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
        if between is not None:
            between()
    return statistics.median(times)
