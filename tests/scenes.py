"""Random scenes and rays for the property tests, with log-uniform scales and positions up to 1e5 away.

Every scene has the same triangle count split the same way over three geometries, and every ray batch the
same size, so that a property test compiles its build and traversal once.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import strategies as st
from reference import edges, grid, grid_boundary, random_rotation

import jaxrt as rt

#: Triangles per geometry in every random scene: a connected grid patch (indexed), a soup without indices,
#: and an indexed soup.
GEOMETRY_COUNTS = (24, 16, 8)
TRIANGLES = sum(GEOMETRY_COUNTS)
RAYS = 256


@dataclasses.dataclass
class Scene:
    geometries: list
    triangles: np.ndarray  # (T, 3, 3) float32, concatenated in geometry order
    counts: tuple[int, ...]
    center: np.ndarray
    scale: float
    patch_loop: np.ndarray  # (L, 3) boundary loop of the grid patch (geometry 0)
    patch_points: np.ndarray  # (P, 3) interior vertices and interior edge midpoints of the patch


@dataclasses.dataclass
class Rays:
    origin: np.ndarray
    direction: np.ndarray
    min_distance: np.ndarray
    max_distance: np.ndarray

    def ray(self) -> rt.Ray:
        return rt.Ray(self.origin, self.direction, self.min_distance, self.max_distance)


def _log_uniform(rng, lo_exp, hi_exp, size=None):
    return 10.0 ** rng.uniform(lo_exp, hi_exp, size)


def random_scene(seed: int, far_exp: float | None, scale_exp: float) -> Scene:
    """A scene around a centre ``10**far_exp`` from the origin (``None``: at the origin).

    The scale is at least ``2e-4`` times the distance of the centre, so vertices stay well apart in float32.
    """
    rng = np.random.default_rng(seed)
    center = np.zeros(3) if far_exp is None else rng.normal(size=3)
    if far_exp is not None:
        center *= 10.0**far_exp / np.linalg.norm(center)
    scale = max(10.0**scale_exp, 2e-4 * float(np.linalg.norm(center)))

    # A grid patch (shared edges and vertices), rotated and placed at random.
    gv, gf = grid(4, 3)
    size = scale * _log_uniform(rng, -1, 0.3)
    gv = (gv - 0.5) * size @ random_rotation(rng).T + center + rng.uniform(-scale, scale, 3)
    patch_vertices = gv.astype(np.float32)

    def soup(count):
        anchor = center + rng.uniform(-scale, scale, (count, 1, 3))
        extent = scale * _log_uniform(rng, -2, 0, (count, 1, 1))
        return (anchor + extent * rng.normal(size=(count, 3, 3))).astype(np.float32)

    soup_triangles = soup(GEOMETRY_COUNTS[1])
    indexed = soup(GEOMETRY_COUNTS[2]).reshape(-1, 3)
    perm = rng.permutation(indexed.shape[0])
    indexed_vertices = indexed[perm]
    indexed_faces = np.argsort(perm).reshape(-1, 3).astype(np.int32)

    geometries = [
        rt.TriangleGeometry(patch_vertices, gf),
        rt.TriangleGeometry(soup_triangles.reshape(-1, 3)),
        rt.TriangleGeometry(indexed_vertices, indexed_faces),
    ]
    triangles = np.concatenate([patch_vertices[gf], soup_triangles, indexed_vertices[indexed_faces]])
    boundary = grid_boundary(4, 3)
    pv = patch_vertices.astype(np.float64)
    interior = np.setdiff1d(np.arange(pv.shape[0]), boundary)
    inner_edges = [e for e in edges(gf) if not (np.isin(e, boundary).all())]
    points = np.concatenate([pv[interior], np.array([pv[e].mean(0) for e in inner_edges])])
    return Scene(geometries, triangles, GEOMETRY_COUNTS, center, scale, pv[boundary], points)


def random_rays(seed: int, scene: Scene, count: int = RAYS, *, intervals: bool = True) -> Rays:
    """Rays aimed at triangle points (interior, vertices, edge midpoints, just outside) and random rays.

    A quarter of the aimed rays are axis-parallel. With ``intervals``, some rays get a finite
    ``[min_distance, max_distance]`` around their target, a few of them empty (disabled).
    """
    rng = np.random.default_rng(seed)
    tri = scene.triangles.astype(np.float64)
    k = rng.integers(0, tri.shape[0], count)
    kind = rng.uniform(size=count)
    bary = rng.dirichlet(np.ones(3), count)
    vertex = np.eye(3)[rng.integers(0, 3, count)]
    edge = np.stack([np.roll([0.5, 0.5, 0.0], s) for s in rng.integers(0, 3, count)])
    outside = rng.uniform(-0.1, 1.1, (count, 3))
    outside /= outside.sum(-1, keepdims=True)
    bary = np.where((kind < 0.2)[:, None], vertex, bary)
    bary = np.where(((kind >= 0.2) & (kind < 0.4))[:, None], edge, bary)
    bary = np.where(((kind >= 0.4) & (kind < 0.55))[:, None], outside, bary)
    target = np.einsum("rv,rvk->rk", bary, tri[k])
    on_patch = (kind >= 0.55) & (kind < 0.75)
    target = np.where(on_patch[:, None], scene.patch_points[rng.integers(0, len(scene.patch_points), count)], target)

    unit = rng.normal(size=(count, 3))
    unit /= np.linalg.norm(unit, axis=-1, keepdims=True)
    axis = rng.uniform(size=count) < 0.25
    one_hot = np.eye(3)[rng.integers(0, 3, count)] * rng.choice([-1.0, 1.0], (count, 1))
    unit = np.where(axis[:, None], one_hot, unit)
    length = _log_uniform(rng, -2, 2, (count, 1))
    along = scene.scale * _log_uniform(rng, -2, 0.7, count)
    origin = target - unit * along[:, None]

    wild = rng.uniform(size=count) < 0.2
    origin = np.where(wild[:, None], scene.center + rng.uniform(-2, 2, (count, 3)) * scene.scale, origin)
    origin = origin.astype(np.float32)
    direction = (unit * length).astype(np.float32)
    t_target = along / length[:, 0]

    tmin = np.zeros(count)
    tmax = np.full(count, np.inf)
    if intervals:
        bounded = rng.uniform(size=count) < 0.3
        tmin = np.where(bounded, t_target * rng.uniform(0, 1.2, count), tmin)
        tmax = np.where(bounded, tmin + t_target * rng.uniform(-0.1, 2, count), tmax)
    return Rays(origin, direction, tmin.astype(np.float32), tmax.astype(np.float32))


#: Hypothesis strategies for :func:`random_scene` and :func:`random_rays` arguments.
seeds = st.integers(0, 2**32 - 1)
far_exponents = st.one_of(st.none(), st.floats(-2.0, 5.0))
scale_exponents = st.floats(-1.0, 3.0)
