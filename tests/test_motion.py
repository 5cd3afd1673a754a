"""Keyframe motion: a ray with time t sees exactly the geometry (and instances) interpolated at t.

Each check traces a motion structure with rays at many times and compares every ray with a static structure
built from the keyframes interpolated at that ray's time (by :func:`jaxrt._src.motion.at_time`, the same blend
the traversal uses): hit or miss, primitive, geometry, instance and distance. Times cover before the range, the
keyframes, between keyframes and after the range; the border modes decide the outside times ("clamp": the
first/last keyframe, "vanish": no hit). Scenes are small and share shapes, so each check compiles a few
traversals only.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt._src.motion import at_time, keyframe_times
from jaxrt._src.scene_view import scene_view

START, END = 0.5, 2.5
#: Two specs cover every border mode at both ends.
SPECS = (
    rt.MotionSpec(START, END, start_border="vanish", end_border="clamp"),
    rt.MotionSpec(START, END, start_border="clamp", end_border="vanish"),
)
RAYS_PER_TIME = 48


def _times(keyframes: int) -> list[float]:
    """Before the range, every keyframe, between keyframes, after the range."""
    keys = keyframe_times(SPECS[0], keyframes)
    between = [0.5 * (a + b) + 0.1 * (b - a) for a, b in zip(keys[:-1], keys[1:], strict=True)]
    return [START - 0.75, *keys, *between, END + 0.75]


def _outside(spec: rt.MotionSpec, t: float) -> bool:
    return (t < spec.start_time and spec.start_border == "vanish") or (
        t > spec.end_time and spec.end_border == "vanish"
    )


def _rays(rng: np.random.Generator, lo, hi, times: list[float]):
    """Rays straight down (-z) through random points of the ``[lo, hi]`` square, ``RAYS_PER_TIME`` per time."""
    n = RAYS_PER_TIME
    xy = rng.uniform(lo, hi, size=(len(times), n, 2)).astype(np.float32)
    origin = np.concatenate([xy, np.full((len(times), n, 1), 10.0, np.float32)], axis=-1)
    direction = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (len(times), n, 1))
    time = np.repeat(np.asarray(times, np.float32)[:, None], n, axis=1)
    return origin, direction, time


def _compare(moving, static, *, instances: bool = False) -> None:
    """One time's rays: the motion trace ``moving`` against the static trace ``static``."""
    hit = np.asarray(moving.type) != 0
    np.testing.assert_array_equal(np.asarray(moving.type), np.asarray(static.type))
    np.testing.assert_array_equal(np.asarray(moving.primitive_id), np.asarray(static.primitive_id))
    np.testing.assert_array_equal(np.asarray(moving.geometry_id), np.asarray(static.geometry_id))
    if instances:
        np.testing.assert_array_equal(np.asarray(moving.instance_id), np.asarray(static.instance_id))
    np.testing.assert_allclose(np.asarray(moving.distance)[hit], np.asarray(static.distance)[hit], rtol=2e-6)


def _triangle_keys(rng, keyframes: int, count: int) -> np.ndarray:
    """``(K, 3 count, 3)`` triangles that move and turn between keyframes, facing +z."""
    base = rng.uniform(-1.0, 1.0, size=(count, 1, 3)) + rng.uniform(-0.6, 0.6, size=(count, 3, 3))
    base[..., 2] = rng.uniform(-0.5, 0.5, size=(count, 1))
    keys = []
    for k in range(keyframes):
        angle = 0.4 * k
        rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        keys.append((base @ rotation.T + np.array([0.3 * k, -0.2 * k, 0.25 * k])).reshape(-1, 3))
    return np.asarray(keys, np.float32)


#: Bounding-box geometry index and function of the mixed scenes.
FUNCTIONS = {2: rt.intersection_functions.sphere}
MOVING = rt.Intersector(rt.tags.primitive_motion, rt.tags.triangle_data, intersection_functions=FUNCTIONS)
STATIC = rt.Intersector(rt.tags.triangle_data, intersection_functions=FUNCTIONS)
KEYS = 3


