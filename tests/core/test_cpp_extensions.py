"""The C++ kernels' build lock: a build killed half-way must not make every later run wait forever."""

import os
import time

from mono_hdr_plugin.core.cpp_extensions import STALE_LOCK_SECONDS, clear_stale_lock


class TestClearStaleLock:
    def test_a_lock_left_by_a_killed_build_is_removed_and_said(self, tmp_path, capsys):
        lock = tmp_path / "lock"
        lock.touch()
        old = time.time() - STALE_LOCK_SECONDS - 60
        os.utime(lock, (old, old))
        clear_stale_lock(tmp_path)
        assert not lock.exists()
        assert f"removed {lock}" in capsys.readouterr().err

    def test_a_fresh_lock_is_kept_and_the_wait_is_said(self, tmp_path, capsys):
        lock = tmp_path / "lock"
        lock.touch()
        clear_stale_lock(tmp_path)
        assert lock.exists()  # another process may be building right now
        err = capsys.readouterr().err
        assert "waiting for another process" in err and f"delete {lock}" in err

    def test_no_lock_says_nothing(self, tmp_path, capsys):
        clear_stale_lock(tmp_path)
        assert capsys.readouterr().err == ""
