"""Saving and loading structures: bit-exact round trips of every kind, and damaged files rejected clearly."""

from __future__ import annotations

import hashlib
import io
import json
import tempfile
import zipfile

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from lifecycle_scenes import (
    assert_same_results,
    assert_same_structure,
    box_case,
    curve_case,
    instance_case,
    linear_curve_case,
    trace,
    triangle_case,
)

import jaxrt as rt

KINDS = {
    "triangles": lambda: triangle_case(100).structure,
    "triangles-high": lambda: triangle_case(100, quality="high").structure,
    "triangles-sah": lambda: triangle_case(100, quality="sah").structure,
    "curves": lambda: curve_case().structure,
    "boxes-with-data": lambda: box_case().structure,
    "instances": lambda: instance_case().structure,
}


@pytest.mark.parametrize("kind", sorted(KINDS))
@pytest.mark.parametrize("compacted", [False, True])
def test_round_trip_is_bit_exact(tmp_path, kind, compacted):
    structure = KINDS[kind]()
    structure = rt.compact(structure) if compacted else structure
    path = tmp_path / "scene.jaxrt"
    rt.save(path, structure)
    assert path.exists() and not list(tmp_path.glob(".jaxrt-*"))  # no temporary left behind
    loaded = rt.load(path)
    assert type(loaded) is type(structure)
    assert_same_structure(loaded, structure)


def test_instance_graph_and_shared_components_survive():
    scene = instance_case().structure
    loaded = rt.load(saved(scene))
    assert loaded.children == scene.children
    assert len(loaded.primitive_structures) == len(scene.primitive_structures) == 2
    assert loaded.levels == scene.levels == 2


def test_loaded_compacted_curves_trace_bit_for_bit():
    """Compaction and a round trip, traced against the original (every field)."""
    case = linear_curve_case()
    loaded = rt.load(saved(rt.compact(case.structure)))
    assert loaded.capacity < case.structure.capacity
    result = trace(case)
    assert (result["type"] == rt.IntersectionType.CURVE).sum() >= 20
    assert_same_results(result, trace(case, loaded))


def test_primitive_data_pytree_is_described_not_pickled():
    path = saved(box_case().structure)
    header = read_header(path)
    (structure,) = header["header"]["primitive_structures"]
    assert structure["primitive_data"]["type"] == "dict"
    assert structure["primitive_data"]["keys"] == ["center", "extra", "radius"]
    assert structure["primitive_data"]["items"][1]["type"] == "tuple"
    assert structure["primitive_data"]["items"][1]["items"][1]["type"] == "list"
    assert header["header"]["format_version"] == 1 and header["header"]["jaxrt_version"] == rt.__version__


def test_save_rejects_what_it_cannot_store(tmp_path):
    with pytest.raises(TypeError, match="save: structure must be a PrimitiveAccelerationStructure"):
        rt.save(tmp_path / "x", {"node_lower": np.zeros(3)})
    with pytest.raises(FileNotFoundError):
        rt.load(tmp_path / "missing.npz")


# --- damaged files ------------------------------------------------------------------------------------------------


_SAVED: dict[int, tuple[object, str]] = {}


def saved(structure) -> str:
    """A file holding ``structure`` (one per structure object for the whole module)."""
    if id(structure) not in _SAVED:
        path = tempfile.mkdtemp(prefix="jaxrt-test-") + "/structure.npz"
        rt.save(path, structure)
        _SAVED[id(structure)] = (structure, path)  # keeps the structure alive, so its id stays unique
    return _SAVED[id(structure)][1]


def read_header(path) -> dict:
    with zipfile.ZipFile(path) as archive:
        raw = np.load(io.BytesIO(archive.read("header.npy")), allow_pickle=False)
    return json.loads(raw.tobytes())


def rewrite(path, out, *, header=None, arrays=None, drop=(), rehash=True) -> None:
    """Copy the archive at ``path`` to ``out`` with a new header and arrays (re-signed unless ``rehash``)."""
    with np.load(path, allow_pickle=False) as archive:
        entries = {name: archive[name] for name in archive.files}
    document = json.loads(entries.pop("header").tobytes())
    if header is not None:
        header(document["header"])
    if rehash:
        body = json.dumps(document["header"], sort_keys=True, separators=(",", ":")).encode()
        document["sha256"] = hashlib.sha256(body).hexdigest()
    entries.update(arrays or {})
    for name in drop:
        entries.pop(name)
    entries["header"] = np.frombuffer(json.dumps(document).encode(), np.uint8)
    with open(out, "wb") as file:
        np.savez(file, **entries)


def base_file() -> str:
    return saved(instance_case().structure)


