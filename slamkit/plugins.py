"""The plugin manager: discovers plugins through the ``slamkit`` entry-point group and keeps the registry
of components, (kind, name) -> config node + target.

Discovery never stops at a broken plugin: each failure (import error, no hook implemented, a hook that
raises or returns the wrong thing, a duplicate component) is recorded with the plugin's name and
distribution, shown by ``slamkit plugins``, and raised as a :class:`PluginError` when a run selects a
component that is missing because of it. A component whose built object does not implement its kind's
protocol is rejected when it is instantiated, with an error naming the plugin and the missing members.
"""

from __future__ import annotations

import importlib.metadata as md
import typing
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib import resources
from typing import Any

import pluggy

from slamkit import hookspecs
from slamkit.errors import PluginError, SlamkitError
from slamkit.hookspecs import ComponentSpec
from slamkit.interfaces import KIND_PROTOCOLS

#: Keys of a component group's composed node that configure the run, not the component: taken out before it is
#: built (``map.save`` / ``map.load`` / ``map.session_start``: saved maps and sessions, read by
#: slamkit/map/mapfile_run.py).
RUN_KEYS: dict[str, tuple[str, ...]] = {"map": ("save", "load", "session_start")}


@dataclass(frozen=True)
class RegisteredComponent:
    """A component together with where it came from."""

    spec: ComponentSpec
    plugin: str
    distribution: str

    @property
    def key(self) -> str:
        return f"{self.spec.kind}={self.spec.name}"

    def config_node(self) -> dict[str, Any]:
        """The Hydra node: ``_target_`` first, then the component's defaults."""
        return {"_target_": self.spec.target, **dict(self.spec.config or {})}


@dataclass(frozen=True)
class PluginFailure:
    """A plugin that could not be used, and why."""

    plugin: str
    distribution: str
    reason: str

    def __str__(self) -> str:
        return f"plugin '{self.plugin}' (distribution {self.distribution}): {self.reason}"


def protocol_members(protocol: type) -> list[str]:
    """Names a class must provide to satisfy ``protocol`` (attributes and methods)."""
    return sorted(typing._get_protocol_attrs(protocol))  # type: ignore[attr-defined]


def missing_members(obj: object, protocol: type) -> list[str]:
    """Members of ``protocol`` that ``obj`` lacks."""
    return [name for name in protocol_members(protocol) if not hasattr(obj, name)]


def _has_packaged_yaml(kind: str, name: str) -> bool:
    """Whether slamkit's own conf/ ships ``<kind>/<name>.yaml``."""
    return (resources.files("slamkit.conf") / kind / f"{name}.yaml").is_file()


def _distribution_label(ep: md.EntryPoint) -> str:
    dist = ep.dist
    if dist is None:
        return "unknown"
    return f"{dist.metadata['Name']} {dist.version}"


