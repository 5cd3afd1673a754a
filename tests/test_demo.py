"""The README's first command renders the demo: a small run checks its image and its accuracy summary."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_demo_renders_an_antialiased_colour_image(tmp_path, monkeypatch):
    image = pytest.importorskip("PIL.Image")
    monkeypatch.syspath_prepend(str(EXAMPLES))
    spec = importlib.util.spec_from_file_location("demo", EXAMPLES / "demo.py")
    demo = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "demo", demo)
    spec.loader.exec_module(demo)
    out = tmp_path / "demo.png"
    summary = demo.main(
        ["--width", "48", "--height", "36", "--spp", "2", "--ao-samples", "2", "--check-rays", "128", "--quiet"]
        + ["--out", str(out)]
    )
    assert summary["hit_miss_mismatches"] == 0 and summary["primitive_mismatches"] == 0
    assert summary["max_rel_distance_error"] < 1e-5
    assert summary["primary_rays"] == 2 * 48 * 36 and summary["occlusion_rays"] > 0
    pixels = np.asarray(image.open(out)).astype(float)
    assert pixels.shape == (36, 48, 3)
    sky, floor = pixels[0].mean(axis=0), pixels[-1].mean(axis=0)
    assert sky[2] > sky[0] + 20, "the sky is blue"
    assert np.abs(sky - floor).max() > 40, "the floor stands out from the sky"
