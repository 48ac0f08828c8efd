"""``cae_lcd.core.files``: a failed write never replaces a good file; output folders are checked before writing."""

import pytest

from cae_lcd.core.errors import ConfigError, DatabaseError
from cae_lcd.core.files import atomic_write, prepare_out_dir, write_text_atomic


class TestAtomicWrite:
    def test_replaces_on_success(self, tmp_path):
        write_text_atomic(tmp_path / "a.txt", "one")
        write_text_atomic(tmp_path / "a.txt", "two")
        assert (tmp_path / "a.txt").read_text() == "two"
        assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]  # no temporary left

    def test_keeps_old_content_on_error(self, tmp_path):
        (tmp_path / "a.txt").write_text("good")
        with pytest.raises(RuntimeError):
            with atomic_write(tmp_path / "a.txt") as f:
                f.write("half")
                raise RuntimeError("killed half-way")
        assert (tmp_path / "a.txt").read_text() == "good"
        assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]

    def test_os_error_is_a_database_error(self, tmp_path):
        with pytest.raises(DatabaseError, match="cannot write"):
            write_text_atomic(tmp_path / "missing-dir" / "a.txt", "x")


class TestPrepareOutDir:
    def test_creates(self, tmp_path):
        assert prepare_out_dir(tmp_path / "a" / "b").is_dir()

    @pytest.mark.parametrize("make, error", [
        (lambda p: (p / "f").write_text("x") and p / "f", "exists and is not a folder"),
        (lambda p: (p / "f").write_text("x") and p / "f" / "sub", "a parent of it is a file"),
    ])
    def test_refuses(self, tmp_path, make, error):
        with pytest.raises(ConfigError, match=error):
            prepare_out_dir(make(tmp_path))
