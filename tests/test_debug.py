"""Traversal heatmaps (``rt.debug``): colormaps, images of the stats counters, PNG output."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from lifecycle_scenes import soup

import jaxrt as rt
from jaxrt import debug


def test_turbo_runs_from_dark_blue_to_dark_red_through_green():
    cold, blue, middle, hot = debug.colormap([0.0, 0.15, 0.5, 1.0], vmax=1.0)
    assert cold.max() < 60  # near black
    assert blue[2] > 200 and blue[2] > blue[0] and blue[2] > blue[1]
    assert middle[1] > 200  # bright green-yellow in the middle
    assert hot[0] > hot[1] and hot[0] > hot[2] and hot.max() < 180  # dark red


@given(hnp.arrays(np.float64, st.integers(1, 50), elements=st.floats(-1e6, 1e6)))
def test_colormap_is_uint8_rgb_and_clips(values):
    rgb = debug.colormap(values, vmin=-10.0, vmax=10.0)
    assert rgb.shape == values.shape + (3,) and rgb.dtype == np.uint8
    assert np.array_equal(
        rgb[values <= -10.0], np.broadcast_to(debug.colormap([-10.0], vmin=-10, vmax=10), rgb[values <= -10.0].shape)
    )


def test_colormap_and_heatmap_errors_name_the_argument():
    with pytest.raises(ValueError, match="colormap: name must be one of"):
        debug.colormap([1.0], name="jet")
    with pytest.raises(ValueError, match="colormap: vmax must exceed vmin"):
        debug.colormap([1.0], vmin=2.0, vmax=1.0)
    with pytest.raises(ValueError, match=r"heatmap: counts must have shape \(H, W\)"):
        debug.heatmap(np.zeros(3))
    assert np.array_equal(debug.colormap([np.nan]), [[0, 0, 0]])
    assert debug.heatmap(np.zeros((2, 2))).shape == (2, 2, 3)  # all zero: no division by zero


def test_traversal_heatmap_shows_the_stats_counters(tmp_path):
    triangles = soup(64, 3)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    rays = rt.shading.pinhole_rays(24, 16, eye=(0.0, 0.0, 9.0), target=(0.0, 0.0, 0.0))
    image, counts = debug.traversal_heatmap(structure, rays)
    expected = rt.Intersector(rt.tags.stats).intersect(rays, structure).nodes_visited
    assert np.array_equal(counts, np.asarray(expected))
    assert image.shape == (16, 24, 3) and counts.max() > counts.min()
    assert np.array_equal(image, debug.heatmap(counts))
    _, tested = debug.traversal_heatmap(structure, rays, field="primitives_tested")
    assert tested.max() >= 1
    with pytest.raises(ValueError, match="traversal_heatmap: field must be one of"):
        debug.traversal_heatmap(structure, rays, field="depth")
    with pytest.raises(ValueError, match="traversal_heatmap: intersector needs the rt.tags.stats tag"):
        debug.traversal_heatmap(structure, rays, intersector=rt.Intersector())

    path = tmp_path / "heat.png"
    debug.write_png(path, image)
    image_module = pytest.importorskip("PIL.Image")
    assert np.array_equal(np.asarray(image_module.open(path).convert("RGB")), image)


def test_write_png_rejects_other_images(tmp_path):
    with pytest.raises(ValueError, match=r"write_png: image must be \(H, W, 3\) uint8"):
        debug.write_png(tmp_path / "x.png", np.zeros((4, 4), np.uint8))
    bar = debug.colorbar(32, 2)
    assert bar.shape == (2, 32, 3) and np.array_equal(bar[0], bar[1])
