"""Peer tracers on the same machine and rays: Embree through embreex, and Open3D's ``RaycastingScene``.

embreex's ``EmbreeScene.run`` loops over the batch in compiled code calling Embree's single-ray
``rtcIntersect1``/``rtcOccluded1`` and holds the Python GIL while it does, so tracing runs on **one
thread** (splitting a batch over Python threads does not run them at the same time). Embree's build
(``rtcCommitScene``) uses its own TBB worker threads, one per core. embreex fixes ``tnear = 0``; rays here
have ``min_distance = 0`` as well. The scene uses Embree's default build quality and flags (not
``robust``).

Open3D's ``RaycastingScene`` (Embree underneath) is what a user who wants bulk ray casting on the CPU reaches
for: its ``cast_rays`` and ``test_occlusions`` trace a batch on every core by default (``threads=0``).
"""

from __future__ import annotations

import importlib.metadata
from typing import Any

import numpy as np

from jaxrt.bench.rays import RayBatch
from jaxrt.bench.reference import Hits

__all__ = ["Embree", "Open3D", "embree_unavailable_reason", "open3d_unavailable_reason"]


def embree_unavailable_reason() -> str | None:
    """Why Embree cannot run here (embreex missing), or ``None`` when it can."""
    try:
        import embreex.mesh_construction  # noqa: F401
        import embreex.rtcore_scene  # noqa: F401
    except ImportError as error:
        return f"embreex is not installed ({error}); pip install embreex"
    return None


class Embree:
    """Embree 4 through embreex: build a scene once, then trace batches of rays.

    Args:
      vertices: ``(V, 3)`` float32.
      indices: ``(T, 3)`` int32.
    """

    name = "embree"
    #: Threads that trace (see the module docstring).
    trace_threads = 1

    def __init__(self, vertices: np.ndarray, indices: np.ndarray):
        self.vertices = np.ascontiguousarray(vertices, np.float32)
        self.indices = np.ascontiguousarray(indices, np.int32)
        self.scene: Any = None

    @staticmethod
    def version() -> str:
        """The installed embreex version."""
        return importlib.metadata.version("embreex")

    def build(self) -> None:
        """Create the scene and commit it (embreex commits on the first trace, so one ray is traced)."""
        from embreex import mesh_construction, rtcore_scene

        scene = rtcore_scene.EmbreeScene()
        mesh_construction.TriangleMesh(scene, self.vertices, self.indices)
        scene.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32))
        self.scene = scene

    @staticmethod
    def _far(rays: RayBatch) -> np.ndarray | None:
        far = np.ascontiguousarray(rays.max_distance, np.float32)
        return None if np.isinf(far).all() else np.where(np.isinf(far), np.float32(1e37), far)

    def closest(self, rays: RayBatch) -> Hits:
        """Nearest hits (``inf`` / ``-1`` on a miss)."""
        out = self.scene.run(
            np.ascontiguousarray(rays.origin), np.ascontiguousarray(rays.direction), dists=self._far(rays), output=1
        )
        primitive = out["primID"].astype(np.int64)
        return Hits(np.where(primitive >= 0, out["tfar"], np.inf), primitive)

    def any_hit(self, rays: RayBatch) -> np.ndarray:
        """Whether each ray hits anything (occlusion query)."""
        out = self.scene.run(
            np.ascontiguousarray(rays.origin),
            np.ascontiguousarray(rays.direction),
            dists=self._far(rays),
            query="OCCLUDED",
        )
        return np.asarray(out) >= 0


def open3d_unavailable_reason() -> str | None:
    """Why Open3D cannot run here (``open3d`` missing or failing to import), or ``None`` when it can."""
    try:
        import open3d  # noqa: F401
    except Exception as error:  # noqa: BLE001 - a broken install (missing system library) raises OSError too
        return f"open3d cannot be imported ({type(error).__name__}: {error}); pip install open3d-cpu"
    return None


class Open3D:
    """Open3D's ``RaycastingScene``: build once, then trace batches on ``threads`` threads (0: every core).

    Args:
      vertices: ``(V, 3)`` float32.
      indices: ``(T, 3)`` int32.
      threads: the ``nthreads`` of Open3D's queries (0: Open3D's default, every core).
    """

    name = "open3d"

    def __init__(self, vertices: np.ndarray, indices: np.ndarray, threads: int = 0):
        self.vertices = np.ascontiguousarray(vertices, np.float32)
        self.indices = np.ascontiguousarray(indices, np.uint32)
        self.threads = int(threads)
        self.scene: Any = None

    @staticmethod
    def version() -> str:
        """The installed Open3D version."""
        import open3d

        return str(open3d.__version__)

    def build(self) -> None:
        """Create the scene and trace one ray (Open3D builds its Embree scene on the first query)."""
        import open3d

        scene = open3d.t.geometry.RaycastingScene()
        scene.add_triangles(open3d.core.Tensor(self.vertices), open3d.core.Tensor(self.indices))
        scene.cast_rays(open3d.core.Tensor(np.array([[0, 0, 0, 0, 0, 1]], np.float32)))
        self.scene = scene

    @staticmethod
    def _rays(rays: RayBatch) -> Any:
        import open3d

        return open3d.core.Tensor(np.concatenate([rays.origin, rays.direction], axis=1).astype(np.float32))

    def closest(self, rays: RayBatch) -> Hits:
        """Nearest hits (``inf`` / ``-1`` on a miss; Open3D takes no ``tfar``: hits past ``max_distance`` are
        dropped afterwards)."""
        out = self.scene.cast_rays(self._rays(rays), nthreads=self.threads)
        distance = out["t_hit"].numpy()
        hit = np.isfinite(distance) & (distance <= np.asarray(rays.max_distance, np.float32))
        primitive = np.where(hit, out["primitive_ids"].numpy().astype(np.int64), -1)
        return Hits(np.where(hit, distance, np.inf), primitive)

    def any_hit(self, rays: RayBatch) -> np.ndarray:
        """Whether each ray hits anything (occlusion query; Open3D takes one ``tfar`` for the whole batch)."""
        far = np.asarray(rays.max_distance, np.float32)
        if not (far == far[0]).all():
            raise ValueError("Open3D.any_hit: Open3D takes one tfar per batch; got rays with different max_distance")
        out = self.scene.test_occlusions(self._rays(rays), tfar=float(far[0]), nthreads=self.threads)
        return out.numpy().astype(bool)
