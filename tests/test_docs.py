"""The reference built from the docstrings (mkdocs + mkdocstrings, ``mkdocs.yml``) builds in strict mode: a docstring
whose sections griffe cannot read (a parameter the signature lacks, a ``Raises:`` line without its exception) or a
page naming a module that does not exist fails CI. Offline: the built-in theme, sources read statically."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).parents[1]


def test_mkdocs_build_strict(tmp_path):
    pytest.importorskip("mkdocstrings", reason="the 'docs' extra (in 'test') is not installed")
    site = tmp_path / "site"
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(REPO / "mkdocs.yml"),
                          "--site-dir", str(site)], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    sequences = (site / "reference" / "sequences" / "index.html").read_text()
    assert "open_sequence" in sequences and "find_sequences" in sequences
    assert "LoopDetector" in (site / "reference" / "retrieval" / "index.html").read_text()
