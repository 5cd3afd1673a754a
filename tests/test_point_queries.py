"""Closest point, winding number, inside test and signed distance against float64 brute force in NumPy."""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

import jaxrt as rt
from jaxrt.bench.scenes import noisy_sphere

# --- float64 references (NumPy, every triangle; independent of the library's region logic) ---------------


def _segment_closest(p, a, b):
    """Closest points on segments ``a b`` to points ``p`` (broadcast), float64."""
    ab = b - a
    den = np.sum(ab * ab, axis=-1)
    t = np.where(den > 0, np.sum((p - a) * ab, axis=-1) / np.where(den > 0, den, 1), 0)
    return a + np.clip(t, 0, 1)[..., None] * ab


def has_area(triangles):
    """Triangles whose float32 edge vectors have a non-zero cross product (the others the builder leaves out:
    a ray can never hit them, and neither does a point query find them)."""
    t = np.asarray(triangles, np.float32)
    e1, e2 = (t[:, 1] - t[:, 0]).astype(np.float64), (t[:, 2] - t[:, 0]).astype(np.float64)
    return (np.cross(e1, e2) != 0).any(axis=-1)


def brute_closest(points, triangles):
    """``(distance (n,), index (n,), all distances (n, T))``: the face projection where it falls inside the
    triangle, else the nearest of the three edges; zero-area triangles are absent (``inf``)."""
    p = np.asarray(points, np.float64)[:, None, :]
    tri = np.asarray(triangles, np.float64)[None]
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    n = np.cross(b - a, c - a)
    nn = np.sum(n * n, axis=-1)
    safe = np.where(nn > 0, nn, 1)
    proj = p - (np.sum((p - a) * n, axis=-1) / safe)[..., None] * n
    inside = np.broadcast_to(nn > 0, proj.shape[:-1]).copy()
    for e0, e1 in ((a, b), (b, c), (c, a)):
        inside &= np.sum(np.cross(e1 - e0, proj - e0) * n, axis=-1) >= 0
    best = np.where(inside, np.linalg.norm(p - proj, axis=-1), np.inf)
    for e0, e1 in ((a, b), (b, c), (c, a)):
        best = np.minimum(best, np.linalg.norm(p - _segment_closest(p, e0, e1), axis=-1))
    best = np.where(has_area(triangles)[None], best, np.inf)
    return best.min(axis=1), best.argmin(axis=1), best


def brute_winding(points, triangles):
    """Exact generalized winding numbers (solid angles summed over every triangle), float64."""
    p = np.asarray(points, np.float64)[:, None, None, :]
    v = np.asarray(triangles, np.float64)[None] - p
    a, b, c = v[..., 0, :], v[..., 1, :], v[..., 2, :]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.sum(a * np.cross(b, c), axis=-1)
    den = la * lb * lc + np.sum(a * b, -1) * lc + np.sum(a * c, -1) * lb + np.sum(b * c, -1) * la
    return np.sum(2 * np.arctan2(det, den), axis=1) / (4 * np.pi)


