"""Atomic output files: whole or absent, with ordinary permissions."""

from __future__ import annotations

import stat

import pytest

from softgrasp.io.atomic import write_json, write_text


def test_written_files_get_the_permissions_of_an_ordinary_new_file(tmp_path):
    ref = tmp_path / "ref.txt"
    ref.write_text("x")
    for path in (write_text(tmp_path / "a.txt", "x"), write_json(tmp_path / "b.json", {"a": 1})):
        assert stat.S_IMODE(path.stat().st_mode) == stat.S_IMODE(ref.stat().st_mode)


def test_a_failing_writer_leaves_nothing(tmp_path):
    class Unserialisable:
        pass

    with pytest.raises(TypeError):
        write_json(tmp_path / "c.json", {"a": Unserialisable()})
    assert list(tmp_path.iterdir()) == []
