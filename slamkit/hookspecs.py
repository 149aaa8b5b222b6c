"""Hook specifications of slamkit's plugin system (pluggy). Every hook is prefixed ``slamkit_``.

A plugin is a module (or object) named by an entry point in the ``slamkit`` group::

    [project.entry-points.slamkit]
    my_plugin = "my_package.slamkit_plugin"

and implements one or more of the hooks below with ``@slamkit.hookimpl``. The first-party plugins in
``plugins/`` register exactly this way; nothing in the core imports a plugin by name.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import pluggy

PROJECT_NAME = "slamkit"
ENTRY_POINT_GROUP = "slamkit"

hookspec = pluggy.HookspecMarker(PROJECT_NAME)
hookimpl = pluggy.HookimplMarker(PROJECT_NAME)


@dataclass(frozen=True)
class ComponentSpec:
    """One swappable component a plugin provides.

    kind: the interface it implements, which is also its Hydra config group: one of
        ``slamkit.interfaces.KIND_PROTOCOLS`` ("features", "place", "initializer", "optimizer", "map",
        "dataset").
    name: the option name within the group: ``<kind>=<name>`` selects it (e.g. ``features=orb``).
    target: dotted path of the class or factory Hydra instantiates (the node's ``_target_``).
    config: the component's default config node (without ``_target_``: it is added from ``target``).
        Registered in Hydra's ConfigStore as ``<kind>/<name>``. None when the node is already a YAML file
        in slamkit's own ``conf/<kind>/<name>.yaml`` (core components only).
    description: one line shown by ``slamkit plugins``.
    """

    kind: str
    name: str
    target: str
    config: Mapping[str, Any] | None = field(default=None)
    description: str = ""


class SlamkitHookSpecs:
    """The hooks a slamkit plugin may implement."""

    @hookspec
    def slamkit_components(self) -> list[ComponentSpec]:  # type: ignore[empty-body]
        """Return the components this plugin provides.

        Called once when the plugin manager starts. Each component's config node is registered in Hydra's
        ConfigStore under its kind (= config group) and name, so ``<kind>=<name>`` selects it. Two plugins
        may not register the same (kind, name): that is reported as an error naming both.
        """

    @hookspec
    def slamkit_cli_commands(self, subparsers: Any) -> None:
        """Add subcommands to the ``slamkit`` command line.

        subparsers: the ``argparse`` sub-parsers object of ``slamkit``; call ``subparsers.add_parser(NAME)`` and
        ``set_defaults(func=...)`` with a function ``(argparse.Namespace) -> int`` (the exit code). Used by
        ``slamkit vocab`` (the place recognition plugin).
        """
