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
    argv = ["--size", "24", "--samples-per-pixel", "4", "--edge-samples", "1024", "--out", str(out)]
    result = load("silhouette_gradients").main(argv)
    assert out.stat().st_size > 0
    assert result["silhouette_pixels"] > 0
    # Away from the silhouette autodiff matches finite differences; the mean brightness derivative does not.
    assert result["interior_max_abs_error_relative"] < 0.05
    assert math.isfinite(result["pixel_integral_derivative_edge_sampling"])


def test_shape_from_silhouette_example_runs(tmp_path):
    pytest.importorskip("optax")
    pytest.importorskip("matplotlib")
    argv = ["--size", "12", "--iterations", "2", "--edge-samples", "64", "--quiet", "--out", str(tmp_path)]
    result = load("shape_from_silhouette").main(argv)
    for picture in ("silhouettes", "loss"):
        assert (tmp_path / f"{picture}.png").stat().st_size > 0, picture
    for run in ("edge_sampling", "plain_autodiff"):
        assert all(math.isfinite(v) for v in result[run].values()), result[run]
    # Plain autodiff has no gradient from silhouettes alone: it does not move.
    assert result["plain_autodiff"]["centre_error"] == pytest.approx(result["start"]["centre_error"])