def _mixed_scene(rng, spec: rt.MotionSpec):
    """Moving triangles, a static floor triangle, moving boxes (spheres inscribed) and moving linear curves
    in one structure: ``(moving structure, static structure at time t)``. Same shapes for every ``rng``."""
    triangles = _triangle_keys(rng, KEYS, 6)
    floor = rt.TriangleGeometry(np.array([[-3.0, -3, -3], [3, -3, -3], [-3, 3, -3]], np.float32))
    center = rng.uniform(-1.0, 1.5, size=(4, 3)).astype(np.float32)
    center[:, 2] = rng.uniform(-0.5, 0.5, size=4)
    half = np.array([0.25, 0.4, 0.3], np.float32)[:, None, None]  # the box (and its sphere) grows and shrinks
    shift = np.array([0.5, 0.3, 0.4], np.float32)
    lower = np.stack([center + k * shift for k in range(KEYS)]) - half
    upper = np.stack([center + k * shift for k in range(KEYS)]) + half
    path = np.stack([np.linspace(-1.5, 1.5, 5), rng.uniform(-1.0, 1.0, 5), np.zeros(5)], axis=-1)
    points = np.stack([path + [0.2 * k, 0.3 * k, 0.3 * k] for k in range(KEYS)]).astype(np.float32)
    radii = np.stack([np.full(5, 0.1 + 0.05 * k) for k in range(KEYS)]).astype(np.float32)
    curve = dict(indices=np.arange(4), basis="linear", control_point_count=2)
    moving = rt.build_primitive_structure(
        [
            rt.MotionTriangleGeometry(triangles),
            floor,
            rt.MotionBoundingBoxGeometry(lower, upper),
            rt.MotionCurveGeometry(points, radii, **curve),
        ],
        motion=spec,
    )

    def static(t):
        # Vanished primitives are moved out of every ray's reach (the same shapes: no new compile).
        away = 1e3 if _outside(spec, t) else 0.0
        at = lambda keys: at_time(keys, spec, t) + away  # noqa: E731
        geometries = [
            rt.TriangleGeometry(at(triangles)),
            floor,
            rt.BoundingBoxGeometry(at(lower), at(upper)),
            rt.CurveGeometry(at(points), at(radii), **curve),
        ]
        return rt.build_primitive_structure(geometries)

    return moving, static


def test_triangles_boxes_and_curves_match_the_interpolated_static_structure():
    """Every kind at once (one compile each way): before the range ("vanish": only the floor is there),
    at every keyframe, between keyframes, and after it ("clamp": the last keyframe)."""
    rng = np.random.default_rng(1)
    spec = SPECS[0]
    moving, static = _mixed_scene(rng, spec)
    times = _times(KEYS)
    origin, direction, time = _rays(rng, -1.5, 2.5, times)
    hit = MOVING.intersect(rt.Ray(origin, direction, time=time), moving)
    found = np.asarray(hit.type) != 0
    np.testing.assert_array_equal(np.asarray(hit.time)[found], time[found])  # the result's time field
    np.testing.assert_array_equal(np.asarray(hit.time)[~found], 0.0)
    kinds = set()
    for i, t in enumerate(times):
        ref = STATIC.intersect(rt.Ray(origin[i], direction[i]), static(t))
        part = jax.tree_util.tree_map(lambda a, i=i: a[i], hit)
        _compare(part, ref)
        kinds |= set(np.asarray(part.type).tolist())
    assert kinds == {0, 1, 2, 3}, f"every kind should be hit and missed somewhere, got {kinds}"


