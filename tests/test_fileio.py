"""Atomic writes and output folders (aerovis_slam.fileio), used by every tool that writes results."""

from __future__ import annotations

import json
import os

import pytest

from aerovis_slam.errors import DataError
from aerovis_slam.fileio import atomic_write, atomic_write_json, atomic_write_text, prepare_out_dir


def test_atomic_write_replaces_whole_files_and_cleans_up(tmp_path):
    p = tmp_path / "sub" / "m.json"
    atomic_write_json(p, {"a": 1})
    assert json.loads(p.read_text()) == {"a": 1} and oct(p.stat().st_mode & 0o777) == "0o644"
    atomic_write_text(p, "second")
    assert p.read_text() == "second"
    assert sorted(x.name for x in p.parent.iterdir()) == ["m.json"]  # no temporary left behind


def test_a_failing_writer_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "traj.txt"
    p.write_text("old")

    def half_then_crash(tmp):
        tmp.write_text("half")
        raise KeyboardInterrupt  # Ctrl-C in the middle of a write

    with pytest.raises(KeyboardInterrupt):
        atomic_write(p, half_then_crash)
    assert p.read_text() == "old" and os.listdir(tmp_path) == ["traj.txt"]


def test_prepare_out_dir_names_the_folder(tmp_path):
    assert prepare_out_dir(tmp_path / "a" / "b").is_dir()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(DataError, match="file"):
        prepare_out_dir(blocker / "sub")
