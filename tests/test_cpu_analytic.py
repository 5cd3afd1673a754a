"""Bounding boxes with the built-in intersection functions (sphere, disk, capped cylinder) on the compiled CPU
traversal, against the portable traversal and a float64 brute force (scenes, rays and references of
``test_gpu_analytic.py``).

The CPU traversal repeats each function's formula in the GPU kernel's operation order, unfused (a dot product
is ``(x0 y0 + x1 y1) + x2 y2``), with correctly rounded divisions and square roots; the portable function runs
in XLA, which contracts some multiply-adds into fused ones depending on how it fuses the program around the
leaf test. So the analytic distances equal the portable path's to rounding, not to the bit (triangle distances
stay bit for bit): leaves, instance chains, hit counts and traversal counters are compared exactly, distances
with ``rtol`` 1e-6 (capped cylinders :data:`CYLINDER_RTOL`, whose wall quadratic subtracts nearly equal
products), and every hit against the float64 roots.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from test_gpu_analytic import (
    CYLINDER_RTOL,
    FUNCTIONS,
    SHAPES,
    as_ray,
    assert_float64,
    assert_same_fields,
    rays,
    shape_data,
    shape_geometry,
    shapes_structure,
)
from test_gpu_instanced import _instances, _mesh

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt._src.scene_view import scene_view
from jaxrt._src.traversal import cpu

pytestmark = pytest.mark.skipif(cpu.unavailable_reason() is not None, reason=str(cpu.unavailable_reason()))


def _both(args: dict, ray: rt.Ray, structure, tags=(), rtol: float = 1e-6):
    """The result fields on the CPU traversal (which must cover the case) and on the portable traversal."""
    compiled = rt.Intersector(*tags, backend="cpu", **args)
    infos = scene_view(structure).geometry_info
    assert pipeline.kernel_declines(compiled, infos, "cpu") is None
    got = compiled.intersect(ray, structure)
    want = rt.Intersector(*tags, backend="portable", **args).intersect(ray, structure)
    assert_same_fields(got, want, rtol)
    return got


@pytest.mark.parametrize(
    "shape, with_data", [("sphere", True), ("sphere", False), ("disk", True), ("capped_cylinder", True)]
)
def test_each_shape(shape, with_data):
    structure, functions, params = shapes_structure(10 + SHAPES.index(shape), (shape,), 12, with_data=with_data)
    ray = as_ray(rays(256, 20 + SHAPES.index(shape), params))
    rtol = CYLINDER_RTOL if shape == "capped_cylinder" else 1e-6
    tags = (rt.tags.stats,)
    got = _both(dict(intersection_functions=functions), ray, structure, tags, rtol)
    assert assert_float64(got, params, ray, max(rtol, 1e-4)) > 50


@pytest.mark.parametrize("any_hit, cull", [(False, "front"), (True, "none")])
def test_shapes_mixed_with_triangles(any_hit, cull):
    """All three shapes and triangles in one structure (triangles culled, shapes never), nearest and any hit."""
    structure, functions, _ = shapes_structure(30, SHAPES, 5, triangles=8)
    ray = as_ray(rays(256, 31))
    args = dict(intersection_functions=functions, accept_any_intersection=any_hit, triangle_cull_mode=cull)
    tags = (rt.tags.triangle_data, rt.tags.primitive_data, rt.tags.stats)
    got = _both(args, ray, structure, tags, CYLINDER_RTOL)
    hit = np.asarray(got.type) != 0
    assert set(np.asarray(got.geometry_id)[hit].tolist()) == {0, 1, 2, 3}


def test_hit_lists_and_counts():
    structure, functions, _ = shapes_structure(40, SHAPES, 5, triangles=6)
    ray = as_ray(rays(256, 41))
    got = _both(dict(intersection_functions=functions, max_hits=3), ray, structure, (rt.tags.stats,), CYLINDER_RTOL)
    assert (np.asarray(got.hit_count) >= 2).sum() > 10
    counts = [
        np.asarray(rt.count_intersections(ray, structure, rt.Intersector(intersection_functions=functions, backend=b)))
        for b in ("cpu", "portable")
    ]
    np.testing.assert_array_equal(counts[0], counts[1])
    assert counts[0].max() >= 3


def test_below_instances():
    """Shapes one and two instance levels deep (masks, mirrored transforms), next to a mesh."""
    rng = np.random.default_rng(52)
    shapes, functions, _ = shapes_structure(53, ("sphere", "capped_cylinder", "disk"), 6)
    inner = rt.build_instance_structure([shapes, _mesh(rng)], _instances(rng, [0, 1, 0], 1.0, masks=True))
    structure = rt.build_instance_structure([inner, shapes], _instances(rng, [0, 1, 0], 1.6, masks=True))
    ray = as_ray(rays(256, 62, spread=1.5, masks=True))
    tags = (rt.tags.instancing, rt.tags.max_levels(2), rt.tags.primitive_data, rt.tags.stats)
    got = _both(dict(intersection_functions=functions), ray, structure, tags, CYLINDER_RTOL)
    hit = np.asarray(got.type) == int(rt.IntersectionType.BOUNDING_BOX)
    depth = np.asarray(got.instance_count)[hit]
    assert hit.sum() > 10 and (depth == 1).any() and (depth == 2).any()


def test_float64_and_vmap():
    """Float64 rows and rays (the scene's dtype end to end), and ``vmap`` over rays."""
    structure32, functions, params = shapes_structure(70, SHAPES, 6)
    ray_args = rays(256, 71, params)
    with jax.enable_x64(True):
        rng = np.random.default_rng(70)
        geometries = []
        for shape in SHAPES:
            data = {k: v.astype(np.float64) for k, v in shape_data(rng, 6).items()}
            geometries.append(shape_geometry(shape, data))
        structure = rt.build_primitive_structure(geometries)
        assert structure.node_lower.dtype == np.float64
        ray = as_ray(tuple(np.asarray(a, np.float64) if a.dtype == np.float32 else a for a in ray_args))
        got = _both(dict(intersection_functions=functions), ray, structure, (), 1e-9)
        assert got.distance.dtype == np.float64 and (np.asarray(got.type) != 0).sum() > 50
    compiled = rt.Intersector(intersection_functions=functions, backend="cpu")
    ray = as_ray(ray_args)
    flat = compiled.intersect(ray, structure32)
    folded = jax.tree_util.tree_map(lambda a: a.reshape(2, 128, *a.shape[1:]), ray)
    batched = jax.vmap(lambda r: compiled.intersect(r, structure32).distance)(folded)
    np.testing.assert_array_equal(np.asarray(batched).reshape(-1), np.asarray(flat.distance))


def test_user_functions_and_filters_stay_declined():
    structure, functions, _ = shapes_structure(100, SHAPES, 2, triangles=2)
    infos = structure.geometry_info
    assert pipeline.kernel_declines(rt.Intersector(intersection_functions=functions), infos, "cpu") is None

    def my_disk(ray, candidate):
        return FUNCTIONS.disk(ray, candidate)

    user = rt.Intersector(intersection_functions={**functions, 1: my_disk})
    reason = pipeline.kernel_declines(user, infos, "cpu")
    assert reason.startswith("bounding-box geometry with user intersection functions (geometry 1: my_disk)")
    assert reason.endswith("not covered by the CPU traversal (it traces rt.intersection_functions.sphere, disk and capped_cylinder)")  # fmt: skip
    with pytest.raises(ValueError, match="backend='cpu' cannot run: bounding-box geometry with user"):
        rt.Intersector(intersection_functions={**functions, 1: my_disk}, backend="cpu").intersect(
            as_ray(rays(4, 1)), structure
        )
