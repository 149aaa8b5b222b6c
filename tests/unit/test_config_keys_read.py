"""Every key of conf/ (and of every plugin's config node) is read by the code it configures.

A key nothing reads is a bug (docs: RULES "a key nothing reads is a bug"): sweeping it changes nothing while the
config says it is a tunable. The check is static (``ast`` over every module of slamkit/ and plugins/), so it runs in
a second and covers code paths no short run reaches. The rule, per kind of config node:

- **pipeline** (conf/pipeline/*.yaml, typed by slamkit/pipeline/config.py): each key ``pipeline.SECTION.NAME`` is a
  field of the section's dataclass (``PipelineConfig.from_node`` refuses others) and the field is *read* somewhere
  in slamkit/ or plugins/ outside its declaration: an attribute load ``<receiver>.NAME`` whose receiver is a config
  object (its last name is ``cfg``, ``config``, a section name, or the name of the dataclass's field holding it).
- **components** (every node with a ``_target_``: conf/dataset/*.yaml, conf/map/*.yaml and the nodes the plugins
  register through ``slamkit_components``): each key is a parameter of the target's ``__init__`` and the
  constructor *uses* it beyond keeping it: a load of the parameter in ``__init__`` that is not just
  ``self.ATTR = <expression of it>`` counts (passed on, validated in a condition, computed with); when it is only
  stored, ``ATTR`` must be loaded somewhere in slamkit/ or plugins/ (``self.ATTR`` in a method, ``x.ATTR`` elsewhere).
  A key that is not a constructor parameter must be taken out of the node by name before instantiation
  (``node.pop("KEY")``/``node.get("KEY")``/``node["KEY"]`` in slamkit/, e.g. ``optimizer.worker``).
- **runner** (conf/runner/*.yaml) and the primary config's own keys (``seed``): read by name in slamkit/ (a string
  constant in ``.get("KEY")``/``["KEY"]``/a call argument, or an attribute load ``.KEY`` on a ``runner``/``cfg``
  receiver).
- **@package _global_ configs** (conf/backend, conf/experiment, conf/sweep): every key they set, and every
  parameter a sweep sweeps, exists in the config they apply to (so it is one of the keys checked above).
- **any other group** (a new one without a ``_target_``): like the runner, each key read by name in slamkit/.
- conf/hydra/ configures Hydra's own launcher (validated by its structured config), and is not checked here.

The check is name-based, not type-based: a field counts as read when any config-like receiver loads that name,
so two sections must not share a field name unless both are read.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import textwrap
import typing
from collections.abc import Iterable, Iterator
from functools import cache
from pathlib import Path
from typing import Any

import pytest
import yaml
from omegaconf import OmegaConf

from slamkit.config import compose_config
from slamkit.pipeline.config import PipelineConfig
from slamkit.plugins import ComponentRegistry

REPO = Path(__file__).resolve().parents[2]
CONF = REPO / "conf"
SOURCE_ROOTS = (REPO / "slamkit", REPO / "plugins")
PIPELINE_DECLARATION = REPO / "slamkit" / "pipeline" / "config.py"
CONFIG_RECEIVERS = {"cfg", "config"}


# ---- the source corpus ---------------------------------------------------------------------------------------


def _source_files() -> Iterator[Path]:
    for root in SOURCE_ROOTS:
        for path in sorted(root.rglob("*.py")):
            if not any(part in {"build", ".venv"} or part.endswith(".egg-info") for part in path.parts):
                yield path


@cache
def _trees() -> dict[Path, ast.Module]:
    return {path: ast.parse(path.read_text(), str(path)) for path in _source_files()}


def _last_name(node: ast.expr) -> str | None:
    """``self.cfg`` -> "cfg", ``pipeline.tracking`` -> "tracking", ``cfg`` -> "cfg"; else None."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def attribute_loads(trees: Iterable[ast.Module]) -> list[tuple[str, str | None]]:
    """(attribute, receiver's last name) of every attribute load ``<receiver>.<attribute>``."""
    out = []
    for tree in trees:
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
                out.append((node.attr, _last_name(node.value)))
    return out


