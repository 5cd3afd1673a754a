"""Instancing: multi-level instance structures against a float64 brute force over the flattened scene.

Every scene of one level count has the same shapes (meshes of ``MESH_TRIANGLES`` triangles, ``SLOTS``
instances per level), and every test shares one intersector, so each level count compiles its trace once.

The oracle flattens the scene in float64 (the float32 transforms composed exactly) and tests every ray
against every world-space triangle. A hit is *certain* when the ray passes inside the triangle with a
barycentric margin that float32 rounding of the instance transforms cannot cross, *possible* when it is
within that margin. A library answer must be possible, within the distance tolerance, and not farther than a
certain hit.
"""

from __future__ import annotations

import dataclasses
import logging

import hypothesis
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import strategies as st

import jaxrt as rt

MESH_TRIANGLES = 6
#: Instance slots of the structure at each level (level 1 instances meshes; level k > 1 instances level k - 1).
SLOTS = {1: 4, 2: 3, 3: 2}
RAYS = 64
BAKED_CAPACITY = 256
#: Barycentric margin of the oracle, and the relative distance tolerance (float32 transforms, up to 3 levels
#: of non-uniform scale in [0.5, 2]).
MARGIN = 2e-4
DISTANCE_RTOL = 2e-5

INTERSECTOR = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(3), rt.tags.triangle_data, rt.tags.world_space_data)


# --- scenes ---------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Node:
    """A scene-graph node mirroring a structure: a mesh, or instances of child nodes."""

    triangles: np.ndarray | None = None  # (T, 3, 3) float32, for a mesh
    children: list[Node] = dataclasses.field(default_factory=list)  # the ``structures`` list
    index: np.ndarray | None = None  # (N,) structure_index
    transform: np.ndarray | None = None  # (N, 3, 4) float32
    mask: np.ndarray | None = None
    user_id: np.ndarray | None = None
    options: np.ndarray | None = None
    count: int | None = None
    structure: object = None


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def random_transform(rng, kind: str, spread: float) -> np.ndarray:
    """A rigid, non-uniformly scaled, or (half of the time) mirrored transform."""
    a = random_rotation(rng)
    if kind in ("scaled", "mirrored"):
        a = a @ np.diag(10.0 ** rng.uniform(-0.3, 0.3, 3)) @ random_rotation(rng)
    if kind == "mirrored" and rng.uniform() < 0.5:
        a = a @ np.diag([-1.0, 1.0, 1.0])
    t = rng.uniform(-spread, spread, 3)
    return np.concatenate([a, t[:, None]], axis=1).astype(np.float32)


def random_mesh(rng) -> Node:
    centers = rng.uniform(-1, 1, (MESH_TRIANGLES, 1, 3))
    triangles = (centers + 0.6 * rng.normal(size=(MESH_TRIANGLES, 3, 3))).astype(np.float32)
    geometry = rt.TriangleGeometry(triangles.reshape(-1, 3))
    return Node(triangles=triangles, structure=rt.build_primitive_structure(geometry))


def instance_node(rng, children: list[Node], slots: int, kind: str, spread: float, **fields) -> Node:
    index = rng.integers(0, len(children), slots).astype(np.int32)
    index[0] = 0  # the deeper child is always used, so the level count is fixed
    transform = np.stack([random_transform(rng, kind, spread) for _ in range(slots)])
    node = Node(children=children, index=index, transform=transform, **fields)
    instances = rt.Instances(
        index,
        transform,
        **{
            k: v
            for k, v in (("mask", node.mask), ("user_id", node.user_id), ("options", node.options))
            if v is not None
        },
    )
    node.structure = rt.build_instance_structure([c.structure for c in children], instances, count=node.count)
    return node


def random_scene(seed: int, levels: int, kind: str, *, masks: bool = False) -> Node:
    """``levels`` of instances; level k > 1 instances the level below and a mesh (mixed depths)."""
    rng = np.random.default_rng(seed)
    mesh_a, mesh_b = random_mesh(rng), random_mesh(rng)
    extra = {}
    node = None
    for level in range(1, levels + 1):
        slots = SLOTS[level]
        if masks:
            extra = dict(mask=rng.choice([1, 2, 4, 8, 3, 12], slots).astype(np.uint32))
        extra["user_id"] = rng.integers(0, 1000, slots).astype(np.uint32)
        children = [mesh_a, mesh_b] if level == 1 else [node, mesh_b if level == 2 else mesh_a]
        node = instance_node(rng, children, slots, kind, 2.0 + 2.0 * level, **extra)
    return node