@settings(max_examples=10, derandomize=True, deadline=None)
@given(seed=st.integers(0, 2**16), t=st.floats(START - 0.5, END + 0.5, width=32))
def test_property_a_ray_sees_the_scene_at_its_time(seed, t):
    """Random mixed scenes (the shapes of the test above, so no new compile) at a random time."""
    rng = np.random.default_rng(seed)
    spec = SPECS[0]
    moving, static = _mixed_scene(rng, spec)
    origin, direction, time = _rays(rng, -1.5, 2.5, [t] * len(_times(KEYS)))  # the batch size of the test above
    hit = MOVING.intersect(rt.Ray(origin, direction, time=time), moving)
    ref = STATIC.intersect(rt.Ray(origin[0], direction[0]), static(t))
    _compare(jax.tree_util.tree_map(lambda a: a[0], hit), ref)


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        (SPECS[0], [(False, 0, 0.0), (True, 0, 0.0), (True, 1, 0.5), (True, 1, 1.0), (True, 1, 1.0)]),
        (SPECS[1], [(True, 0, 0.0), (True, 0, 0.0), (True, 1, 0.5), (True, 1, 1.0), (False, 1, 1.0)]),
    ],
)
def test_keyframe_position_and_border_modes(spec, expected):
    """Times before, at the start, between, at the end and after: ``(visible, segment, weight)``."""
    from jaxrt._src.motion import spec_position

    for t, (visible, index, weight) in zip([0.0, 0.5, 2.0, 2.5, 3.0], expected, strict=True):
        p = spec_position(spec, 3, jnp.float32(t))
        assert (bool(p.visible), int(p.index), float(p.weight)) == (visible, index, weight), t


def _transform(angle: float, translation) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0, translation[0]], [s, c, 0, translation[1]], [0, 0, 1, translation[2]]], np.float32)


def test_instances_moving_and_static_at_two_levels():
    """A moving instance of a moving primitive structure, beside a constant one, under a moving top level; the
    result's transforms are the chain's, blended at the ray's time."""
    rng = np.random.default_rng(5)
    keys = _triangle_keys(rng, 2, 6) * 0.5
    plate = rt.TriangleGeometry(np.array([[-1.0, -1, 0], [1, -1, 0], [-1, 1, 0]], np.float32))
    inner_keys = np.stack(
        [[_transform(0.0, (0.5, 0, 0)), _transform(0.6, (0.9, 0.3, 0.2))], [_transform(0.3, (-1.0, -0.5, -0.5))] * 2]
    )
    outer_keys = np.stack([_transform(0.0, (0, 0, 0)), _transform(-0.3, (0.2, 0.1, 0.3))])[None]
    times = _times(2)

    def moving(spec):
        blas = rt.build_primitive_structure(rt.MotionTriangleGeometry(keys), motion=spec)
        still = rt.build_primitive_structure(plate)
        inner = rt.build_instance_structure([blas, still], rt.Instances([0, 1], inner_keys), motion=spec)
        return rt.build_instance_structure([inner], rt.Instances([0], outer_keys), motion=spec)

    def static(spec, t):
        blas = rt.build_primitive_structure(rt.TriangleGeometry(at_time(keys, spec, t)))
        still = rt.build_primitive_structure(plate)
        inner = rt.Instances([0, 1], at_time(np.moveaxis(inner_keys, 1, 0), spec, t))
        inner = rt.build_instance_structure([blas, still], inner)
        return rt.build_instance_structure([inner], rt.Instances([0], at_time(np.moveaxis(outer_keys, 1, 0), spec, t)))

    tags = (rt.tags.instancing, rt.tags.max_levels(2))
    intersector = rt.Intersector(*tags, rt.tags.primitive_motion, rt.tags.instance_motion, rt.tags.world_space_data)
    static_intersector = rt.Intersector(*tags, rt.tags.world_space_data)
    origin, direction, time = _rays(rng, -1.5, 1.5, times)
    for spec in SPECS[1:]:  # clamped before the range, vanished after it
        s = moving(spec)
        hit = intersector.intersect(rt.Ray(origin, direction, time=time), s)
        for i, t in enumerate(times):
            ref = static_intersector.intersect(rt.Ray(origin[i], direction[i]), static(spec, t))
            part = jax.tree_util.tree_map(lambda a, i=i: a[i], hit)
            if _outside(spec, t):  # the top instance vanishes: nothing below it is there
                assert not np.asarray(part.type).any()
                continue
            _compare(part, ref, instances=True)
            found = np.asarray(part.type) != 0
            np.testing.assert_allclose(
                np.asarray(part.object_to_world_transform)[found],
                np.asarray(ref.object_to_world_transform)[found],
                atol=1e-6,
            )