def string_reads(trees: Iterable[ast.Module]) -> set[str]:
    """String constants used as a key: ``x.get("k")``, ``x.pop("k")``, ``x["k"]``, or any call's argument."""
    out: set[str] = set()
    for tree in trees:
        for node in ast.walk(tree):
            if isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Load):
                if isinstance(node.slice, ast.Constant) and isinstance(node.slice.value, str):
                    out.add(node.slice.value)
            elif isinstance(node, ast.Call):
                for arg in node.args:
                    if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                        out.add(arg.value)
    return out


# ---- the rules ------------------------------------------------------------------------------------------------


def unread_pipeline_fields(
    sections: dict[str, type], yaml_node: dict[str, dict[str, Any]], loads: list[tuple[str, str | None]]
) -> list[str]:
    """Keys ``pipeline.SECTION.NAME`` of ``yaml_node`` that are not a field of the section's dataclass or that no
    config-like receiver loads."""
    problems = []
    for section, keys in yaml_node.items():
        cls = sections.get(section)
        if cls is None:
            problems.append(f"pipeline.{section}: no dataclass in PipelineConfig holds this section")
            continue
        fields = {f.name for f in dataclasses.fields(cls)}
        receivers = CONFIG_RECEIVERS | {section} | {name for name, c in sections.items() if c is cls}
        for name in keys:
            if name not in fields:
                problems.append(f"pipeline.{section}.{name}: not a field of {cls.__name__}")
            elif not any(attr == name and recv in receivers for attr, recv in loads):
                problems.append(f"pipeline.{section}.{name}: declared in {cls.__name__} but read by no code")
    return problems


def _init_function(cls: type) -> ast.FunctionDef | None:
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return None
    for node in ast.parse(source).body[0].body:  # type: ignore[attr-defined]
        if isinstance(node, ast.FunctionDef) and node.name == "__init__":
            return node
    return None


def _stored_attributes_only(init: ast.FunctionDef, param: str) -> set[str] | None:
    """The ``self.ATTR`` that ``param`` is stored into when storing is all ``__init__`` does with it, else None
    (it is used: passed on, tested, computed with)."""
    parents: dict[ast.AST, ast.AST] = {}
    for node in ast.walk(init):
        for child in ast.iter_child_nodes(node):
            parents[child] = node
    stored: set[str] = set()
    for node in ast.walk(init):
        if not (isinstance(node, ast.Name) and node.id == param and isinstance(node.ctx, ast.Load)):
            continue
        stmt: ast.AST = node
        while not isinstance(stmt, ast.stmt):
            stmt = parents[stmt]
        targets = (
            stmt.targets if isinstance(stmt, ast.Assign) else [stmt.target] if isinstance(stmt, ast.AnnAssign) else []
        )
        attrs = [t.attr for t in targets if isinstance(t, ast.Attribute) and _last_name(t.value) == "self"]
        if not targets or len(attrs) != len(targets):
            return None  # used in something other than a store into self
        # stored through a plain expression of the parameter: still only stored
        stored.update(attrs)
    return stored


def component_key_problems(
    label: str, node: dict[str, Any], loads: list[tuple[str, str | None]], strings: set[str]
) -> list[str]:
    """Keys of a component node that its target's constructor neither takes nor uses (see the module docstring)."""
    module_name, _, class_name = str(node["_target_"]).rpartition(".")
    cls = getattr(importlib.import_module(module_name), class_name)
    params = inspect.signature(cls.__init__).parameters
    init = _init_function(cls)
    attr_loads = {attr for attr, _ in loads}
    problems = []
    for key in node:
        if key == "_target_":
            continue
        if key not in params:
            if key not in strings:
                problems.append(f"{label}.{key}: not a parameter of {cls.__name__}.__init__ and not read by name")
            continue
        if init is None:
            problems.append(f"{label}.{key}: {cls.__name__}.__init__ has no source to check")
            continue
        stored = _stored_attributes_only(init, key)
        if stored is None:
            continue
        if not stored:
            problems.append(f"{label}.{key}: {cls.__name__}.__init__ takes it and never uses it")
        elif not stored & attr_loads:
            problems.append(f"{label}.{key}: {cls.__name__} stores it as {sorted(stored)} and nothing reads that")
    return problems


