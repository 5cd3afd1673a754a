"""Shared test configuration: a deterministic hypothesis profile, the test-helper import path, and the shared
data folder."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import hypothesis

# Under ``--import-mode=importlib`` the tests folder is not on ``sys.path``; the float64 reference and the
# tolerance table live in ``tests/reference.py`` and are imported by name.
sys.path.insert(0, str(Path(__file__).resolve().parent))


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
    "thorough",
    derandomize=True,
    deadline=None,
    max_examples=300,
    suppress_health_check=[hypothesis.HealthCheck.too_slow, hypothesis.HealthCheck.data_too_large],
)
hypothesis.settings.load_profile(os.environ.get("JAXRT_HYPOTHESIS_PROFILE", "ci"))
