"""docs/architecture.md stays true: the core's rooms import only what the page says they may, and every file the
page names exists.

A room is a top-level module or sub-package of ``slamkit`` (``pipeline``, ``map``, ``errors``, ...). ``ALLOWED``
below is the "may import" column of the page's table; an import of another room that is not listed fails, so a new
dependency between rooms is a decision written down in both places, not an accident.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE = ROOT / "slamkit"
DOC = ROOT / "docs" / "architecture.md"

#: Plain-data modules every room may import (thread_budget: a per-thread hint, no state beyond a thread-local).
PLAIN = {"errors", "sensors", "features", "problems", "thread_budget"}

#: room -> rooms it may import (besides itself and PLAIN), as docs/architecture.md's table says.
ALLOWED: dict[str, set[str]] = {
    "errors": set(),
    "sensors": set(),
    "features": set(),
    "problems": set(),
    "thread_budget": set(),
    "geometry": set(),
    "interfaces": {"map"},
    "events": {"interfaces"},
    "hookspecs": {"events", "interfaces"},
    "plugins": {"hookspecs", "interfaces"},
    "builtin": {"hookspecs", "interfaces"},
    "config": {"plugins", "hookspecs", "interfaces"},
    "io": {"geometry", "interfaces"},
    "frontend": {"geometry", "interfaces"},
    "map": {"geometry", "interfaces"},
    "optim": {"geometry", "interfaces", "plugins"},
    "pipeline": {"geometry", "interfaces", "map", "optim"},
    "runtime": {"pipeline", "map", "events", "interfaces", "geometry", "plugins", "hookspecs"},
    "eval": {"events", "hookspecs", "io", "pipeline", "geometry", "interfaces"},
    "report": set(),
    "export": {"map", "geometry", "interfaces", "io", "plugins"},
    "app": {
        "api",
        "geometry",
        "interfaces",
        "events",
        "hookspecs",
        "plugins",
        "builtin",
        "config",
        "io",
        "frontend",
        "map",
        "optim",
        "pipeline",
        "runtime",
        "eval",
    },
    "api": {"app", "config", "plugins", "frontend", "geometry", "interfaces", "map", "pipeline", "runtime"},
}
#: Rooms that may import anything of the core (the command line and the benchmarks sit on top of everything).
TOP = {"cli", "bench", "__main__", "__init__"}

#: What the pipeline's algorithms must never know about: who runs them and who listens.
PIPELINE_NEVER = {"runtime", "eval", "app", "cli", "bench", "events", "hookspecs", "report"}


def _room_of(module: str) -> str | None:
    """``slamkit.pipeline.tracking`` -> ``pipeline``; None for a module outside the core."""
    parts = module.split(".")
    if parts[0] != "slamkit" or len(parts) < 2:
        return None
    return parts[1]


def _imported_modules(path: Path) -> list[str]:
    """Every ``slamkit...`` module a file imports (``from slamkit import x`` counts as ``slamkit.x``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "slamkit":
                found += [f"slamkit.{alias.name}" for alias in node.names]
            else:
                found.append(node.module)
    return [m for m in found if m.startswith("slamkit.")]


def room_edges() -> dict[tuple[str, str], list[str]]:
    """(importing room, imported room) -> the files that make the edge."""
    edges: dict[tuple[str, str], list[str]] = {}
    for path in sorted(CORE.rglob("*.py")):
        rel = path.relative_to(ROOT)
        src = _room_of(".".join(rel.with_suffix("").parts))
        if src is None or rel.parts[1] == "conf":
            continue
        for module in _imported_modules(path):
            dst = _room_of(module)
            if dst is not None and dst != src:
                edges.setdefault((src, dst), []).append(str(rel))
    return edges


def forbidden_edges(edges: dict[tuple[str, str], list[str]]) -> list[str]:
    bad = []
    for (src, dst), files in sorted(edges.items()):
        if src in TOP or (dst in PLAIN and src not in PLAIN):
            continue
        allowed = ALLOWED.get(src)
        if allowed is None:
            bad.append(f"room slamkit/{src} is not in docs/architecture.md's table ({files[0]})")
        elif dst not in allowed:
            bad.append(f"slamkit/{src} may not import slamkit/{dst}: {', '.join(sorted(set(files)))}")
    return bad


def test_rooms_import_only_what_the_architecture_page_allows() -> None:
    assert forbidden_edges(room_edges()) == []


def test_the_pipeline_never_knows_who_runs_or_listens() -> None:
    edges = room_edges()
    assert [f"{src}->{dst}" for (src, dst) in edges if src == "pipeline" and dst in PIPELINE_NEVER] == []


def test_the_rule_catches_a_new_edge(tmp_path: Path) -> None:
    """The check itself can fail: a pipeline module importing the runtime is reported."""
    edges = dict(room_edges())
    edges[("pipeline", "runtime")] = ["slamkit/pipeline/example.py"]
    edges[("geometry", "map")] = ["slamkit/geometry/example.py"]
    bad = forbidden_edges(edges)
    assert any("slamkit/pipeline may not import slamkit/runtime" in b for b in bad)
    assert any("slamkit/geometry may not import slamkit/map" in b for b in bad)


def test_every_room_of_the_core_is_on_the_page() -> None:
    rooms = {
        p.stem if p.is_file() else p.name for p in CORE.iterdir() if p.suffix == ".py" or (p / "__init__.py").exists()
    }
    rooms -= TOP | {"conf"}
    assert sorted(rooms - set(ALLOWED)) == []
    text = DOC.read_text()
    missing = [r for r in sorted(rooms) if f"`{r}/`" not in text and f"`{r}.py`" not in text]
    assert missing == [], f"rooms not described in docs/architecture.md: {missing}"


@pytest.mark.parametrize(
    "path", sorted(set(re.findall(r"`((?:slamkit|plugins|tests|conf|docs)/[\w./]+)`", DOC.read_text())))
)
def test_files_named_on_the_page_exist(path: str) -> None:
    assert (ROOT / path.rstrip("/")).exists(), f"docs/architecture.md names {path}, which does not exist"