def test_instance_box_bounds_every_keyframe():
    blas = rt.build_primitive_structure(rt.TriangleGeometry(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)))
    keys = np.stack([_transform(0.0, (0, 0, 0)), _transform(1.0, (3, 0, 0))])[None]
    s = rt.build_instance_structure([blas], rt.Instances([0], keys), motion=rt.MotionSpec(0.0, 1.0))
    lower = np.asarray(s.root.node_lower[0, 0])
    upper = np.asarray(s.root.node_upper[0, 0])
    for t in np.linspace(0.0, 1.0, 11):
        m = np.asarray(at_time(keys[0], rt.MotionSpec(0.0, 1.0), t))
        corners = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]) @ m[:, :3].T + m[:, 3]
        assert (corners >= lower - 1e-5).all() and (corners <= upper + 1e-5).all()


def test_node_boxes_are_the_union_and_per_keyframe_boxes():
    keys = _triangle_keys(np.random.default_rng(6), 4, 5)
    s = rt.build_primitive_structure(rt.MotionTriangleGeometry(keys), motion=SPECS[0])
    assert s.keyframe_count == 4 and s.motion_triangle.shape == (4, 8, 3, 3)
    children = np.asarray(s.node_children)
    lower, upper = np.asarray(s.node_lower), np.asarray(s.node_upper)
    leaf_keys = np.asarray(s.motion_triangle)
    for node, side in zip(*np.nonzero(children < 0), strict=True):
        leaf = -1 - children[node, side]
        if np.asarray(s.leaf_geometry)[leaf] < 0:
            continue
        np.testing.assert_array_equal(lower[node, side], leaf_keys[:, leaf].min(axis=(0, 1)))
        np.testing.assert_array_equal(upper[node, side], leaf_keys[:, leaf].max(axis=(0, 1)))
        # Per keyframe (what the traversal blends at a ray's time): the leaf's own box at that keyframe.
        np.testing.assert_array_equal(np.asarray(s.motion_node_lower)[:, node, side], leaf_keys[:, leaf].min(axis=1))
        np.testing.assert_array_equal(np.asarray(s.motion_node_upper)[:, node, side], leaf_keys[:, leaf].max(axis=1))
    # Inner nodes: each keyframe's box holds its children's boxes at that keyframe.
    keyed_lower, keyed_upper = np.asarray(s.motion_node_lower), np.asarray(s.motion_node_upper)
    for node, side in zip(*np.nonzero(children >= 0), strict=True):
        child = children[node, side]
        assert (keyed_lower[:, node, side] <= keyed_lower[:, child].min(axis=1)).all()
        assert (keyed_upper[:, node, side] >= keyed_upper[:, child].max(axis=1)).all()


def test_gradients_with_respect_to_keyframes_and_time():
    """A plane triangle at height z(t) = (1 - w) z_k + w z_{k+1}: the distance of a ray going down from z = 5
    is 5 - z(t), so d/dz_k = -(1 - w), d/dz_{k+1} = -w, d/dt = -(z_{k+1} - z_k) (K - 1) / (end - start)."""
    base = np.array([[-1.0, -1, 0], [2, -1, 0], [-1, 2, 0]], np.float32)
    heights = jnp.array([0.0, 1.0, 3.0], jnp.float32)
    spec = rt.MotionSpec(0.0, 2.0)
    intersector = rt.Intersector(rt.tags.primitive_motion)

    def distance(heights, time):
        keys = jnp.asarray(base)[None] + jnp.stack([jnp.zeros_like(heights)] * 2 + [heights], -1)[:, None, :]
        s = rt.build_primitive_structure(rt.MotionTriangleGeometry(keys), motion=spec)
        return intersector.intersect(rt.Ray([0.0, 0, 5], [0.0, 0, -1], time=time), s).distance

    time = jnp.float32(1.25)  # segment 1, weight 0.25
    value = distance(heights, time)
    np.testing.assert_allclose(value, 5.0 - (0.75 * 1.0 + 0.25 * 3.0), rtol=1e-6)
    d_heights, d_time = jax.grad(distance, argnums=(0, 1))(heights, time)
    np.testing.assert_allclose(d_heights, [0.0, -0.75, -0.25], atol=1e-6)
    np.testing.assert_allclose(d_time, -(3.0 - 1.0) * 2 / 2.0, rtol=1e-5)


