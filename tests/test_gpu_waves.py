"""Candidate waves on the GPU kernel: user intersection functions and filters, against float64 and the portable path.

The scenes and the float64 reference are ``test_custom_geometry.py``'s (opaque and alpha-tested triangles,
spheres, disks and capped cylinders as bounding boxes), except that the sphere and cylinder functions are user
functions here (a JAX function wrapping the built-in one is not recognised as built-in), so the kernel lists
their boxes as candidates and JAX decides them; the disks keep the built-in function (decided in the kernel).
The alpha filter is user code too. As in ``test_gpu_instanced.py``, the kernel runs in Triton's interpreter
on the CPU (in a fresh process) or on a CUDA GPU.

Every query is checked against the float64 reference and against the portable traversal: the same primitive
for each ray (no two primitives of these random scenes lie at equal distances), distances to rounding, equal
hit lists and counts. Fewer candidates per wave (1 and 2) force many waves, whose results must not change.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from test_custom_geometry import (
    CYLINDERS,
    DISKS,
    SPHERES,
    alpha_filter,
    assert_data_round_trip,
    assert_nearest,
    build,
    check_any,
    expected,
    random_rays,
    random_scene,
)
from test_gpu_instanced import (
    INTERPRETED,
    LAUNCHES,
    ON_GPU,
    kernel_launches_here,
    kernel_test,
    run_kernel_tests_in_interpreter,
)

import jaxrt as rt
from jaxrt._src import pipeline
from jaxrt._src.traversal import gpu, waves

RAYS = 128


def user_sphere(ray: rt.Ray, candidate: rt.BoundingBoxCandidate):
    """A user intersection function (the built-in sphere, called from user code)."""
    return rt.intersection_functions.sphere(ray, candidate)


def user_cylinder(ray: rt.Ray, candidate: rt.BoundingBoxCandidate):
    return rt.intersection_functions.capped_cylinder(ray, candidate)


FUNCTIONS = {SPHERES: user_sphere, DISKS: rt.intersection_functions.disk, CYLINDERS: user_cylinder}


def intersector(backend: str, **kw) -> rt.Intersector:
    return rt.Intersector(
        rt.tags.primitive_data,
        rt.tags.triangle_data,
        intersection_functions=FUNCTIONS,
        filter=alpha_filter,
        backend=backend,
        **kw,
    )


kernel_here = pytest.fixture(kernel_launches_here, name="kernel_here")


@pytest.fixture
def kernel_path(kernel_here, monkeypatch):
    """``backend="gpu"`` reaches the kernel here (the interpreter on the CPU)."""
    if not ON_GPU:
        monkeypatch.setattr(gpu, "unavailable_reason", lambda intersector: None)
    jax.clear_caches()
    yield
    jax.clear_caches()


def test_kernel_in_interpreter():
    """Runs this module's kernel tests in Triton's interpreter, in a fresh process."""
    run_kernel_tests_in_interpreter(__file__)


def test_waves_cover_user_code_in_primitive_structures_only():
    """The GPU kernel covers filters and user functions in a static primitive structure without curves; the
    CPU traversal does not (they take the portable path there)."""
    scene = random_scene(0)
    info = build(scene).geometry_info
    user = intersector("auto")
    assert pipeline.kernel_declines(user, info, "gpu") is None
    assert "user intersection functions" in pipeline.kernel_declines(user, info, "cpu")
    assert "below instances" in pipeline.kernel_declines(user, info, "gpu", levels=1)
    filtered_only = rt.Intersector(filter=alpha_filter)
    assert "filters on non-opaque geometry below instances" in pipeline.kernel_declines(
        filtered_only, info[:2], "gpu", levels=1
    )
    assert "keyframe motion" in pipeline.kernel_declines(user, info, "gpu", motion=True)
    built_in = rt.Intersector(intersection_functions={SPHERES: rt.intersection_functions.sphere})
    from jaxrt._src.scene_view import scene_view

    view = scene_view(build(scene))
    assert waves.needs_waves(user, view)
    assert not waves.needs_waves(built_in, view)


# --- the kernel's tests -------------------------------------------------------------------------------------------


def few_candidates(monkeypatch, first: int, later: int) -> int:
    """Candidates per ray in the first wave and in later ones (fewer: more waves); returns ``first``."""
    monkeypatch.setattr(waves, "CANDIDATES", first)
    monkeypatch.setattr(waves, "LATER_CANDIDATES", later)
    return first


def _trace(backend: str, ray: rt.Ray, structure, **kw):
    return intersector(backend, **kw).intersect(ray, structure)


def _same(got, want, *, rtol: float = 1e-6) -> None:
    """The same primitive per ray and distances to rounding."""
    for name in ("type", "geometry_id", "primitive_id"):
        np.testing.assert_array_equal(np.asarray(got[name]), np.asarray(want[name]), err_msg=name)
    np.testing.assert_allclose(np.asarray(got.distance), np.asarray(want.distance), rtol=rtol, err_msg="distance")


@kernel_test
@pytest.mark.parametrize("candidates", [(4, 16), (1, 1)])
def test_nearest_against_float64_and_the_portable_path(candidates, kernel_path, monkeypatch):
    candidates = few_candidates(monkeypatch, *candidates)
    scene = random_scene(3)
    structure = build(scene)
    rays = random_rays(4, scene, RAYS)
    got = _trace("gpu", rays.ray(), structure)
    assert_nearest(got, expected(scene, rays))
    _same(got, _trace("portable", rays.ray(), structure))
    assert_data_round_trip(got, scene)
    kinds = set(np.asarray(got.type).tolist())
    assert {int(rt.IntersectionType.TRIANGLE), int(rt.IntersectionType.BOUNDING_BOX)} <= kinds
    if not ON_GPU and candidates == 1:
        assert len(LAUNCHES) >= 2  # more than one wave


@kernel_test
@pytest.mark.parametrize("candidates", [(4, 16), (2, 3)])
def test_any_hit_with_culling_against_float64(candidates, kernel_path, monkeypatch):
    few_candidates(monkeypatch, *candidates)
    scene = random_scene(5)
    structure = build(scene)
    rays = random_rays(6, scene, RAYS)
    options = dict(accept_any_intersection=True, triangle_cull_mode="front", front_facing_winding="counterclockwise")
    got = _trace("gpu", rays.ray(), structure, **options)
    failures, _ = check_any(got, expected(scene, rays, cull="front", front_facing_winding="counterclockwise"))
    assert not failures, "\n".join(failures[:20])
    want = _trace("portable", rays.ray(), structure, **options)
    np.testing.assert_array_equal(np.asarray(got.type) != 0, np.asarray(want.type) != 0)


@kernel_test
@pytest.mark.parametrize("candidates", [(4, 16), (1, 2)])
def test_hit_lists_and_counts_equal_the_portable_path(candidates, kernel_path, monkeypatch):
    """``max_hits=3`` (the three nearest accepted hits, their count and overflow) and counting."""
    few_candidates(monkeypatch, *candidates)
    scene = random_scene(7)
    structure = build(scene)
    ray = random_rays(8, scene, RAYS).ray()
    got = _trace("gpu", ray, structure, max_hits=3)
    want = _trace("portable", ray, structure, max_hits=3)
    for name in ("type", "geometry_id", "primitive_id", "hit_count", "hit_overflow"):
        np.testing.assert_array_equal(np.asarray(got[name]), np.asarray(want[name]), err_msg=name)
    np.testing.assert_allclose(np.asarray(got.distance), np.asarray(want.distance), rtol=1e-6)
    assert (np.asarray(got.hit_count) >= 2).sum() > 5
    got_count = rt.count_intersections(ray, structure, rt.Intersector(**COUNTING, backend="gpu"))
    want_count = rt.count_intersections(ray, structure, rt.Intersector(**COUNTING, backend="portable"))
    np.testing.assert_array_equal(np.asarray(got_count), np.asarray(want_count))
    assert np.asarray(want_count).max() >= 3


COUNTING = dict(intersection_functions=FUNCTIONS, filter=alpha_filter)


@kernel_test
def test_inside_jit_and_vmap(kernel_path):
    """One compiled program for two halves of the batch under ``vmap`` (the while loop of waves batched)."""
    scene = random_scene(9)
    structure = build(scene)
    rays = random_rays(10, scene, RAYS)
    user = intersector("gpu")
    halves = rays.ray().reshape(2, -1)
    got = jax.jit(jax.vmap(lambda r: user.intersect(r, structure)))(halves)
    got = jax.tree_util.tree_map(lambda a: a.reshape(-1, *a.shape[2:]), got)
    _same(got, _trace("portable", rays.ray(), structure))
    assert INTERPRETED or ON_GPU


@kernel_test
def test_vmap_over_rays_and_structures(kernel_path, monkeypatch):
    """``vmap`` over (rays, structure) pairs: one launch per wave traces both scenes (their leaves moved into
    one index range, each ray's cursor with them), with many waves (one candidate each), and gives each pair
    what tracing it alone gives (the same arithmetic; the kernel's built-in disk may round differently from
    the portable one at a rim, which ``test_gpu_analytic.py`` covers)."""
    few_candidates(monkeypatch, 1, 1)
    scenes = [random_scene(9), random_scene(14)]
    structures = [build(scene) for scene in scenes]
    rays = [random_rays(10 + i, scene, RAYS // 2).ray() for i, scene in enumerate(scenes)]
    stack = lambda *a: np.stack([np.asarray(x) for x in a])  # noqa: E731
    user = intersector("gpu")
    LAUNCHES.clear()
    got = jax.jit(jax.vmap(user.intersect))(
        jax.tree_util.tree_map(stack, *rays), jax.tree_util.tree_map(stack, *structures)
    )
    if not ON_GPU:
        assert {n for _, n in LAUNCHES} == {RAYS} and len(LAUNCHES) >= 2  # both scenes in each wave's launch
    for i in range(2):
        one = jax.tree_util.tree_map(lambda a, i=i: a[i], got)
        alone = user.intersect(rays[i], structures[i])
        for name in ("type", "geometry_id", "primitive_id", "distance"):
            np.testing.assert_array_equal(np.asarray(one[name]), np.asarray(alone[name]), err_msg=name)
        assert (np.asarray(alone.type) == int(rt.IntersectionType.BOUNDING_BOX)).sum() > 5


# --- filters that read only the primitive -------------------------------------------------------------------------


BUILT_IN = {
    SPHERES: rt.intersection_functions.sphere,
    DISKS: rt.intersection_functions.disk,
    CYLINDERS: rt.intersection_functions.capped_cylinder,
}


def primitive_filter(candidate: rt.TriangleCandidate):
    """Rejects the primitives whose cutoff rejects everything (reads the primitive data only)."""
    return candidate.primitive_data["cutoff"] < 1.0


def test_filters_that_read_the_hit_are_called_per_candidate():
    """Only a filter whose decision cannot depend on the distance, barycentrics or facing is decided per
    primitive (the jaxpr is followed conservatively)."""
    from jaxrt._src import filter_states
    from jaxrt._src.scene_view import scene_view

    view = scene_view(build(random_scene(11)))
    candidate = filter_states._candidate(view, np.int32(0), view.leaves.primitive_data)
    assert filter_states.reads_only_primitive(primitive_filter, candidate)
    assert filter_states.reads_only_primitive(lambda c: c.primitive_id % 3 != c.geometry_id, candidate)
    assert not filter_states.reads_only_primitive(alpha_filter, candidate)  # the texture at the barycentrics
    assert not filter_states.reads_only_primitive(lambda c: c.distance > 1.0, candidate)
    assert not filter_states.reads_only_primitive(lambda c: c.front_facing & (c.primitive_id > 2), candidate)
    rejected = filter_states.rejected_leaves(rt.Intersector(filter=primitive_filter), view)
    cutoff = np.asarray(view.leaves.primitive_data["cutoff"])
    non_opaque = np.asarray(view.leaf_flag(view.slot_table((1,)), np.arange(cutoff.shape[0])))
    np.testing.assert_array_equal(np.asarray(rejected), non_opaque & (cutoff >= 1.0))
    assert np.asarray(rejected).any()
    assert filter_states.rejected_leaves(rt.Intersector(filter=alpha_filter), view) is None


@kernel_test
@pytest.mark.parametrize("query", ["nearest", "any", "max_hits", "count"])
def test_filters_that_read_the_primitive_take_one_launch(query, kernel_path):
    """Decided once per primitive: one launch (no waves), and the portable path's results."""
    scene = random_scene(12)
    structure = build(scene)
    ray = random_rays(13, scene, RAYS).ray()
    kw = {"nearest": {}, "any": {"accept_any_intersection": True}, "max_hits": {"max_hits": 3}}.get(query, {})

    def run(backend):
        inter = rt.Intersector(
            rt.tags.primitive_data, intersection_functions=BUILT_IN, filter=primitive_filter, backend=backend, **kw
        )
        if query == "count":
            return rt.count_intersections(ray, structure, inter)
        return inter.intersect(ray, structure)

    LAUNCHES.clear()
    got, want = run("gpu"), run("portable")
    if not ON_GPU:
        assert len(LAUNCHES) == 1
    if query == "count":
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
        assert np.asarray(want).max() >= 2
        return
    fields = ("type",) if query == "any" else ("type", "geometry_id", "primitive_id")
    fields += ("hit_count", "hit_overflow") if query == "max_hits" else ()
    for name in fields:
        np.testing.assert_array_equal(np.asarray(got[name]), np.asarray(want[name]), err_msg=name)
    if query != "any":  # the kernel's capped cylinder rounds differently (CYLINDER_RTOL, test_gpu_analytic.py)
        cylinder = np.asarray(want.geometry_id) == CYLINDERS
        for part, rtol in ((cylinder, 1e-3), (~cylinder, 1e-6)):
            np.testing.assert_allclose(np.asarray(got.distance)[part], np.asarray(want.distance)[part], rtol=rtol)
    assert (np.asarray(want.type) == int(rt.IntersectionType.TRIANGLE)).sum() > 10


# --- intersection queries -----------------------------------------------------------------------------------------


QUERY_RAYS = 64  # each listing is a launch for every ray: the interpreter's cost


@kernel_test
@pytest.mark.parametrize("listed", [8, 1])
def test_intersection_query_lists_candidates_with_the_kernel(listed, kernel_path, monkeypatch):
    """``rt.intersection_query`` of a static primitive structure lists its candidates with the kernel (``listed``
    per launch; 1: a launch per candidate): Metal's alpha-test loop over non-opaque triangles and sphere boxes
    commits what the intersector's filter and function accept, and ends with the intersector's hit."""
    from test_query import _INTERSECTOR, _loop, _scene

    from jaxrt._src import query

    monkeypatch.setattr(query, "KERNEL_CANDIDATES", listed)
    structure, rays = _scene(5)
    rays = rt.Ray(
        *(np.asarray(a)[:QUERY_RAYS] for a in (rays.origin, rays.direction, rays.min_distance, rays.max_distance))
    )
    assert query.lists_with_the_kernel(_INTERSECTOR, structure)
    _loop.clear_cache()
    LAUNCHES.clear()
    got = _loop(structure, rays)
    _loop.clear_cache()
    if not ON_GPU:
        assert LAUNCHES, "the query did not list with the kernel"
    portable = rt.Intersector(
        rt.tags.triangle_data, rt.tags.primitive_data, triangle_cull_mode="back", filter=_INTERSECTOR.filter,
        intersection_functions=dict(_INTERSECTOR.intersection_functions), backend="portable",
    )  # fmt: skip
    want = portable.intersect(rays, structure)
    for name in ("type", "primitive_id", "geometry_id"):
        np.testing.assert_array_equal(np.asarray(got[name]), np.asarray(want[name]), err_msg=name)
    kinds = np.asarray(want.type)
    assert (kinds == int(rt.IntersectionType.TRIANGLE)).any() and (kinds == int(rt.IntersectionType.BOUNDING_BOX)).any()
    # The kernel's triangle distances are the portable test's to an ulp; the loop's sphere test is compiled
    # in another program (test_query.py).
    np.testing.assert_allclose(np.asarray(got["distance"]), np.asarray(want.distance), rtol=4e-7)
    np.testing.assert_array_equal(np.asarray(got["barycentric"]), np.asarray(want.triangle_barycentric_coord))
