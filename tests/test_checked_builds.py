"""``checks=True`` builds: inside ``jax.jit`` each kind of bad input raises an error naming the function, the
argument, the element and the value, where an unchecked build makes rays miss silently."""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrt as rt

QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
QUAD_INDICES = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
IDENTITY = np.tile(np.eye(3, 4, dtype=np.float32), (3, 1, 1))


def raises_check(pattern: str):
    """Inside ``jit`` the host error reaches the caller as a ``JaxRuntimeError`` carrying its message."""
    return pytest.raises(jax.errors.JaxRuntimeError, match=r"(?s)BuildCheckError: .*" + pattern)


def build_triangles(vertices, indices, checks=True):
    structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, indices), checks=checks)
    return jax.block_until_ready(structure)


def build_curves(points, radii, indices):
    geometry = rt.CurveGeometry(points, radii, indices, basis="linear", control_point_count=2)
    return jax.block_until_ready(rt.build_primitive_structure(geometry, checks=True))


def build_boxes(lower, upper):
    return jax.block_until_ready(rt.build_primitive_structure(rt.BoundingBoxGeometry(lower, upper), checks=True))


@pytest.fixture(scope="module")
def blas():
    return rt.build_primitive_structure(rt.TriangleGeometry(QUAD, QUAD_INDICES))


def build_instances(blas, transform, index, count=None):
    instances = rt.Instances(index, transform)
    return jax.block_until_ready(rt.build_instance_structure([blas], instances, count=count, checks=True))


def test_valid_inputs_pass_and_build_the_same_structure():
    checked = jax.jit(build_triangles)(QUAD, QUAD_INDICES)
    plain = jax.jit(lambda v, i: build_triangles(v, i, checks=False))(QUAD, QUAD_INDICES)
    for a, b in zip(jax.tree.leaves(checked), jax.tree.leaves(plain), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_checks_are_off_by_default():
    bad = QUAD.copy()
    bad[1, 0] = np.nan
    jax.jit(lambda v, i: build_triangles(v, i, checks=False))(bad, QUAD_INDICES)  # no error: rays may miss


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_non_finite_vertex(value):
    bad = QUAD.copy()
    bad[2, 1] = value
    name = re.escape("build_primitive_structure: geometries[0] (TriangleGeometry) vertices[2] = [")
    with raises_check(name + rf" *1\., *{value}, *0\.\] is not finite"):
        jax.jit(build_triangles)(bad, QUAD_INDICES)


def test_triangle_index_out_of_range():
    bad = QUAD_INDICES.copy()
    bad[1, 2] = 7
    with raises_check(r"geometries\[0\] \(TriangleGeometry\) indices\[1\] = \[0, 2, 7\] is out of range for 4"):
        jax.jit(build_triangles)(QUAD, bad)


def test_curve_control_point_radius_and_index():
    points = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], np.float32)
    radii = np.full(3, 0.1, np.float32)
    indices = np.array([0, 1], np.int32)
    nan_point = points.copy()
    nan_point[1, 2] = np.nan
    with raises_check(r"geometries\[0\] \(CurveGeometry\) control_points\[1\] = .*nan.* is not finite"):
        jax.jit(build_curves)(nan_point, radii, indices)
    negative = radii.copy()
    negative[2] = -0.5
    with raises_check(r"\(CurveGeometry\) radii\[2\] = -0\.5 is negative or not finite"):
        jax.jit(build_curves)(points, negative, indices)
    with raises_check(r"\(CurveGeometry\) indices\[1\] = 2: the segment's 2 control points run past the 3"):
        jax.jit(build_curves)(points, radii, np.array([0, 2], np.int32))


def test_bounding_boxes_non_finite_and_inverted():
    lower = np.zeros((2, 3), np.float32)
    upper = np.ones((2, 3), np.float32)
    with raises_check(r"\(BoundingBoxGeometry\) box 1 \(lower, upper\) = .*nan.* is not finite"):
        jax.jit(build_boxes)(lower, _set(upper, (1, 0), np.nan))
    with raises_check(r"\(BoundingBoxGeometry\) box 0 \(lower, upper\) = .* has lower > upper"):
        jax.jit(build_boxes)(_set(lower, (0, 2), 2.0), upper)


def _set(array: np.ndarray, index, value) -> np.ndarray:
    out = array.copy()
    out[index] = value
    return out


def test_instance_transform_non_finite(blas):
    bad = _set(IDENTITY, (1, 0, 3), np.nan)
    with raises_check(r"build_instance_structure: instances\.transform\[1\] = .*nan.* is not finite"):
        jax.jit(build_instances)(blas, bad, np.zeros(3, np.int32))


def test_instance_transform_singular(blas):
    bad = _set(IDENTITY, (2, 1, 1), 0.0)
    with raises_check(r"build_instance_structure: instances\.transform\[2\] = .* is singular"):
        jax.jit(build_instances)(blas, bad, np.zeros(3, np.int32))


def test_instance_structure_index_out_of_range(blas):
    with raises_check(r"build_instance_structure: instances\.structure_index\[0\] = 3 is out of range for 1"):
        jax.jit(build_instances)(blas, IDENTITY, np.array([3, 0, 0], np.int32))


def test_instances_past_count_are_not_checked(blas):
    bad = _set(IDENTITY, (2, 0, 0), np.nan)
    jax.jit(build_instances)(blas, bad, np.zeros(3, np.int32), jnp.int32(2))
    with raises_check(r"instances\.transform\[2\]"):
        jax.jit(build_instances)(blas, bad, np.zeros(3, np.int32), jnp.int32(3))


def test_checks_under_vmap(blas):
    transforms = np.stack([IDENTITY, _set(IDENTITY, (0, 2, 2), np.inf)])
    build = jax.jit(jax.vmap(lambda t: build_instances(blas, t, np.zeros(3, np.int32))))
    with raises_check(r"instances\.transform\[0\] = .*inf.* is not finite"):
        build(transforms)
    build(np.stack([IDENTITY, IDENTITY]))


def test_except_build_check_error_around_jitted_code(capfd):
    bad = _set(QUAD, (2, 1), np.nan)
    build = jax.jit(build_triangles)
    with pytest.raises(rt.BuildCheckError) as caught:
        with rt.build_check_errors():
            build(bad, QUAD_INDICES)
    message = str(caught.value)
    assert (
        message
        == "build_primitive_structure: geometries[0] (TriangleGeometry) vertices[2] = [ 1., nan, 0.] is not finite"
    )
    assert caught.value.__cause__ is None and caught.value.__suppress_context__
    assert "io_callback failed" not in capfd.readouterr().err  # one report, not a second traceback on stderr


def test_build_check_errors_as_a_decorator_with_a_one_line_transform(blas):
    @rt.build_check_errors()
    def checked(transform):
        return jax.jit(build_instances)(blas, transform, np.zeros(3, np.int32))

    checked(IDENTITY)  # valid input: no error
    with pytest.raises(
        rt.BuildCheckError, match=r"^build_instance_structure: instances\.transform\[1\] = \[\["
    ) as caught:
        checked(_set(IDENTITY, (1, 0, 3), np.nan))
    assert "\n" not in str(caught.value) and "nan" in str(caught.value)


def test_build_check_errors_lets_other_errors_through():
    with pytest.raises(ValueError, match="not a check"):
        with rt.build_check_errors():
            raise ValueError("not a check")