def test_gradient_with_respect_to_instance_keyframes():
    blas = rt.build_primitive_structure(
        rt.TriangleGeometry(np.array([[-1.0, -1, 0], [2, -1, 0], [-1, 2, 0]], np.float32))
    )
    spec = rt.MotionSpec(0.0, 1.0)
    intersector = rt.Intersector(rt.tags.instancing, rt.tags.instance_motion)

    def distance(lift):
        keys = jnp.stack([jnp.eye(3, 4), jnp.eye(3, 4).at[2, 3].set(lift)])[None]
        s = rt.build_instance_structure([blas], rt.Instances([0], keys), motion=spec)
        return intersector.intersect(rt.Ray([0.0, 0, 5], [0.0, 0, -1], time=0.25), s).distance

    np.testing.assert_allclose(distance(2.0), 5.0 - 0.5, rtol=1e-6)
    np.testing.assert_allclose(jax.grad(distance)(2.0), -0.25, rtol=1e-5)


def test_motion_tags_and_coverage():
    keys = _triangle_keys(np.random.default_rng(7), 2, 2)
    s = rt.build_primitive_structure(rt.MotionTriangleGeometry(keys), motion=rt.MotionSpec())
    ray = rt.Ray([0.0, 0, 5], [0.0, 0, -1], time=0.5)
    with pytest.raises(ValueError, match="tags.primitive_motion"):
        rt.Intersector().intersect(ray, s)
    with pytest.raises(AttributeError, match="tags.primitive_motion"):
        _ = rt.Intersector().intersect(ray, rt.build_primitive_structure(rt.TriangleGeometry(keys[0]))).time
    view = scene_view(s)
    assert view.layout.motion and view.leaves.motion is not None
    # Counting crosses the triangles blended at each ray's time: a plate that rises through z = 0 by t = 1.
    plate = np.array([[-1.0, -1, -1], [2, -1, -1], [-1, 2, -1]], np.float32)
    rising = rt.build_primitive_structure(
        rt.MotionTriangleGeometry(np.stack([plate, plate + [0, 0, 2]])), motion=rt.MotionSpec()
    )
    up = rt.Ray([[0.0, 0, 0]] * 3, [0.0, 0, 1], 0.0, 5.0, time=[0.0, 0.4, 0.6])
    counts = rt.count_intersections(up, rising, rt.Intersector(rt.tags.primitive_motion))
    assert counts.tolist() == [0, 0, 1]
    assert not scene_view(rt.build_primitive_structure(rt.TriangleGeometry(keys[0]))).layout.motion
    assert pipeline.kernel_declines(rt.Intersector(rt.tags.primitive_motion), s.geometry_info) is None  # GPU
    assert pipeline.kernel_declines(rt.Intersector(rt.tags.primitive_motion), s.geometry_info, "cpu") is None
    with pytest.raises(NotImplementedError, match="keyframe motion"):
        rt.save("/nonexistent/never-written.npz", s)
    with pytest.raises(NotImplementedError, match="keyframe motion"):
        rt.intersection_query(ray, s, rt.Intersector(rt.tags.primitive_motion))
    compact = rt.compact(s)
    assert compact.motion_triangle.shape[1] == compact.capacity
    sizes = rt.structure_sizes(rt.MotionTriangleGeometry(keys), motion=rt.MotionSpec())
    assert sizes.total == rt.structure_sizes(s).total