# --- scenes ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sphere():
    """A closed noisy sphere of about 2,000 counterclockwise-outward triangles, its structure and points."""
    scene = noisy_sphere(2_000, seed=3, noise=0.05)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(scene.vertices, scene.indices))
    rng = np.random.default_rng(7)
    directions = rng.normal(size=(512, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    near = directions * rng.uniform(0.8, 1.2, (512, 1))
    box = rng.uniform(-1.6, 1.6, (384, 3))
    far = rng.normal(size=(128, 3)) * 20
    points = np.concatenate([near, box, far]).astype(np.float32)
    return scene, structure, points


def _triangles(scene):
    return scene.vertices[scene.indices]


def _radius(scene):
    return float(np.abs(scene.vertices).max())


def assert_closest(result, points, triangles, *, atol):
    """Distances within ``atol`` of the reference; the primitive is a nearest one (ties allowed); the point
    lies on that primitive at the reported barycentrics and distance."""
    ref, _, every = brute_closest(points, triangles)
    distance = np.asarray(result.distance, np.float64)
    np.testing.assert_allclose(distance, ref, rtol=0, atol=atol)
    prim = np.asarray(result.primitive_id)
    assert (prim >= 0).all()
    np.testing.assert_allclose(every[np.arange(len(prim)), prim], ref, rtol=0, atol=atol)
    tri = np.asarray(triangles, np.float64)[prim]
    uv = np.asarray(result.triangle_barycentric_coord, np.float64)
    assert (uv >= 0).all() and (uv.sum(-1) <= 1 + 1e-6).all()
    on = tri[:, 0] + uv[:, :1] * (tri[:, 1] - tri[:, 0]) + uv[:, 1:] * (tri[:, 2] - tri[:, 0])
    np.testing.assert_allclose(np.asarray(result.point), on, rtol=0, atol=atol)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(result.point, np.float64) - points, axis=-1), ref, atol=atol)


# --- closest point -----------------------------------------------------------------------------------------


def test_closest_point_matches_brute_force(sphere):
    scene, structure, points = sphere
    result = rt.closest_point(points, structure)
    assert isinstance(result, rt.ClosestPointResult)
    assert (np.asarray(result.geometry_id) == 0).all()
    # float32 inputs: a few ulps of the coordinates (|p| up to ~60).
    assert_closest(result, points, _triangles(scene), atol=2e-5 * (1 + np.abs(points).max()))
    # The exact nearest primitive wherever the runner-up is clearly farther (no tie).
    ref, index, every = brute_closest(points, _triangles(scene))
    second = np.partition(every, 1, axis=1)[:, 1]
    clear = second - ref > 1e-4
    assert clear.sum() > 100
    np.testing.assert_array_equal(np.asarray(result.primitive_id)[clear], index[clear])


def test_closest_point_max_distance_misses(sphere):
    scene, structure, points = sphere
    full = rt.closest_point(points, structure)
    limited = rt.closest_point(points, structure, max_distance=0.1)
    ref, _, _ = brute_closest(points, _triangles(scene))
    within = ref <= 0.1 - 1e-5
    beyond = ref > 0.1 + 1e-5
    assert within.sum() > 50 and beyond.sum() > 50
    np.testing.assert_array_equal(np.asarray(limited.primitive_id)[beyond], -1)
    np.testing.assert_array_equal(np.asarray(limited.geometry_id)[beyond], -1)
    assert np.isinf(np.asarray(limited.distance)[beyond]).all()
    assert np.isinf(np.asarray(limited.point)[beyond]).all()
    assert (np.asarray(limited.triangle_barycentric_coord)[beyond] == 0).all()
    np.testing.assert_allclose(np.asarray(limited.distance)[within], np.asarray(full.distance)[within], atol=1e-6)
    zero = rt.closest_point(points[:4], structure, max_distance=0.0)
    assert (np.asarray(zero.primitive_id) == -1).all()


