"""``rt.io.load_mesh`` refuses what it would misread: unsupported formats, glTF GPU instancing; warns for several
glTF scenes. Synthetic files (one triangle, buffers in ``data:`` URIs) so nothing depends on the shared data."""

from __future__ import annotations

import base64
import json
import struct
import warnings

import numpy as np
import pytest
from conftest import data_dir

import jaxrt as rt

pytest.importorskip("trimesh")

TRIANGLE = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)


def _gltf(path, *, instancing=False, scenes=1):
    """A one-triangle glTF file: optionally with EXT_mesh_gpu_instancing (3 copies) or several scenes."""
    blob = TRIANGLE.tobytes()
    views = [dict(buffer=0, byteOffset=0, byteLength=len(blob))]
    accessors = [dict(bufferView=0, componentType=5126, count=3, type="VEC3", min=[0, 0, 0], max=[1, 1, 0])]
    node = dict(mesh=0)
    document = dict(asset=dict(version="2.0"), meshes=[dict(primitives=[dict(attributes=dict(POSITION=0))])])
    if instancing:
        shifts = np.array([[0, 0, 0], [2, 0, 0], [4, 0, 0]], np.float32).tobytes()
        views.append(dict(buffer=0, byteOffset=len(blob), byteLength=len(shifts)))
        accessors.append(dict(bufferView=1, componentType=5126, count=3, type="VEC3"))
        node["extensions"] = {"EXT_mesh_gpu_instancing": {"attributes": {"TRANSLATION": 1}}}
        document["extensionsUsed"] = ["EXT_mesh_gpu_instancing"]
        blob += shifts
    uri = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
    document.update(
        buffers=[dict(byteLength=len(blob), uri=uri)],
        bufferViews=views,
        accessors=accessors,
        nodes=[node],
        scenes=[dict(nodes=[0])] * scenes,
        scene=0,
    )
    path.write_text(json.dumps(document))
    return path


def test_unsupported_format_names_the_file_and_the_formats(tmp_path):
    for name in ("model.3ds", "model.xyzzy", "model.3ds.gz"):
        path = tmp_path / name
        path.write_bytes(b"\0" * 64)
        with pytest.raises(ValueError, match=r"load_mesh: cannot read .*" + name.replace(".", r"\.")) as error:
            rt.io.load_mesh(path)
        assert ".obj" in str(error.value) and ".ply" in str(error.value) and "not supported" in str(error.value)


def test_shared_3ds_file_raises_value_error():
    path = data_dir() / "sibenik-3ds" / "sibenik.3ds"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    with pytest.raises(ValueError, match=r"sibenik\.3ds.*\.3ds format is not supported.*\.obj"):
        rt.io.load_mesh(path)


def test_gpu_instancing_raises_and_points_to_load_gltf(tmp_path):
    path = _gltf(tmp_path / "instanced.gltf", instancing=True)
    with pytest.raises(ValueError, match=r"instanced\.gltf.*EXT_mesh_gpu_instancing.*rt\.io\.load_gltf"):
        rt.io.load_mesh(path)
    # load_gltf reads all three copies.
    pytest.importorskip("pygltflib")
    assert rt.io.load_gltf(path).instanced_triangle_count == 3


def test_several_scenes_warn_and_read_the_default(tmp_path):
    path = _gltf(tmp_path / "scenes.gltf", scenes=2)
    with pytest.warns(UserWarning, match=r"scenes\.gltf.*2 scenes.*default scene \(0\).*load_gltf"):
        vertices, indices = rt.io.load_mesh(path)
    np.testing.assert_array_equal(vertices[indices[0]], TRIANGLE)
    # One scene, no instancing: no warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        vertices, indices = rt.io.load_mesh(_gltf(tmp_path / "plain.gltf"))
    assert indices.shape == (1, 3)


def test_gpu_instancing_in_a_glb_raises(tmp_path):
    document = json.loads(_gltf(tmp_path / "instanced.gltf", instancing=True).read_text()).copy()
    chunk = json.dumps(document).encode()
    chunk += b" " * (-len(chunk) % 4)
    header = b"glTF" + struct.pack("<II", 2, 12 + 8 + len(chunk))
    path = tmp_path / "instanced.glb"
    path.write_bytes(header + struct.pack("<II", len(chunk), 0x4E4F534A) + chunk)
    with pytest.raises(ValueError, match=r"instanced\.glb.*EXT_mesh_gpu_instancing.*load_gltf"):
        rt.io.load_mesh(path)


def _load_error(path) -> str:
    with pytest.raises(ValueError) as error:
        rt.load(path)
    return str(error.value)


def test_load_of_a_text_file_gives_no_advice_to_unpickle(tmp_path):
    path = tmp_path / "notes.npz"
    path.write_text("hello\n")
    message = _load_error(path)
    assert message == (
        f"load: {path} is not a readable .npz archive: it starts with b'hello\\n', not with a zip archive's b'PK' "
        "(jaxrt structure files are written by rt.save)"
    )
    assert "allow_pickle" not in message and "unsafe" not in message


def test_load_of_pickled_data_refuses_without_advice_to_unpickle(tmp_path):
    objects = np.array([{"a": 1}], dtype=object)
    np.save(tmp_path / "objects.npy", objects, allow_pickle=True)
    np.savez(tmp_path / "objects.npz", header=objects)
    for name in ("objects.npy", "objects.npz"):
        message = _load_error(tmp_path / name)
        assert "pickled (object) data, which no jaxrt structure file holds" in message, message
        assert "allow_pickle" not in message and "pickle.load" not in message