def test_validation_errors():
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    with pytest.raises(ValueError, match=r"MotionTriangleGeometry: vertices needs at least 2 keyframes"):
        rt.MotionTriangleGeometry(tri[None])
    with pytest.raises(ValueError, match=r"MotionTriangleGeometry: keyframe 1 of vertices has shape \(4, 3\)"):
        rt.MotionTriangleGeometry([tri, np.zeros((4, 3), np.float32)])
    with pytest.raises(ValueError, match=r"MotionTriangleGeometry: vertices has a non-finite value"):
        rt.MotionTriangleGeometry(np.stack([tri, tri * np.nan]))
    with pytest.raises(ValueError, match=r"MotionTriangleGeometry: keyframe 0: indices\[0, 2\] = 7"):
        rt.MotionTriangleGeometry(np.stack([tri, tri]), [[0, 1, 7]])
    with pytest.raises(ValueError, match=r"MotionBoundingBoxGeometry: lower \(2, 1, 3\) and upper \(3, 1, 3\)"):
        rt.MotionBoundingBoxGeometry(np.zeros((2, 1, 3)), np.ones((3, 1, 3)))
    with pytest.raises(ValueError, match=r"MotionBoundingBoxGeometry: keyframe 1: box 0 is inverted"):
        rt.MotionBoundingBoxGeometry(np.zeros((2, 1, 3)), np.stack([np.ones((1, 3)), -np.ones((1, 3))]))
    with pytest.raises(ValueError, match=r"MotionCurveGeometry: radii must have shape \(K, P\) = \(2, 2\)"):
        rt.MotionCurveGeometry(np.zeros((2, 2, 3)), np.ones((3, 2)), [0], basis="linear", control_point_count=2)
    with pytest.raises(ValueError, match=r"MotionCurveGeometry: keyframe 1: radii must be non-negative"):
        rt.MotionCurveGeometry(
            np.zeros((2, 2, 3)), [[1.0, 1.0], [1.0, -1.0]], [0], basis="linear", control_point_count=2
        )
    with pytest.raises(ValueError, match=r"MotionSpec: end_time=1.0 must be greater than start_time=1.0"):
        rt.MotionSpec(1.0, 1.0)
    with pytest.raises(ValueError, match=r"MotionSpec: start_border must be one of \('clamp', 'vanish'\), got 'wrap'"):
        rt.MotionSpec(0.0, 1.0, start_border="wrap")
    with pytest.raises(ValueError, match=r"MotionSpec: end_time must be finite"):
        rt.MotionSpec(0.0, float("inf"))
    moving = rt.MotionTriangleGeometry(np.stack([tri, tri]))
    with pytest.raises(ValueError, match=r"build_primitive_structure: geometries\[0\] is a MotionTriangleGeometry"):
        rt.build_primitive_structure(moving)
    with pytest.raises(ValueError, match=r"needs at least one Motion\*Geometry"):
        rt.build_primitive_structure(rt.TriangleGeometry(tri), motion=rt.MotionSpec())
    with pytest.raises(ValueError, match=r"different keyframe counts \{0: 2, 1: 3\}"):
        rt.build_primitive_structure([moving, rt.MotionTriangleGeometry(np.stack([tri] * 3))], motion=rt.MotionSpec())
    with pytest.raises(TypeError, match=r"motion must be an rt.MotionSpec"):
        rt.build_primitive_structure(moving, motion=(0.0, 1.0))
    blas = rt.build_primitive_structure(rt.TriangleGeometry(tri))
    eye = np.eye(3, 4, dtype=np.float32)
    with pytest.raises(ValueError, match=r"motion=MotionSpec.* needs keyframed transforms"):
        rt.build_instance_structure([blas], rt.Instances([0], eye[None]), motion=rt.MotionSpec())
    with pytest.raises(ValueError, match=r"Instances \(keyframe 1\): transform\[0\] is singular"):
        rt.Instances([0], np.stack([eye, eye * 0])[None])