def test_closest_point_degenerate_triangles_and_ties():
    """Slivers (near-collinear, nearly repeated vertices) and exact duplicates: finite values equal to the
    reference; zero-area triangles (collinear, repeated vertices, a point) are never found, as no ray hits
    them."""
    triangles = np.array(
        [
            [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
            [[0, 0, 0], [1, 0, 0], [0, 1, 0]],  # a duplicate: a tie everywhere
            [[2, 0, 0], [3, 0, 0], [4, 0, 0]],  # collinear
            [[2, 1, 0], [2, 1, 0], [3, 2, 0]],  # two equal vertices
            [[5, 5, 5], [5, 5, 5], [5, 5, 5]],  # a point
            [[0, 0, 3], [0, 2, 3], [0, 1, 3]],  # collinear, middle vertex last
            [[2, 0, 2], [3, 0, 2], [4, 1e-6, 2]],  # a sliver
            [[2, 1, 2], [2, 1 + 1e-6, 2], [3, 2, 2]],  # nearly equal vertices
            [[0, 3, 0], [1, 4, 1], [2, 5, 2.00001]],  # nearly collinear
        ],
        np.float32,
    )
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    points = np.random.default_rng(0).uniform(-1, 6, (200, 3)).astype(np.float32)
    result = rt.closest_point(points, structure)
    for field in result:
        assert np.isfinite(np.asarray(field)).all()
    assert_closest(result, points, triangles, atol=1e-5)
    assert set(np.asarray(result.primitive_id).tolist()) <= {0, 1, 6, 7, 8}
    assert {6, 7, 8} <= set(np.asarray(result.primitive_id).tolist())


def test_closest_point_batch_shapes_jit_vmap(sphere):
    _, structure, points = sphere
    flat = rt.closest_point(points[:24], structure)
    shaped = rt.closest_point(points[:24].reshape(2, 3, 4, 3), structure)
    assert shaped.distance.shape == (2, 3, 4) and shaped.point.shape == (2, 3, 4, 3)
    assert shaped.triangle_barycentric_coord.shape == (2, 3, 4, 2)
    np.testing.assert_array_equal(np.asarray(shaped.primitive_id).reshape(-1), np.asarray(flat.primitive_id))
    single = rt.closest_point(points[0], structure)
    assert single.distance.shape == () and single.point.shape == (3,)
    assert float(single.distance) == float(flat.distance[0])
    jitted = jax.jit(lambda p, s: rt.closest_point(p, s))(points[:24], structure)
    np.testing.assert_array_equal(np.asarray(jitted.distance), np.asarray(flat.distance))
    mapped = jax.vmap(lambda p: rt.closest_point(p, structure))(points[:24].reshape(4, 6, 3))
    np.testing.assert_array_equal(np.asarray(mapped.primitive_id).reshape(-1), np.asarray(flat.primitive_id))
    # The same primitive; its distance comes from a differently compiled program, which jax 0.12 may contract
    # into other multiply-adds: equal within a few float32 ulps.
    np.testing.assert_allclose(np.asarray(mapped.distance).reshape(-1), np.asarray(flat.distance), rtol=5e-7, atol=0)


def test_closest_point_gradients_match_finite_differences():
    """d distance / d point and / d vertices in float64 against central differences of the reference."""
    triangles = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 1], [1, 0.2, 1.5], [0, 1, 1.2]]])
    points = np.array([[0.2, 0.3, 0.4], [1.5, -0.5, 0.3], [-0.4, 0.4, 0.9], [0.3, 0.3, 1.6]])
    with jax.enable_x64(True):

        def total(vertices, p):
            s = rt.build_primitive_structure(rt.TriangleGeometry(vertices.reshape(-1, 3)))
            return jnp.sum(rt.closest_point(p, s).distance)

        vertices = jnp.asarray(triangles, jnp.float64)
        grad_v, grad_p = jax.grad(total, argnums=(0, 1))(vertices, jnp.asarray(points))
        grad_v, grad_p = np.asarray(grad_v), np.asarray(grad_p)
    h = 1e-6

    def reference(v, p):
        return brute_closest(p, v)[0].sum()

    for array, grad, other in ((points, grad_p, "p"), (triangles.astype(np.float64), grad_v, "v")):
        fd = np.zeros_like(array, np.float64)
        for index in np.ndindex(array.shape):
            plus, minus = array.astype(np.float64).copy(), array.astype(np.float64).copy()
            plus[index] += h
            minus[index] -= h
            if other == "p":
                fd[index] = (reference(triangles, plus) - reference(triangles, minus)) / (2 * h)
            else:
                fd[index] = (reference(plus, points) - reference(minus, points)) / (2 * h)
        np.testing.assert_allclose(grad, fd, atol=1e-6)
    assert np.abs(grad_v).sum() > 0.5


