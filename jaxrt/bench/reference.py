"""The float64 reference and the error of a tracer against it.

Two references, both in float64 on the exact float32 input values (float32 vertices and rays are exact
in float64):

- ``"numpy"``: an independent tracer written here: a complete binary BVH over Morton-ordered triangles,
  traversed by all rays at once in NumPy, with a Möller–Trumbore test in float64. It shares no code with
  jaxrt's traversal, so a traversal bug cannot hide in the reference.
- ``"jaxrt-x64"``: jaxrt itself under ``jax.enable_x64`` with float64 geometry and rays.

On top of either, :func:`triangle_distances` recomputes in float64 the distance of the primitive a tracer
reported, so that a different primitive at the same distance (a shared edge or vertex: a tie) is told
apart from a wrong one.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaxrt.bench.rays import RayBatch

__all__ = [
    "Hits",
    "REFERENCES",
    "TIE_RTOL",
    "BARYCENTRIC_TOL",
    "reference_hits",
    "numpy_reference",
    "jaxrt_x64_reference",
    "triangle_distances",
    "error_stats",
    "occlusion_mismatches",
]

#: Two hits are a tie when their float64 distances differ by at most this, relative (about 8 float32 ulps).
TIE_RTOL = 1e-6
#: A reported primitive counts as hit in float64 when its smallest barycentric is at least ``-BARYCENTRIC_TOL``.
BARYCENTRIC_TOL = 1e-6


class Hits(NamedTuple):
    """Closest hits of ``N`` rays."""

    distance: np.ndarray
    """``(N,)``; ``inf`` on a miss."""
    primitive: np.ndarray
    """``(N,)`` int; ``-1`` on a miss."""


def _morton_order(centroid: np.ndarray) -> np.ndarray:
    """Indices sorting ``centroid`` along a 30-bit Morton curve (10 bits per axis)."""
    lower, upper = centroid.min(axis=0), centroid.max(axis=0)
    q = ((centroid - lower) / np.maximum(upper - lower, 1e-300) * 1023.0).astype(np.uint64)
    code = np.zeros(len(centroid), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + (2 - axis))
    return np.argsort(code, kind="stable")


class _Float64Bvh:
    """A complete binary BVH in heap order: node ``k`` has children ``2k``, ``2k+1``; leaves are ``C..2C-1``."""

    def __init__(self, vertices: np.ndarray, indices: np.ndarray):
        tri = vertices.astype(np.float64)[indices]
        order = _morton_order(tri.mean(axis=1))
        capacity = 1 << max(0, (len(tri) - 1).bit_length())
        lower = np.full((2 * capacity, 3), np.inf)
        upper = np.full((2 * capacity, 3), -np.inf)
        lower[capacity : capacity + len(tri)] = tri[order].min(axis=1)
        upper[capacity : capacity + len(tri)] = tri[order].max(axis=1)
        level = capacity
        while level > 1:
            parent = np.arange(level // 2, level)
            lower[parent] = np.minimum(lower[2 * parent], lower[2 * parent + 1])
            upper[parent] = np.maximum(upper[2 * parent], upper[2 * parent + 1])
            level //= 2
        # Widen every box by a hair so that rounding in the float64 slab test cannot cull a grazed box.
        pad = 1e-9 * float(np.max(np.abs(tri))) + 1e-300
        self.lower, self.upper = lower - pad, upper + pad
        self.leaf_primitive = np.full(capacity, -1, np.int64)
        self.leaf_primitive[: len(tri)] = order
        self.triangles = tri
        self.capacity = capacity

    def closest(self, origin: np.ndarray, direction: np.ndarray, t_max: np.ndarray) -> Hits:
        n = len(origin)
        o, d = origin.astype(np.float64), direction.astype(np.float64)
        with np.errstate(divide="ignore"):
            inv = 1.0 / np.where(d == 0.0, np.copysign(1e-300, d), d)
        best_t = t_max.astype(np.float64).copy()
        best_p = np.full(n, -1, np.int64)
        depth = self.capacity.bit_length() + 1
        stack = np.zeros((n, depth), np.int64)
        stack[:, 0] = 1
        size = np.ones(n, np.int64)
        active = np.arange(n)
        while active.size:
            size[active] -= 1
            node = stack[active, size[active]]
            # Near and far slabs by the direction's sign (not min/max), so empty boxes (+inf, -inf) are missed.
            positive = inv[active] >= 0.0
            t0 = (np.where(positive, self.lower[node], self.upper[node]) - o[active]) * inv[active]
            t1 = (np.where(positive, self.upper[node], self.lower[node]) - o[active]) * inv[active]
            enter = np.maximum(t0.max(axis=1), 0.0)
            leave = np.minimum(t1.min(axis=1), best_t[active])
            hit = enter <= leave
            leaf = node >= self.capacity
            test = hit & leaf
            if test.any():
                rays = active[test]
                primitive = self.leaf_primitive[node[test] - self.capacity]
                real = primitive >= 0
                rays, primitive = rays[real], primitive[real]
                t, margin = _moller_trumbore(self.triangles[primitive], o[rays], d[rays])
                better = (margin >= 0.0) & (t >= 0.0) & (t < best_t[rays])
                best_t[rays[better]] = t[better]
                best_p[rays[better]] = primitive[better]
            push = hit & ~leaf
            rays, parent = active[push], node[push]
            stack[rays, size[rays]] = 2 * parent + 1
            stack[rays, size[rays] + 1] = 2 * parent
            size[rays] += 2
            active = active[size[active] > 0]
        return Hits(np.where(best_p >= 0, best_t, np.inf), best_p)


def _moller_trumbore(tri: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Float64 plane distance and smallest barycentric of rays ``(N, 3)`` against triangles ``(N, 3, 3)``.

    The margin is ``-inf`` for a ray parallel to a (or a degenerate) triangle.
    """
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = det != 0.0
    inv = 1.0 / np.where(ok, det, 1.0)
    s = o - tri[:, 0]
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, q) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    margin = np.where(ok, np.minimum(np.minimum(u, v), 1.0 - u - v), -np.inf)
    return np.where(ok, t, np.inf), margin


