"""The rooms' import rules, read from the source (AST): the pipeline, the runtime and app.py see the map only
through the MapStore protocol (never slamkit's concrete store), and the core (slamkit/) imports no plugin: plugins
are discovered through entry points (DESIGN section 3).

Every import counts: at module level, inside functions, under ``if TYPE_CHECKING``, relative ones, and
``importlib.import_module`` / ``__import__`` with a constant name.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
CORE = REPO_ROOT / "slamkit"
#: What may not see a concrete store: the algorithm rooms and the wiring.
PROTOCOL_ONLY = [CORE / "pipeline", CORE / "runtime", CORE / "app.py"]
#: Concrete MapStore implementations of the core, and their class names.
CONCRETE_STORE_MODULES = ("slamkit.map.store",)
CONCRETE_STORE_NAMES = ("InMemoryMapStore",)
#: The first-party plugin packages (each a folder of plugins/), plus the folder itself.
PLUGIN_PACKAGES = [*sorted(p.parent.name for p in (REPO_ROOT / "plugins").glob("*/__init__.py")), "plugins"]


def module_name(path: Path) -> str:
    """slamkit/pipeline/tracking.py -> slamkit.pipeline.tracking (a package's __init__ -> the package)."""
    parts = list(path.relative_to(REPO_ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imported_modules(source: str, module: str, is_package: bool = False) -> Iterator[tuple[int, str]]:
    """(line, fully qualified module or module.name) of every import in ``source``, a module named ``module``."""
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            yield node.lineno, base
            for alias in node.names:
                yield node.lineno, f"{base}.{alias.name}"
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
            if name in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                yield node.lineno, node.args[0].value


def concrete_store_imports(source: str, module: str, is_package: bool = False) -> list[str]:
    found = []
    for line, name in imported_modules(source, module, is_package):
        hits_module = any(name == m or name.startswith(m + ".") for m in CONCRETE_STORE_MODULES)
        if hits_module or name.rpartition(".")[2] in CONCRETE_STORE_NAMES:
            found.append(f"{module}:{line} imports {name}")
    return found


def plugin_imports(source: str, module: str, is_package: bool = False) -> list[str]:
    return [
        f"{module}:{line} imports {name}"
        for line, name in imported_modules(source, module, is_package)
        if name.split(".")[0] in PLUGIN_PACKAGES
    ]


def python_files(*roots: Path) -> list[Path]:
    return sorted(f for root in roots for f in ([root] if root.is_file() else root.rglob("*.py")))


def test_pipeline_runtime_and_app_see_no_concrete_store() -> None:
    files = python_files(*PROTOCOL_ONLY)
    assert len(files) > 20  # the rooms are where they are said to be
    found = [
        hit for f in files for hit in concrete_store_imports(f.read_text(), module_name(f), f.name == "__init__.py")
    ]
    assert not found, "import the MapStore protocol (slamkit.interfaces) instead:\n" + "\n".join(found)


def test_the_core_imports_no_plugin() -> None:
    assert {"slamkit_orb", "slamkit_dbow", "slamkit_gtsam", "slamkit_scipy", "slamkit_twoview"} <= set(PLUGIN_PACKAGES)
    files = python_files(CORE)
    found = [hit for f in files for hit in plugin_imports(f.read_text(), module_name(f), f.name == "__init__.py")]
    assert not found, "the core discovers plugins through entry points, it never imports one:\n" + "\n".join(found)


@pytest.mark.parametrize(
    "source",
    [
        "from slamkit.map.store import InMemoryMapStore",
        "import slamkit.map.store",
        "import slamkit.map.store as s",
        "from slamkit.map import store",
        "from ..map.store import X",
        "from ..map import store",
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from slamkit.map.store import InMemoryMapStore",
        "def f():\n    from slamkit.map.store import InMemoryMapStore\n    return InMemoryMapStore()",
        "import importlib\nS = importlib.import_module('slamkit.map.store')",
        "from somewhere.other import InMemoryMapStore",
    ],
)
def test_the_check_finds_every_form_of_a_concrete_store_import(source: str) -> None:
    assert concrete_store_imports(source, "slamkit.pipeline.tracking")


@pytest.mark.parametrize(
    "source",
    [
        "from slamkit_orb.extractor import OrbExtractor",
        "import slamkit_gtsam",
        "import plugins.slamkit_scipy.optimizer",
        "def f():\n    import slamkit_dbow.vocabulary",
        "x = __import__('slamkit_twoview')",
    ],
)
def test_the_check_finds_every_form_of_a_plugin_import(source: str) -> None:
    assert plugin_imports(source, "slamkit.app")


def test_the_protocol_and_the_entities_are_allowed() -> None:
    source = "from slamkit.interfaces import MapStore\nfrom slamkit.map.entities import KeyFrame\nfrom . import frame"
    assert not concrete_store_imports(source, "slamkit.pipeline.tracking")
    assert not plugin_imports(source, "slamkit.pipeline.tracking")
