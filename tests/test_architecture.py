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


# --------------------------------------------------------------------------- the app's layers
# app.ui -> app.control -> handanno_core: viser only in app.ui (app/cli.py reaches it through
# app.ui.server); app.control never imports app.ui; app.ui never builds session commands.

APP = ROOT / "app"


def module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def resolved_imports(path: Path) -> set[str]:
    """Every module ``path`` imports, relative imports resolved to absolute names."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module_name(path).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            mod = ".".join([*base, *([node.module] if node.module else [])])
            names.add(mod)
            if node.module is None:  # from . import x
                names.update(f"{mod}.{alias.name}" for alias in node.names)
    return names


CONTROL_FILES = sorted((APP / "control").rglob("*.py"))
UI_FILES = sorted((APP / "ui").rglob("*.py"))
APP_FILES = sorted(APP.rglob("*.py"))


def _layer(name: str) -> str:
    for prefix in ("app.ui", "app.control", "app.cli", "handanno_core", "viser"):
        if name == prefix or name.startswith(prefix + "."):
            return prefix
    return "other"


@pytest.mark.parametrize("path", CONTROL_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_control_imports_neither_viser_nor_ui(path: Path) -> None:
    bad = {m for m in resolved_imports(path) if _layer(m) in ("viser", "app.ui", "app.cli")}
    assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


@pytest.mark.parametrize("path", APP_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_viser_is_imported_in_app_ui_only(path: Path) -> None:
    uses_viser = any(_layer(m) == "viser" for m in resolved_imports(path))
    assert not uses_viser or path.is_relative_to(APP / "ui"), (
        f"{path.relative_to(ROOT)} imports viser outside app/ui"
    )


def test_cli_reaches_the_ui_only_through_its_server() -> None:
    ui = {m for m in resolved_imports(APP / "cli.py") if _layer(m) == "app.ui"}
    assert ui <= {"app.ui.server"}, ui


#: command classes of the session: the UI asks app.control to build and execute them
COMMAND_NAMES = {
    "Batch", "SetFrameAnnotation", "SetJointState", "SetJoint2D", "SetJoint3D", "SetOutside", "SetVisibility",
    "SetDepthOrder", "SetReference", "SetReview", "parse_command",
}  # fmt: skip


@pytest.mark.parametrize("path", UI_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_ui_builds_and_executes_no_session_command(path: Path) -> None:
    tree = ast.parse(path.read_text(), filename=str(path))
    imported = {
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and (node.module or "").endswith("session")
        for alias in node.names
    }
    calls = {
        node.func.attr
        for node in ast.walk(tree)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
    }
    assert not imported & COMMAND_NAMES, (
        f"{path.relative_to(ROOT)} imports {imported & COMMAND_NAMES}"
    )
    assert "execute" not in calls, f"{path.relative_to(ROOT)} calls session.execute"


#: modules allowed to touch other objects' private attributes, and why
PRIVATE_ACCESS_ALLOWED = {
    "app/ui/guard.py": "hardens viser itself (its websocket and upload handlers have no public hook)",
    "app/cli.py": "super()._get_help_string of argparse's help formatter",
}


@pytest.mark.parametrize("path", APP_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_object_reaches_into_another_objects_privates(path: Path) -> None:
    """``x._name`` only on ``self``/``cls``: no panel takes the server's lock or hides another
    panel's nodes by attribute name (what the app did before app.ui/app.control)."""
    rel = str(path.relative_to(ROOT))
    if rel in PRIVATE_ACCESS_ALLOWED:
        return
    bad = [
        f"{node.lineno}: {ast.unparse(node)}"
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Attribute)
        and node.attr.startswith("_")
        and not node.attr.startswith("__")
        and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))
    ]
    assert not bad, f"{rel}: {bad}"


def _units(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            yield node, node.end_lineno - node.lineno + 1


#: (file, unit) -> why it may be longer than the limit (see the README's Development section)
LONG_UNITS_ALLOWED = {
    ("app/cli.py", "build_parser"): "the CLI's argparse declaration table, one block per command",
    ("app/cli.py", "_run"): "the CLI's command dispatch, one branch per command",
}


@pytest.mark.parametrize("path", APP_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_app_units_are_short(path: Path) -> None:
    """No function over 80 lines, no class over 300 lines in app/ (listed exceptions aside)."""
    rel = str(path.relative_to(ROOT))
    long = [
        f"{node.name} ({n} lines)"
        for node, n in _units(path)
        if n > (300 if isinstance(node, ast.ClassDef) else 80)
        and (rel, node.name) not in LONG_UNITS_ALLOWED
    ]
    assert not long, f"{rel}: {long}"


def test_layer_checker_resolves_relative_imports(tmp_path: Path) -> None:
    assert "app.ui.hand_scene" in resolved_imports(APP / "ui" / "client_ui.py")
    assert "app.control.context" in resolved_imports(APP / "ui" / "client_ui.py")
    assert _layer("app.ui.server") == "app.ui" and _layer("viser.uplot") == "viser"