class ComponentRegistry:
    """Every component registered by the installed plugins.

    Build it with :meth:`discover` (entry points) or add plugin objects directly with :meth:`add_plugin`
    (tests, embedding applications).
    """

    def __init__(self) -> None:
        self._pm = pluggy.PluginManager(hookspecs.PROJECT_NAME)
        self._pm.add_hookspecs(hookspecs.SlamkitHookSpecs)
        self._components: dict[tuple[str, str], RegisteredComponent] = {}
        self.failures: list[PluginFailure] = []

    @classmethod
    def discover(cls, entry_points: Iterable[md.EntryPoint] | None = None) -> ComponentRegistry:
        """Load every plugin of the ``slamkit`` entry-point group (or the given entry points)."""
        registry = cls()
        eps = md.entry_points(group=hookspecs.ENTRY_POINT_GROUP) if entry_points is None else entry_points
        for ep in sorted(eps, key=lambda e: e.name):
            distribution = _distribution_label(ep)
            try:
                plugin = ep.load()
            except Exception as exc:  # any import-time failure of third-party code
                registry.failures.append(
                    PluginFailure(ep.name, distribution, f"failed to import '{ep.value}': {type(exc).__name__}: {exc}")
                )
                continue
            registry.add_plugin(ep.name, plugin, distribution)
        return registry

    def add_plugin(self, name: str, plugin: object, distribution: str = "unknown") -> None:
        """Register one plugin object and collect its components; failures are recorded, not raised."""
        if self._pm.has_plugin(name):
            self.failures.append(PluginFailure(name, distribution, "a plugin with this name is already registered"))
            return
        try:
            self._pm.register(plugin, name=name)
            self._pm.check_pending()
        except pluggy.PluginValidationError as exc:
            if self._pm.has_plugin(name):
                self._pm.unregister(name=name)
            self.failures.append(PluginFailure(name, distribution, f"invalid hook implementation: {exc}"))
            return
        impls = [i for i in self._pm.hook.slamkit_components.get_hookimpls() if i.plugin_name == name]
        if not impls and not self._implements_any_hook(name):
            self._pm.unregister(name=name)
            self.failures.append(
                PluginFailure(
                    name,
                    distribution,
                    "implements no slamkit hook (slamkit_components, slamkit_cli_commands, lifecycle hooks)",
                )
            )
            return
        for impl in impls:
            try:
                specs = impl.function()
            except Exception as exc:
                self.failures.append(
                    PluginFailure(name, distribution, f"slamkit_components raised {type(exc).__name__}: {exc}")
                )
                continue
            self._add_specs(name, distribution, specs)

    def _implements_any_hook(self, name: str) -> bool:
        plugin = self._pm.get_plugin(name)
        return any(caller.get_hookimpls() for caller in self._pm.get_hookcallers(plugin) or [])

    @property
    def hook(self) -> pluggy.HookRelay:
        """The plugin manager's hook relay: the runners fire the lifecycle hooks through it
        (slamkit.runtime.events.EventDispatcher)."""
        return self._pm.hook

    def add_cli_commands(self, subparsers: Any) -> None:
        """Let every plugin add its subcommands (hook ``slamkit_cli_commands``)."""
        self._pm.hook.slamkit_cli_commands(subparsers=subparsers)

    def _add_specs(self, plugin: str, distribution: str, specs: object) -> None:
        if not isinstance(specs, list | tuple) or not all(isinstance(s, ComponentSpec) for s in specs):
            self.failures.append(
                PluginFailure(
                    plugin, distribution, f"slamkit_components returned {specs!r}; expected list[ComponentSpec]"
                )
            )
            return
        for spec in specs:
            if spec.kind not in KIND_PROTOCOLS:
                kinds = ", ".join(KIND_PROTOCOLS)
                self.failures.append(
                    PluginFailure(
                        plugin, distribution, f"component '{spec.name}' has unknown kind '{spec.kind}' ({kinds})"
                    )
                )
                continue
            existing = self._components.get((spec.kind, spec.name))
            if existing is not None:
                self.failures.append(
                    PluginFailure(
                        plugin,
                        distribution,
                        f"component {spec.kind}={spec.name} is already provided by plugin '{existing.plugin}' "
                        f"({existing.distribution})",
                    )
                )
                continue
            self._components[(spec.kind, spec.name)] = RegisteredComponent(spec, plugin, distribution)

    # ---- queries -------------------------------------------------------------------------------

    def components(self, kind: str | None = None) -> list[RegisteredComponent]:
        """Registered components, sorted by kind then name (optionally of one kind)."""
        items = [c for c in self._components.values() if kind is None or c.spec.kind == kind]
        return sorted(items, key=lambda c: (c.spec.kind, c.spec.name))

    def get(self, kind: str, name: str) -> RegisteredComponent:
        """The component ``kind=name``; a PluginError lists the alternatives and any broken plugins."""
        found = self._components.get((kind, name))
        if found is not None:
            return found
        names = ", ".join(c.spec.name for c in self.components(kind)) or "none"
        msg = f"no component {kind}={name} is registered (available: {names})"
        if self.failures:
            msg += "; plugins that failed to load: " + "; ".join(str(f) for f in self.failures)
        raise PluginError(msg)

    def by_target(self, target: str) -> RegisteredComponent | None:
        for comp in self._components.values():
            if comp.spec.target == target:
                return comp
        return None

    # ---- Hydra ---------------------------------------------------------------------------------

    def register_config_nodes(self) -> None:
        """Store each component's config node in Hydra's ConfigStore as ``<kind>/<name>``.

        Skipped only for core components whose node is a YAML file in slamkit's own ``conf/<kind>/``.
        """
        from hydra.core.config_store import ConfigStore

        store = ConfigStore.instance()
        for comp in self._components.values():
            if comp.spec.config is None and _has_packaged_yaml(comp.spec.kind, comp.spec.name):
                continue
            store.store(group=comp.spec.kind, name=comp.spec.name, node=comp.config_node(), provider=comp.plugin)

    def instantiate(self, kind: str, node: Mapping[str, Any], **kwargs: Any) -> Any:
        """Build the component described by a composed config node and check it implements ``kind``.

        node: the composed config of the group (has ``_target_``). kwargs: runtime arguments (not config).
        Errors from the component's own validation (slamkit errors) pass through unchanged; import
        failures and protocol violations become PluginError naming the plugin.
        """
        from hydra.errors import InstantiationException
        from hydra.utils import instantiate

        target = str(node.get("_target_", ""))
        if not target:
            raise PluginError(f"config group '{kind}' has no _target_: cannot build a component from it")
        comp = self.by_target(target)
        origin = f"plugin '{comp.plugin}' ({comp.distribution})" if comp else "an unregistered target"
        label = comp.key if comp else f"{kind} target {target}"
        run_keys = [key for key in RUN_KEYS.get(kind, ()) if key in node]
        if run_keys:
            node = {str(k): v for k, v in node.items() if k not in run_keys}
        try:
            obj = instantiate(node, _convert_="all", **kwargs)
        except InstantiationException as exc:
            cause = exc.__cause__
            if isinstance(cause, SlamkitError):
                raise cause from None
            raise PluginError(f"{label} from {origin} could not be built: {exc}") from exc
        protocol = KIND_PROTOCOLS.get(kind)
        if protocol is not None and not isinstance(obj, protocol):
            missing = ", ".join(missing_members(obj, protocol)) or "(members of the wrong kind)"
            raise PluginError(
                f"{label} from {origin} built a {type(obj).__name__}, which does not implement "
                f"{protocol.__name__}: missing {missing}"
            )
        return obj
