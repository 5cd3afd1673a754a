"""Indices out of range that only a traced build sees (inside ``jax.jit``, without ``checks=True``): the
primitive they name does not exist, so rays miss it on every path. A plain gather would clamp or wrap the
index to a real vertex and make a triangle, curve or instance that rays hit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt

# Two triangles over the unit square: 0 = [0, 1, 2] (lower left), 1 = [1, 3, 2] (upper right). Index 7 clamps
# to 3 and -1 wraps to 3, so the bad rows below would rebuild triangle 1 exactly.
SQUARE = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
GOOD = np.array([[0, 1, 2], [1, 3, 2]], np.int32)
BAD_ROWS = [[1, 7, 2], [1, -1, 2], [-4, 3, 2], [1, 3, 2**31 - 1]]
# down the z axis onto triangle 0, triangle 1, and the origin (where a zeroed triangle would sit)
RAYS = rt.Ray(
    jnp.array([[0.2, 0.2, 1.0], [0.7, 0.7, 1.0], [0.0, 0.0, 1.0]], jnp.float32),
    jnp.array([[0.0, 0.0, -1.0]] * 3, jnp.float32),
)


#: The compiled traversal of this machine: the Numba loop on the CPU, the Triton kernel on a GPU.
COMPILED = "cpu" if jax.default_backend() == "cpu" else "gpu"


def _intersector(*tags, backend: str) -> rt.Intersector:
    if backend != "portable":
        try:
            rt.Intersector(backend=backend).intersect(
                RAYS, rt.build_primitive_structure(rt.TriangleGeometry(SQUARE, GOOD))
            )
        except ValueError as error:  # the compiled traversal cannot run here (a GPU machine without Triton)
            pytest.skip(str(error))
    return rt.Intersector(*tags, backend=backend)


def _with_second(row) -> np.ndarray:
    return np.array([GOOD[0], row], np.int32)


@pytest.fixture(scope="module", params=["portable", COMPILED])
def trace_triangles(request):
    intersector = _intersector(rt.tags.primitive_data, backend=request.param)

    @jax.jit
    def trace(indices):
        geometry = rt.TriangleGeometry(SQUARE, indices, primitive_data=jnp.array([10.0, 11.0]))
        hits = intersector.intersect(RAYS, rt.build_primitive_structure(geometry))
        return hits.distance, hits.primitive_id, hits.primitive_data

    return trace


def test_valid_indices_hit(trace_triangles):
    distance, primitive, data = trace_triangles(GOOD)
    np.testing.assert_array_equal(distance, [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(primitive, [0, 1, 0])
    np.testing.assert_array_equal(data, [10.0, 11.0, 10.0])


@pytest.mark.parametrize("row", BAD_ROWS)
def test_triangle_with_an_index_out_of_range_is_missed(trace_triangles, row):
    distance, primitive, data = trace_triangles(_with_second(row))
    np.testing.assert_array_equal(distance, [1.0, np.inf, 1.0])
    np.testing.assert_array_equal(primitive, [0, -1, 0])
    np.testing.assert_array_equal(data, [10.0, 0.0, 10.0])


def test_refit_with_an_index_out_of_range_is_missed():
    structure = rt.build_primitive_structure(rt.TriangleGeometry(SQUARE, GOOD))
    intersector = rt.Intersector(backend="portable")
    trace = jax.jit(lambda i: intersector.intersect(RAYS, rt.refit(structure, rt.TriangleGeometry(SQUARE, i))).distance)
    np.testing.assert_array_equal(trace(_with_second([1, 7, 2])), [1.0, np.inf, 1.0])


def test_gradients_stay_finite_next_to_a_bad_triangle():
    intersector = rt.Intersector(backend="portable")

    def total(vertices, indices):
        hits = intersector.intersect(RAYS, rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices)))
        return jnp.sum(jnp.where(jnp.isfinite(hits.distance), hits.distance, 0.0))

    gradient = jax.jit(jax.grad(total))(jnp.asarray(SQUARE), _with_second([1, -1, 2]))
    assert np.all(np.isfinite(gradient))
    assert np.any(gradient != 0)


def test_motion_triangle_with_an_index_out_of_range_is_missed():
    spec = rt.MotionSpec(0.0, 1.0)
    keys = jnp.stack([jnp.asarray(SQUARE), jnp.asarray(SQUARE) + jnp.array([0.0, 0.0, 0.5])])
    intersector = rt.Intersector(rt.tags.primitive_motion, backend="portable")

    @jax.jit
    def trace(indices):
        return intersector.intersect(
            RAYS, rt.build_primitive_structure(rt.MotionTriangleGeometry(keys, indices), motion=spec)
        ).distance

    np.testing.assert_array_equal(trace(GOOD), [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(trace(_with_second([1, 7, 2])), [1.0, np.inf, 1.0])


def test_curve_segment_past_the_control_points_is_missed():
    # linear segments along x at y = 0 and y = 0.5; index -1 would wrap into a diagonal from (1, .5) to (-1, 0)
    points = jnp.array([[-1.0, 0, 0], [1, 0, 0], [-1, 0.5, 0], [1, 0.5, 0]])
    radii = jnp.full((4,), 0.1)
    rays = rt.Ray(jnp.array([[0.0, 0.25, 1.0], [0, 0, 1], [0, 0.5, 1]]), jnp.array([[0.0, 0, -1]] * 3))
    intersector = rt.Intersector(rt.tags.curve_data, backend="portable")

    @jax.jit
    def trace(first):
        geometry = rt.CurveGeometry(points, radii, first, basis=rt.CurveBasis.LINEAR, control_point_count=2)
        return intersector.intersect(rays, rt.build_primitive_structure(geometry)).distance

    np.testing.assert_allclose(trace(jnp.array([0, 2])), [np.inf, 0.9, 0.9], rtol=1e-6)
    np.testing.assert_allclose(trace(jnp.array([-1, 2])), [np.inf, np.inf, 0.9], rtol=1e-6)
    np.testing.assert_allclose(trace(jnp.array([0, 3])), [np.inf, 0.9, np.inf], rtol=1e-6)


@pytest.mark.parametrize("backend", ["portable", COMPILED])
def test_instance_of_a_structure_out_of_range_is_missed(backend):
    blas = rt.build_primitive_structure(rt.TriangleGeometry(SQUARE, GOOD))
    transform = np.eye(3, 4, dtype=np.float32)[None]
    intersector = _intersector(rt.tags.instancing, backend=backend)

    @jax.jit
    def trace(index):
        return intersector.intersect(RAYS, rt.build_instance_structure([blas], rt.Instances(index, transform))).distance

    np.testing.assert_array_equal(trace(jnp.array([0])), [1.0, 1.0, 1.0])
    np.testing.assert_array_equal(trace(jnp.array([1])), [np.inf] * 3)
    np.testing.assert_array_equal(trace(jnp.array([-1])), [np.inf] * 3)


def test_shading_helpers_read_no_substituted_vertex():
    primitive = jnp.array([0, 1, 1])
    geometry_id = jnp.array([0, 0, 1])
    other = jnp.asarray(SQUARE) + jnp.array([0.0, 0.0, 1.0])
    uv = jnp.full((3, 2), 0.25)

    @jax.jit
    def shade(indices):
        normals = rt.shading.triangle_normals([SQUARE, other], [indices, GOOD], primitive, geometry_id)
        values = rt.shading.interpolate([SQUARE[:, 0], other[:, 0]], [indices, GOOD], primitive, uv, geometry_id)
        return normals, values, rt.shading.vertex_normals(SQUARE, indices)

    normals, values, smooth = shade(GOOD)
    np.testing.assert_allclose(normals, [[0, 0, 1]] * 3, atol=1e-6)
    np.testing.assert_allclose(values, [0.25, 0.75, 0.75], atol=1e-6)
    np.testing.assert_allclose(smooth, [[0, 0, 1]] * 4, atol=1e-6)
    # geometry 0's triangle 1 names vertex 4, which exists only in the concatenation with geometry 1
    for row in ([1, 4, 2], [1, -1, 2]):
        normals, values, smooth = shade(_with_second(row))
        np.testing.assert_allclose(normals, [[0, 0, 1], [0, 0, 0], [0, 0, 1]], atol=1e-6)
        np.testing.assert_allclose(values, [0.25, 0.0, 0.75], atol=1e-6)
        np.testing.assert_allclose(smooth[:3], [[0, 0, 1]] * 3, atol=1e-6)
        np.testing.assert_array_equal(smooth[3], [0, 0, 0])  # used by the bad triangle only
