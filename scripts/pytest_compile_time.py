"""A pytest plugin that reports how much of a run JAX spends compiling: the totals of JAX's compile-phase
duration events (tracing to a jaxpr, lowering to MLIR, XLA's backend compile) and the backend compile time of
each test file.

    PYTHONPATH=scripts python -m pytest jaxrt tests -q -p no:cacheprovider -p pytest_compile_time
"""

from __future__ import annotations

import collections

import jax

_TOTALS: collections.Counter[str] = collections.Counter()
_PER_FILE: collections.Counter[str] = collections.Counter()
_CURRENT: list[str | None] = [None]


def _listener(event: str, duration: float, **_: object) -> None:
    _TOTALS[event] += duration
    if _CURRENT[0] is not None and event.endswith("backend_compile_duration"):
        _PER_FILE[_CURRENT[0]] += duration


jax.monitoring.register_event_duration_secs_listener(_listener)


def pytest_runtest_setup(item) -> None:
    """Attribute the compiles that follow to this test's file."""
    _CURRENT[0] = item.nodeid.split("::")[0]


def pytest_terminal_summary(terminalreporter) -> None:
    """Print the compile-phase totals and the files with the most backend compile time."""
    write = terminalreporter.write_line
    for event, seconds in sorted(_TOTALS.items(), key=lambda item: -item[1])[:8]:
        write(f"jax compile time {seconds:9.1f} s  {event}")
    for path, seconds in _PER_FILE.most_common(20):
        write(f"backend compile  {seconds:9.1f} s  {path}")
