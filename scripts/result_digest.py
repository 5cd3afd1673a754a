"""Every structure array and result field of a few small scenes, saved for a before/after comparison.

A refactor must leave results bit for bit as they were. Run this script with each checkout on the same machine
(the default backend picks the traversals: the GPU kernel on a GPU, the CPU traversal on the CPU, and the
portable one for both), then compare the two files::

    PYTHONPATH=/path/to/before python scripts/result_digest.py save before.npz
    PYTHONPATH=/path/to/after python scripts/result_digest.py save after.npz
    python scripts/result_digest.py compare before.npz after.npz

Scenes: triangles, triangles with curves, with boxes (built-in sphere function), keyframe motion, instances,
a refit and a compaction; queries: nearest with tags, ``max_hits``, a filter on non-opaque geometry, and a
gradient of distances with respect to vertices.
"""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np

import jaxrt as rt


def digest() -> dict[str, np.ndarray]:
    """The arrays to compare, by name."""
    rng = np.random.default_rng(0)
    out: dict[str, np.ndarray] = {}

    def save(prefix, tree):
        for i, x in enumerate(jax.tree_util.tree_leaves(tree)):
            out[f"{prefix}/{i}"] = np.asarray(x)

    tri = rng.normal(size=(60, 3)).astype(np.float32)
    mesh = rt.TriangleGeometry(tri)
    s = rt.build_primitive_structure(mesh)
    save("mesh", s)
    curves = rt.CurveGeometry(
        rng.normal(size=(16, 3)).astype(np.float32),
        np.full(16, 0.05, np.float32),
        np.arange(0, 12, 1),
        basis=rt.CurveBasis.CATMULL_ROM,
        control_point_count=4,
    )
    sc = rt.build_primitive_structure([mesh, curves])
    save("curves", sc)
    lo = rng.normal(size=(8, 3)).astype(np.float32)
    boxes = rt.BoundingBoxGeometry(lo, lo + 0.3)
    sb = rt.build_primitive_structure([mesh, boxes])
    save("boxes", sb)
    keys = np.stack([tri, tri + 0.1]).astype(np.float32)
    sm = rt.build_primitive_structure(rt.MotionTriangleGeometry(keys), motion=rt.MotionSpec(0.0, 1.0))
    save("motion", sm)
    inst = rt.build_instance_structure(
        [s],
        rt.Instances(
            np.zeros(3, np.int32),
            np.tile(np.eye(3, 4, dtype=np.float32), (3, 1, 1))
            + np.arange(3, dtype=np.float32)[:, None, None] * np.array([0, 0, 0, 1], np.float32),
        ),
    )
    save("inst", inst)
    save("refit", rt.refit(s, rt.TriangleGeometry(tri * 1.1)))
    save("compact", rt.compact(s))
    n = 256
    o = rng.normal(size=(n, 3)).astype(np.float32) * 3
    d = -o + rng.normal(size=(n, 3)).astype(np.float32)
    rays = rt.Ray(o, d, time=rng.uniform(size=n).astype(np.float32))
    for backend in ("portable", "auto"):
        save(
            f"r_mesh_{backend}",
            dict(rt.Intersector(rt.tags.triangle_data, rt.tags.stats, backend=backend).intersect(rays, s)),
        )
        save(
            f"r_curves_{backend}",
            dict(rt.Intersector(rt.tags.curve_data, rt.tags.triangle_data, backend=backend).intersect(rays, sc)),
        )
        fns = {1: rt.intersection_functions.sphere}
        save(
            f"r_boxes_{backend}", dict(rt.Intersector(intersection_functions=fns, backend=backend).intersect(rays, sb))
        )
        save(f"r_motion_{backend}", dict(rt.Intersector(rt.tags.primitive_motion, backend=backend).intersect(rays, sm)))
        save(
            f"r_inst_{backend}",
            dict(rt.Intersector(rt.tags.instancing, rt.tags.world_space_data, backend=backend).intersect(rays, inst)),
        )
        save(f"r_k_{backend}", dict(rt.Intersector(max_hits=3, backend=backend).intersect(rays, s)))
        alpha = rt.build_primitive_structure(rt.TriangleGeometry(tri, opaque=False))
        save(
            f"r_filter_{backend}",
            dict(rt.Intersector(filter=lambda c: c.primitive_id % 2 == 0, backend=backend).intersect(rays, alpha)),
        )
    g = jax.grad(
        lambda v: jnp.sum(
            rt.Intersector(rt.tags.triangle_data)
            .intersect(rays, rt.build_primitive_structure(rt.TriangleGeometry(v)))
            .distance.clip(0, 100)
        )
    )(jnp.asarray(tri))
    out["grad"] = np.asarray(g)
    return out


def compare(before: str, after: str) -> int:
    """Print the arrays that differ (dtype, shape or any bit; NaNs equal); the exit status counts them."""
    a, b = np.load(before), np.load(after)
    names = sorted(set(a.files) | set(b.files))
    differ = [
        n
        for n in names
        if n not in a.files
        or n not in b.files
        or a[n].dtype != b[n].dtype
        or a[n].shape != b[n].shape
        or not np.array_equal(a[n], b[n], equal_nan=a[n].dtype.kind == "f")
    ]
    print(f"{len(names)} arrays, {len(differ)} differ" + (": " + ", ".join(differ) if differ else ""))
    return len(differ)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "save":
        arrays = digest()
        np.savez(sys.argv[2], **arrays)
        print(f"{len(arrays)} arrays saved to {sys.argv[2]} ({jax.default_backend()})")
    elif len(sys.argv) == 4 and sys.argv[1] == "compare":
        sys.exit(min(compare(sys.argv[2], sys.argv[3]), 1))
    else:
        sys.exit("usage: result_digest.py save FILE | compare BEFORE AFTER")
