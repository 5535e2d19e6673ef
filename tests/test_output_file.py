"""Outputs written whole or not at all (instancing/io/output_file.py): a writer that fails
half-way leaves the previous file as it was and no partial file beside it."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

import instancing
import instancing.cli
from instancing.io.image import ImageFileError, read_exr, write_exr
from instancing.io.output_file import remove_partials, replaced


def test_a_finished_write_replaces_the_file_and_leaves_nothing_else(tmp_path):
    path = tmp_path / "out.json"
    path.write_text("old")
    with replaced(path) as partial:
        assert partial != str(path) and partial.endswith(".json")
        with open(partial, "w") as f:
            f.write("new")
        assert path.read_text() == "old"
    assert path.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]


@pytest.mark.parametrize("interruption", [RuntimeError("disk full"), KeyboardInterrupt()])
def test_an_interrupted_write_keeps_the_old_file(tmp_path, interruption):
    path = tmp_path / "out.json"
    path.write_text("old")
    with pytest.raises(type(interruption)):
        with replaced(path) as partial:
            with open(partial, "w") as f:
                f.write("ne")
            raise interruption
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]


def test_an_exr_writer_failing_half_way_leaves_the_previous_image(tmp_path, monkeypatch):
    path = tmp_path / "image.exr"
    before = np.full((4, 5, 3), 0.25, np.float32)
    write_exr(path, before)

    def write_half(self, filename):
        with open(filename, "wb") as f:
            f.write(b"\x76\x2f\x31\x01 truncated")
        raise RuntimeError("device full")

    monkeypatch.setattr(OpenEXR.File, "write", write_half)
    with pytest.raises(ImageFileError, match="device full"):
        write_exr(path, np.zeros((4, 5, 3), np.float32))
    monkeypatch.undo()
    image, _ = read_exr(path)
    np.testing.assert_array_equal(image, before)
    assert [p.name for p in tmp_path.iterdir()] == ["image.exr"]


def test_ctrl_c_exits_with_status_130_and_one_line(monkeypatch, capsys):
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(instancing.cli, "run_render", interrupted)
    assert instancing.cli.main(["render", "scenes/showcase.json"]) == 130
    err = capsys.readouterr().err
    assert err == "instancing: render interrupted\n"


def test_remove_partials_deletes_only_what_a_killed_writer_left(tmp_path):
    left = [tmp_path / ".history.0123456789ab.partial.json", tmp_path / ".after.ba9876543210.partial.png"]
    kept = [tmp_path / "history.json", tmp_path / "partial.json", tmp_path / ".hidden"]
    for path in left + kept:
        path.write_text("x")
    remove_partials(tmp_path)
    assert not any(p.exists() for p in left) and all(p.exists() for p in kept)
