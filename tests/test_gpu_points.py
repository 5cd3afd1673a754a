"""The GPU point kernels (:mod:`jaxrt._src.traversal.triton_points`) against the float64 brute force and the other
walks, on tiny scenes: on a GPU directly, elsewhere in Triton's interpreter (a fresh process)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt
from jaxrt._src.traversal import points as points_backend

sys.path.insert(0, str(Path(__file__).parent))
from test_gpu_instanced import _HostArray, run_kernel_tests_in_interpreter  # noqa: E402
from test_point_queries import assert_closest, brute_closest, brute_winding  # noqa: E402

INTERPRETED = os.environ.get("TRITON_INTERPRET") == "1"
ON_GPU = jax.default_backend() == "gpu" and points_backend._gpu_unavailable(jnp.float32) is None
kernel_test = pytest.mark.skipif(not (INTERPRETED or ON_GPU), reason="runs in the interpreter process or on a GPU")


def test_point_kernels_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__, "kernel_")


def _interpreted_launch(kernel: str, programs: int, args: tuple, out_shape: tuple, params: dict):
    """:func:`triton_points._launch` in Triton's interpreter, through a host callback."""
    from jaxrt._src.traversal import triton_points

    function = getattr(triton_points, kernel)
    arrays = [a for a in args if not isinstance(a, int)]

    def host(*values):
        inputs = iter(values)
        host_args = [a if isinstance(a, int) else _HostArray(np.asarray(next(inputs))) for a in args]
        outs = [_HostArray(np.full(s.shape, -7 if s.dtype == jnp.int32 else np.nan, s.dtype)) for s in out_shape]
        function[(programs,)](*host_args, *outs, **params)
        return tuple(o.array for o in outs)

    return jax.pure_callback(host, tuple(out_shape), *arrays)


@pytest.fixture
def kernel_here(monkeypatch):
    if not ON_GPU:
        from jaxrt._src.traversal import triton_points

        monkeypatch.setattr(triton_points, "_launch", _interpreted_launch)
        monkeypatch.setattr(triton_points, "MAX_PROGRAMS", 2)  # programs stride over the blocks
        monkeypatch.setattr(points_backend, "_gpu_unavailable", lambda dtype: None)


def _soup(seed: int, n: int = 40) -> np.ndarray:
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1.0, 1.0, (n, 1, 3))
    triangles = centre + 0.3 * rng.standard_normal((n, 3, 3))
    triangles[:2, 2] = triangles[:2, 0]  # zero area: never found
    return triangles.astype(np.float32)


def _octahedron(scale: float = 1.0):
    vertices = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float32) * scale
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return vertices, faces


@kernel_test
def test_kernel_nearest_matches_brute_force_and_the_cpu_walk(kernel_here):
    triangles = _soup(1)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    points = np.random.default_rng(2).uniform(-1.5, 1.5, (70, 3)).astype(np.float32)  # three blocks of lanes
    gpu = rt.closest_point(points, structure, backend="gpu")
    assert_closest(gpu, points, triangles, atol=1e-5)
    portable = rt.closest_point(points, structure, backend="portable")
    every = brute_closest(points, triangles)[2]
    a, b = np.asarray(portable.primitive_id), np.asarray(gpu.primitive_id)
    rows = np.arange(len(points))
    assert ((a == b) | (np.abs(every[rows, a] - every[rows, b]) <= 1e-6)).all()
    limited = rt.closest_point(points, structure, max_distance=0.05, backend="gpu")
    ref = brute_closest(points, triangles)[0]
    np.testing.assert_array_equal(np.asarray(limited.primitive_id) >= 0, ref <= 0.05)
    bad = jnp.array([[jnp.nan, 0.0, 0.0], [0.0, jnp.inf, 0.0], [0.1, 0.2, 0.3]], jnp.float32)
    r = jax.jit(lambda p: rt.closest_point(p, structure, backend="gpu"))(bad)
    np.testing.assert_array_equal(np.asarray(r.primitive_id)[:2], -1)
    assert int(r.primitive_id[2]) >= 0


