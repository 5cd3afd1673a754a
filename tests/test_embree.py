"""jaxrt against Embree (through embreex) on the Stanford bunny and dragon from the shared data folder
(``$JAXRT_DATA_DIR``, else ``../shared/data``).

Both trace the same float32 rays against the same float32 triangles. Where they disagree (hit or miss,
primitive, or distance), and on a sample of rays where they agree, jaxrt must match the float64 brute-force
oracle; Embree's own disagreements with the oracle are reported in the failure message only.
"""

from __future__ import annotations

import gzip
import io

import numpy as np
import pytest
from conftest import data_dir
from reference import brute_force_chunked, check_nearest

import jaxrt as rt

DATA = data_dir()  # $JAXRT_DATA_DIR, else shared/data beside the repository
MESHES = {
    "bunny": ("stanford-bunny/bun_zipper.binary.ply", "stanford-bunny/stanford-bunny.obj.gz"),
    "dragon": ("stanford-dragon-decimated/dragon_vrip_res3.obj.gz",),
}
RAYS = 4096
EMBREE_MISS = 1e30  # embreex reports tfar = 1e37 for a miss


def _load(name):
    trimesh = pytest.importorskip("trimesh", reason="trimesh is needed to read the shared meshes")
    for relative in MESHES[name]:
        path = DATA / relative
        if not path.is_file():
            continue
        if path.suffix == ".gz":
            data, kind = io.BytesIO(gzip.decompress(path.read_bytes())), path.with_suffix("").suffix[1:]
        else:
            data, kind = io.BytesIO(path.read_bytes()), path.suffix[1:]
        mesh = trimesh.load(data, file_type=kind, force="mesh", process=False)
        return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)
    pytest.skip(f"no {name} mesh under {DATA} (looked for {', '.join(MESHES[name])})")


def _rays(vertices, faces, rng):
    """Half the rays aimed at surface points (vertices, edge midpoints, interiors), half at the bounding box,
    all from a sphere around the mesh."""
    lo, hi = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    center, radius = (lo + hi) / 2, np.linalg.norm(hi - lo)
    start = rng.normal(size=(RAYS, 3))
    origin = center + radius * start / np.linalg.norm(start, axis=-1, keepdims=True)
    tri = vertices[faces[rng.integers(0, len(faces), RAYS)]].astype(np.float64)
    kind = rng.integers(0, 3, RAYS)[:, None]
    bary = np.where(kind == 0, np.eye(3)[rng.integers(0, 3, RAYS)], rng.dirichlet(np.ones(3), RAYS))
    edge = np.stack([np.roll([0.5, 0.5, 0.0], k) for k in rng.integers(0, 3, RAYS)])
    bary = np.where(kind == 1, edge, bary)
    target = np.einsum("rv,rvk->rk", bary, tri)
    half = RAYS // 2
    target[half:] = rng.uniform(lo, hi, (RAYS - half, 3))
    return origin.astype(np.float32), (target - origin).astype(np.float32)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(MESHES))
def test_against_embree(name):
    if not DATA.is_dir():
        pytest.skip(f"shared data folder {DATA} is absent")
    rtcore_scene = pytest.importorskip("embreex.rtcore_scene", reason="embreex is not installed")
    mesh_construction = pytest.importorskip("embreex.mesh_construction", reason="embreex is not installed")
    vertices, faces = _load(name)
    rng = np.random.default_rng(2024)
    origin, direction = _rays(vertices, faces, rng)

    structure = rt.build_primitive_structure(rt.TriangleGeometry(vertices, faces))
    result = rt.Intersector().intersect(rt.Ray(origin, direction), structure)
    prim = np.asarray(result.primitive_id)
    distance = np.asarray(result.distance, np.float64)

    scene = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(scene, vertices, faces)
    embree = scene.run(origin, direction, output=1)
    e_prim = np.where(embree["tfar"] < EMBREE_MISS, embree["primID"], -1)
    e_distance = np.where(e_prim >= 0, embree["tfar"].astype(np.float64), np.inf)

    close = np.isclose(distance, e_distance, rtol=1e-4, atol=0) | (np.isinf(distance) & np.isinf(e_distance))
    disagree = np.flatnonzero(~close)  # hit against miss, or another distance
    ties = np.flatnonzero(close & (prim != e_prim))  # e.g. rays through shared vertices and edges
    hits = (prim >= 0).mean()
    assert 0.3 < hits < 0.95, f"the rays should mix hits and misses, got {hits:.0%} hits"
    assert len(disagree) < RAYS // 100, f"jaxrt and Embree disagree on {len(disagree)} of {RAYS} rays"

    sample = rng.choice(np.setdiff1d(np.arange(RAYS), np.concatenate([disagree, ties])), 64, replace=False)
    rows = np.concatenate([disagree, ties, sample])
    triangles = vertices[faces]
    ref = brute_force_chunked(
        origin[rows], direction[rows], np.zeros(len(rows)), np.full(len(rows), np.inf), triangles, budget=400_000
    )
    sub = rt.IntersectionResult({k: np.asarray(v)[rows] for k, v in result.items()})
    failures = check_nearest(sub, ref, (len(faces),))
    e_sub = rt.IntersectionResult(
        {"type": (e_prim[rows] >= 0).astype(np.int32), "distance": e_distance[rows],
         "primitive_id": e_prim[rows], "geometry_id": np.where(e_prim[rows] >= 0, 0, -1)}
    )  # fmt: skip
    embree_failures = check_nearest(e_sub, ref, (len(faces),))
    assert not failures, (
        f"{name}: jaxrt disagrees with the float64 reference on {len(failures)} of {len(rows)} checked rays "
        f"(Embree on {len(embree_failures)}; {len(disagree)} rays disagree, {len(ties)} ties):\n"
        + "\n".join(failures[:10])
    )