def numpy_reference(vertices: np.ndarray, indices: np.ndarray, rays: RayBatch) -> Hits:
    """Closest hits from the independent float64 NumPy tracer (see the module docstring)."""
    return _Float64Bvh(vertices, indices).closest(rays.origin, rays.direction, rays.max_distance)


def jaxrt_x64_reference(vertices: np.ndarray, indices: np.ndarray, rays: RayBatch) -> Hits:
    """Closest hits from jaxrt under ``jax.enable_x64`` with float64 geometry and rays."""
    import jax

    import jaxrt as rt

    with jax.enable_x64(True):
        structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices.astype(np.float64), indices))
        ray = rt.Ray(
            rays.origin.astype(np.float64), rays.direction.astype(np.float64), 0.0, rays.max_distance.astype(np.float64)
        )
        result = rt.Intersector(backend="portable").intersect(ray, structure)
        return Hits(np.asarray(result.distance, np.float64), np.asarray(result.primitive_id, np.int64))


#: Reference tracers by name.
REFERENCES = {"numpy": numpy_reference, "jaxrt-x64": jaxrt_x64_reference}


def reference_hits(vertices: np.ndarray, indices: np.ndarray, rays: RayBatch, *, method: str = "numpy") -> Hits:
    """Float64 closest hits of ``rays`` with the reference called ``method`` (a key of :data:`REFERENCES`)."""
    if method not in REFERENCES:
        raise ValueError(f"reference_hits: method must be one of {sorted(REFERENCES)}, got {method!r}")
    return REFERENCES[method](vertices, indices, rays)


def triangle_distances(
    vertices: np.ndarray, indices: np.ndarray, rays: RayBatch, primitive: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Float64 distance along each ray to the plane of ``primitive`` and the smallest barycentric there.

    Independent of any tracer: used to check the primitive each tracer reported. Entries with
    ``primitive < 0`` get ``(inf, -inf)``.
    """
    valid = primitive >= 0
    tri = vertices.astype(np.float64)[indices[np.where(valid, primitive, 0)]]
    t, margin = _moller_trumbore(tri, rays.origin.astype(np.float64), rays.direction.astype(np.float64))
    return np.where(valid, t, np.inf), np.where(valid, margin, -np.inf)


def _percentile(x: np.ndarray, q: float) -> float:
    return float(np.percentile(x, q)) if x.size else 0.0


def error_stats(vertices: np.ndarray, indices: np.ndarray, rays: RayBatch, hits: Hits, reference: Hits) -> dict:
    """Errors of a tracer's closest hits against the reference, on the same rays.

    Returns:
      A dict: ``rays``; ``hit_mismatch`` (hit in one, miss in the other); ``primitive_mismatch`` (both hit,
      different primitives, and not a tie: the reported primitive's float64 distance is more than
      :data:`TIE_RTOL` from the reference's, or the ray misses it in float64 by more than
      :data:`BARYCENTRIC_TOL`); ``ties``; ``distance_max_rel`` and ``distance_p99_rel`` (relative distance
      error against the reference over rays both hit); ``own_primitive_max_rel`` (against the float64
      distance of the primitive the tracer reported itself: its arithmetic error alone).
    """
    hit, ref_hit = hits.primitive >= 0, reference.primitive >= 0
    both = hit & ref_hit
    differs = both & (hits.primitive != reference.primitive)
    own_t, own_margin = triangle_distances(vertices, indices, rays, hits.primitive)
    ref_t = reference.distance.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        tie = differs & (np.abs(own_t - ref_t) <= TIE_RTOL * np.abs(ref_t)) & (own_margin >= -BARYCENTRIC_TOL)
        rel = np.abs(hits.distance[both].astype(np.float64) - ref_t[both]) / np.abs(ref_t[both])
        own_rel = np.abs(hits.distance[hit].astype(np.float64) - own_t[hit]) / np.abs(own_t[hit])
    return {
        "rays": int(len(rays)),
        "reference_hits": int(ref_hit.sum()),
        "hit_mismatch": int((hit != ref_hit).sum()),
        "primitive_mismatch": int((differs & ~tie).sum()),
        "ties": int(tie.sum()),
        "distance_max_rel": float(rel.max()) if rel.size else 0.0,
        "distance_p99_rel": _percentile(rel, 99.0),
        "own_primitive_max_rel": float(own_rel.max()) if own_rel.size else 0.0,
    }


def occlusion_mismatches(occluded: np.ndarray, reference: Hits) -> int:
    """Rays whose any-hit answer (occluded or not) disagrees with the reference's closest hit."""
    return int((np.asarray(occluded, bool) != (reference.primitive >= 0)).sum())
