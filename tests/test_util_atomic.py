"""dtoc.util.atomic.outputs_together: a command's outputs appear all together or not at all."""

import os

import pytest

from dtoc.util.atomic import atomic_write_bytes, outputs_together


def test_nothing_appears_before_the_end_of_the_block(tmp_path):
    with outputs_together():
        atomic_write_bytes(tmp_path / "a", b"A")
        assert not (tmp_path / "a").exists()  # staged, not yet in place
        atomic_write_bytes(tmp_path / "b", b"B")
    assert (tmp_path / "a").read_bytes() == b"A" and (tmp_path / "b").read_bytes() == b"B"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]  # no temporaries left


def test_a_failure_inside_the_block_writes_nothing(tmp_path):
    (tmp_path / "a").write_bytes(b"old")
    with pytest.raises(RuntimeError), outputs_together():
        atomic_write_bytes(tmp_path / "a", b"new", force=True)
        atomic_write_bytes(tmp_path / "b", b"B")
        raise RuntimeError("rendering the PNG failed")
    assert (tmp_path / "a").read_bytes() == b"old" and not (tmp_path / "b").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]


def test_a_failed_move_restores_what_was_replaced(tmp_path, monkeypatch):
    (tmp_path / "a").write_bytes(b"old")
    calls = {"n": 0}

    def flaky(real):
        def move(src, dst):
            if str(dst).endswith("b"):
                calls["n"] += 1
                raise OSError(28, "No space left on device", str(dst))
            return real(src, dst)

        return move

    # a new file is published with a hard link, a replaced one with a rename: both fail for "b"
    monkeypatch.setattr("dtoc.util.atomic.os.replace", flaky(os.replace))
    monkeypatch.setattr("dtoc.util.atomic.os.link", flaky(os.link))
    with pytest.raises(OSError), outputs_together():
        atomic_write_bytes(tmp_path / "a", b"new", force=True)
        atomic_write_bytes(tmp_path / "b", b"B")
    assert calls["n"] == 1
    assert (tmp_path / "a").read_bytes() == b"old" and not (tmp_path / "b").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]


def test_the_same_path_twice_is_refused(tmp_path):
    from dtoc.errors import InputError

    with pytest.raises(InputError, match="written twice"), outputs_together():
        atomic_write_bytes(tmp_path / "a", b"1")
        atomic_write_bytes(tmp_path / "a", b"2", force=True)
    assert not (tmp_path / "a").exists()
