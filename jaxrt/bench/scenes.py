"""Benchmark scenes: procedural meshes (any size, deterministic from a seed) and the shared real meshes.

Every scene is plain NumPy data: ``vertices (V, 3) float32`` and ``indices (T, 3) int32``, so that any
tracer (jaxrt, Embree, a GPU library) can be fed the same triangles.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = [
    "Scene",
    "SHARED_MESHES",
    "PROCEDURAL",
    "noisy_sphere",
    "random_soup",
    "shared_mesh",
    "default_data_dir",
    "load_scene",
]


class Scene(NamedTuple):
    """A triangle mesh to trace, with an optional camera that frames it (see :func:`~jaxrt.bench.rays.primary_rays`)."""

    name: str
    vertices: np.ndarray
    """``(V, 3)`` float32 positions."""
    indices: np.ndarray
    """``(T, 3)`` int32 vertex indices."""
    description: str
    eye: tuple[float, float, float] | None = None
    """Camera position; ``None`` places it outside the bounding box (see ``primary_rays``)."""
    target: tuple[float, float, float] | None = None
    """Point the camera looks at; ``None``: the bounding-box centre."""

    @property
    def triangle_count(self) -> int:
        """Number of triangles."""
        return int(self.indices.shape[0])


def _cube_sphere_lattice(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer lattice points on the surface of the cube ``[0, m]^3`` and the triangles joining them.

    Each of the six faces is an ``m x m`` grid of quads split into two triangles; vertices on shared cube
    edges are merged, so the mesh is closed (every edge is shared by exactly two triangles).
    """
    i, j = np.meshgrid(np.arange(m + 1), np.arange(m + 1), indexing="ij")
    i, j = i.ravel(), j.ravel()
    points, faces = [], []
    for axis in range(3):
        for side in (0, m):
            p = np.empty((i.size, 3), np.int64)
            p[:, axis] = side
            p[:, (axis + 1) % 3] = i
            p[:, (axis + 2) % 3] = j
            base = sum(len(q) for q in points)
            cell = (np.arange(m)[:, None] * (m + 1) + np.arange(m)[None, :]).ravel()
            a, b, c, d = cell, cell + (m + 1), cell + (m + 2), cell + 1
            faces.append(base + np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))
            points.append(p)
    points = np.concatenate(points)
    faces = np.concatenate(faces)
    key = (points[:, 0] * (m + 1) + points[:, 1]) * (m + 1) + points[:, 2]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return points[first], inverse.reshape(-1)[faces]


