"""recorder.files: a finished file appears whole or not at all."""

from __future__ import annotations

from pathlib import Path

import pytest

from slamreplay.recorder.files import atomic_write, replacing


def test_atomic_write_replaces_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "metrics.json"
    target.write_text("old")
    atomic_write(target, "new")
    assert target.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]


def test_an_error_while_writing_keeps_the_old_file_and_removes_the_temporary(tmp_path: Path) -> None:
    target = tmp_path / "graph.g2o"
    target.write_text("whole")
    with pytest.raises(RuntimeError, match="cut off"), replacing(target) as tmp:
        tmp.write_text("half")
        assert tmp.parent == tmp_path and tmp.name.startswith(".graph.g2o.") and tmp.name.endswith(".partial")
        raise RuntimeError("cut off")
    assert target.read_text() == "whole"
    assert [p.name for p in tmp_path.iterdir()] == ["graph.g2o"]


def test_nothing_written_means_no_target(tmp_path: Path) -> None:
    """A block that raises before writing anything leaves neither the target nor a temporary."""
    with pytest.raises(KeyboardInterrupt), replacing(tmp_path / "shot.png"):
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
