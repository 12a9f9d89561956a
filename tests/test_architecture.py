"""Import rules of the layers, checked on the AST: the engine (``handanno_core``) never imports
viser or the app, so it stays usable as a library and from the CLI; the app calls the engine, never
the other way round."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(path: Path) -> set[str]:
    """Top-level names of every module ``path`` imports (absolute imports only)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
    return names


ENGINE_FILES = sorted((ROOT / "handanno_core").rglob("*.py"))


@pytest.mark.parametrize("path", ENGINE_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_engine_imports_neither_viser_nor_app(path: Path) -> None:
    bad = {m for m in imported_modules(path) if m.split(".")[0] in ("viser", "app")}
    assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


def test_rule_checker_sees_imports(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("import viser\nfrom app.ui.server import serve\nfrom . import x\n")
    assert imported_modules(module) == {"viser", "app.ui.server"}