def test_closest_point_to_boxes():
    boxes = np.array([[[0, 0, 0], [1, 1, 1]], [[3, 0, 0], [4, 2, 1]]], np.float32)
    triangle = rt.TriangleGeometry([[0.0, 5, 0], [1, 5, 0], [0, 6, 0]])
    structure = rt.build_primitive_structure([rt.BoundingBoxGeometry(boxes[:, 0], boxes[:, 1]), triangle])
    points = np.array([[0.5, 0.5, 0.5], [1.8, 0.5, 0.5], [3.5, 3.0, 0.5], [0.2, 5.2, 1.0], [-1, -1, -1]], np.float32)
    r = rt.closest_point(points, structure)
    np.testing.assert_allclose(np.asarray(r.distance), [0.0, 0.8, 1.0, 1.0, math.sqrt(3)], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(r.geometry_id), [0, 0, 0, 1, 0])
    np.testing.assert_array_equal(np.asarray(r.primitive_id), [0, 0, 1, 0, 0])
    np.testing.assert_allclose(np.asarray(r.point)[1], [1.0, 0.5, 0.5], atol=1e-6)


@settings(max_examples=10)
@given(seed=st.integers(0, 2**31 - 1), scale_exp=st.integers(-3, 3), offset_exp=st.integers(-2, 3))
def test_closest_point_property_random_soups(seed, scale_exp, offset_exp):
    """Random soups (100 triangles, some tiny or degenerate) at random scales and offsets."""
    rng = np.random.default_rng(seed)
    scale, offset = 10.0**scale_exp, rng.normal(size=3) * 10.0**offset_exp
    centers = rng.uniform(-1, 1, (100, 1, 3))
    sizes = 10.0 ** rng.uniform(-3, 0, (100, 1, 1))
    triangles = centers + sizes * rng.normal(size=(100, 3, 3))
    triangles[:5, 2] = triangles[:5, 0]  # degenerate
    triangles = (triangles * scale + offset).astype(np.float32)
    points = (rng.uniform(-1.5, 1.5, (64, 3)) * scale + offset).astype(np.float32)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    result = rt.closest_point(points, structure)
    extent = np.abs(points).max() + np.abs(triangles).max()
    assert_closest(result, points, triangles, atol=3e-6 * extent)


