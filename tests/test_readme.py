"""The README's Python code runs as written: every ```python block, in order, in one interpreter (later blocks use
what earlier ones defined), from a folder beside ``../shared`` as the README's relative paths assume. A block that
needs a running server is skipped, with its reason (its calls are tested in ``tests/fleet``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).parents[1]
SHARED = REPO.parent / "shared"
#: a fragment of a block -> why that block is not run here
SKIP = {"FleetClient(": "needs a running fleet server (cae-lcd serve); the client is tested in tests/fleet",
        "admin.": "the admin's calls continue the fleet client's block (a running server; tested in tests/fleet)"}


def python_blocks(text: str) -> list[str]:
    """The ```python blocks of a Markdown text, in order."""
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_blocks_are_found():
    blocks = python_blocks((REPO / "README.md").read_text())
    assert len(blocks) >= 3 and any("LoopDetector" in b for b in blocks)
    assert python_blocks("```python\na = 1\n```\n```bash\nls\n```\n") == ["a = 1\n"]


@pytest.mark.skipif(not (SHARED / "datasets" / "kitti" / "sequences" / "90").is_dir(), reason="needs ../shared")
def test_readme_python_runs(tmp_path):
    blocks = [b for b in python_blocks((REPO / "README.md").read_text()) if not any(k in b for k in SKIP)]
    work = tmp_path / "work"
    work.mkdir()
    (tmp_path / "shared").symlink_to(SHARED)
    script = "\n".join(f"# --- README block {n}\n{b}" for n, b in enumerate(blocks))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    run = subprocess.run([sys.executable, "-c", script], cwd=work, env=env, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert (work / "runs" / "api" / "keyframes.h5").is_file()
    assert re.search(r"^\d+ -> \d+ \d+", run.stdout, flags=re.M), run.stdout[-2000:]  # loops were printed
