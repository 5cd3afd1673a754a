"""Wall-clock timing of jitted calls: a first (compiling) call, then the median of warm repeats."""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Callable, Iterable
from typing import Any, NamedTuple, TypeVar

import jax

__all__ = ["Timing", "progress", "timed"]

T = TypeVar("T")


class Timing(NamedTuple):
    """Seconds taken by one call, measured after ``jax.block_until_ready`` on its output."""

    first_s: float
    """The first call: compilation (if any) plus one run."""
    median_s: float
    """Median of the warm repeats (the first call when there are none)."""
    times_s: tuple[float, ...]
    """Every warm repeat."""

    @property
    def compile_s(self) -> float:
        """First call minus a warm call: an estimate of tracing and compilation time."""
        return max(0.0, self.first_s - self.median_s)

    def as_dict(self, items: int | None = None, unit: str = "mrays_s") -> dict[str, Any]:
        """JSON-ready numbers; with ``items``, also the rate in millions per second under the key ``unit``."""
        out: dict[str, Any] = {
            "first_s": self.first_s,
            "compile_s": self.compile_s,
            "median_s": self.median_s,
            "times_s": list(self.times_s),
        }
        if items is not None:
            out[unit] = items / self.median_s / 1e6 if self.median_s > 0 else float("inf")
        return out


def timed(fn: Callable[[], Any], repeats: int) -> tuple[Timing, Any]:
    """Call ``fn()`` once (warm-up, compiling), then ``repeats`` more times; return the timing and the last output.

    Every call is followed by ``jax.block_until_ready`` on its output, so asynchronous dispatch is waited for.
    """
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    median = statistics.median(times) if times else first
    return Timing(first, median, tuple(times)), out


def progress(iterable: Iterable[T], *, enabled: bool = True, **options: Any) -> Iterable[T]:
    """``iterable`` with a transient tqdm bar on stderr when ``enabled``, stderr is a terminal and tqdm is
    installed (``pip install 'jaxrt[bench]'``); else ``iterable`` itself, so logs and tests stay clean."""
    if not enabled or not sys.stderr.isatty():
        return iterable
    try:
        from tqdm import tqdm
    except ImportError:
        return iterable
    return tqdm(iterable, leave=False, dynamic_ncols=True, **options)