def test_bad_input_errors(sphere):
    _, structure, points = sphere
    with pytest.raises(ValueError, match=r"closest_point: points must have shape \(\.\.\., 3\)"):
        rt.closest_point(np.zeros((4, 2)), structure)
    with pytest.raises(ValueError, match="closest_point: points must be finite"):
        rt.closest_point(np.array([[0, 0, 0], [np.nan, 0, 0]]), structure)
    with pytest.raises(ValueError, match="signed_distance: points must be finite"):
        rt.signed_distance(np.array([[np.inf, 0, 0]]), structure)
    with pytest.raises(TypeError, match="closest_point: points must be real"):
        rt.closest_point(np.zeros((2, 3), complex), structure)
    with pytest.raises(ValueError, match="max_distance must be non-negative"):
        rt.closest_point(points[:2], structure, max_distance=-1.0)
    with pytest.raises(TypeError, match="closest_point: structure must be"):
        rt.closest_point(points[:2], "mesh")
    with pytest.raises(ValueError, match="winding_number: beta"):
        rt.winding_number(points[:2], structure, beta=0.0)
    instances = rt.build_instance_structure([structure], rt.Instances([0], np.eye(3, 4, dtype=np.float32)[None]))
    with pytest.raises(NotImplementedError, match="closest_point: instance structures"):
        rt.closest_point(points[:2], instances)
    control = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], np.float32)
    curve = rt.CurveGeometry(
        control, np.full(4, 0.1, np.float32), np.array([0], np.int32), basis=rt.CurveBasis.BEZIER, control_point_count=4
    )
    with pytest.raises(NotImplementedError, match="contains: curve geometry"):
        rt.contains(points[:2], rt.build_primitive_structure(curve))
    # Inside jit nothing is checked and nothing crashes: a NaN point is a miss.
    r = jax.jit(lambda p: rt.closest_point(p, structure))(jnp.array([[jnp.nan, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    assert int(r.primitive_id[0]) == -1 and int(r.primitive_id[1]) >= 0


# --- winding numbers, inside tests, signed distance --------------------------------------------------------


def test_winding_number_exact_and_fast_match_reference(sphere):
    scene, structure, points = sphere
    reference = brute_winding(points, _triangles(scene))
    exact = np.asarray(rt.winding_number(points, structure, exact=True))
    np.testing.assert_allclose(exact, reference, atol=2e-4)
    fast = np.asarray(rt.winding_number(points, structure))
    # The approximation is close away from the surface; its sign (>= 1/2) agrees everywhere here.
    np.testing.assert_array_equal(fast >= 0.5, reference >= 0.5)
    assert np.abs(fast - reference).max() < 0.05
    assert ((reference > 0.99) & (reference < 1.01)).sum() > 100 and (np.abs(reference) < 0.01).sum() > 100
    np.testing.assert_array_equal(np.asarray(rt.contains(points, structure)), reference >= 0.5)


def test_signed_distance_and_small_holes(sphere):
    scene, structure, points = sphere
    ref, _, _ = brute_closest(points, _triangles(scene))
    inside = brute_winding(points, _triangles(scene)) >= 0.5
    sd = np.asarray(rt.signed_distance(points, structure))
    np.testing.assert_allclose(sd, np.where(inside, -ref, ref), atol=2e-5 * (1 + np.abs(points).max()))
    # Three triangles removed: the winding number still tells inside from outside away from the holes.
    holed = rt.build_primitive_structure(rt.TriangleGeometry(scene.vertices, scene.indices[3:]))
    probe = np.array([[0.0, 0, 0], [0.3, -0.2, 0.1], [2.0, 0, 0], [0, 0, -3]], np.float32)
    np.testing.assert_array_equal(np.asarray(rt.contains(probe, holed)), [True, True, False, False])
    # Gradient of the signed distance: the outward unit normal direction outside, inward inside.
    g = jax.grad(lambda p: jnp.sum(rt.signed_distance(p, structure)))(jnp.asarray(points[:64]))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(g), axis=1), 1.0, atol=1e-4)


def test_winding_number_of_boxes_and_inward_meshes(sphere):
    scene, _, _ = sphere
    inverted = rt.build_primitive_structure(rt.TriangleGeometry(scene.vertices, scene.indices[:, ::-1]))
    probe = np.array([[0.0, 0, 0], [3, 0, 0]])
    np.testing.assert_allclose(np.asarray(rt.winding_number(probe, inverted, exact=True)), [-1, 0], atol=1e-4)
    np.testing.assert_allclose(np.asarray(rt.winding_number(probe, inverted)), [-1, 0], atol=0.05)
    boxes = rt.build_primitive_structure(rt.BoundingBoxGeometry([[0.0, 0, 0]], [[1.0, 1, 1]]))
    probe = np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]], np.float32)
    np.testing.assert_array_equal(np.asarray(rt.contains(probe, boxes)), [True, False])
    np.testing.assert_allclose(np.asarray(rt.signed_distance(probe, boxes)), [0.0, 0.5], atol=1e-6)


# --- shared meshes -----------------------------------------------------------------------------------------


def _data_dir() -> Path | None:
    from jaxrt.bench.scenes import default_data_dir

    return default_data_dir()


