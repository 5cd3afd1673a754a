"""Bad inputs raise the named error, with a message that names the argument and the offending value."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt

TRI = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
QUAD = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
FACES = np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def _with(array, index, value):
    array = np.array(array)
    array[index] = value
    return array


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(vertices=QUAD[:, :2]), ValueError, r"vertices must have shape \(V, 3\), got \(4, 2\)"),
        (dict(vertices=QUAD.ravel()), ValueError, r"vertices must have shape \(V, 3\), got \(12,\)"),
        (dict(vertices=QUAD[None]), ValueError, r"vertices must have shape \(V, 3\), got \(1, 4, 3\)"),
        (dict(vertices=np.zeros((0, 3), np.float32)), ValueError, r"vertices is empty \(shape \(0, 3\)\)"),
        (dict(vertices=QUAD.astype(np.int32)), TypeError, "vertices must be float32 or float64, got dtype int32"),
        (dict(vertices=QUAD.astype(np.float16)), TypeError, "vertices must be float32 or float64, got dtype float16"),
        (dict(vertices=QUAD.astype(bool)), TypeError, "vertices .* got dtype bool"),
        (dict(vertices=_with(QUAD, (2, 1), np.nan)), ValueError, r"vertices has a non-finite value nan at index \(2, 1\)"),
        (dict(vertices=_with(QUAD, (3, 0), -np.inf)), ValueError, r"vertices has a non-finite value -inf at index \(3, 0\)"),
        (dict(vertices=QUAD), ValueError, "without indices the vertex count must be a multiple of 3, got 4"),
        (dict(vertices=QUAD, indices=FACES.astype(np.float32)), TypeError, "indices must have an integer dtype, got float32"),
        (dict(vertices=QUAD, indices=FACES[:, :2]), ValueError, r"indices must have shape \(T, 3\), got \(2, 2\)"),
        (dict(vertices=QUAD, indices=FACES.ravel()), ValueError, r"indices must have shape \(T, 3\), got \(6,\)"),
        (dict(vertices=QUAD, indices=np.zeros((0, 3), np.int32)), ValueError, r"indices is empty \(shape \(0, 3\)\)"),
        (dict(vertices=QUAD, indices=_with(FACES, (1, 2), 4)), ValueError, r"indices\[1, 2\] = 4 is out of range for 4 vertices"),
        (dict(vertices=QUAD, indices=_with(FACES, (0, 1), -1)), ValueError, r"indices\[0, 1\] = -1 is out of range"),
        (
            dict(vertices=QUAD, indices=FACES, primitive_data={"albedo": np.ones(3)}),
            ValueError,
            r"primitive_data leaf \['albedo'\] has shape \(3,\); its leading dimension must equal the primitive count 2",
        ),
        (
            dict(vertices=QUAD, indices=FACES, primitive_data=np.float32(1.0)),
            ValueError,
            r"primitive_data leaf .* has shape \(\)",
        ),
    ],
)  # fmt: skip
def test_triangle_geometry_rejects(kwargs, error, match):
    with pytest.raises(error, match=f"TriangleGeometry: {match}"):
        rt.TriangleGeometry(**kwargs)


def test_triangle_geometry_accepts_valid_inputs():
    geometry = rt.TriangleGeometry(QUAD.astype(np.float64), FACES.astype(np.int64), primitive_data={"id": np.arange(2)})
    assert geometry.primitive_count == 2
    assert geometry.vertices.dtype == jnp.float32 and geometry.indices.dtype == jnp.int32
    assert rt.TriangleGeometry(TRI.tolist()).primitive_count == 1  # nested lists of Python floats


def test_float64_vertices_are_kept_under_x64():
    with jax.enable_x64(True):
        assert rt.TriangleGeometry(TRI.astype(np.float64)).vertices.dtype == jnp.float64


def test_traced_geometry_checks_shapes_and_dtypes():
    with pytest.raises(TypeError, match="TriangleGeometry: indices must have an integer dtype"):
        jax.jit(lambda v, i: rt.TriangleGeometry(v, i).vertices)(QUAD, FACES.astype(np.float32))
    with pytest.raises(ValueError, match=r"TriangleGeometry: vertices must have shape \(V, 3\), got \(4, 2\)"):
        jax.jit(lambda v: rt.TriangleGeometry(v).vertices)(QUAD[:, :2])


@pytest.mark.parametrize(
    "geometries, kwargs, error, match",
    [
        ([], {}, ValueError, "geometries is empty"),
        ("triangles", {}, TypeError, "geometries must be a geometry or a sequence of them, got str"),
        (TRI, {}, TypeError, "geometries must be a geometry or a sequence of them, got ndarray"),
        ([rt.TriangleGeometry(TRI), "x"], {}, TypeError, r"geometries\[1\] is a str"),
        (rt.TriangleGeometry(QUAD, FACES), {"capacity": 1}, ValueError, "capacity=1 is below the primitive count 2"),
    ],
)
def test_build_rejects(geometries, kwargs, error, match):
    with pytest.raises(error, match=f"build_primitive_structure: {match}"):
        rt.build_primitive_structure(geometries, **kwargs)


@pytest.mark.parametrize(
    "args, kwargs, match",
    [
        (("triangle_data",), {}, "unknown tag 'triangle_data'"),
        ((rt.tags.Tag("bogus"),), {}, r"unknown tag Tag\(name='bogus'"),
        ((), {"triangle_cull_mode": "sideways"}, "triangle_cull_mode must be one of .*, got 'sideways'"),
        ((), {"triangle_cull_mode": None}, "triangle_cull_mode must be one of .*, got None"),
        ((), {"front_facing_winding": "cw"}, "front_facing_winding must be one of .*, got 'cw'"),
        ((), {"backend": "tpu"}, "backend must be one of .*, got 'tpu'"),
        ((), {"accept_any_intersection": 1}, "accept_any_intersection must be a bool, got 1"),
    ],
)
def test_intersector_rejects_bad_tags_and_options(args, kwargs, match):
    with pytest.raises(ValueError, match=f"Intersector: {match}"):
        rt.Intersector(*args, **kwargs)


def test_intersector_options_are_static_and_hashable():
    a = rt.Intersector(rt.tags.stats, rt.tags.triangle_data, triangle_cull_mode="back")
    b = rt.Intersector(rt.tags.triangle_data, rt.tags.stats, triangle_cull_mode="back")
    assert a == b and hash(a) == hash(b)
    assert a != rt.Intersector(rt.tags.triangle_data, rt.tags.stats)


@pytest.mark.parametrize("n", [0, -1, 1.5, True])
def test_max_levels_rejects(n):
    with pytest.raises(ValueError, match=f"tags.max_levels: n must be a positive int, got {n!r}"):
        rt.tags.max_levels(n)


def test_intersect_rejects_non_ray_and_non_structure():
    structure = rt.build_primitive_structure(rt.TriangleGeometry(TRI))
    intersector = rt.Intersector()
    with pytest.raises(TypeError, match="Intersector.intersect: rays must be a jaxrt.Ray, got tuple"):
        intersector.intersect((np.zeros(3), np.ones(3)), structure)
    with pytest.raises(TypeError, match="Intersector.intersect: structure must be an acceleration structure, got"):
        intersector.intersect(rt.Ray([0.0, 0, 0], [0.0, 0, 1]), rt.TriangleGeometry(TRI))


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(origin=[0.0, 0.0], direction=[0.0, 0, 1]), ValueError, r"origin must have shape \(\.\.\., 3\), got \(2,\)"),
        (dict(origin=0.0, direction=[0.0, 0, 1]), ValueError, r"origin must have shape \(\.\.\., 3\), got \(\)"),
        (dict(origin=[0.0, 0, 0], direction=np.zeros((4, 2))), ValueError, r"direction must have shape \(\.\.\., 3\), got \(4, 2\)"),
        (
            dict(origin=np.zeros((2, 3)), direction=np.ones((3, 3))),
            ValueError,
            r"origin \(2, 3\) and direction \(3, 3\) batch shapes do not broadcast",
        ),
        (dict(origin=["a", "b", "c"], direction=[0.0, 0, 1]), TypeError, "origin must be a float array, got dtype <U1"),
        (dict(origin=[0.0, 0, 0], direction=[True, False, True]), TypeError, "direction must be a float array, got dtype bool"),
        (
            dict(origin=np.zeros((3, 3)), direction=np.ones((3, 3)), min_distance=np.zeros(2)),
            ValueError,
            r"min_distance of shape \(2,\) does not broadcast to \(3,\)",
        ),
        (
            dict(origin=np.zeros((3, 3)), direction=np.ones((3, 3)), max_distance=np.ones((3, 3))),
            ValueError,
            r"max_distance of shape \(3, 3\) does not broadcast to \(3,\)",
        ),
        (dict(origin=[0.0, 0, 0], direction=[0.0, 0, 1], mask=-1), ValueError, r"mask values must be in \[0, 2\*\*32\), got -1"),
        (dict(origin=[0.0, 0, 0], direction=[0.0, 0, 1], mask=2**32), ValueError, r"mask values must be in \[0, 2\*\*32\)"),
        (dict(origin=[0.0, 0, 0], direction=[0.0, 0, 1], mask=1.0), TypeError, "mask must be an integer array, got dtype float"),
    ],
)  # fmt: skip
def test_ray_rejects(kwargs, error, match):
    with pytest.raises(error, match=f"Ray: {match}"):
        rt.Ray(**kwargs)


def test_refit_rejects_a_non_geometry():
    structure = rt.build_primitive_structure(rt.TriangleGeometry(TRI))
    with pytest.raises(TypeError, match="geometries must be a geometry or a sequence of them, got int"):
        rt.refit(structure, 3)
