"""Smoke tests of the gradient examples: each ``main`` at a tiny size and a few iterations.

The examples themselves take minutes (they are not run here); this checks that they run end to end, write
their pictures and report finite errors. The procedural mesh keeps the build small.
"""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load(name: str):
    # A script run as `python examples/NAME.py` finds its sibling modules (the progress bar helper): so here.
    if str(EXAMPLES) not in sys.path:
        sys.path.insert(0, str(EXAMPLES))
    spec = importlib.util.spec_from_file_location(f"jaxrt_example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    "name, argv, pictures",
    [
        ("inverse_albedo", ["--procedural"], ["target", "before", "after", "texture", "loss"]),
        ("inverse_depth", ["--cells", "6"], ["target", "before", "after", "loss"]),
        ("inverse_pose", ["--procedural"], ["target", "before", "after", "loss"]),
    ],
)
def test_inverse_example_runs(name, argv, pictures, tmp_path):
    pytest.importorskip("optax")
    pytest.importorskip("matplotlib")
    result = load(name).main([*argv, "--size", "12", "--iterations", "2", "--out", str(tmp_path)])
    for picture in pictures:
        assert (tmp_path / f"{picture}.png").stat().st_size > 0, picture
    numbers = {k: v for k, v in result.items() if isinstance(v, float)}
    assert numbers and all(math.isfinite(v) for v in numbers.values()), numbers


def test_silhouette_example_runs(tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "silhouette.png"
    result = load("silhouette_gradients").main(["--size", "24", "--out", str(out)])
    assert out.stat().st_size > 0
    assert result["silhouette_pixels"] > 0
    # Away from the silhouette autodiff matches finite differences; the mean brightness derivative does not.
    assert result["interior_max_abs_error_relative"] < 0.05
