"""The data folder of the examples, tests and benchmarks: which files they read, and a check of a folder.

The meshes and hair are public third-party assets (Stanford scans, Sponza, TressFX, glTF samples); jaxrt does
not ship them. A data folder holds them as ``<dataset>/<file>`` (the paths in :data:`FILES`); the scripts look
for it at ``$JAXRT_DATA_DIR``, else at ``shared/data`` beside the repository
(:func:`jaxrt.bench.scenes.default_data_dir`). Everything works without it: examples fall back to procedural
scenes, tests that need a file skip and say which.

``python -m jaxrt.bench.data [--data-dir DIR] [--write-sums]`` runs offline on a folder you already have: it
lists what is present and missing, and checks each file against the folder's ``SHA256SUMS`` (the format of
``sha256sum``; ``--write-sums`` writes one for the files present, to check later copies against).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
from pathlib import Path

__all__ = ["FILES", "SUMS_FILE", "check_folder", "read_sums", "sha256", "write_sums"]

#: The files that examples, tests and benchmarks read (relative to the data folder), and what reads them.
FILES: dict[str, str] = {
    "stanford-bunny/bun_zipper.binary.ply": "benchmarks (bunny), heatmap and inverse_* examples, Embree tests",
    "stanford-bunny/stanford-bunny.obj.gz": "Embree tests (bunny, OBJ)",
    "stanford-dragon-decimated/dragon_vrip_res3.obj.gz": "benchmarks (dragon), Embree tests",
    "sponza-dabrovic-3ds/sponza.derived.ply": "benchmarks (Sponza interior), heatmap example",
    "sibenik-3ds/sibenik.3ds": "load_mesh error test (.3ds is refused)",
    "tressfx-fur-bear/bear.tfx": "fur example, curve benchmarks, hair loader tests",
    "tressfx-hair-ponytail/back.tfx": "curve benchmarks (ponytail)",
    "tressfx-hair-ponytail/front_top.tfx": "curve benchmarks (ponytail)",
    "tressfx-hair-ponytail/side.tfx": "curve benchmarks (ponytail)",
    "tressfx-hair-ponytail/tail.tfx": "curve benchmarks (ponytail), hair loader tests",
    "tressfx-hair-sintel/sintel_hair.tfx": "hair example",
    "tressfx-hair-sintel/sintel_bust.obj": "hair example",
    "gltf-simple-instancing/SimpleInstancing.gltf": "glTF instancing tests",
    "gltf-simple-instancing/SimpleInstancing.bin": "glTF instancing tests (its buffer)",
    "gltf-2cylinderengine-hierarchy/2CylinderEngine.glb": "glTF node hierarchy tests",
    "gltf-interpolation-test/InterpolationTest.gltf": "glTF animation tests",
    "gltf-interpolation-test/interpolation.bin": "glTF animation tests (its buffer)",
    "gltf-animated-morph-sphere/AnimatedMorphSphere.gltf": "glTF morph target tests",
    "gltf-animated-morph-sphere/AnimatedMorphSphere.bin": "glTF morph target tests (its buffer)",
}

#: The checksum list of a data folder, in ``sha256sum``'s format (``<hex digest>  <relative path>``).
SUMS_FILE = "SHA256SUMS"


def sha256(path: str | os.PathLike[str]) -> str:
    """The hex SHA-256 digest of a file."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_sums(folder: str | os.PathLike[str]) -> dict[str, str]:
    """``{relative path: digest}`` from the folder's :data:`SUMS_FILE` (empty when it has none)."""
    path = Path(folder) / SUMS_FILE
    if not path.is_file():
        return {}
    sums = {}
    for line in path.read_text().splitlines():
        if line.strip():
            digest, name = line.split(maxsplit=1)
            sums[name.lstrip("*").strip()] = digest.lower()
    return sums


def check_folder(folder: str | os.PathLike[str]) -> dict[str, str]:
    """The state of every file of :data:`FILES` in ``folder``: ``"ok"`` (present, checksum matches),
    ``"present"`` (no checksum listed), ``"missing"``, or ``"checksum mismatch"``."""
    folder = Path(folder)
    sums = read_sums(folder)
    states = {}
    for name in FILES:
        path = folder / name
        if not path.is_file():
            states[name] = "missing"
        elif name not in sums:
            states[name] = "present"
        else:
            states[name] = "ok" if sha256(path) == sums[name] else "checksum mismatch"
    return states


def write_sums(folder: str | os.PathLike[str]) -> Path:
    """Write :data:`SUMS_FILE` for the files of :data:`FILES` present in ``folder``; returns its path."""
    folder = Path(folder)
    lines = [f"{sha256(folder / name)}  {name}" for name in FILES if (folder / name).is_file()]
    path = folder / SUMS_FILE
    path.write_text("".join(line + "\n" for line in lines))
    return path


def main(argv: list[str] | None = None) -> int:
    from jaxrt.bench.scenes import default_data_dir

    parser = argparse.ArgumentParser(prog="python -m jaxrt.bench.data", description=__doc__.splitlines()[0])
    parser.add_argument("--data-dir", help="the folder to check (default: $JAXRT_DATA_DIR, else ../shared/data)")
    parser.add_argument("--write-sums", action="store_true", help=f"write {SUMS_FILE} for the files present")
    args = parser.parse_args(argv)
    folder = Path(args.data_dir) if args.data_dir else default_data_dir()
    if folder is None or not folder.is_dir():
        where = folder if folder is not None else "$JAXRT_DATA_DIR or shared/data beside the repository"
        print(f"no data folder at {where}: examples use procedural scenes, data tests skip (docs/data.md)")
        return 1
    if args.write_sums:
        print(f"wrote {write_sums(folder)}")
    states = check_folder(folder)
    width = max(map(len, FILES))
    print(f"data folder: {folder}")
    for name, state in states.items():
        print(f"  {name:<{width}}  {state:<17}  {FILES[name]}")
    counts = {s: sum(v == s for v in states.values()) for s in ("ok", "present", "missing", "checksum mismatch")}
    print(", ".join(f"{n} {s}" for s, n in counts.items()))
    return 2 if counts["checksum mismatch"] else 0


if __name__ == "__main__":
    sys.exit(main())