@dataclasses.dataclass
class Flat:
    triangles: np.ndarray  # (F, 3, 3) float64 world space
    chains: np.ndarray  # (F, 3) local instance indices, outermost first, -1 past the chain
    user_ids: np.ndarray  # (F, 3)
    masks: np.ndarray  # (F, 3) instance masks along the chain (0xFFFFFFFF past it)
    geometry: np.ndarray  # (F,)
    primitive: np.ndarray  # (F,)
    object_to_world: np.ndarray  # (F, 3, 4)


def flatten(node: Node, count: int | None = None) -> Flat:
    """Every triangle of the scene in world space (float64), with its instance chain."""
    out = dict(triangles=[], chains=[], user_ids=[], masks=[], geometry=[], primitive=[], object_to_world=[])

    def walk(n: Node, matrix: np.ndarray, chain: list, users: list, masks: list, limit: int | None):
        if n.triangles is not None:
            tri = n.triangles.astype(np.float64)
            world = tri @ matrix[:3, :3].T + matrix[:3, 3]
            for k in range(tri.shape[0]):
                out["triangles"].append(world[k])
                out["chains"].append(chain + [-1] * (3 - len(chain)))
                out["user_ids"].append(users + [-1] * (3 - len(users)))
                out["masks"].append(masks + [0xFFFFFFFF] * (3 - len(masks)))
                out["geometry"].append(0)
                out["primitive"].append(k)
                out["object_to_world"].append(matrix[:3].copy())
            return
        slots = len(n.index) if limit is None else limit
        for i in range(slots):
            local = np.eye(4)
            local[:3] = n.transform[i].astype(np.float64)
            mask = 0xFF if n.mask is None else int(n.mask[i])
            user = 0 if n.user_id is None else int(n.user_id[i])
            walk(n.children[n.index[i]], matrix @ local, chain + [i], users + [user], masks + [mask], None)

    walk(node, np.eye(4), [], [], [], count)
    return Flat(**{k: np.asarray(v) for k, v in out.items()})


def aimed_rays(seed: int, flat: Flat) -> tuple[np.ndarray, np.ndarray]:
    """Rays aimed at interior points of random flattened triangles (plus a few that may miss)."""
    rng = np.random.default_rng(seed + 1)
    target = rng.integers(0, flat.triangles.shape[0], RAYS)
    bary = rng.dirichlet([2.0, 2.0, 2.0], RAYS)
    point = np.einsum("rk,rkj->rj", bary, flat.triangles[target])
    # From the front or back side, at least 15 degrees off the triangle's plane (grazing rays turn float32
    # rounding of the instance transforms into large distance errors).
    tri = flat.triangles[target]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = rng.normal(size=(RAYS, 3))
    offset /= np.linalg.norm(offset, axis=1, keepdims=True)
    along = np.sum(offset * normal, axis=1, keepdims=True)
    offset = np.where(np.abs(along) < 0.3, offset + np.sign(along + 1e-9) * 0.5 * normal, offset)
    offset *= rng.uniform(3, 15, (RAYS, 1)) / np.linalg.norm(offset, axis=1, keepdims=True)
    origin = point + offset
    direction = (point - origin) * rng.uniform(0.2, 3.0, (RAYS, 1))
    direction[-8:] = rng.normal(size=(8, 3))
    return origin.astype(np.float32), direction.astype(np.float32)