# ---- the config nodes -------------------------------------------------------------------------------------------


def _yaml(path: Path) -> dict[str, Any]:
    data = yaml.safe_load(path.read_text()) or {}
    assert isinstance(data, dict), f"{path}: expected a mapping"
    return data


def _component_nodes() -> dict[str, dict[str, Any]]:
    """label -> node: every conf/ file with a _target_ and every plugin-registered node."""
    nodes: dict[str, dict[str, Any]] = {}
    for path in sorted(CONF.glob("*/*.yaml")):
        data = _yaml(path)
        if "_target_" in data:
            nodes[f"{path.parent.name}={path.stem} ({path.relative_to(REPO)})"] = data
    for comp in ComponentRegistry.discover().components():
        if comp.spec.config is not None:
            nodes[f"{comp.key} (plugin {comp.plugin})"] = comp.config_node()
    return nodes


def _sections() -> dict[str, type]:
    hints = typing.get_type_hints(PipelineConfig)
    return {f.name: hints[f.name] for f in dataclasses.fields(PipelineConfig)}


def _runtime_loads() -> list[tuple[str, str | None]]:
    return attribute_loads(t for p, t in _trees().items() if p != PIPELINE_DECLARATION)


# ---- the tests ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("path", sorted(CONF.glob("pipeline/*.yaml")), ids=lambda p: p.name)
def test_every_pipeline_key_is_read(path: Path) -> None:
    node = _yaml(path)
    PipelineConfig.from_node(node)  # every key is a field (ConfigError otherwise)
    assert unread_pipeline_fields(_sections(), node, _runtime_loads()) == []


COMPONENT_NODES = _component_nodes()


@pytest.mark.parametrize("label", sorted(COMPONENT_NODES))
def test_every_component_key_is_used_by_its_constructor(label: str) -> None:
    assert (
        component_key_problems(label, COMPONENT_NODES[label], _runtime_loads(), string_reads(_trees().values())) == []
    )


@pytest.mark.parametrize("path", sorted(CONF.glob("runner/*.yaml")), ids=lambda p: p.name)
def test_every_runner_key_is_read(path: Path) -> None:
    strings = string_reads(_trees().values())
    runner_loads = {attr for attr, recv in _runtime_loads() if recv in {"runner", "cfg"}}
    unread = [k for k in _yaml(path) if k not in strings and k not in runner_loads]
    assert unread == [], f"{path.name}: runner keys read by no code: {unread}"


#: groups with a rule of their own above (every other group falls to the by-name rule)
OWN_RULES = {"pipeline", "runner", "experiment", "sweep", "backend", "hydra"}


def _other_group_files() -> list[Path]:
    return [
        p
        for p in sorted(CONF.glob("*/*.yaml"))
        if p.parent.name not in OWN_RULES and "_target_" not in _yaml(p) and not _is_global(p)
    ]


def _is_global(path: Path) -> bool:
    return "@package _global_" in path.read_text().split("\n", 1)[0]


def test_every_other_group_key_is_read() -> None:
    strings = string_reads(_trees().values())
    loads = {attr for attr, _ in _runtime_loads()}
    unread = {
        str(path.relative_to(REPO)): [k for k in _yaml(path) if k != "defaults" and k not in strings | loads]
        for path in _other_group_files()
    }
    assert {f: keys for f, keys in unread.items() if keys} == {}, "keys read by no code"