@given(fraction=st.floats(0.0, 0.999))
def test_truncated_files_are_rejected(fraction):
    data = open(base_file(), "rb").read()
    cut = int(len(data) * fraction)
    path = base_file() + f".cut{cut}"
    with open(path, "wb") as file:
        file.write(data[:cut])
    with pytest.raises(ValueError, match=r"load: .* (is not a readable \.npz archive|has a damaged array|is missing)"):
        rt.load(path)


@given(position=st.floats(0.0, 0.999), flip=st.integers(1, 255))
def test_flipped_bytes_are_rejected(position, flip):
    data = bytearray(open(base_file(), "rb").read())
    index = int(len(data) * position)
    data[index] ^= flip
    path = base_file() + f".flip{index}-{flip}"
    with open(path, "wb") as file:
        file.write(bytes(data))
    try:
        loaded = rt.load(path)
    except ValueError as error:
        assert str(error).startswith(f"load: {path} ")
    else:  # a flip in bytes no reader looks at (zip comments, padding) must leave the structure unchanged
        assert_same_structure(loaded, instance_case().structure)


def test_wrong_version_and_format(tmp_path):
    out = tmp_path / "v2.npz"
    rewrite(base_file(), out, header=lambda h: h.update(format_version=2))
    with pytest.raises(ValueError, match="has format version 2; this jaxrt reads version 1"):
        rt.load(out)
    rewrite(base_file(), out, header=lambda h: h.update(format="other"))
    with pytest.raises(ValueError, match="has format 'other', not 'jaxrt.structure'"):
        rt.load(out)


def test_hand_edited_header_is_rejected(tmp_path):
    out = tmp_path / "edited.npz"

    def opaque(h):
        h["primitive_structures"][0]["geometry_info"][0]["opaque"] = False

    rewrite(base_file(), out, header=opaque, rehash=False)
    with pytest.raises(ValueError, match="header whose SHA-256 does not match its content"):
        rt.load(out)


def test_edited_array_is_rejected(tmp_path):
    out = tmp_path / "edited.npz"
    children = np.load(base_file())["p0.node_children"].copy()
    children[0, 0] = 10_000
    rewrite(base_file(), out, arrays={"p0.node_children": children})
    with pytest.raises(ValueError, match="array 'p0.node_children' whose SHA-256 does not match its header"):
        rt.load(out)


def test_consistently_edited_file_is_still_checked(tmp_path):
    """Someone who also fixes the checksums gets the layout checks: indices out of range, wrong shapes."""
    out = tmp_path / "resigned.npz"
    children = np.load(base_file())["p0.node_children"].copy()
    children[0, 0] = 10_000

    def resign(h):
        h["arrays"]["p0.node_children"]["sha256"] = hashlib.sha256(children.tobytes()).hexdigest()

    rewrite(base_file(), out, header=resign, arrays={"p0.node_children": children})
    with pytest.raises(ValueError, match=r"primitive structure 0.node_children\[0, 0\] = 10000 outside"):
        rt.load(out)
    graph = lambda h: h.update(children=[[2, 1], [2, 0]])  # noqa: E731 - table 0 refers to itself
    rewrite(base_file(), out, header=graph)
    with pytest.raises(ValueError, match="invalid instance graph .*cycle"):
        rt.load(out)


def test_missing_array_is_rejected(tmp_path):
    out = tmp_path / "missing.npz"
    rewrite(base_file(), out, drop=["t0.transform"])
    with pytest.raises(ValueError, match=r"is missing the arrays \['t0.transform'\]"):
        rt.load(out)


def test_extra_and_object_arrays_are_rejected(tmp_path):
    out = tmp_path / "extra.npz"
    rewrite(base_file(), out, arrays={"payload": np.zeros(3)})
    with pytest.raises(ValueError, match=r"has entries \['payload'\] that its header does not list"):
        rt.load(out)
    out = tmp_path / "object.npz"
    objects = np.array([{"code": "print('hi')"}, None], dtype=object)

    def listed(h):
        h["arrays"]["p0.leaf_geometry"] = {"dtype": "|O", "shape": [2], "sha256": "0" * 64}

    rewrite(base_file(), out, header=listed, arrays={"p0.leaf_geometry": objects})
    with pytest.raises(ValueError, match=r"has a damaged array 'p0.leaf_geometry' \(it holds pickled \(object\) data.*it was not loaded\)"):
        rt.load(out)


def test_not_an_archive(tmp_path):
    path = tmp_path / "plain.npy"
    np.save(path, np.zeros(3))
    with pytest.raises(ValueError, match="is a bare .npy array"):
        rt.load(path)
    path.write_text("hello")
    with pytest.raises(ValueError, match="is not a readable .npz archive"):
        rt.load(path)
    with open(path, "wb") as file:
        np.savez(file, a=np.zeros(2))
    with pytest.raises(ValueError, match="has no 'header' entry"):
        rt.load(path)