def oracle(origin, direction, triangles):
    """``(t, bary_min, clockwise)`` of every ray/triangle pair in float64 (Möller-Trumbore)."""
    o = origin.astype(np.float64)[:, None]
    d = direction.astype(np.float64)[:, None]
    v0, v1, v2 = (triangles[None, :, i] for i in range(3))
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d, e2)
    det = np.sum(e1 * p, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = o - v0
        u = np.sum(s * p, axis=-1) * inv
        q = np.cross(s, e1)
        v = np.sum(d * q, axis=-1) * inv
        t = np.sum(e2 * q, axis=-1) * inv
    bary_min = np.where(np.isfinite(t), np.minimum(np.minimum(u, v), 1 - u - v), -np.inf)
    normal = np.cross(e1, e2)
    facing = np.sum(normal * d, axis=-1) / (np.linalg.norm(normal, axis=-1) * np.linalg.norm(d, axis=-1))
    return np.where(np.isfinite(t), t, np.inf), bary_min, facing, np.stack([u, v], axis=-1)


def check_against_oracle(result, origin, direction, flat: Flat, visible=None) -> None:
    """Every ray's answer is a possible hit at the right distance, not behind a certain one."""
    if flat.triangles.shape[0] == 0:
        assert not (np.asarray(result.type) != 0).any()
        return
    t, bary_min, facing, bary = oracle(origin, direction, flat.triangles)
    # Rounding moves the object-space ray by about DISTANCE_RTOL of the coordinates' magnitude; along the
    # ray that is divided by the cosine to the triangle's plane.
    length = np.linalg.norm(direction, axis=1, keepdims=True)
    scale = np.abs(origin).max(axis=1, keepdims=True) / length
    cosine = np.maximum(np.abs(facing), 1e-3)
    tol = DISTANCE_RTOL * (np.abs(t) + scale + 1.0) / cosine
    front = t > 0
    if visible is not None:
        front &= visible
    certain = front & (bary_min > MARGIN / cosine) & (t - tol > 0)
    possible = front & (bary_min > -MARGIN / cosine) & (t + tol >= 0)
    kind = np.asarray(result.type)
    distance = np.asarray(result.distance, np.float64)
    chain = np.asarray(result.instance_id)
    count = np.asarray(result.instance_count)
    failures = []
    for r in range(origin.shape[0]):
        nearest_certain = np.min(np.where(certain[r], t[r] - tol[r], np.inf))
        if kind[r] == int(rt.IntersectionType.NONE):
            if np.isfinite(nearest_certain):
                failures.append(f"ray {r}: missed, but a certain hit exists at {nearest_certain}")
            continue
        match = np.flatnonzero(
            (flat.chains == chain[r]).all(axis=1)
            & (flat.primitive == int(result.primitive_id[r]))
            & (flat.geometry == int(result.geometry_id[r]))
        )
        if match.size != 1:
            failures.append(f"ray {r}: chain {chain[r]} primitive {int(result.primitive_id[r])} names no triangle")
            continue
        k = int(match[0])
        if not possible[r, k]:
            failures.append(f"ray {r}: hit triangle {k} (chain {chain[r]}), which float64 misses")
            continue
        if abs(distance[r] - t[r, k]) > tol[r, k]:
            failures.append(f"ray {r}: distance {distance[r]} vs float64 {t[r, k]} (tol {tol[r, k]:.3g})")
        if t[r, k] - tol[r, k] > nearest_certain:
            failures.append(f"ray {r}: hit at {t[r, k]}, but a certain hit is nearer at {nearest_certain}")
        if count[r] != int((flat.chains[k] >= 0).sum()):
            failures.append(f"ray {r}: instance_count {count[r]} for chain {flat.chains[k]}")
        if not np.array_equal(
            np.asarray(result.user_instance_id[r]).astype(np.int64) & 0xFFFFFFFF,
            np.where(flat.user_ids[k] >= 0, flat.user_ids[k], 0xFFFFFFFF),
        ):
            failures.append(f"ray {r}: user ids {result.user_instance_id[r]} vs {flat.user_ids[k]}")
        if abs(facing[r, k]) > 1e-3 and bool(result.triangle_front_facing[r]) != bool(facing[r, k] > 0):
            failures.append(f"ray {r}: front facing {bool(result.triangle_front_facing[r])}, cosine {facing[r, k]}")
        if np.abs(np.asarray(result.triangle_barycentric_coord[r]) - bary[r, k]).max() > 1e-3 / cosine[r, k]:
            failures.append(f"ray {r}: barycentrics {result.triangle_barycentric_coord[r]} vs {bary[r, k]}")
        if "object_to_world_transform" in result:
            o2w = np.asarray(result.object_to_world_transform[r], np.float64)
            w2o = np.asarray(result.world_to_object_transform[r], np.float64)
            expected = flat.object_to_world[k]
            if np.abs(o2w - expected).max() > 1e-4 * (1 + np.abs(expected).max()):
                failures.append(f"ray {r}: object_to_world {o2w} vs {expected}")
            square = np.vstack([expected, [0, 0, 0, 1]])
            inverse = np.linalg.inv(square)[:3]
            if np.abs(w2o - inverse).max() > 1e-4 * (1 + np.abs(inverse).max()):
                failures.append(f"ray {r}: world_to_object {w2o} vs {inverse}")
    assert not failures, f"{len(failures)} of {origin.shape[0]} rays wrong:\n" + "\n".join(failures[:12])


def baked_structure(flat: Flat):
    geometry = rt.TriangleGeometry(flat.triangles.reshape(-1, 3).astype(np.float32))
    return rt.build_primitive_structure(geometry, capacity=BAKED_CAPACITY)


# --- tests ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("levels", [1, 2, 3])
# Shrinking a random seed finds nothing simpler; it only re-traces.
@hypothesis.settings(
    max_examples=4, phases=[hypothesis.Phase.explicit, hypothesis.Phase.reuse, hypothesis.Phase.generate]
)
@hypothesis.given(seed=st.integers(0, 2**20), kind=st.sampled_from(["rigid", "scaled", "mirrored"]))
def test_instanced_equals_baked(levels, seed, kind):
    scene = random_scene(seed, levels, kind)
    assert scene.structure.levels == levels
    flat = flatten(scene)
    origin, direction = aimed_rays(seed, flat)
    result = INTERSECTOR.intersect(rt.Ray(origin, direction), scene.structure)
    check_against_oracle(result, origin, direction, flat)

    baked = rt.Intersector(rt.tags.triangle_data).intersect(rt.Ray(origin, direction), baked_structure(flat))
    # Where the float64 nearest hit is unambiguous, both traces name the same triangle (and so the same chain).
    t, bary_min, _, _ = oracle(origin, direction, flat.triangles)
    t = np.where((t > 0) & (bary_min > -MARGIN), t, np.inf)
    order = np.sort(t, axis=1)
    with np.errstate(invalid="ignore"):
        clear = np.isfinite(order[:, 0]) & (order[:, 1] - order[:, 0] > 1e-3 * (1 + order[:, 0]))
    clear &= np.take_along_axis(bary_min, np.argmin(t, axis=1)[:, None], 1)[:, 0] > MARGIN
    nearest = np.argmin(t, axis=1)
    baked_index = np.asarray(baked.primitive_id)
    assert np.array_equal(baked_index[clear], nearest[clear])
    chain = np.asarray(result.instance_id)
    assert np.array_equal(chain[clear], flat.chains[nearest[clear]])
    assert np.array_equal(np.asarray(result.primitive_id)[clear], flat.primitive[nearest[clear]])
    np.testing.assert_allclose(np.asarray(result.distance)[clear], np.asarray(baked.distance)[clear], rtol=1e-4)
    assert np.array_equal(
        np.asarray(result.triangle_front_facing)[clear], np.asarray(baked.triangle_front_facing)[clear]
    )


def test_masks_and_with_the_ray_mask_at_every_level():
    scene = random_scene(7, 2, "scaled", masks=True)
    flat = flatten(scene)
    origin, direction = aimed_rays(7, flat)
    ray_mask = np.random.default_rng(3).choice([1, 2, 4, 8, 6, 0xFF, 0x100], RAYS).astype(np.uint32)
    result = INTERSECTOR.intersect(rt.Ray(origin, direction, mask=ray_mask), scene.structure)
    visible = ((flat.masks[None] & ray_mask[:, None, None]) != 0).all(axis=2)
    check_against_oracle(result, origin, direction, flat, visible=visible)
    hit = np.asarray(result.type) != 0
    assert not hit[ray_mask == 0x100].any()
    assert hit.any() and (~hit).any()


def _compiles(caplog, names):
    return [
        r.getMessage()
        for r in caplog.records
        if "Compiling" in r.getMessage() and any(n in r.getMessage() for n in names)
    ]


def test_indirect_count_equals_build_over_first_instances_without_recompiling(caplog):
    rng = np.random.default_rng(11)
    mesh_a, mesh_b = random_mesh(rng), random_mesh(rng)
    slots = 4
    index = np.array([0, 1, 0, 1], np.int32)
    transform = np.stack([random_transform(rng, "scaled", 4.0) for _ in range(slots)])
    instances = rt.Instances(index, transform)
    structures = [mesh_a.structure, mesh_b.structure]
    full = Node(children=[mesh_a, mesh_b], index=index, transform=transform)
    flat_all = flatten(full)
    origin, direction = aimed_rays(11, flat_all)
    rays = rt.Ray(origin, direction)

    # Warm up with one count, then change only the count: nothing is compiled again.
    INTERSECTOR.intersect(rays, rt.build_instance_structure(structures, instances, count=jnp.int32(4)))
    caplog.set_level(logging.WARNING)
    results = {}
    with jax.log_compiles(True):
        for count in (2, 3, 0):
            scene = rt.build_instance_structure(structures, instances, count=jnp.int32(count))
            results[count] = INTERSECTOR.intersect(rays, scene)
    assert not _compiles(caplog, ["_intersect_jit", "_build_table"]), _compiles(caplog, ["jit"])

    for count, result in results.items():
        check_against_oracle(result, origin, direction, flatten(full, count))
        assert (np.asarray(result.instance_id)[:, 0] < count).all()
    assert not (np.asarray(results[0].type) != 0).any()

    # Against a structure built over the first two instances only.
    first = rt.build_instance_structure(structures, rt.Instances(index[:2], transform[:2]))
    expected = INTERSECTOR.intersect(rays, first)
    for name in ("type", "primitive_id", "instance_id", "distance", "triangle_barycentric_coord"):
        np.testing.assert_array_equal(np.asarray(results[2][name]), np.asarray(expected[name]), err_msg=name)

    # A traced count inside jit: one compile for all counts.
    traced = jax.jit(
        lambda c: INTERSECTOR.intersect(rays, rt.build_instance_structure(structures, instances, count=c)).distance
    )
    # One program for build and trace may round the transform's inverse differently in the last place.
    np.testing.assert_allclose(np.asarray(traced(jnp.int32(3))), np.asarray(results[3].distance), rtol=1e-6)
    before = traced._cache_size()
    traced(jnp.int32(1))
    assert traced._cache_size() == before


def test_vmap_over_scenes_equals_a_loop():
    batch = 3
    scenes = [random_scene(100 + b, 1, "mirrored") for b in range(batch)]
    flats = [flatten(s) for s in scenes]
    rays = [aimed_rays(100 + b, f) for b, f in enumerate(flats)]

    # Batched builds: primitive structures, then instance structures, over a leading scene axis.
    stack = lambda *xs: jnp.stack(xs)  # noqa: E731
    geometry = [[rt.TriangleGeometry(c.triangles.reshape(-1, 3)) for c in s.children] for s in scenes]
    meshes = [jax.vmap(rt.build_primitive_structure)(jax.tree.map(stack, *[g[i] for g in geometry])) for i in range(2)]
    instances = jax.tree.map(stack, *[rt.Instances(s.index, s.transform, user_id=s.user_id) for s in scenes])
    batched = jax.vmap(lambda a, b, i: rt.build_instance_structure([a, b], i))(*meshes, instances)
    origin = np.stack([r[0] for r in rays])
    direction = np.stack([r[1] for r in rays])
    together = jax.vmap(INTERSECTOR.intersect)(rt.Ray(origin, direction), batched)

    for b in range(batch):
        alone = INTERSECTOR.intersect(rt.Ray(origin[b], direction[b]), scenes[b].structure)
        for name in alone:
            # Batched and single builds may round transforms differently in the last place.
            # Barycentrics lie in [0, 1]: compared absolutely too (two programs may round a near-zero one apart).
            np.testing.assert_allclose(
                np.asarray(together[name][b]), np.asarray(alone[name]), rtol=1e-5, atol=1e-6, err_msg=name
            )
        check_against_oracle(jax.tree.map(lambda a, b=b: a[b], together), origin[b], direction[b], flats[b])


def test_refit_with_moved_instances_equals_a_rebuild():
    scene = random_scene(21, 1, "scaled")
    moved = scene.transform.copy()
    moved[:, :, 3] += np.random.default_rng(5).uniform(-3, 3, (len(moved), 3)).astype(np.float32)
    instances = rt.Instances(scene.index, moved, user_id=scene.user_id)
    refit = rt.refit(scene.structure, instances)
    rebuilt = rt.build_instance_structure([c.structure for c in scene.children], instances)
    flat = flatten(dataclasses.replace(scene, transform=moved))
    origin, direction = aimed_rays(21, flat)
    a = INTERSECTOR.intersect(rt.Ray(origin, direction), refit)
    b = INTERSECTOR.intersect(rt.Ray(origin, direction), rebuilt)
    for name in a:
        np.testing.assert_array_equal(np.asarray(a[name]), np.asarray(b[name]), err_msg=name)
    check_against_oracle(a, origin, direction, flat)
    with pytest.raises(ValueError, match="instances has 2 slots, the structure was built with 4"):
        rt.refit(scene.structure, rt.Instances(scene.index[:2], moved[:2]))


def test_culling_follows_mirroring_and_instance_options():
    # One triangle, clockwise seen from +z looking down (normal along -z): front-facing for rays going -z.
    triangle = np.array([[0, 0, 0], [0, 1, 0], [1, 0, 0]], np.float32)
    blas = rt.build_primitive_structure(rt.TriangleGeometry(triangle))
    place = lambda x, mirror: np.array([[mirror, 0, 0, x], [0, 1, 0, 0], [0, 0, 1, 0]], np.float32)  # noqa: E731
    # Mirroring in x flips the winding (the world triangle is counterclockwise); options override as Metal does.
    transforms = np.stack([place(0, 1), place(10, -1), place(20, -1), place(30, 1)])
    options = [
        rt.InstanceOptions.NONE,
        rt.InstanceOptions.NONE,
        rt.InstanceOptions.DISABLE_TRIANGLE_CULLING,
        rt.InstanceOptions.TRIANGLE_FRONT_FACING_WINDING_COUNTERCLOCKWISE,
    ]
    scene = rt.build_instance_structure([blas], rt.Instances([0, 0, 0, 0], transforms, options=options))
    xs = np.array([0.2, 9.8, 19.8, 30.2], np.float32)
    rays = rt.Ray(
        np.stack([xs, np.full(4, 0.2), np.full(4, 1.0)], -1).astype(np.float32), np.array([0, 0, -1], np.float32)
    )
    front = np.array([True, False, False, False])
    cull_back = rt.Intersector(rt.tags.instancing, rt.tags.triangle_data, triangle_cull_mode="back")
    result = cull_back.intersect(rays, scene)
    # Back faces are culled except under DISABLE_TRIANGLE_CULLING.
    np.testing.assert_array_equal(np.asarray(result.type) != 0, front | np.array([False, False, True, False]))
    np.testing.assert_array_equal(np.asarray(result.triangle_front_facing), front)
    # The same rays on the baked triangles agree (the option-free instances).
    baked = np.stack([triangle @ t[:, :3].T + t[:, 3] for t in transforms[:2]]).reshape(-1, 3)
    flat = rt.Intersector(rt.tags.triangle_data, triangle_cull_mode="back").intersect(
        rays, rt.build_primitive_structure(rt.TriangleGeometry(baked))
    )
    np.testing.assert_array_equal(np.asarray(flat.type)[:2], np.asarray(result.type)[:2])


def test_primitive_structure_with_instancing_reports_no_instances():
    blas = rt.build_primitive_structure(rt.TriangleGeometry(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)))
    it = rt.Intersector(rt.tags.instancing, rt.tags.max_levels(2), rt.tags.world_space_data)
    result = it.intersect(
        rt.Ray(np.array([[0.2, 0.2, 1], [5, 5, 1]], np.float32), np.array([0, 0, -1], np.float32)), blas
    )
    assert np.asarray(result.instance_id).tolist() == [[-1, -1], [-1, -1]]
    assert np.asarray(result.instance_count).tolist() == [0, 0]
    np.testing.assert_array_equal(np.asarray(result.object_to_world_transform[0]), np.eye(3, 4))
    np.testing.assert_array_equal(np.asarray(result.world_to_object_transform[1]), np.zeros((3, 4)))


