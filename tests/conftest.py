"""Shared test configuration: a deterministic hypothesis profile, the test-helper import path, the shared
data folder, a guard that ends a run whose test hangs, and one that drops JAX's compiled programs before the
process runs out of memory mappings."""

from __future__ import annotations

import faulthandler
import os
import sys
from pathlib import Path

import hypothesis
import pytest

# Under ``--import-mode=importlib`` the tests folder is not on ``sys.path``; the float64 reference and the
# tolerance table live in ``tests/reference.py`` and are imported by name.
sys.path.insert(0, str(Path(__file__).resolve().parent))

# A module of Triton kernels for tests/test_gpu_curves.py (imported there only where Triton is installed): not a
# test module, and ``--doctest-modules`` would import it without Triton.
collect_ignore = ["curve_leaf_kernels.py"]


def data_dir() -> Path:
    """The shared data folder: ``$JAXRT_DATA_DIR`` when set, else ``shared/data`` beside the repository (as
    ``jaxrt.bench.scenes.default_data_dir``). It may be absent: tests that need it skip."""
    env = os.environ.get("JAXRT_DATA_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


hypothesis.settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    max_examples=12,
    print_blob=True,
    suppress_health_check=[hypothesis.HealthCheck.too_slow, hypothesis.HealthCheck.data_too_large],
)
hypothesis.settings.register_profile(
    "quick",  # a local check while editing: JAXRT_HYPOTHESIS_PROFILE=quick
    derandomize=True,
    deadline=None,
    max_examples=3,
    suppress_health_check=[hypothesis.HealthCheck.too_slow, hypothesis.HealthCheck.data_too_large],
)
hypothesis.settings.register_profile(
    "thorough",
    derandomize=True,
    deadline=None,
    max_examples=300,
    suppress_health_check=[hypothesis.HealthCheck.too_slow, hypothesis.HealthCheck.data_too_large],
)
hypothesis.settings.load_profile(os.environ.get("JAXRT_HYPOTHESIS_PROFILE", "ci"))

#: A test still running after this many seconds (the slowest take about a minute) prints every thread's stack
#: and ends the run with a failure, instead of holding it until an outer time limit without saying where.
HANG_SECONDS = float(os.environ.get("JAXRT_TEST_HANG_SECONDS", "900"))
_stderr: list[int] = []  # a copy of the terminal's stderr, taken while pytest does not capture it


def pytest_configure(config: pytest.Config) -> None:
    _stderr.append(os.dup(2))


@pytest.fixture(autouse=True)
def _end_the_run_on_a_hang():
    faulthandler.dump_traceback_later(HANG_SECONDS, exit=True, file=_stderr[0] if _stderr else 2)
    yield
    faulthandler.cancel_dump_traceback_later()


def _map_limit() -> int | None:
    """The kernel's limit on a process's memory mappings (``vm.max_map_count``), where it can be read."""
    try:
        return int(Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return None


#: Each program XLA compiles for the CPU holds memory mappings until JAX's caches let it go; a whole run
#: compiles thousands and would pass Linux's default limit of 65,530 mappings, where the next compilation
#: crashes the process (a segmentation fault). Past this many mappings the caches are cleared between tests.
MAP_BUDGET = int(0.7 * (_map_limit() or 0))


@pytest.fixture(autouse=True)
def _drop_compiled_programs_before_the_mapping_limit():
    if MAP_BUDGET:
        with open("/proc/self/maps", "rb") as maps:
            if sum(1 for _ in maps) > MAP_BUDGET:
                import jax

                jax.clear_caches()
    yield


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs_after_each_module():
    """Each test file's compiled programs are let go when it ends: few are shared between files (one run of the
    suite compiles about 7,000 programs, and JAX's persistent cache finds a repeat for about 2% of their compile
    time), while holding them all took 5-7 GB per worker. ``scripts/test.sh`` keeps a persistent cache, so a
    program a later file repeats is read from disk, not compiled again."""
    yield
    import jax

    jax.clear_caches()
