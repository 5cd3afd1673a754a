"""Hair loaders: TressFX .tfx v3/v4 (synthetic files, and the shared assets when present) and .hair."""

from __future__ import annotations

import struct

import numpy as np
import pytest

import jaxrt as rt
from jaxrt._src.curves import bezier_segments
from jaxrt._src.io.hair import load_hair, read_hair, read_tfx, strands_to_curves, write_hair
from jaxrt.bench.scenes import default_data_dir

DATA = default_data_dir()


def _tfx(path, points, version):
    """A minimal TressFX file: ``points`` ``(strands, per_strand, 3)``."""
    strands, per_strand, _ = points.shape
    if version == 3:
        header = struct.pack("<fIIII", 3.0, strands, per_strand, 0, 0) + bytes(4 * 31)
        header += struct.pack("<6I", 296, 0, 0, 0, 0, 0) + bytes(4 * 32)
        body = points.astype("<f4").tobytes()
    else:
        header = struct.pack("<fII5I", 4.0, strands, per_strand, 160, 0, 0, 0, 0) + bytes(4 * 32)
        w = np.zeros((strands, per_strand, 1), np.float32)
        body = np.concatenate([points, w], axis=-1).astype("<f4").tobytes()
    path.write_bytes(header + body)


@pytest.mark.parametrize("version", [3, 4])
def test_tfx_round_trip(tmp_path, version):
    points = np.random.default_rng(0).normal(size=(3, 5, 3)).astype(np.float32)
    path = tmp_path / f"hair{version}.tfx"
    _tfx(path, points, version)
    strands = read_tfx(path)
    np.testing.assert_array_equal(strands.points, points.reshape(-1, 3))
    np.testing.assert_array_equal(strands.counts, [5, 5, 5])
    assert strands.radii is None
    with pytest.raises(ValueError, match="pass width="):
        load_hair(path)
    curves = load_hair(path, width=0.2)
    assert len(curves.indices) == 3 * 4 and np.allclose(curves.radii, 0.1)


def test_tfx_bad_files(tmp_path):
    path = tmp_path / "bad.tfx"
    path.write_bytes(struct.pack("<fII", 5.0, 1, 1) + bytes(300))
    with pytest.raises(ValueError, match="version 5.0"):
        read_tfx(path)
    _tfx(path, np.zeros((2, 4, 3), np.float32), 3)
    path.write_bytes(path.read_bytes()[:-8])
    with pytest.raises(ValueError, match="need bytes up to"):
        read_tfx(path)


def test_hair_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    counts = np.array([2, 6, 1, 4])
    points = rng.normal(size=(counts.sum(), 3)).astype(np.float32)
    thickness = rng.uniform(0.1, 0.3, counts.sum()).astype(np.float32)
    path = tmp_path / "fixture.hair"
    write_hair(path, points, counts, thickness=thickness, info="jaxrt test")
    strands = read_hair(path)
    np.testing.assert_array_equal(strands.points, points)
    np.testing.assert_array_equal(strands.counts, counts)
    np.testing.assert_allclose(strands.radii, thickness / 2)
    path.write_bytes(b"HAIX" + path.read_bytes()[4:])
    with pytest.raises(ValueError, match="signed 'HAIR'"):
        read_hair(path)


@pytest.mark.parametrize("basis", ["linear", "catmull_rom", "bspline"])
def test_curves_pass_through_the_strand_ends(basis):
    rng = np.random.default_rng(2)
    counts = np.array([4, 1, 7])
    points = np.cumsum(rng.normal(size=(counts.sum(), 3)), axis=0).astype(np.float32)
    strands = read_like(points, counts, radius=0.05)
    curves = strands_to_curves(strands, basis=basis)
    geometry = curves.geometry(end_caps="sphere")
    assert geometry.primitive_count == (4 - 1) + (7 - 1)  # the 1-point strand is dropped
    bezier = np.asarray(bezier_segments(geometry))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    # Every strand starts at its first point and ends at its last; interpolating bases hit every point.
    np.testing.assert_allclose(bezier[0, 0, :3], points[0], atol=1e-5)
    np.testing.assert_allclose(bezier[2, 3, :3], points[3], atol=1e-5)
    np.testing.assert_allclose(bezier[3, 0, :3], points[starts[2]], atol=1e-5)
    np.testing.assert_allclose(bezier[-1, 3, :3], points[-1], atol=1e-5)
    if basis != "bspline":
        np.testing.assert_allclose(bezier[1, 0, :3], points[1], atol=1e-5)


def read_like(points, counts, radius):
    from jaxrt._src.io.hair import HairStrands

    return HairStrands(points, counts, np.full(len(points), radius, np.float32))


TFX = {
    "tressfx-hair-ponytail/tail.tfx": (474, 16, 3),
    "tressfx-fur-bear/bear.tfx": (48113, 4, 3),
    "tressfx-hair-sintel/sintel_hair.tfx": (228, 32, 4),
    "tressfx-hair-ratboy-mohawk/Ratboy_mohawk.tfx": (2228, 32, 4),
}


@pytest.mark.parametrize("name", list(TFX))
def test_shared_tressfx_assets(name):
    if DATA is None or not (DATA / name).is_file():
        pytest.skip(f"{name} is not in the shared data folder (set JAXRT_DATA_DIR)")
    strands_count, per_strand, _ = TFX[name]
    strands = read_tfx(DATA / name)
    assert len(strands.counts) == strands_count and (strands.counts == per_strand).all()
    curves = load_hair(DATA / name, width=0.1)
    geometry = rt.CurveGeometry(*curves[:3], **curves.options)
    assert geometry.primitive_count == strands_count * (per_strand - 1)


def test_bench_pieces_without_tracing():
    """The curve bench's scene, tubes and reference (numpy only; the traced part runs in the bench itself)."""
    from jaxrt.bench.curves import camera_rays, hair_ball, reference_scene, tessellate

    geometry = hair_ball(2000).geometry()
    triangles = tessellate(geometry, 4, 2)
    assert triangles.shape == (geometry.primitive_count * 4 * 2 * 2, 3, 3)
    origin, direction = camera_rays(geometry, 256)
    hit, distance, ambiguous = reference_scene(origin, direction, geometry, band=1e-4)
    assert hit.any() and np.isfinite(distance[hit]).all() and len(ambiguous) == 256
