"""Curves below instances: instanced hair against the same curves moved to world space and traced without
instances, and against the float64 curve reference in each instance's object space; gradients.

Curves below instances are traced in object space (as Metal, OptiX and Embree do): under a rigid transform
with a uniform scale ``s`` the instanced curve is the world-space curve with radii times ``s``; under a
non-uniform scale it is the object-space tube seen through the transform. The reference therefore tests every
instance chain's object-space ray against the object-space segments (float64), for every kind of transform.

Every scene of a level count has the same shapes (one level: an inner structure instancing the hair twice and
a triangle mesh once; two levels: a top structure instancing the inner one twice and the hair once more, so
chains of one and two levels), and the traces share one intersector, so each level count compiles its trace
once. The gradient test traces linear strands, whose exact test compiles faster.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_curves_primitive import BAND, DISTANCE, EPS32, ROUNDING, aimed_rays
from test_curves_structure import hair
from test_instancing import oracle, random_rotation

import jaxrt as rt
from jaxrt.bench.curves import host_segments, reference_hits

CURVE = int(rt.IntersectionType.CURVE)
TRIANGLE = int(rt.IntersectionType.TRIANGLE)
NONE = int(rt.IntersectionType.NONE)
INTERSECTOR = rt.Intersector(
    rt.tags.instancing, rt.tags.max_levels(2), rt.tags.curve_data, rt.tags.triangle_data, rt.tags.world_space_data
)
FLAT = rt.Intersector(rt.tags.curve_data, rt.tags.triangle_data)
STRANDS = 4  # of 3 Catmull-Rom segments each
RADIUS = 0.06
RAYS = 64
#: Barycentric margin of the triangle reference (as in test_instancing).
MARGIN = 2e-4


@dataclasses.dataclass
class Chain:
    """One path from the top structure to a primitive structure."""

    instances: tuple[int, ...]  # local instance index at each level, outermost first
    matrix: np.ndarray  # (4, 4) float64 object-to-world (the float32 transforms composed exactly)
    kind: str  # "curve" or "triangle"


@dataclasses.dataclass
class Scene:
    structure: rt.InstanceAccelerationStructure
    curves: rt.CurveGeometry
    triangles: np.ndarray  # (T, 3, 3) float32 object space
    chains: list[Chain]


def transform(rng, kind: str) -> np.ndarray:
    """A rigid transform, one with a uniform scale, or one with a non-uniform scale (mirrored half the time)."""
    a = random_rotation(rng)
    if kind == "uniform":
        a = a * 10.0 ** rng.uniform(-0.3, 0.3)
    elif kind == "nonuniform":
        a = a @ np.diag(10.0 ** rng.uniform(-0.3, 0.3, 3)) @ random_rotation(rng)
        if rng.uniform() < 0.5:
            a = a @ np.diag([-1.0, 1.0, 1.0])
    t = rng.uniform(-2.0, 2.0, 3)
    return np.concatenate([a, t[:, None]], axis=1).astype(np.float32)


def square(m: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3] = m.astype(np.float64)
    return out


def random_scene(seed: int, kind: str, levels: int = 2) -> Scene:
    """Two levels: the top places the inner structure twice and the strands once; one level: the inner
    structure (the strands twice, the mesh once)."""
    rng = np.random.default_rng(seed)
    curves = hair(seed=seed, strands=STRANDS, end_caps="sphere", radius=RADIUS)
    triangles = (rng.uniform(-1, 1, (4, 1, 3)) + 0.7 * rng.normal(size=(4, 3, 3))).astype(np.float32)
    hair_structure = rt.build_primitive_structure(curves)
    mesh_structure = rt.build_primitive_structure(rt.TriangleGeometry(triangles.reshape(-1, 3)))
    inner_transforms = np.stack([transform(rng, kind) for _ in range(3)])
    inner = rt.build_instance_structure([hair_structure, mesh_structure], rt.Instances([0, 0, 1], inner_transforms))
    if levels == 1:
        chains = [Chain((j,), square(m), "curve" if j < 2 else "triangle") for j, m in enumerate(inner_transforms)]
        return Scene(inner, curves, triangles, chains)
    top_transforms = np.stack([transform(rng, kind) for _ in range(3)])
    top = rt.build_instance_structure([inner, hair_structure], rt.Instances([0, 0, 1], top_transforms))
    chains = []
    for i in range(2):
        for j in range(3):
            matrix = square(top_transforms[i]) @ square(inner_transforms[j])
            chains.append(Chain((i, j), matrix, "curve" if j < 2 else "triangle"))
    chains.append(Chain((2,), square(top_transforms[2]), "curve"))
    return Scene(top, curves, triangles, chains)


def world_curves(scene: Scene) -> rt.CurveGeometry:
    """Every instanced strand in world space, chain after chain (radii times the chain's uniform scale)."""
    points = np.asarray(scene.curves.control_points, np.float64)
    radii = np.asarray(scene.curves.radii, np.float64)
    indices = np.asarray(scene.curves.indices)
    moved, scaled, first = [], [], []
    for chain in (c for c in scene.chains if c.kind == "curve"):
        linear = chain.matrix[:3, :3]
        first.append(indices + sum(len(p) for p in moved))
        moved.append(points @ linear.T + chain.matrix[:3, 3])
        scaled.append(radii * abs(np.linalg.det(linear)) ** (1 / 3))
    return rt.CurveGeometry(
        np.concatenate(moved).astype(np.float32),
        np.concatenate(scaled).astype(np.float32),
        np.concatenate(first),
        basis=scene.curves.basis,
        control_point_count=scene.curves.control_point_count,
        curve_type=scene.curves.curve_type,
        end_caps=scene.curves.end_caps,
    )


def world_triangles(scene: Scene) -> np.ndarray:
    return np.concatenate(
        [
            scene.triangles.astype(np.float64) @ c.matrix[:3, :3].T + c.matrix[:3, 3]
            for c in scene.chains
            if c.kind == "triangle"
        ]
    )


def rays(seed: int, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Rays aimed near the world-space strands, a few at the triangles, a few in random directions."""
    rng = np.random.default_rng(seed + 1)
    origin, direction = aimed_rays(rng, world_curves(scene), RAYS)
    triangles = world_triangles(scene)
    target = triangles[rng.integers(0, len(triangles), 8)].mean(axis=1)
    origin[-12:-4] = target + rng.normal(size=(8, 3)) * 4.0
    direction[-12:-4] = (target - origin[-12:-4]) * rng.uniform(0.3, 2.0, (8, 1))
    direction[-4:] = rng.normal(size=(4, 3))
    return origin.astype(np.float32), direction.astype(np.float32)


def trace(intersector, structure, origin, direction) -> dict:
    result = intersector.intersect(rt.Ray(jnp.asarray(origin), jnp.asarray(direction)), structure)
    return jax.tree_util.tree_map(np.asarray, dict(result))


# --- the float64 reference, chain by chain in object space -------------------------------------------------------


@dataclasses.dataclass
class Candidates:
    """Per ray, every hit of every chain: ``(chain, primitive, kind, t, tolerance)``, and undecided rays."""

    hits: list[list[tuple[int, int, int, float, float]]]
    ambiguous: np.ndarray  # (R,) bool: some decision is within the reference's band (grazing rays)

    def nearest(self, r: int):
        return min(self.hits[r], key=lambda h: h[3]) if self.hits[r] else None

    def unique(self, r: int) -> bool:
        """The nearest hit is clear of every other hit of the ray (by their tolerances)."""
        ordered = sorted(self.hits[r], key=lambda h: h[3])
        return len(ordered) < 2 or ordered[1][3] - ordered[0][3] > 2 * (ordered[0][4] + ordered[1][4])


def reference(scene: Scene, origin: np.ndarray, direction: np.ndarray) -> Candidates:
    r = len(origin)
    segments = host_segments(scene.curves)
    s = segments.points.shape[0]
    ray_index, segment_index = np.repeat(np.arange(r), s), np.tile(np.arange(s), r)
    radius = float(np.max(np.asarray(scene.curves.radii)))
    points = np.asarray(scene.curves.control_points, np.float64)
    hits: list[list] = [[] for _ in range(r)]
    ambiguous = np.zeros(r, bool)
    for c, chain in enumerate(scene.chains):
        inverse = np.linalg.inv(chain.matrix)
        o = origin.astype(np.float64) @ inverse[:3, :3].T + inverse[:3, 3]
        d = direction.astype(np.float64) @ inverse[:3, :3].T
        length = np.linalg.norm(d, axis=1)
        if chain.kind == "curve":
            # Float32 rounding of the object-space ray: the world coordinates' rounding carried through the
            # chain's inverse, on top of the curve test's own (in object units).
            world_scale = np.linalg.norm(origin, axis=1) + 1.0
            spread = np.linalg.norm(inverse[:3, :3], 2)
            scale = np.max(np.linalg.norm(points[None] - o[:, None], axis=-1), axis=1) + spread * world_scale
            rounding = ROUNDING * EPS32 * scale
            ref = reference_hits(
                o,
                d,
                np.zeros(r),
                np.full(r, np.inf),
                segments,
                ray_index,
                segment_index,
                band=BAND * radius + rounding[ray_index],
            )
            np.logical_or.at(ambiguous, ray_index, ref.ambiguous)
            allowed = (DISTANCE * radius + rounding) / length
            for k in np.flatnonzero(ref.hit):
                ray = int(ray_index[k])
                hits[ray].append((c, int(segment_index[k]), CURVE, float(ref.distance[k]), float(allowed[ray])))
        else:
            world = scene.triangles.astype(np.float64) @ chain.matrix[:3, :3].T + chain.matrix[:3, 3]
            t, bary_min, _, _ = oracle(origin, direction, world)
            ambiguous |= ((t > 0) & (np.abs(bary_min) <= MARGIN)).any(axis=1)
            for ray, k in zip(*np.nonzero((t > 0) & (bary_min > MARGIN)), strict=True):
                hits[ray].append((c, int(k), TRIANGLE, float(t[ray, k]), 1e-4 * (1.0 + float(t[ray, k]))))
    return Candidates(hits, ambiguous)


def check_against_reference(result: dict, scene: Scene, origin, direction) -> int:
    """Every decided ray: hit or miss, distance, and (where the nearest hit is clear) chain, primitive, type.

    Returns the number of curve hits checked.
    """
    ref = reference(scene, origin, direction)
    failures, checked = [], 0
    for r in range(len(origin)):
        if ref.ambiguous[r]:
            continue
        nearest = ref.nearest(r)
        if nearest is None:
            if result["type"][r] != NONE:
                failures.append(f"ray {r}: hit at {result['distance'][r]}, the reference misses")
            continue
        c, primitive, kind, t, allowed = nearest
        if result["type"][r] == NONE:
            failures.append(f"ray {r}: missed, the reference hits chain {c} at {t}")
            continue
        if abs(float(result["distance"][r]) - t) > allowed:
            failures.append(f"ray {r}: distance {result['distance'][r]} vs reference {t} (allowed {allowed:.3g})")
        if not ref.unique(r):
            continue
        chain = scene.chains[c]
        got_chain = tuple(int(i) for i in result["instance_id"][r][: result["instance_count"][r]])
        if (result["type"][r], got_chain, result["primitive_id"][r]) != (kind, chain.instances, primitive):
            failures.append(
                f"ray {r}: type {result['type'][r]} chain {got_chain} primitive {result['primitive_id'][r]}, "
                f"reference type {kind} chain {chain.instances} primitive {primitive}"
            )
            continue
        expected = chain.matrix[:3]
        if np.abs(result["object_to_world_transform"][r] - expected).max() > 1e-4 * (1 + np.abs(expected).max()):
            failures.append(f"ray {r}: object_to_world {result['object_to_world_transform'][r]} vs {expected}")
        checked += kind == CURVE
    assert not failures, f"{len(failures)} of {len(origin)} rays wrong:\n" + "\n".join(failures[:12])
    return checked


# --- tests --------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("seed", "kind", "levels"), [(0, "rigid", 2), (1, "uniform", 2), (2, "nonuniform", 2), (3, "nonuniform", 1)]
)
def test_instanced_curves_against_the_float64_reference_in_object_space(seed, kind, levels):
    scene = random_scene(seed, kind, levels)
    assert scene.structure.levels == levels
    origin, direction = rays(seed, scene)
    result = trace(INTERSECTOR, scene.structure, origin, direction)
    assert check_against_reference(result, scene, origin, direction) > RAYS // 3
    curve = result["type"] == CURVE
    assert set(range(1, levels + 1)) <= set(result["instance_count"][curve].tolist())
    assert (result["curve_parameter"][curve] >= 0).all() and (result["curve_parameter"][curve] <= 1).all()
    assert (result["curve_parameter"][~curve] == 0).all()
    assert (result["triangle_barycentric_coord"][curve] == 0).all() and not result["triangle_front_facing"][curve].any()
    miss = result["type"] == NONE
    assert (result["primitive_id"][miss] == -1).all() and (result["instance_id"][miss] == -1).all()


@pytest.mark.parametrize(("seed", "kind"), [(3, "rigid"), (4, "uniform")])
def test_instanced_curves_equal_world_space_curves(seed, kind):
    """Rigid transforms with a uniform scale: the instanced trace equals a trace of the curves moved to world
    space (radii scaled), except on grazing rays the reference cannot decide."""
    scene = random_scene(seed, kind)
    origin, direction = rays(seed, scene)
    instanced = trace(INTERSECTOR, scene.structure, origin, direction)
    curves = world_curves(scene)
    flat = trace(
        FLAT,
        rt.build_primitive_structure([curves, rt.TriangleGeometry(world_triangles(scene).reshape(-1, 3))]),
        origin,
        direction,
    )
    ref = reference(scene, origin, direction)
    decided = ~ref.ambiguous
    np.testing.assert_array_equal(instanced["type"][decided], flat["type"][decided])
    both = decided & (instanced["type"] != NONE)
    radius = float(np.max(np.asarray(curves.radii)))
    length = np.linalg.norm(direction, axis=1)
    allowed = 1e-5 * (np.abs(flat["distance"]) + np.linalg.norm(origin, axis=1) / length) + 2e-3 * radius / length
    gap = np.abs(instanced["distance"][both] - flat["distance"][both])
    np.testing.assert_array_less(gap, allowed[both])
    # The same strand segment of the same instance chain, where the nearest hit is clear.
    curve_chains = [c.instances for c in scene.chains if c.kind == "curve"]
    segments = scene.curves.primitive_count
    clear = both & (instanced["type"] == CURVE) & np.array([ref.unique(r) for r in range(len(origin))])
    for r in np.flatnonzero(clear):
        got = tuple(int(i) for i in instanced["instance_id"][r][: instanced["instance_count"][r]])
        k = int(flat["primitive_id"][r])
        assert (got, int(instanced["primitive_id"][r])) == (curve_chains[k // segments], k % segments), r
    np.testing.assert_allclose(instanced["curve_parameter"][clear], flat["curve_parameter"][clear], atol=2e-3)
    assert clear.sum() > RAYS // 3


def test_gradients_with_respect_to_transforms_control_points_and_rays():
    """Two levels: the outer structure places the inner one (two instances of the strands) and the strands
    once more. Gradients are finite, obey the translation identities of each level, and match central
    differences for the linear parts."""
    # Linear segments (the exact round-cone test compiles faster; the re-computation is the same for every basis).
    curves = hair(seed=5, strands=2, basis="linear", count=2, end_caps="sphere", radius=0.1)
    rng = np.random.default_rng(6)
    inner = np.stack([transform(rng, "uniform"), transform(rng, "uniform")])
    outer = np.stack([transform(rng, "uniform"), transform(rng, "uniform")])
    chains = [Chain((0, j), square(outer[0]) @ square(inner[j]), "curve") for j in range(2)]
    chains.append(Chain((1,), square(outer[1]), "curve"))
    scene = Scene(None, curves, np.zeros((0, 3, 3), np.float32), chains)
    # Rays at the centre lines (hits held fixed by small moves).
    origin, direction = aimed_rays(rng, world_curves(scene), 48, spread=0.4)
    intersector = rt.Intersector(
        rt.tags.instancing, rt.tags.max_levels(2), rt.tags.curve_data, rt.tags.world_space_data
    )
    weights = jnp.asarray(rng.uniform(0.5, 1.5, len(origin)), jnp.float32)

    @jax.jit
    def loss_and_grad(inner, outer, points, ray_origin):
        def loss(inner, outer, points, ray_origin):
            geometry = rt.CurveGeometry(
                points, curves.radii, curves.indices, basis="linear", control_point_count=2, end_caps="sphere"
            )
            strands = rt.build_primitive_structure(geometry)
            placed = rt.build_instance_structure([strands], rt.Instances([0, 0], inner))
            structure = rt.build_instance_structure([placed, strands], rt.Instances([0, 1], outer))
            result = intersector.intersect(rt.Ray(ray_origin, jnp.asarray(direction)), structure)
            hit = result.type == CURVE
            value = jnp.sum(jnp.where(hit, weights * result.distance + result.curve_parameter, 0.0))
            return value, dict(result)

        return jax.value_and_grad(loss, argnums=(0, 1, 2, 3), has_aux=True)(inner, outer, points, ray_origin)

    args = (jnp.asarray(inner), jnp.asarray(outer), curves.control_points, jnp.asarray(origin))
    (_, result), grads = loss_and_grad(*args)
    result = jax.tree_util.tree_map(np.asarray, result)
    assert check_against_reference(result, scene, origin, direction) > len(origin) // 2
    grad_inner, grad_outer, grad_points, grad_origin = (np.asarray(g, np.float64) for g in grads)
    assert all(np.isfinite(g).all() for g in grads)
    assert np.abs(grad_inner).max() > 0 and np.abs(grad_outer).max() > 0 and np.abs(grad_points).max() > 0

    # Moving an instance is moving the rays that hit it the other way (through the outer linear part below it).
    curve = result["type"] == CURVE
    chain = np.where(curve[:, None], result["instance_id"], -9)
    along = -np.stack([grad_origin[(chain[:, 0] == i)].sum(axis=0) for i in range(2)])
    np.testing.assert_allclose(grad_outer[:, :, 3], along, rtol=1e-3, atol=1e-3)
    a = outer[0, :, :3].astype(np.float64)
    for j in range(2):
        moved = -grad_origin[(chain[:, 0] == 0) & (chain[:, 1] == j)].sum(axis=0)
        np.testing.assert_allclose(grad_inner[j, :, 3], a.T @ moved, rtol=1e-3, atol=1e-3)
    # Moving every control point by delta is moving each instance just above the strands by its linear part
    # times delta.
    from_instances = sum(inner[j, :, :3].astype(np.float64).T @ grad_inner[j, :, 3] for j in range(2))
    from_instances += outer[1, :, :3].astype(np.float64).T @ grad_outer[1, :, 3]
    np.testing.assert_allclose(grad_points.sum(axis=0), from_instances, rtol=1e-3, atol=1e-3)
    # Linear parts of both levels against central differences (the hits stay the same for these small moves).
    step = 1e-3
    for which, index in [(0, (0, 0, 0)), (0, (1, 2, 1)), (1, (0, 1, 2)), (1, (1, 0, 1))]:
        plus, minus = list(args), list(args)
        bump = np.zeros_like(np.asarray(args[which]))
        bump[index] = step
        plus[which], minus[which] = args[which] + bump, args[which] - bump
        (up, up_result), _ = loss_and_grad(*plus)
        (down, down_result), _ = loss_and_grad(*minus)
        assert np.array_equal(np.asarray(up_result["primitive_id"]), np.asarray(down_result["primitive_id"]))
        numeric = (float(up) - float(down)) / (2 * step)
        analytic = (grad_inner, grad_outer)[which][index]
        np.testing.assert_allclose(analytic, numeric, rtol=3e-2, atol=3e-2, err_msg=f"level {which} {index}")


def test_declarations_are_checked_below_instances():
    scene = random_scene(7, "rigid").structure
    ray = rt.Ray(jnp.zeros((1, 3)), jnp.array([[0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match=r"holds geometry kinds \['curve'\].*geometry_types=\['triangle'\]"):
        rt.Intersector(rt.tags.instancing, rt.tags.max_levels(2), geometry_types="triangle").intersect(ray, scene)
    with pytest.raises(ValueError, match="curve_type='round', but the intersector declares curve_type='flat'"):
        rt.Intersector(rt.tags.instancing, rt.tags.max_levels(2), curve_type="flat").intersect(ray, scene)