# --- validation -----------------------------------------------------------------------------------------------


def _blas():
    return rt.build_primitive_structure(rt.TriangleGeometry(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)))


def test_too_deep_nesting_names_both_depths():
    blas = _blas()
    eye = np.eye(3, 4, dtype=np.float32)[None]
    one = rt.build_instance_structure([blas], rt.Instances([0], eye))
    two = rt.build_instance_structure([one], rt.Instances([0], eye))
    three = rt.build_instance_structure([two, blas], rt.Instances([0, 1], np.concatenate([eye, eye])))
    assert (one.levels, two.levels, three.levels) == (1, 2, 3)
    rays = rt.Ray(np.zeros(3, np.float32), np.array([0, 0, 1], np.float32))
    with pytest.raises(ValueError, match=r"3 instance levels.*max_levels\(2\)"):
        rt.Intersector(rt.tags.instancing, rt.tags.max_levels(2)).intersect(rays, three)
    with pytest.raises(ValueError, match=r"2 instance level.*no tags.instancing.*handles 0"):
        rt.Intersector().intersect(rays, two)
    with pytest.raises(ValueError, match=r"world_space_data needs tags.instancing"):
        rt.Intersector(rt.tags.world_space_data)


def test_cycles_are_rejected_by_name():
    blas = _blas()
    scene = rt.build_instance_structure([blas], rt.Instances([0], np.eye(3, 4, dtype=np.float32)[None]))
    table = scene.root
    with pytest.raises(ValueError, match=r"cycle \(tables 0 -> 1 -> 0\)"):
        rt.InstanceAccelerationStructure(
            primitive_structures=(blas,), instance_tables=(table, table), children=((0, 2), (1,))
        )
    with pytest.raises(ValueError, match=r"cycle \(tables 0 -> 0\)"):
        rt.InstanceAccelerationStructure(primitive_structures=(blas,), instance_tables=(table,), children=((1,),))