def noisy_sphere(n_triangles: int = 100_000, seed: int = 0, *, noise: float = 0.1) -> Scene:
    """A closed, bumpy unit sphere of about ``n_triangles`` triangles (exactly ``12 m^2`` for the nearest m).

    A subdivided cube is projected onto the sphere (equi-angular, so triangles have similar areas), then
    each vertex is moved radially by a smooth random field (a sum of 24 plane waves of increasing frequency
    and decreasing amplitude, drawn from ``seed``). Shared vertices are shared in the index buffer, so the
    mesh is watertight; triangles wind counterclockwise seen from outside.

    Args:
      n_triangles: requested triangle count (at least 12).
      seed: random seed of the displacement field.
      noise: peak-to-peak scale of the radial displacement, relative to the radius.

    Returns:
      A :class:`Scene` named ``"sphere"``.
    """
    m = max(1, round(float(np.sqrt(max(n_triangles, 12) / 12.0))))
    lattice, indices = _cube_sphere_lattice(m)
    cube = np.tan((lattice / m * 2.0 - 1.0) * (np.pi / 4.0))  # equi-angular warp of [-1, 1]
    direction = cube / np.linalg.norm(cube, axis=1, keepdims=True)
    rng = np.random.default_rng(seed)
    waves = 24
    frequency = np.geomspace(2.0, 40.0, waves)
    axes = rng.normal(size=(waves, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    phase = rng.uniform(0.0, 2.0 * np.pi, waves)
    amplitude = 1.0 / frequency
    field = np.sin(direction @ (axes * frequency[:, None]).T + phase) @ amplitude / amplitude.sum()
    vertices = direction * (1.0 + 0.5 * noise * field)[:, None]
    # Orient every triangle outwards (counterclockwise seen from outside).
    tri = vertices[indices]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = np.einsum("ij,ij->i", normal, tri.sum(axis=1)) < 0
    indices[inward] = indices[inward][:, ::-1]
    return Scene(
        name="sphere",
        vertices=vertices.astype(np.float32),
        indices=indices.astype(np.int32),
        description=f"noisy closed sphere, {len(indices):,} triangles (seed {seed})",
    )


def random_soup(n_triangles: int = 100_000, seed: int = 0, *, size: float = 2.0) -> Scene:
    """Independent random triangles in the cube ``[-1, 1]^3`` (an unstructured, overlapping scene).

    Centres are uniform in the cube; each vertex is the centre plus a uniform offset in a cube of side
    ``size`` times the mean spacing of the centres (``2 / n^(1/3)``), so the soup is equally cluttered at
    every triangle count.

    Args:
      n_triangles: number of triangles.
      seed: random seed.
      size: triangle extent relative to the mean spacing of the centres.

    Returns:
      A :class:`Scene` named ``"soup"``; its index buffer is ``arange(3 T).reshape(T, 3)``.
    """
    rng = np.random.default_rng(seed)
    spacing = 2.0 / max(n_triangles, 1) ** (1.0 / 3.0)
    centre = rng.uniform(-1.0, 1.0, (n_triangles, 1, 3))
    vertices = centre + rng.uniform(-0.5, 0.5, (n_triangles, 3, 3)) * (size * spacing)
    return Scene(
        name="soup",
        vertices=vertices.reshape(-1, 3).astype(np.float32),
        indices=np.arange(3 * n_triangles, dtype=np.int32).reshape(n_triangles, 3),
        description=f"random triangle soup, {n_triangles:,} triangles (seed {seed})",
    )


#: Shared meshes by scene name: ``(path under the data folder, description, eye, target)``.
SHARED_MESHES: dict[str, tuple[str, str, tuple | None, tuple | None]] = {
    "bunny": ("stanford-bunny/bun_zipper.binary.ply", "Stanford bunny", None, None),
    "dragon": ("stanford-dragon-decimated/dragon_vrip_res3.obj.gz", "Stanford dragon (vrip res3)", None, None),
    # An interior: the camera stands at one end of the atrium and looks along it (z is up).
    "sponza": (
        "sponza-dabrovic-3ds/sponza.derived.ply",
        "Dabrovic Sponza (interior)",
        (-14.0, 0.0, 3.0),
        (14.0, 0.0, 5.0),
    ),
}

#: Procedural scenes by name: ``fn(n_triangles, seed) -> Scene``.
PROCEDURAL = {"sphere": noisy_sphere, "soup": random_soup}


def default_data_dir() -> Path | None:
    """The shared data folder: ``$JAXRT_DATA_DIR``, else ``../shared/data`` next to the repository, if present."""
    env = os.environ.get("JAXRT_DATA_DIR")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2].parent / "shared" / "data")
    candidates.append(Path.cwd().parent / "shared" / "data")
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    return None


def shared_mesh(name: str, data_dir: str | os.PathLike[str] | None = None) -> Scene:
    """Load one of :data:`SHARED_MESHES` from the shared data folder.

    Raises:
      KeyError: an unknown name. FileNotFoundError: the folder or the file is missing.
    """
    from jaxrt._src.io.meshes import load_mesh

    if name not in SHARED_MESHES:
        raise KeyError(f"shared_mesh: unknown scene {name!r}; known: {sorted(SHARED_MESHES)}")
    folder = Path(data_dir) if data_dir is not None else default_data_dir()
    if folder is None:
        raise FileNotFoundError("shared_mesh: no shared data folder (set JAXRT_DATA_DIR or pass data_dir)")
    relative, description, eye, target = SHARED_MESHES[name]
    vertices, indices = load_mesh(folder / relative)
    return Scene(name, vertices, indices, f"{description}, {len(indices):,} triangles", eye, target)


def load_scene(
    name: str, *, n_triangles: int = 100_000, seed: int = 0, data_dir: str | os.PathLike[str] | None = None
) -> Scene:
    """A procedural scene (``n_triangles``, ``seed``) or a shared mesh, by name."""
    if name in PROCEDURAL:
        return PROCEDURAL[name](n_triangles, seed)
    return shared_mesh(name, data_dir)