def test_every_config_file_falls_under_a_rule() -> None:
    """A new group is checked too: each YAML of conf/ is a component node, a pipeline/runner node, a global
    config, Hydra's, or goes to the by-name rule of the other groups."""
    files = set(CONF.glob("*/*.yaml")) | set(CONF.glob("hydra/*/*.yaml"))
    covered = {p for p in files if p.parent.name in OWN_RULES or p.parent.parent.name == "hydra"}
    covered |= {p for p in files if p.parent.parent == CONF and "_target_" in _yaml(p)}
    covered |= set(_other_group_files())
    globals_ = {p for p in files if _is_global(p)}
    assert not (globals_ - {p for p in files if p.parent.name in {"experiment", "sweep", "backend"}}), (
        "a @package _global_ config outside experiment/, sweep/, backend/: add its group to the global rule"
    )
    assert files - covered == set()


def test_primary_config_keys_are_read() -> None:
    primary = {k for k in _yaml(CONF / "config.yaml") if k not in {"defaults", "hydra"}}
    strings = string_reads(_trees().values())
    loads = {attr for attr, recv in _runtime_loads() if recv == "cfg"}
    assert {k for k in primary if k not in strings and k not in loads} == set()


def _overrides_of(data: dict[str, Any]) -> list[str]:
    """A global config's ``- override /group: option`` defaults as command-line overrides."""
    out = []
    for entry in data.get("defaults", []):
        if isinstance(entry, dict):
            for key, value in entry.items():
                group = str(key).removeprefix("override ").strip().lstrip("/")
                if not group.startswith("hydra"):
                    out.append(f"{group}={value}")
    return out


def _leaf_keys(data: dict[str, Any], prefix: str = "") -> Iterator[str]:
    for key, value in data.items():
        if isinstance(value, dict):
            yield from _leaf_keys(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}"


@pytest.mark.parametrize(
    "path",
    sorted([*CONF.glob("experiment/*.yaml"), *CONF.glob("sweep/*.yaml"), *CONF.glob("backend/*.yaml")]),
    ids=lambda p: f"{p.parent.name}/{p.name}",
)
def test_global_configs_set_existing_keys(path: Path) -> None:
    data = _yaml(path)
    cfg = compose_config(_overrides_of(data))
    keys = [k for k in _leaf_keys({k: v for k, v in data.items() if k not in {"defaults", "hydra"}})]
    params = ((data.get("hydra") or {}).get("sweeper") or {}).get("params") or {}
    keys += [k for k in params if k != "seed"]
    missing = [k for k in keys if OmegaConf.select(cfg, k, default="<missing>") == "<missing>"]
    assert missing == [], f"{path.relative_to(REPO)} sets keys that no config declares: {missing}"


# ---- the checker itself can fail -----------------------------------------------------------------------------


def test_checker_flags_unread_and_stored_only_keys(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The rules report a pipeline field nobody reads and a constructor parameter that is only stored."""

    @dataclasses.dataclass(frozen=True)
    class Section:
        used: int = 1
        unused: int = 2

    code = ast.parse("def f(cfg):\n    return cfg.used + other.unused\n")
    problems = unread_pipeline_fields({"sec": Section}, {"sec": {"used": 1, "unused": 2}}, attribute_loads([code]))
    assert problems == ["pipeline.sec.unused: declared in Section but read by no code"]

    (tmp_path / "fake_component.py").write_text(
        textwrap.dedent(
            """
            class Fake:
                def __init__(self, used: int = 1, kept: int = 2, stored: int = 3, ignored: int = 4) -> None:
                    if used < 0:
                        raise ValueError(used)
                    self.kept = int(kept)
                    self.stored = stored

                def run(self) -> int:
                    return self.kept
            """
        )
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    node = {"_target_": "fake_component.Fake", "used": 1, "kept": 2, "stored": 3, "ignored": 4, "extra": 5}
    loads = attribute_loads([ast.parse((tmp_path / "fake_component.py").read_text())])
    assert component_key_problems("fake", node, loads, set()) == [
        "fake.stored: Fake stores it as ['stored'] and nothing reads that",
        "fake.ignored: Fake.__init__ takes it and never uses it",
        "fake.extra: not a parameter of Fake.__init__ and not read by name",
    ]
