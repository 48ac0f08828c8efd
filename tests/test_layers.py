"""The packages are layers and imports go one way: base layer ``core`` -> ``cae``, ``verify`` -> ``retrieval`` ->
``evaluation`` and, beside it, the fleet server ``fleet`` -> ``bench`` -> ``cli`` (and the ``train.py`` script) on
top. This test parses every import of the project's code (also those inside functions) and fails on one that goes up
or sideways."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).parents[1]

#: package -> layer; a package may import only packages of a strictly lower layer (and itself). A dotted name is a
#: package inside a namespace folder (``cae_lcd.core`` lives in ``cae_lcd/core/``).
LAYERS = {"cae_lcd.core": 0, "cae": 1, "verify": 1, "retrieval": 2, "cae_lcd.evaluation": 3, "cae_lcd.fleet": 3, "bench": 4,
          "cae_lcd.cli": 5}
SCRIPTS = {"train.py": 6}  #: top-level scripts and their layer (above the CLI they call)


def package_of(module: str) -> str | None:
    """The package of ``LAYERS`` a dotted module name belongs to (the longest that is it or holds it), or None."""
    parts = module.split(".")
    return next((".".join(parts[:k]) for k in range(len(parts), 0, -1) if ".".join(parts[:k]) in LAYERS), None)


def module_of(path: Path) -> str:
    """The dotted module name of a project file (``cae_lcd/core/conf.py`` -> ``cae_lcd.core.conf``)."""
    return ".".join(path.relative_to(REPO).with_suffix("").parts)


def project_imports(path: Path, text: str | None = None) -> list[tuple[int, str]]:
    """``(line, package)`` of every import of a project package in ``path`` (or in ``text`` given as its content),
    relative ones resolved."""
    tree = ast.parse(path.read_text() if text is None else text, str(path))
    own = package_of(module_of(path)) or ""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [own] if node.level else [node.module or ""]
        else:
            continue
        found += [(node.lineno, pkg) for pkg in map(package_of, names) if pkg is not None]
    return found


def sources() -> list[Path]:
    files = [p for pkg in LAYERS for p in sorted((REPO / pkg.replace(".", "/")).rglob("*.py"))]
    return files + [REPO / s for s in SCRIPTS]


def layer_of(path: Path) -> tuple[str, int]:
    name = path.relative_to(REPO).parts[0]
    if name in SCRIPTS:
        return name, SCRIPTS[name]
    pkg = package_of(module_of(path))
    return pkg, LAYERS[pkg]


def packages_found() -> set[str]:
    """The packages in the checkout: top-level folders with ``__init__.py``, and those inside a namespace folder
    (a top-level folder without one)."""
    top = {p.parent.name for p in REPO.glob("*/__init__.py")}
    inside = {f"{p.parts[-3]}.{p.parts[-2]}" for p in REPO.glob("*/*/__init__.py")
              if p.parts[-3] not in top and not p.parts[-3].startswith(".") and p.parts[-3] != "tests"}
    return (top | inside) - {"tests"}


class TestImportDirection:
    @pytest.mark.parametrize("path", sources(), ids=lambda p: str(p.relative_to(REPO)))
    def test_imports_go_down(self, path):
        own, layer = layer_of(path)
        bad = [f"line {line}: imports {pkg}" for line, pkg in project_imports(path)
               if pkg != own and LAYERS[pkg] >= layer]
        assert not bad, f"{path.relative_to(REPO)} ({own}, layer {layer}) imports upward or sideways: {bad}"

    @pytest.mark.parametrize("where, text, upward", [
        ("retrieval/x.py", "def f():\n    from cae_lcd.evaluation.metrics import x\n", "cae_lcd.evaluation"),
        ("verify/x.py", "import cae.model\n", "cae"),
        ("cae_lcd/core/x.py", "from retrieval import detect\n", "retrieval"),
    ])
    def test_detects_an_upward_import(self, where, text, upward):
        """The check itself can fail: an import that goes up (or sideways, verify -> cae) is reported."""
        fake = REPO / where
        own, layer = layer_of(fake)
        found = project_imports(fake, text)
        assert found and found[0][1] == upward and LAYERS[upward] >= layer

    def test_every_package_is_known(self):
        assert packages_found() == set(LAYERS), "add the new package to LAYERS (and to DESIGN/README)"
