"""The float64 brute-force oracle every intersection test compares against, and the tolerance table.

The oracle tests every ray against every triangle in float64, from the float32 (or float64) inputs the library
sees. For each ray/triangle pair it computes the three signed volumes ``e_i = d . (a_j x a_k)`` with
``a_i = v_i - o`` (the unsheared form of the watertight edge functions: the ray passes inside the triangle
when all three have one sign) and the plane distance ``t = n . (v0 - o) / n . d`` with
``n = (v1 - v0) x (v2 - v0)``.

Rounding in the library's single-precision test can flip an edge function whose magnitude is below an error
bound derived from the magnitudes it is computed from (``TOLERANCE[dtype].edge * |d| |a_j| |a_k|``). A pair
is therefore *certain* (every correct implementation hits it) when all three edge functions clear their bound
with one sign, and *possible* (a correct implementation may hit it) when none is beyond its bound with the
wrong sign. Distances get a derived tolerance from the same bounds: the watertight distance is
``sum(e_i z_i) / sum(e_i)`` with ``|z_i| <= sqrt(3) |a_i| / |d|``.

A library answer is correct when:
  * a miss: no certain hit;
  * a hit on triangle ``k``: ``k`` is possible, its distance is within tolerance of the float64 distance of
    ``k``, and no certain hit is closer by more than both tolerances (otherwise it is a tie, and either
    primitive id is right).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

import jaxrt as rt


@dataclasses.dataclass(frozen=True)
class Tolerance:
    """Error model of the library's ray/triangle test in one precision.

    Attributes:
      edge: relative bound on an edge function's rounding error: ``|err e_i| <= edge * |d| |a_j| |a_k|``.
      distance: relative rounding of the final division and of the vertex depths.
    """

    edge: float
    distance: float


_EPS32 = float(np.finfo(np.float32).eps)
_EPS64 = float(np.finfo(np.float64).eps)

#: The one tolerance table for distances and hit decisions, per input dtype.
TOLERANCE = {
    np.dtype(np.float32): Tolerance(edge=64 * _EPS32, distance=8 * _EPS32),
    np.dtype(np.float64): Tolerance(edge=64 * _EPS64, distance=8 * _EPS64),
}


class Reference(NamedTuple):
    """Per ray/triangle float64 facts, arrays of shape ``(R, T)``."""

    distance: np.ndarray  # plane distance (inf where the ray is parallel to the plane)
    tolerance: np.ndarray  # tolerance on ``distance``
    certain: np.ndarray  # every correct implementation reports a hit
    possible: np.ndarray  # a correct implementation may report a hit
    clockwise: np.ndarray  # +1 clockwise (n . d > 0), -1 counterclockwise, 0 undecidable in the dtype
    barycentric: np.ndarray  # (R, T, 2) weights of v1 and v2
    barycentric_tolerance: np.ndarray  # (R, T)


def _cross(a, b):
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def ray_enabled(origin, direction, min_distance, max_distance, mask=None) -> np.ndarray:
    """The library's disabled-ray rule, in numpy: finite rays, non-zero direction, min <= max, mask != 0."""
    origin, direction = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
    tmin, tmax = np.asarray(min_distance, np.float64), np.asarray(max_distance, np.float64)
    ok = np.isfinite(origin).all(-1) & np.isfinite(direction).all(-1) & (direction != 0).any(-1)
    ok &= ~np.isnan(tmin) & ~np.isnan(tmax) & (tmin <= tmax)
    if mask is not None:
        ok &= np.asarray(mask) != 0
    return ok