@kernel_test
def test_kernel_winding_numbers_and_signed_distance(kernel_here):
    vertices, faces = _octahedron()
    outer = rt.TriangleGeometry(vertices, faces)
    inner = rt.TriangleGeometry(vertices * np.float32(0.3), faces[:, ::-1])  # a cavity: winding 0 inside it
    structure = rt.build_primitive_structure([outer, inner])
    triangles = np.concatenate([vertices[faces], (vertices * np.float32(0.3))[faces[:, ::-1]]])
    points = np.random.default_rng(3).uniform(-1.3, 1.3, (40, 3)).astype(np.float32)
    reference = brute_winding(points, triangles)
    exact = np.asarray(rt.winding_number(points, structure, exact=True, backend="gpu"))
    fast = np.asarray(rt.winding_number(points, structure, backend="gpu"))
    np.testing.assert_allclose(exact, reference, atol=1e-5)
    np.testing.assert_allclose(fast, np.asarray(rt.winding_number(points, structure, backend="portable")), atol=1e-5)
    inside = reference >= 0.5
    sd = np.asarray(rt.signed_distance(points, structure, backend="gpu"))
    ref = brute_closest(points, triangles)[0]
    np.testing.assert_allclose(sd, np.where(inside, -ref, ref), atol=1e-5)
    # Gradients reach the points through the JAX fields: unit length.
    g = jax.grad(lambda p: jnp.sum(rt.signed_distance(p, structure, backend="gpu")))(jnp.asarray(points[:8]))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(g), axis=1), 1.0, atol=1e-4)


@kernel_test
def test_kernel_boxes_and_vmap(kernel_here):
    boxes = np.array([[[0, 0, 0], [1, 1, 1]], [[3, 0, 0], [4, 2, 1]]], np.float32)
    triangle = rt.TriangleGeometry([[0.0, 5, 0], [1, 5, 0], [0, 6, 0]])
    structure = rt.build_primitive_structure([rt.BoundingBoxGeometry(boxes[:, 0], boxes[:, 1]), triangle])
    points = np.array([[0.5, 0.5, 0.5], [1.8, 0.5, 0.5], [3.5, 3.0, 0.5], [0.2, 5.2, 1.0], [-1, -1, -1]], np.float32)
    r = rt.closest_point(points, structure, backend="gpu")
    np.testing.assert_allclose(np.asarray(r.distance), [0.0, 0.8, 1.0, 1.0, np.sqrt(3)], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(r.primitive_id), [0, 0, 1, 0, 0])
    w = np.asarray(rt.winding_number(points, structure, exact=True, backend="gpu"))
    expected = [1, 0, 0, 0, 0] + brute_winding(points, np.array([[[0.0, 5, 0], [1, 5, 0], [0, 6, 0]]]))
    np.testing.assert_allclose(w, expected, atol=1e-6)
    mapped = jax.vmap(lambda p: rt.closest_point(p, structure, backend="gpu"))(np.stack([points, points[::-1]]))
    np.testing.assert_array_equal(np.asarray(mapped.primitive_id[1]), np.asarray(r.primitive_id)[::-1])


def _variant_answers(structure, points, name: str, limit2=np.inf, winding_too: bool = True):
    """The nearest leaves and fast winding numbers of the point kernels' variant ``name``, called directly."""
    from jaxrt._src import point_query, winding
    from jaxrt._src.traversal import triton_points

    boxes, box_leaf = points_backend.box_leaves(structure, point_query._box_table(structure))
    p = jnp.asarray(points)
    leaf = np.asarray(triton_points.nearest(p, structure, boxes, box_leaf, jnp.float32(limit2), name))
    if not winding_too:
        return leaf
    wind = triton_points.fast_winding(p, structure, boxes, box_leaf, winding._dipoles(structure, 2.0), name)
    return leaf, np.asarray(wind)


