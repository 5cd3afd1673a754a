"""A pytest plugin that reports how much of a run JAX spends compiling: the totals of JAX's compile-phase
duration events (tracing to a jaxpr, lowering to MLIR, XLA's backend compile, the persistent cache's savings),
the backend compile time of each test file, and the functions whose programs took the most backend compile
time (with how many programs each compiled). Works with pytest-xdist: each worker writes its figures to a
folder the controller sums.

    PYTHONPATH=scripts python -m pytest jaxrt tests -q -p no:cacheprovider -p pytest_compile_time
"""

from __future__ import annotations

import collections
import json
import os
import tempfile
from pathlib import Path

import jax

_TOTALS: collections.Counter[str] = collections.Counter()
_PER_FILE: collections.Counter[str] = collections.Counter()
_PER_FUNCTION: collections.Counter[str] = collections.Counter()
_COUNT_PER_FUNCTION: collections.Counter[str] = collections.Counter()
_CURRENT: list[str | None] = [None]
_FOLDER: list[Path] = []
_KEY = "compile_time_folder"


def _listener(event: str, duration: float, fun_name: str | None = None, **_: object) -> None:
    _TOTALS[event] += duration
    if event.endswith("backend_compile_duration"):
        if _CURRENT[0] is not None:
            _PER_FILE[_CURRENT[0]] += duration
        name = f"{fun_name} ({_CURRENT[0]})"
        _PER_FUNCTION[name] += duration
        _COUNT_PER_FUNCTION[name] += 1


jax.monitoring.register_event_duration_secs_listener(_listener)


def pytest_configure(config) -> None:
    """The controller (or a run without workers) makes the folder the figures are written to."""
    workerinput = getattr(config, "workerinput", None)
    if workerinput is not None:
        _FOLDER.append(Path(workerinput[_KEY]))
    else:
        _FOLDER.append(Path(tempfile.mkdtemp(prefix="pytest-compile-time-")))


def pytest_configure_node(node) -> None:
    """pytest-xdist: tell each worker where to write."""
    node.workerinput[_KEY] = str(_FOLDER[0])


def pytest_runtest_setup(item) -> None:
    """Attribute the compiles that follow to this test's file."""
    _CURRENT[0] = item.nodeid.split("::")[0]


def pytest_sessionfinish(session) -> None:
    """Each process writes its figures."""
    figures = {
        "totals": _TOTALS,
        "files": _PER_FILE,
        "functions": _PER_FUNCTION,
        "counts": _COUNT_PER_FUNCTION,
    }
    (_FOLDER[0] / f"{os.getpid()}.json").write_text(json.dumps(figures))


def pytest_terminal_summary(terminalreporter) -> None:
    """Print the compile-phase totals, the files with the most backend compile time and the functions."""
    sums = {key: collections.Counter() for key in ("totals", "files", "functions", "counts")}
    for path in _FOLDER[0].glob("*.json"):
        for key, values in json.loads(path.read_text()).items():
            sums[key].update(values)
    write = terminalreporter.write_line
    write(f"jax backend compiles {sum(sums['counts'].values())}")
    for event, seconds in sorted(sums["totals"].items(), key=lambda item: -item[1])[:8]:
        write(f"jax compile time {seconds:9.1f} s  {event}")
    for path, seconds in sums["files"].most_common(int(os.environ.get("COMPILE_TIME_FILES", "20"))):
        write(f"backend compile  {seconds:9.1f} s  {path}")
    for name, seconds in sums["functions"].most_common(int(os.environ.get("COMPILE_TIME_FUNCTIONS", "0"))):
        write(f"function compile {seconds:9.1f} s  {sums['counts'][name]:5d} programs  {name}")
