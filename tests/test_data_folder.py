"""``python -m jaxrt.bench.data``: the offline check of a data folder (local files only, no network)."""

from __future__ import annotations

import hashlib

from jaxrt.bench import data

BUNNY = "stanford-bunny/bun_zipper.binary.ply"
DRAGON = "stanford-dragon-decimated/dragon_vrip_res3.obj.gz"


def _folder(tmp_path):
    for name, text in ((BUNNY, b"ply bunny"), (DRAGON, b"dragon")):
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(text)
    return tmp_path


def test_states_without_and_with_checksums(tmp_path):
    folder = _folder(tmp_path)
    states = data.check_folder(folder)
    assert states[BUNNY] == states[DRAGON] == "present"
    assert {s for n, s in states.items() if n not in (BUNNY, DRAGON)} == {"missing"}
    sums = data.write_sums(folder)
    assert sums.read_text().splitlines()[0] == f"{hashlib.sha256(b'ply bunny').hexdigest()}  {BUNNY}"
    assert data.check_folder(folder)[BUNNY] == "ok"
    (folder / BUNNY).write_bytes(b"changed")
    assert data.check_folder(folder)[BUNNY] == "checksum mismatch"


def test_command_line_exit_status(tmp_path, capsys, monkeypatch):
    folder = _folder(tmp_path / "data")
    assert data.main(["--data-dir", str(folder), "--write-sums"]) == 0
    out = capsys.readouterr().out
    assert f"data folder: {folder}" in out and "2 ok, 0 present" in out
    (folder / DRAGON).write_bytes(b"other")
    monkeypatch.setenv("JAXRT_DATA_DIR", str(folder))  # found through the variable, as the scripts find it
    assert data.main([]) == 2
    assert "1 checksum mismatch" in capsys.readouterr().out
    assert data.main(["--data-dir", str(tmp_path / "absent")]) == 1
