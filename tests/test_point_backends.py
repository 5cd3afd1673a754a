"""Every walk of the point queries (portable JAX, compiled CPU, and the GPU kernel where a GPU is present)
against the float64 brute force of :mod:`test_point_queries`, against each other, and in gradients."""

from __future__ import annotations

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from test_point_queries import assert_closest, brute_closest, brute_winding

import jaxrt as rt
from jaxrt._src.traversal import points as points_backend
from jaxrt.bench.scenes import noisy_sphere


def _available(backend: str) -> bool:
    if backend == "portable":
        return True
    reason = points_backend._cpu_unavailable() if backend == "cpu" else points_backend._gpu_unavailable(jnp.float32)
    return reason is None


BACKENDS = [pytest.param(b, marks=pytest.mark.skipif(not _available(b), reason=f"no {b} walk here")) for b in ("portable", "cpu", "gpu")]  # fmt: skip
COMPILED = BACKENDS[1:]


@pytest.fixture(scope="module")
def sphere():
    """The closed noisy sphere of test_point_queries (same sizes: the same compiled programs) and points near
    it, inside, outside and far away."""
    scene = noisy_sphere(2_000, seed=3, noise=0.05)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(scene.vertices, scene.indices))
    rng = np.random.default_rng(11)
    directions = rng.normal(size=(256, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    near = directions * rng.uniform(0.9, 1.1, (256, 1))
    box = rng.uniform(-1.6, 1.6, (192, 3))
    far = rng.normal(size=(64, 3)) * 20
    # Points on vertices and at edge midpoints of the mesh: ties between the triangles that share them.
    vertices = scene.vertices[scene.indices[:16, 0]]
    midpoints = 0.5 * (scene.vertices[scene.indices[16:32, 0]] + scene.vertices[scene.indices[16:32, 1]])
    points = np.concatenate([near, box, far, vertices, midpoints]).astype(np.float32)
    return scene, structure, points


@pytest.mark.parametrize("backend", BACKENDS)
def test_walk_matches_brute_force(sphere, backend):
    scene, structure, points = sphere
    triangles = scene.vertices[scene.indices]
    result = rt.closest_point(points, structure, backend=backend)
    atol = 2e-5 * (1 + np.abs(points).max())
    assert_closest(result, points, triangles, atol=atol)
    # Winding numbers off the surface (on it, at the vertices and edge midpoints, they are undefined).
    ref = brute_closest(points, triangles)[0]
    off = ref > 1e-3
    winding = brute_winding(points, triangles)
    fast = np.asarray(rt.winding_number(points, structure, backend=backend))
    exact = np.asarray(rt.winding_number(points, structure, exact=True, backend=backend))
    np.testing.assert_allclose(exact[off], winding[off], atol=2e-4)
    assert np.abs(fast - winding)[off].max() < 0.05
    inside = winding >= 0.5
    np.testing.assert_array_equal(np.asarray(rt.contains(points, structure, backend=backend))[off], inside[off])
    sd = np.asarray(rt.signed_distance(points, structure, backend=backend))
    np.testing.assert_allclose(np.abs(sd), ref, atol=atol)
    np.testing.assert_allclose(sd[off], np.where(inside, -ref, ref)[off], atol=atol)


@pytest.mark.parametrize("backend", COMPILED)
def test_compiled_walk_picks_the_portable_primitive(sphere, backend):
    """The same primitive as the portable walk except at ties (distances equal to float32 rounding: shared
    vertices and edges), and the same result fields from it; winding numbers equal to rounding."""
    scene, structure, points = sphere
    portable = rt.closest_point(points, structure, backend="portable")
    compiled = rt.closest_point(points, structure, backend=backend)
    every = brute_closest(points, scene.vertices[scene.indices])[2]
    a, b = np.asarray(portable.primitive_id), np.asarray(compiled.primitive_id)
    rows = np.arange(len(points))
    tie = np.abs(every[rows, a] - every[rows, b]) <= 1e-6 * (1 + np.abs(points).max(axis=1))
    assert (tie | (a == b)).all()
    assert (a == b).mean() > 0.9
    same = a == b
    for field in ("distance", "point", "triangle_barycentric_coord"):
        np.testing.assert_array_equal(
            np.asarray(getattr(compiled, field))[same], np.asarray(getattr(portable, field))[same]
        )
    off = np.asarray(portable.distance) > 1e-3  # winding numbers are undefined on the surface
    for exact in (False, True):
        w0 = np.asarray(rt.winding_number(points, structure, exact=exact, backend="portable"))
        w1 = np.asarray(rt.winding_number(points, structure, exact=exact, backend=backend))
        np.testing.assert_allclose(w1[off], w0[off], atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_max_distance_nan_points_jit_and_vmap(sphere, backend):
    scene, structure, points = sphere
    ref = brute_closest(points, scene.vertices[scene.indices])[0]
    limited = rt.closest_point(points, structure, max_distance=0.1, backend=backend)
    beyond, within = ref > 0.1 + 1e-5, ref < 0.1 - 1e-5
    assert beyond.sum() > 50 and within.sum() > 50
    assert (np.asarray(limited.primitive_id)[beyond] == -1).all() and (
        np.asarray(limited.primitive_id)[within] >= 0
    ).all()
    assert np.isinf(np.asarray(limited.distance)[beyond]).all()
    # Inside jit nothing is checked: NaN and infinite points are misses, and the other points are unharmed.
    bad = jnp.array([[jnp.nan, 0.0, 0.0], [0.0, jnp.inf, 0.0], [-jnp.inf, 1.0, 2.0], [0.3, 0.2, 0.1]], jnp.float32)
    r = jax.jit(lambda p: rt.closest_point(p, structure, backend=backend))(bad)
    np.testing.assert_array_equal(np.asarray(r.primitive_id)[:3], -1)
    assert np.isinf(np.asarray(r.distance)[:3]).all() and np.isfinite(np.asarray(r.distance)[3])
    w = np.asarray(jax.jit(lambda p: rt.winding_number(p, structure, backend=backend))(bad))
    assert np.isnan(w[:3]).all() and 0.9 < w[3] < 1.1  # no winding number at a NaN point
    sd = np.asarray(jax.jit(lambda p: rt.signed_distance(p, structure, backend=backend))(bad))
    assert (sd[:3] == np.inf).all() and sd[3] < 0
    flat = rt.closest_point(points[:24], structure, backend=backend)
    mapped = jax.vmap(lambda p: rt.closest_point(p, structure, backend=backend))(points[:24].reshape(4, 6, 3))
    np.testing.assert_array_equal(np.asarray(mapped.primitive_id).reshape(-1), np.asarray(flat.primitive_id))


@pytest.mark.parametrize("backend", COMPILED)
def test_vmap_over_points_and_structures(sphere, backend):
    """A batch of (points, structure) pairs: each pair's answer is that of its own query."""
    scene, structure, points = sphere
    shifted = rt.build_primitive_structure(rt.TriangleGeometry(scene.vertices + np.float32(0.5), scene.indices))
    stacked = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), structure, shifted)
    batch = np.stack([points[:32], points[32:64]])
    mapped = jax.vmap(lambda p, s: rt.closest_point(p, s, backend=backend))(batch, stacked)
    for i, s in enumerate((structure, shifted)):
        one = rt.closest_point(batch[i], s, backend=backend)
        np.testing.assert_array_equal(np.asarray(mapped.primitive_id[i]), np.asarray(one.primitive_id))
    wind = jax.vmap(lambda p, s: rt.winding_number(p, s, backend=backend))(batch, stacked)
    np.testing.assert_allclose(np.asarray(wind[1]), np.asarray(rt.winding_number(batch[1], shifted, backend=backend)), atol=1e-6)  # fmt: skip


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_match_finite_differences(backend):
    """d distance / d point and / d vertices in float64 against central differences of the brute force."""
    if backend == "gpu":
        pytest.skip("the GPU walk takes float32 structures; its gradients are those of the JAX fields")
    triangles = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 1], [1, 0.2, 1.5], [0, 1, 1.2]]])
    points = np.array([[0.2, 0.3, 0.4], [1.5, -0.5, 0.3], [-0.4, 0.4, 0.9], [0.3, 0.3, 1.6]])
    with jax.enable_x64(True):

        def total(vertices, p):
            s = rt.build_primitive_structure(rt.TriangleGeometry(vertices.reshape(-1, 3)))
            return jnp.sum(rt.closest_point(p, s, backend=backend).distance)

        grad_v, grad_p = jax.grad(total, argnums=(0, 1))(jnp.asarray(triangles, jnp.float64), jnp.asarray(points))
        grad_v, grad_p = np.asarray(grad_v), np.asarray(grad_p)
    h = 1e-6
    for array, grad, which in ((points, grad_p, "p"), (triangles.astype(np.float64), grad_v, "v")):
        fd = np.zeros_like(array, np.float64)
        for index in np.ndindex(array.shape):
            plus, minus = array.copy(), array.copy()
            plus[index] += h
            minus[index] -= h
            if which == "p":
                fd[index] = (brute_closest(plus, triangles)[0].sum() - brute_closest(minus, triangles)[0].sum()) / (
                    2 * h
                )
            else:
                fd[index] = (brute_closest(points, plus)[0].sum() - brute_closest(points, minus)[0].sum()) / (2 * h)
        np.testing.assert_allclose(grad, fd, atol=1e-6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_boxes_and_mixed_structures(backend):
    boxes = np.array([[[0, 0, 0], [1, 1, 1]], [[3, 0, 0], [4, 2, 1]]], np.float32)
    triangle = rt.TriangleGeometry([[0.0, 5, 0], [1, 5, 0], [0, 6, 0]])
    structure = rt.build_primitive_structure([rt.BoundingBoxGeometry(boxes[:, 0], boxes[:, 1]), triangle])
    points = np.array([[0.5, 0.5, 0.5], [1.8, 0.5, 0.5], [3.5, 3.0, 0.5], [0.2, 5.2, 1.0], [-1, -1, -1]], np.float32)
    r = rt.closest_point(points, structure, backend=backend)
    np.testing.assert_allclose(np.asarray(r.distance), [0.0, 0.8, 1.0, 1.0, np.sqrt(3)], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(r.geometry_id), [0, 0, 0, 1, 0])
    np.testing.assert_array_equal(np.asarray(r.primitive_id), [0, 0, 1, 0, 0])
    # A box adds 1 inside it; the open triangle its solid angle.
    reference = [1, 0, 0, 0, 0] + brute_winding(points, np.array([[[0.0, 5, 0], [1, 5, 0], [0, 6, 0]]]))
    np.testing.assert_allclose(np.asarray(rt.winding_number(points, structure, exact=True, backend=backend)), reference, atol=1e-6)  # fmt: skip
    np.testing.assert_allclose(np.asarray(rt.winding_number(points, structure, backend=backend)), reference, atol=1e-3)


@pytest.mark.parametrize("backend", BACKENDS)
def test_empty_structure_is_a_named_error(backend):
    structure = rt.build_primitive_structure(rt.TriangleGeometry(np.zeros((3, 3), np.float32)))  # no area
    for query in (rt.closest_point, rt.winding_number, rt.signed_distance, rt.contains):
        with pytest.raises(ValueError, match=rf"{query.__name__}: the structure is empty"):
            query(np.zeros((2, 3), np.float32), structure, backend=backend)


def test_backend_argument_errors(sphere):
    _, structure, points = sphere
    with pytest.raises(ValueError, match="closest_point: backend must be one of"):
        rt.closest_point(points[:2], structure, backend="embree")
    if jax.default_backend() != "gpu":
        with pytest.raises(ValueError, match="winding_number: backend='gpu' cannot run: the default JAX backend"):
            rt.winding_number(points[:2], structure, backend="gpu")


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale_exp=st.integers(-3, 3), offset_exp=st.integers(-2, 3))
def test_compiled_walk_on_random_soups(seed, scale_exp, offset_exp):
    """Random soups (100 triangles, some tiny or degenerate) at random scales and offsets: the CPU walk against
    the float64 brute force, and the same primitive as the portable walk except at ties."""
    if not _available("cpu"):
        pytest.skip("no cpu walk here")
    rng = np.random.default_rng(seed)
    scale, offset = 10.0**scale_exp, rng.normal(size=3) * 10.0**offset_exp
    centers = rng.uniform(-1, 1, (100, 1, 3))
    sizes = 10.0 ** rng.uniform(-3, 0, (100, 1, 1))
    triangles = centers + sizes * rng.normal(size=(100, 3, 3))
    triangles[:5, 2] = triangles[:5, 0]  # degenerate
    triangles = (triangles * scale + offset).astype(np.float32)
    points = (rng.uniform(-1.5, 1.5, (64, 3)) * scale + offset).astype(np.float32)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    compiled = rt.closest_point(points, structure, backend="cpu")
    extent = np.abs(points).max() + np.abs(triangles).max()
    assert_closest(compiled, points, triangles, atol=3e-6 * extent)
    portable = rt.closest_point(points, structure, backend="portable")
    every = brute_closest(points, triangles)[2]
    a, b = np.asarray(portable.primitive_id), np.asarray(compiled.primitive_id)
    rows = np.arange(len(points))
    assert ((a == b) | (np.abs(every[rows, a] - every[rows, b]) <= 3e-6 * extent)).all()
    reference = brute_winding(points, triangles)
    np.testing.assert_allclose(np.asarray(rt.winding_number(points, structure, exact=True, backend="cpu")), reference, atol=2e-4)  # fmt: skip


