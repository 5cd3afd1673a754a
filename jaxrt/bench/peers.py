"""Peer tracers on the same machine and rays: Embree through embreex.

embreex's ``EmbreeScene.run`` loops over the batch in compiled code calling Embree's single-ray
``rtcIntersect1``/``rtcOccluded1`` and holds the Python GIL while it does, so tracing runs on **one
thread** (splitting a batch over Python threads does not run them at the same time). Embree's build
(``rtcCommitScene``) uses its own TBB worker threads, one per core. embreex fixes ``tnear = 0``; rays here
have ``min_distance = 0`` as well. The scene uses Embree's default build quality and flags (not
``robust``).
"""

from __future__ import annotations

import importlib.metadata
from typing import Any

import numpy as np

from jaxrt.bench.rays import RayBatch
from jaxrt.bench.reference import Hits

__all__ = ["Embree", "embree_unavailable_reason"]


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