def brute_force(
    origin,
    direction,
    min_distance,
    max_distance,
    triangles,
    *,
    dtype=np.float32,
    cull: str = "none",
    front_facing_winding: str = "clockwise",
    pairs: bool = False,
) -> Reference:
    """Test every ray against every triangle in float64.

    Args:
      origin, direction: ``(R, 3)`` rays (as given to the library).
      min_distance, max_distance: ``(R,)`` intervals.
      triangles: ``(T, 3, 3)`` vertices; with ``pairs``, ``(R, 3, 3)``: one triangle per ray (the result then
        has ``T = 1``).
      dtype: the precision the library computes in (selects the tolerance row).
      cull, front_facing_winding: the intersector's options; culled pairs are neither certain nor possible
        unless their winding is undecidable in ``dtype``.
    """
    tol = TOLERANCE[np.dtype(dtype)]
    o = np.asarray(origin, np.float64)[:, None, :]
    d = np.asarray(direction, np.float64)
    tri = np.asarray(triangles, np.float64)
    tri = tri[:, None] if pairs else tri[None]  # (R or 1, T, 3, 3)
    tmin = np.asarray(min_distance, np.float64)[:, None]
    tmax = np.asarray(max_distance, np.float64)[:, None]
    enabled = ray_enabled(origin, direction, min_distance, max_distance)[:, None]
    d_safe = np.where(enabled[..., None], d[:, None, :], 1.0)

    a = [tri[..., i, :] - o for i in range(3)]  # (R, T, 3) each
    norm_a = [np.linalg.norm(x, axis=-1) for x in a]
    norm_d = np.linalg.norm(d_safe, axis=-1)
    e = [np.sum(d_safe * _cross(a[(i + 1) % 3], a[(i + 2) % 3]), axis=-1) for i in range(3)]
    b = [tol.edge * norm_d * norm_a[(i + 1) % 3] * norm_a[(i + 2) % 3] for i in range(3)]

    n = _cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])  # (R or 1, T, 3)
    det = np.sum(d_safe * n, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.sum(n * a[0], axis=-1) / det
    t = np.where(det == 0, np.inf, t)
    bound_sum = b[0] + b[1] + b[2]
    abs_det = np.abs(det)
    certain = ((e[0] > b[0]) & (e[1] > b[1]) & (e[2] > b[2])) | ((e[0] < -b[0]) & (e[1] < -b[1]) & (e[2] < -b[2]))
    possible = ((e[0] >= -b[0]) & (e[1] >= -b[1]) & (e[2] >= -b[2])) | (
        (e[0] <= b[0]) & (e[1] <= b[1]) & (e[2] <= b[2])
    )
    possible &= abs_det > 0  # an exactly coplanar ray has no single crossing to report

    z = [np.sqrt(3.0) * norm_a[i] / norm_d for i in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        tolerance = (
            sum(b[i] * (z[i] + np.abs(t)) for i in range(3)) + tol.distance * sum(np.abs(e[i]) * z[i] for i in range(3))
        ) / abs_det + tol.distance * np.abs(t)
        bary = np.stack([e[1] / det, e[2] / det], axis=-1)
        bary_tol = 2.0 * bound_sum / abs_det + tol.distance
    tolerance = np.where(np.isfinite(tolerance), tolerance, np.inf)

    with np.errstate(invalid="ignore"):  # inf - inf for rays parallel to a plane: NaN compares False
        certain &= (t - tolerance >= tmin) & (t + tolerance <= tmax) & enabled
        possible &= (t + tolerance >= tmin) & (t - tolerance <= tmax) & enabled

    clockwise = np.where(abs_det > bound_sum, np.sign(det), 0).astype(np.int8)
    if cull != "none":
        front = 1 if front_facing_winding == "clockwise" else -1
        culled = front if cull == "front" else -front
        certain &= clockwise == -culled
        possible &= clockwise != culled
    return Reference(t, tolerance, certain, possible, clockwise, bary, bary_tol)


def brute_force_chunked(origin, direction, min_distance, max_distance, triangles, *, budget=2_000_000, **kw):
    """:func:`brute_force` over chunks of rays so that ``R * T`` stays within ``budget`` pairs per chunk."""
    rays = np.asarray(origin).shape[0]
    step = max(1, budget // max(1, np.asarray(triangles).shape[0]))
    parts = [
        brute_force(
            origin[i : i + step],
            direction[i : i + step],
            min_distance[i : i + step],
            max_distance[i : i + step],
            triangles,
            **kw,
        )
        for i in range(0, rays, step)
    ]
    return Reference(*(np.concatenate(f, axis=0) for f in zip(*parts, strict=True)))


def global_index(geometry_id, primitive_id, counts) -> np.ndarray:
    """Index into the concatenated triangles of all geometries (``-1`` for misses)."""
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    geometry_id = np.asarray(geometry_id, np.int64)
    primitive_id = np.asarray(primitive_id, np.int64)
    return np.where(geometry_id >= 0, offsets[np.maximum(geometry_id, 0)] + primitive_id, -1)


def assert_finite_fields(result) -> None:
    """No NaN in any field of a result (``inf`` distances of misses are fine)."""
    for name, value in result.items():
        value = np.asarray(value)
        if np.issubdtype(value.dtype, np.floating):
            assert not np.isnan(value).any(), f"NaN in result field {name}: {value}"


def check_nearest(result, ref: Reference, counts, *, any_hit: bool = False, barycentrics: bool = True) -> list[str]:
    """Failures (as readable strings) of a flat result against the oracle; empty when all rays are right.

    With ``any_hit`` the reported hit need only be a possible one (not the nearest).
    """
    failures = []
    kind = np.asarray(result.type)
    distance = np.asarray(result.distance, np.float64)
    geometry = np.asarray(result.geometry_id)
    primitive = np.asarray(result.primitive_id)
    k_all = global_index(geometry, primitive, counts)
    bary = (
        np.asarray(result["triangle_barycentric_coord"], np.float64) if "triangle_barycentric_coord" in result else None
    )
    assert_finite_fields(result)
    for r in range(kind.shape[0]):
        certain = np.flatnonzero(ref.certain[r])
        if kind[r] == int(rt.IntersectionType.NONE):
            if not (np.isinf(distance[r]) and distance[r] > 0 and geometry[r] == -1 and primitive[r] == -1):
                failures.append(f"ray {r}: miss with distance {distance[r]}, ids ({geometry[r]}, {primitive[r]})")
            if certain.size:
                j = certain[np.argmin(ref.distance[r, certain])]
                failures.append(f"ray {r}: missed, but triangle {j} is certainly hit at {ref.distance[r, j]}")
            continue
        if kind[r] != int(rt.IntersectionType.TRIANGLE):
            failures.append(f"ray {r}: type {kind[r]}")
            continue
        k = k_all[r]
        if not (0 <= k < ref.distance.shape[1]) or primitive[r] < 0 or primitive[r] >= counts[geometry[r]]:
            failures.append(f"ray {r}: bad ids ({geometry[r]}, {primitive[r]})")
            continue
        if not ref.possible[r, k]:
            failures.append(f"ray {r}: hit triangle {k} at {distance[r]}, which the float64 reference misses")
            continue
        if abs(distance[r] - ref.distance[r, k]) > ref.tolerance[r, k]:
            failures.append(
                f"ray {r}: triangle {k} distance {distance[r]!r} vs float64 {ref.distance[r, k]!r} "
                f"(tolerance {ref.tolerance[r, k]:.3g})"
            )
        if not any_hit and certain.size:
            closer = certain[
                ref.distance[r, certain] + ref.tolerance[r, certain] < ref.distance[r, k] - ref.tolerance[r, k]
            ]
            if closer.size:
                j = closer[np.argmin(ref.distance[r, closer])]
                failures.append(
                    f"ray {r}: hit triangle {k} at {distance[r]}, but triangle {j} is nearer at {ref.distance[r, j]}"
                )
        if (
            bary is not None
            and barycentrics
            and np.any(np.abs(bary[r] - ref.barycentric[r, k]) > ref.barycentric_tolerance[r, k])
        ):
            failures.append(f"ray {r}: barycentrics {bary[r]} vs float64 {ref.barycentric[r, k]}")
    return failures


def crosses_loop(origin, direction, min_distance, max_distance, loop, *, dtype=np.float32) -> np.ndarray:
    """``(R,)`` whether each ray certainly crosses every surface spanning the closed vertex loop ``(L, 3)``.

    The loop is the boundary of a connected patch of triangles (a disk). A ray whose signed volumes with all
    consecutive boundary vertex pairs have one sign, each beyond its rounding bound, passes through the loop;
    with the whole patch in front of its origin and an unbounded interval it must hit the patch or something
    nearer, whatever the rounding inside the patch: this is what watertightness promises.
    """
    tol = TOLERANCE[np.dtype(dtype)]
    o = np.asarray(origin, np.float64)[:, None, :]
    d = np.asarray(direction, np.float64)[:, None, :]
    a = np.asarray(loop, np.float64)[None] - o  # (R, L, 3)
    b = np.roll(a, -1, axis=1)
    e = np.sum(d * _cross(a, b), axis=-1)
    bound = tol.edge * np.linalg.norm(d, axis=-1) * np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    inside = (e > bound).all(-1) | (e < -bound).all(-1)
    in_front = (np.sum(a * d, axis=-1) > 0).all(-1)
    unbounded = (np.asarray(min_distance) <= 0) & np.isposinf(np.asarray(max_distance))
    return inside & in_front & unbounded & ray_enabled(origin, direction, min_distance, max_distance)


def check_watertight(result, ref: Reference, crossing: np.ndarray, group: np.ndarray) -> list[str]:
    """Failures of rays that certainly cross a patch (``crossing``, from :func:`crosses_loop`) of the triangles
    ``group``: each must hit, no farther than the farthest crossing of a patch triangle."""
    failures = []
    kind = np.asarray(result.type)
    distance = np.asarray(result.distance, np.float64)
    t = np.where(np.isfinite(ref.distance[:, group]), ref.distance[:, group] + ref.tolerance[:, group], -np.inf)
    for r in np.flatnonzero(crossing):
        if kind[r] == int(rt.IntersectionType.NONE):
            failures.append(f"ray {r}: leaked through the patch")
        elif distance[r] > t[r].max():
            failures.append(f"ray {r}: hit at {distance[r]}, beyond the patch (at most {t[r].max()})")
    return failures


def assert_matches_reference(result, ref: Reference, counts, **kw) -> None:
    failures = check_nearest(result, ref, counts, **kw)
    assert not failures, f"{len(failures)} rays disagree with the float64 reference:\n" + "\n".join(failures[:20])


# --- meshes ---------------------------------------------------------------------------------------------------


def octahedron() -> tuple[np.ndarray, np.ndarray]:
    """Unit octahedron (vertices on the axes), outward counterclockwise faces seen from outside."""
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    f = []
    for x in (0, 1):
        for y in (2, 3):
            for z in (4, 5):
                tri = [x, y, z]
                if np.dot(np.cross(v[y] - v[x], v[z] - v[x]), v[x] + v[y] + v[z]) < 0:
                    tri = [x, z, y]
                f.append(tri)
    return v, np.array(f, np.int32)


def cube(lower=(-1.0, -1.0, -1.0), upper=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box as 12 triangles; each face split along a diagonal (a shared edge)."""
    lo, hi = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
    v = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)])
    quads = [(0, 2, 6, 4), (1, 5, 7, 3), (0, 4, 5, 1), (2, 3, 7, 6), (0, 1, 3, 2), (4, 6, 7, 5)]
    f = []
    for a, b, c, d in quads:
        f += [[a, b, c], [a, c, d]]
    f = np.array(f, np.int32)
    centre = v.mean(0)
    for i, (a, b, c) in enumerate(f):  # orient outward, counterclockwise from outside
        if np.dot(np.cross(v[b] - v[a], v[c] - v[a]), v[a] - centre) < 0:
            f[i] = [a, c, b]
    return v, f


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: ``20 * 4**subdivisions`` triangles, outward counterclockwise, closed."""
    p = (1 + 5**0.5) / 2
    v = [[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p], [0, -1, -p], [0, 1, -p]]
    v += [[p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]]
    verts = [np.array(x, np.float64) / np.linalg.norm(x) for x in v]
    faces = [
        [0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6],
        [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
        [8, 6, 7], [9, 8, 1],
    ]  # fmt: skip
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def midpoint(i, j, cache=cache):
            key = (min(i, j), max(i, j))
            if key not in cache:
                m = verts[i] + verts[j]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            new += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = new
    return np.array(verts), np.array(faces, np.int32)


def edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges ``(E, 2)`` of a triangle mesh."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def grid(nx: int, ny: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat ``nx`` by ``ny`` grid in the unit square of the z = 0 plane, two triangles per cell."""
    x, y = np.meshgrid(np.linspace(0, 1, nx + 1), np.linspace(0, 1, ny + 1), indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=-1)
    idx = np.arange(v.shape[0]).reshape(nx + 1, ny + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)])
    return v, f.astype(np.int32)


def grid_boundary(nx: int, ny: int) -> np.ndarray:
    """Vertex indices of the boundary loop of :func:`grid`, in order."""
    idx = np.arange((nx + 1) * (ny + 1)).reshape(nx + 1, ny + 1)
    return np.concatenate([idx[:-1, 0], idx[-1, :-1], idx[:0:-1, -1], idx[0, :0:-1]])


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# --- the tree ---------------------------------------------------------------------------------------------------


def assert_valid_tree(structure, triangles, counts) -> int:
    """Check a primitive structure against its node-layout contract; returns the deepest leaf's depth.

    Every real leaf is reachable from the root exactly once, every padding leaf and every internal node at
    most once (the LBVH links only the real leaves, at least two; the clustering tree also the padding), and
    the root covers every reachable leaf; rows no node references are empty; children split their parent's
    ``node_range`` into two contiguous halves; each child box is exactly the union of the boxes of the
    triangles under it (padding boxes are empty); every primitive of every geometry sits in one leaf with its
    own vertices; the depth is within ``structure.max_depth``.
    """
    children = np.asarray(structure.node_children)
    node_range = np.asarray(structure.node_range)
    lower = np.asarray(structure.node_lower, np.float64)
    upper = np.asarray(structure.node_upper, np.float64)
    leaf_geometry = np.asarray(structure.leaf_geometry)
    leaf_primitive = np.asarray(structure.leaf_primitive)
    leaf_triangle = np.asarray(structure.leaf_triangle, np.float64)
    capacity = structure.capacity
    total = int(sum(counts))
    assert capacity >= max(2, total) and capacity & (capacity - 1) == 0, capacity
    assert children.shape == (capacity - 1, 2) and node_range.shape == (capacity - 1, 2)
    assert lower.shape == upper.shape == (capacity - 1, 2, 3)
    assert leaf_geometry.shape == leaf_primitive.shape == (capacity,) and leaf_triangle.shape == (capacity, 3, 3)

    real = leaf_geometry >= 0
    assert real.sum() == total
    np.testing.assert_array_equal(leaf_primitive < 0, ~real)
    ids = global_index(leaf_geometry[real], leaf_primitive[real], counts)
    np.testing.assert_array_equal(np.sort(ids), np.arange(total))
    np.testing.assert_array_equal(leaf_triangle[real], np.asarray(triangles, np.float64)[ids])
    # Zero-area triangles (exactly zero cross product) get empty boxes: no ray can hit them.
    area = np.cross(leaf_triangle[:, 1] - leaf_triangle[:, 0], leaf_triangle[:, 2] - leaf_triangle[:, 0])
    enterable = real & np.any(area != 0, axis=-1)
    leaf_lo = np.where(enterable[:, None], leaf_triangle.min(axis=1), np.inf)
    leaf_hi = np.where(enterable[:, None], leaf_triangle.max(axis=1), -np.inf)

    linked = capacity if node_range[0, 1] == capacity - 1 else max(total, 2)
    assert tuple(node_range[0]) == (0, linked - 1), node_range[0]
    leaf_seen = np.zeros(capacity, np.int64)
    node_seen = np.zeros(capacity - 1, np.int64)
    deepest = 0
    stack = [(0, 1)]
    while stack:
        node, depth = stack.pop()
        node_seen[node] += 1
        assert node_seen[node] == 1, f"internal node {node} reached twice"
        deepest = max(deepest, depth)
        first, last = node_range[node]
        spans = []
        for side in range(2):
            child = children[node, side]
            if child < 0:
                k = -1 - child
                leaf_seen[k] += 1
                span = (k, k)
            else:
                span = tuple(node_range[child])
                stack.append((child, depth + 1))
            spans.append(span)
            a, b = span
            np.testing.assert_array_equal(lower[node, side], leaf_lo[a : b + 1].min(axis=0), err_msg=f"node {node}")
            np.testing.assert_array_equal(upper[node, side], leaf_hi[a : b + 1].max(axis=0), err_msg=f"node {node}")
        assert spans[0][0] == first and spans[0][1] + 1 == spans[1][0] and spans[1][1] == last, (node, spans)
    np.testing.assert_array_equal(leaf_seen[:linked], 1, err_msg="every linked leaf is reachable exactly once")
    np.testing.assert_array_equal(leaf_seen[linked:], 0, err_msg="leaves past the linked ones are unreachable")
    np.testing.assert_array_equal(node_seen[: linked - 1], 1, err_msg="every tree node is reachable exactly once")
    np.testing.assert_array_equal(node_seen[linked - 1 :], 0, err_msg="unused rows are unreachable")
    assert (lower[linked - 1 :] == np.inf).all() and (upper[linked - 1 :] == -np.inf).all(), "unused rows are empty"
    assert deepest <= structure.max_depth, (deepest, structure.max_depth)
    return deepest


def same_box_triangles(count: int, center=(4.0, -2.0, 8.0), half: float = 1.0, seed: int = 0) -> np.ndarray:
    """``count`` different, non-degenerate triangles with one and the same bounding box (so equal Morton codes).

    Vertex a is at ``(-h, -h, s)``, b at ``(h, s, h)``, c at ``(s, h, -h)`` relative to the centre, with the
    free coordinates ``s`` drawn in ``(-h, h)``.
    """
    rng = np.random.default_rng(seed)
    s = rng.uniform(-0.9, 0.9, (count, 3)) * half
    h = np.full(count, half)
    a = np.stack([-h, -h, s[:, 0]], -1)
    b = np.stack([h, s[:, 1], h], -1)
    c = np.stack([s[:, 2], h, -h], -1)
    return (np.stack([a, b, c], 1) + np.asarray(center)).astype(np.float32)


# --- tracing in shared shapes -------------------------------------------------------------------------------------

#: Ray batch for structures of up to :data:`SMALL_CAPACITY` primitives, and for larger ones. Tests trace in
#: these shapes (padding with disabled rays) and build with these capacities, so that they share compiled code.
SMALL_BATCH, LARGE_BATCH = 256, 4096
SMALL_CAPACITY, LARGE_CAPACITY = 256, 8192


def capacity_for(count: int) -> int:
    """The shared capacity bucket for ``count`` primitives."""
    if count <= SMALL_CAPACITY:
        return SMALL_CAPACITY
    if count <= LARGE_CAPACITY:
        return LARGE_CAPACITY
    return None


def trace(intersector, structure, origin, direction, min_distance=0.0, max_distance=np.inf, mask=0xFFFFFFFF):
    """Intersect ``(N, 3)`` rays in fixed-size batches padded with disabled rays; returns the result for N rays
    with numpy fields, and checks it for NaN and stack overflow."""
    direction = np.asarray(direction, np.float32)
    n = direction.shape[0]
    origin = np.broadcast_to(np.asarray(origin, np.float32), (n, 3))
    fields = [np.broadcast_to(np.asarray(a, dt), (n,)) for a, dt in
              ((min_distance, np.float32), (max_distance, np.float32), (mask, np.uint32))]  # fmt: skip
    batch = SMALL_BATCH if structure.capacity <= SMALL_CAPACITY else LARGE_BATCH
    total = -(-n // batch) * batch
    pad = lambda a: np.concatenate([a, np.zeros((total - n, *a.shape[1:]), a.dtype)])  # noqa: E731
    origin, direction, tmin, tmax, mask = (pad(a) for a in (origin, direction, *fields))
    parts = []
    for i in range(0, total, batch):
        s = slice(i, i + batch)
        parts.append(intersector.intersect(rt.Ray(origin[s], direction[s], tmin[s], tmax[s], mask[s]), structure))
    result = rt.IntersectionResult({k: np.concatenate([np.asarray(p[k]) for p in parts])[:n] for k in parts[0]})
    assert_finite_fields(result)
    if "stack_overflow" in result:
        assert not result.stack_overflow.any(), "traversal stack overflow"
    return result