@pytest.mark.parametrize("backend", BACKENDS)
def test_sdf_grid_equals_signed_distance_at_the_grid_points(sphere, backend, monkeypatch):
    from jaxrt._src import sdf_grid

    _, structure, _ = sphere
    monkeypatch.setattr(sdf_grid, "STEP_POINTS", 100)  # several steps, the last one padded
    bounds = np.array([[-1.5, -1.2, -1.0], [1.5, 1.3, 1.1]])
    grid = np.asarray(rt.sdf_grid(structure, bounds, (7, 5, 4), backend=backend))
    axes = [np.linspace(bounds[0, a], bounds[1, a], r) for a, r in enumerate((7, 5, 4))]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).astype(np.float32)
    np.testing.assert_array_equal(grid, np.asarray(rt.signed_distance(points, structure, backend=backend)))
    assert (grid[3, 2, 2] < 0) and (grid[0, 0, 0] > 0)
    with pytest.raises(ValueError, match="sdf_grid: resolution must be"):
        rt.sdf_grid(structure, bounds, 1)
    with pytest.raises(ValueError, match="sdf_grid: bounds must be"):
        rt.sdf_grid(structure, bounds[::-1], 4)


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_compiled_walk_on_random_boxes_and_triangles(seed):
    """Random solid boxes and triangles in one structure: the CPU walk's distance against the float64 minimum
    over every box (0 inside) and every triangle, and its winding number against boxes' 1 inside plus the
    triangles' solid angles."""
    if not _available("cpu"):
        pytest.skip("no cpu walk here")
    rng = np.random.default_rng(seed)
    lower = rng.uniform(-1, 1, (12, 3)).astype(np.float32)
    upper = (lower + rng.uniform(0.01, 0.5, (12, 3))).astype(np.float32)
    triangles = (rng.uniform(-1, 1, (20, 1, 3)) + 0.3 * rng.normal(size=(20, 3, 3))).astype(np.float32)
    geometries = [rt.BoundingBoxGeometry(lower, upper), rt.TriangleGeometry(triangles.reshape(-1, 3))]
    structure = rt.build_primitive_structure(geometries)
    points = rng.uniform(-1.5, 1.5, (96, 3)).astype(np.float32)
    result = rt.closest_point(points, structure, backend="cpu")
    p = points.astype(np.float64)[:, None]
    gap = np.maximum(np.maximum(lower[None] - p, p - upper[None]), 0)
    box_distance = np.linalg.norm(gap, axis=-1)  # (n, boxes)
    reference = np.minimum(box_distance.min(axis=1), brute_closest(points, triangles)[0])
    np.testing.assert_allclose(np.asarray(result.distance), reference, atol=1e-5)
    portable = rt.closest_point(points, structure, backend="portable")
    np.testing.assert_allclose(np.asarray(result.distance), np.asarray(portable.distance), atol=1e-6)
    inside = np.all((p >= lower[None]) & (p <= upper[None]), axis=-1).sum(axis=1)
    winding = inside + brute_winding(points, triangles)
    np.testing.assert_allclose(np.asarray(rt.winding_number(points, structure, exact=True, backend="cpu")), winding, atol=1e-4)  # fmt: skip