@pytest.mark.parametrize(
    "transform, message",
    [
        (np.full((1, 3, 4), np.nan, np.float32), r"transform has a non-finite value nan at index \(0, 0, 0\)"),
        (np.zeros((1, 3, 4), np.float32), r"transform\[0\] is singular"),
        (np.array([[[1, 0, 0, 0], [1, 0, 0, 0], [0, 0, 1, 0]]], np.float32), r"transform\[0\] is singular"),
        (np.eye(3, 4, dtype=np.float32), r"transform must have shape \(N, 3, 4\)"),
    ],
)
def test_bad_transforms_are_rejected(transform, message):
    with pytest.raises(ValueError, match=message):
        rt.Instances([0], transform)


def test_bad_instances_are_rejected():
    eye = np.eye(3, 4, dtype=np.float32)[None]
    with pytest.raises(ValueError, match=r"structure_index\[0\] = 1 is out of range for 1 structures"):
        rt.build_instance_structure([_blas()], rt.Instances([1], eye))
    with pytest.raises(ValueError, match=r"structure_index\[0\] = -1 is negative"):
        rt.Instances([-1], eye)
    with pytest.raises(ValueError, match=r"count = 2 is outside \[0, 1\]"):
        rt.build_instance_structure([_blas()], rt.Instances([0], eye), count=2)
    with pytest.raises(ValueError, match=r"options\[0\] sets both OPAQUE and NON_OPAQUE"):
        rt.Instances([0], eye, options=rt.InstanceOptions.OPAQUE | rt.InstanceOptions.NON_OPAQUE)
    with pytest.raises(ValueError, match=r"mask values must be in \[0, 2\*\*32\)"):
        rt.Instances([0], eye, mask=-1)
    with pytest.raises(ValueError, match=r"need K >= 2 keyframes"):
        rt.Instances([0], eye[:, None])
    with pytest.raises(ValueError, match="keyframed.*instance motion.*motion=rt.MotionSpec"):
        rt.build_instance_structure([_blas()], rt.Instances([0], np.stack([eye, eye], axis=1)))
    with pytest.raises(TypeError, match=r"structures\[0\] is a str"):
        rt.build_instance_structure(["x"], rt.Instances([0], eye))