def _tested_variants() -> list[str]:
    """On a GPU every variant whose code differs (a program cap aside); in the interpreter, where each walk takes
    seconds, variants that between them take every code path (each walk, each flag on and off, programs
    striding over blocks, lanes refilled)."""
    import dataclasses

    from jaxrt._src.traversal import triton_points

    if ON_GPU:
        codes = {}
        for name, v in triton_points.VARIANTS.items():
            codes.setdefault(dataclasses.replace(v, programs=None), name)
        return list(dict.fromkeys([triton_points.VARIANT, *codes.values()]))
    names = list(dict.fromkeys([triton_points.VARIANT, "stack", "near", "near-plain", "refill", "stackless-8k"]))
    chosen = [triton_points.VARIANTS[name] for name in names]
    for field in ("vector_loads", "leaf_batch", "skip"):
        assert {getattr(v, field) for v in chosen if v.walk == "near"} == {False, True}
    assert {v.walk for v in chosen} == {"stack", "near", "refill", "stackless"}
    return names


def _variant_scenes():
    """Three small structures with query points: a soup (two blocks of lanes), a closed octahedron with a cavity (points on its
    vertices and edge midpoints: ties between the triangles that share them), and boxes beside a triangle;
    each with NaN and infinite points."""
    bad = np.array([[np.nan, 0, 0], [0, np.inf, 0], [-np.inf, 1, 2]], np.float32)
    soup = _soup(4)
    yield (
        rt.build_primitive_structure(rt.TriangleGeometry(soup.reshape(-1, 3))),
        np.random.default_rng(5).uniform(-1.5, 1.5, (40, 3)).astype(np.float32),
    )
    vertices, faces = _octahedron()
    outer = rt.TriangleGeometry(vertices, faces)
    inner = rt.TriangleGeometry(vertices * np.float32(0.3), faces[:, ::-1])
    edges = 0.5 * (vertices[faces[:, 0]] + vertices[faces[:, 1]])
    random = np.random.default_rng(6).uniform(-1.3, 1.3, (16, 3)).astype(np.float32)
    points = np.concatenate([vertices, edges, 0.3 * edges, np.zeros((1, 3), np.float32), random, bad])
    yield rt.build_primitive_structure([outer, inner]), points.astype(np.float32)
    boxes = np.array([[[0, 0, 0], [1, 1, 1]], [[3, 0, 0], [4, 2, 1]], [[0, 3, 0], [1, 4, 1]]], np.float32)
    triangle = rt.TriangleGeometry([[0.0, 5, 0], [1, 5, 0], [0, 6, 0]])
    structure = rt.build_primitive_structure([rt.BoundingBoxGeometry(boxes[:, 0], boxes[:, 1]), triangle])
    points = np.random.default_rng(7).uniform(-1, 6, (20, 3)).astype(np.float32)
    yield structure, np.concatenate([points, bad])


@kernel_test
def test_kernel_variants_make_the_default_decisions(kernel_here, monkeypatch):
    """Every kernel variant picks the default variant's leaf (ties included, also within a radius) and sums
    the same fast winding number, bit for bit; NaN and infinite points take no step."""
    from jaxrt._src.traversal import triton_points

    monkeypatch.setattr(triton_points, "MAX_PROGRAMS", 1)  # one program strides over two blocks, or refills

    default = triton_points.VARIANT
    names = _tested_variants()
    for i, (structure, points) in enumerate(_variant_scenes()):
        want_leaf, want_wind = _variant_answers(structure, points, default)
        bad = ~np.isfinite(points).all(axis=1)
        assert (want_leaf[bad] == -1).all() and (want_leaf[~bad] >= 0).all() and np.isnan(want_wind[bad]).all()
        if i == 1:  # within a radius: some points find no leaf
            want_near = _variant_answers(structure, points, default, limit2=0.04, winding_too=False)
            assert (want_near == -1).any() and (want_near >= 0).any()
        for name in names:
            leaf, wind = _variant_answers(structure, points, name)
            np.testing.assert_array_equal(leaf, want_leaf, err_msg=name)
            np.testing.assert_array_equal(wind, want_wind, err_msg=name)
            if i == 1:
                near = _variant_answers(structure, points, name, limit2=0.04, winding_too=False)
                np.testing.assert_array_equal(near, want_near, err_msg=name)


def test_unknown_variant_is_refused():
    pytest.importorskip("triton")
    from jaxrt._src.traversal import triton_points

    with pytest.raises(ValueError, match="unknown point kernel variant 'nope'"):
        triton_points.variant("nope")
