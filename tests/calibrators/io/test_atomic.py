import os
import stat

import pytest

from calibrators.io.atomic import atomic_write


def test_success_replaces_with_normal_permissions(tmp_path):
    target = tmp_path / "out.json"
    target.write_text("old")
    old = os.umask(0o022)
    try:
        with atomic_write(target) as fh:
            fh.write("new")
    finally:
        os.umask(old)
    assert target.read_text() == "new"
    assert stat.S_IMODE(target.stat().st_mode) == 0o644
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]


def test_failure_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "out.json"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_write(target) as fh:
        fh.write("half")
        raise RuntimeError("disk full")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]