@pytest.mark.slow
@pytest.mark.parametrize("name", ["bunny", "dragon", "sponza"])
def test_shared_mesh_against_brute_force(name):
    from jaxrt.bench.scenes import SHARED_MESHES, shared_mesh

    folder = _data_dir()
    if folder is None or not (Path(folder) / SHARED_MESHES[name][0]).exists():
        pytest.skip(f"{name} mesh absent (set JAXRT_DATA_DIR; looked in {folder or os.environ.get('JAXRT_DATA_DIR')})")
    scene = shared_mesh(name, folder)
    structure = rt.build_primitive_structure(rt.TriangleGeometry(scene.vertices, scene.indices))
    rng = np.random.default_rng(1)
    lo, hi = scene.vertices.min(0), scene.vertices.max(0)
    points = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (64, 3)).astype(np.float32)
    triangles = _triangles(scene)
    result = rt.closest_point(points, structure)
    assert_closest(result, points, triangles, atol=2e-5 * float(np.abs(points).max()))
    exact = np.asarray(rt.winding_number(points, structure, exact=True))
    np.testing.assert_array_equal(np.asarray(rt.contains(points, structure)), exact >= 0.5)


def test_points_bench_quick_row():
    """The bench row runs and its errors against the float64 brute force are nil on a small sphere (sizes
    that share the compiled programs of the tests above)."""
    from jaxrt.bench import points

    args = ["--quick", "--scenes", "sphere", "--triangles", "2000", "--points", "1024", "--reference-points", "128"]
    row = points.main(args)["scenes"][0]
    assert row["triangles"] > 1900 and row["points"] == 1024 and row["reference_points"] == 128
    assert row["wrong_primitive"] == 0 and row["sign_disagree_fast"] == 0 and row["sign_disagree_exact"] == 0
    assert row["max_distance_error_rel"] < 1e-6
    assert row["closest_point"]["mpoints_s"] > 0 and row["signed_distance"]["mpoints_s"] > 0


# --- open surfaces -------------------------------------------------------------------------------------------


QUAD = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
QUAD_FACES = np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def test_is_closed_counts_boundary_edges(sphere):
    scene, structure, _ = sphere
    closed = rt.TriangleGeometry(scene.vertices, scene.indices)
    assert rt.is_closed(closed) and rt.is_closed(structure) and rt.boundary_edge_count(structure) == 0
    quad = rt.TriangleGeometry(QUAD, QUAD_FACES)
    assert not rt.is_closed(quad) and rt.boundary_edge_count(quad) == 4
    assert rt.boundary_edge_count(rt.build_primitive_structure(quad)) == 4  # welded by position, as by index
    holed = rt.TriangleGeometry(scene.vertices, scene.indices[1:])
    assert rt.boundary_edge_count(holed) == 3
    flipped = scene.indices.copy()
    flipped[0] = flipped[0, ::-1]  # one triangle wound against its neighbours: its 3 edges in both directions
    assert rt.boundary_edge_count(rt.TriangleGeometry(scene.vertices, flipped)) == 6
    assert rt.is_closed(rt.BoundingBoxGeometry([[0.0, 0, 0]], [[1.0, 1, 1]]))
    with pytest.raises(TypeError, match="is_closed: expected a TriangleGeometry"):
        rt.is_closed(QUAD)


def test_open_surface_signed_distance_is_positive_on_both_sides_and_warns_once():
    structure = rt.build_primitive_structure(rt.TriangleGeometry(QUAD, QUAD_FACES))
    probe = np.array([[0.5, 0.5, 0.1], [0.5, 0.5, -0.1]], np.float32)
    with pytest.warns(UserWarning, match=r"signed_distance: .* open surface \(4 boundary edges, rt\.is_closed"):
        distance = np.asarray(rt.signed_distance(probe, structure))
    np.testing.assert_allclose(distance, [0.1, 0.1], rtol=1e-6)  # the documented behaviour: no inside
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per structure
        rt.signed_distance(probe, structure)
    with pytest.warns(UserWarning, match="contains: .* open surface"):
        assert not np.asarray(rt.contains(probe, structure)).any()


def test_closed_surface_does_not_warn(sphere):
    _, structure, points = sphere
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rt.contains(points[:8], structure)
