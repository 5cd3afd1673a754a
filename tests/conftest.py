"""Shared test configuration: a deterministic hypothesis profile and the test-helper import path."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import hypothesis

# Under ``--import-mode=importlib`` the tests folder is not on ``sys.path``; the float64 reference and the
# tolerance table live in ``tests/reference.py`` and are imported by name.
sys.path.insert(0, str(Path(__file__).resolve().parent))

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
