"""Atomic writes: whole files or none, with the permissions of a plain open."""

import os
import stat

import pytest

from infinirl.utils.atomic import atomic_open, atomic_path, new_file_mode, write_json_atomic


@pytest.fixture
def umask_027():
    previous = os.umask(0o027)
    yield
    os.umask(previous)


def _mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_atomic_files_get_the_mode_a_plain_open_gives(tmp_path, umask_027):
    assert new_file_mode() == 0o640
    write_json_atomic(tmp_path / "a.json", {"x": 1})
    with atomic_path(tmp_path / "b.mp4", suffix=".tmp.mp4") as tmp:
        open(tmp, "wb").close()  # an encoder opening the name itself
    with open(tmp_path / "plain", "w"):
        pass
    assert _mode(tmp_path / "a.json") == _mode(tmp_path / "b.mp4") == _mode(tmp_path / "plain") == 0o640


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "ckpt.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_open(target) as handle:
        handle.write(b"half")
        raise RuntimeError("disk full")
    assert target.read_bytes() == b"old" and os.listdir(tmp_path) == ["ckpt.bin"]


def test_a_private_file_is_never_readable_by_others(tmp_path, umask_027):
    seen = []
    with atomic_open(tmp_path / "edge.key", permissions=0o600) as handle:
        seen.append(_mode(handle.name))  # already private while its bytes are written
        handle.write(b"secret")
    assert seen == [0o600] and _mode(tmp_path / "edge.key") == 0o600
