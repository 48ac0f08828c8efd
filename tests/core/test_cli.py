"""``cae_lcd.core.cli.run_cli``: every failure is one line on stderr and an exit code, never a traceback."""

import pytest

from cae_lcd.core.cli import run_cli
from cae_lcd.core.errors import ConfigError, DatabaseError, ImageError


def _raise(err):
    def body():
        raise err
    return body


class TestRunCli:
    @pytest.mark.parametrize("err, code, prefix", [
        (ConfigError("'search.k' must be an integer >= 1; got 0"), 2, "error: 'search.k'"),
        (ImageError("bad image"), 2, "error: bad image"),
        (DatabaseError("db damaged"), 2, "error: db damaged"),
        (PermissionError(13, "Permission denied", "/x"), 2, "error: Permission denied: /x"),
        (OSError(28, "No space left on device"), 2, "error: No space left on device"),
        (ZeroDivisionError("division by zero"), 1, "internal error (a bug"),
    ])
    def test_one_line(self, capsys, monkeypatch, err, code, prefix):
        monkeypatch.delenv("CAE_LCD_DEBUG", raising=False)
        assert run_cli(_raise(err)) == code
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(prefix), lines

    def test_success_and_interrupt(self, capsys):
        assert run_cli(lambda: None) == 0
        assert run_cli(_raise(KeyboardInterrupt())) == 130
        assert "interrupted" in capsys.readouterr().err
