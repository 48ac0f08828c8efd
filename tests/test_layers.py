"""The packages are layers and imports go one way: base layer ``core`` -> ``cae``, ``verify`` -> ``retrieval`` ->
``evaluation`` and, beside it, the fleet server ``fleet`` -> ``bench`` -> ``cli`` (and the ``train.py`` script) on
top. This test parses every import of the project's code (also those inside functions) and fails on one that goes up
or sideways."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).parents[1]

#: package -> layer; a package may import only packages of a strictly lower layer (and itself)
LAYERS = {"core": 0, "cae": 1, "verify": 1, "retrieval": 2, "evaluation": 3, "fleet": 3, "bench": 4, "cli": 5}
SCRIPTS = {"train.py": 6}  #: top-level scripts and their layer (above the CLI they call)


def project_imports(path: Path, text: str | None = None) -> list[tuple[int, str]]:
    """``(line, top-level package)`` of every import of a project package in ``path`` (or in ``text`` given as its
    content), relative ones resolved."""
    tree = ast.parse(path.read_text() if text is None else text, str(path))
    own = path.relative_to(REPO).parts[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [own] if node.level else [node.module or ""]
        else:
            continue
        found += [(node.lineno, n.split(".")[0]) for n in names if n.split(".")[0] in LAYERS]
    return found


def sources() -> list[Path]:
    files = [p for pkg in LAYERS for p in sorted((REPO / pkg).rglob("*.py"))]
    return files + [REPO / s for s in SCRIPTS]


def layer_of(path: Path) -> tuple[str, int]:
    rel = path.relative_to(REPO)
    name = rel.parts[0]
    return name, SCRIPTS[name] if name in SCRIPTS else LAYERS[name]


class TestImportDirection:
    @pytest.mark.parametrize("path", sources(), ids=lambda p: str(p.relative_to(REPO)))
    def test_imports_go_down(self, path):
        own, layer = layer_of(path)
        bad = [f"line {line}: imports {pkg}" for line, pkg in project_imports(path)
               if pkg != own and LAYERS[pkg] >= layer]
        assert not bad, f"{path.relative_to(REPO)} ({own}, layer {layer}) imports upward or sideways: {bad}"

    @pytest.mark.parametrize("where, text, upward", [
        ("retrieval/x.py", "def f():\n    from evaluation.metrics import x\n", "evaluation"),
        ("verify/x.py", "import cae.model\n", "cae"),
        ("core/x.py", "from retrieval import detect\n", "retrieval"),
    ])
    def test_detects_an_upward_import(self, where, text, upward):
        """The check itself can fail: an import that goes up (or sideways, verify -> cae) is reported."""
        fake = REPO / where
        own, layer = layer_of(fake)
        found = project_imports(fake, text)
        assert found and found[0][1] == upward and LAYERS[upward] >= layer

    def test_every_package_is_known(self):
        packages = {p.parent.name for p in REPO.glob("*/__init__.py")}
        assert packages - {"tests"} == set(LAYERS), "add the new package to LAYERS (and to DESIGN/README)"
