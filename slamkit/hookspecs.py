"""Hook specifications of slamkit's plugin system (pluggy). Every hook is prefixed ``slamkit_``.

A plugin is a module (or object) named by an entry point in the ``slamkit`` group::

    [project.entry-points.slamkit]
    my_plugin = "my_package.slamkit_plugin"

and implements one or more of the hooks below with ``@slamkit.hookimpl``. The first-party plugins in
``plugins/`` register exactly this way; nothing in the core imports a plugin by name.

Two families of hooks:

- **Registration** (``slamkit_components``, ``slamkit_cli_commands``): called once when the plugin manager starts.
- **Lifecycle** (``slamkit_run_started`` ... ``slamkit_run_finished``): notifications of what a run does, for
  viewers, loggers and recorders (the run's own output files are written by the built-in plugin
  ``slamkit.eval.outputs`` on them). Each receives one frozen event dataclass of plain data from
  :mod:`slamkit.events` and returns nothing. The runners fire them through
  :class:`slamkit.runtime.events.EventDispatcher`: in the sequential runner from the running thread, in the
  threaded runner from one dispatcher thread, in the order the pipeline produced them (so a listener never
  needs a lock and never slows tracking). A listener that raises is logged with its plugin's name and not
  called again for the rest of the run; the run goes on (except for the run's own outputs plugin, whose failure
  fails the run). Implement them as plain functions (no ``wrapper``/``hookwrapper``: the dispatcher calls each
  implementation on its own so that one listener's failure cannot reach another).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import pluggy

from slamkit.events import (
    FrameSkipped,
    FrameTracked,
    KeyFrameCulled,
    KeyFrameInserted,
    LoopChecked,
    LoopClosed,
    MapCreated,
    MapsMerged,
    PointsCulled,
    RunFinished,
    RunStarted,
)

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

    # ---- lifecycle events (notifications; see the module docstring for threads and failures) ----------

    @hookspec
    def slamkit_run_started(self, event: RunStarted) -> None:
        """A run begins: the runner, the dataset, the run directory and the composed config.

        Fired once per run, before the first frame. Plugins that keep state per run create it here, keyed on
        ``event.run_id``.
        """

    @hookspec
    def slamkit_frame_tracked(self, event: FrameTracked) -> None:
        """Tracking finished a frame: its state, how it was tracked, its pose, matches and timings.

        Fired for every frame tracking received, in frame order. The threaded runner fires it right after
        tracking; the sequential runner after local mapping (and loop closing) processed the keyframes the frame
        made, which is when it records the frame's pose relative to its reference keyframe (``T_c_r``).
        """

    @hookspec
    def slamkit_frame_skipped(self, event: FrameSkipped) -> None:
        """The dataset could not read a frame (a missing, undecodable or truncated image) and the run left it out
        (``runner.bad_frames: skip``); fired from the thread that reads the frames, before the next frame is
        tracked."""

    @hookspec
    def slamkit_map_created(self, event: MapCreated) -> None:
        """Tracking initialised a map: the first of the run, or a new one after a reset (a new ``map_id``).

        Fired before the ``slamkit_frame_tracked`` of the initialising frame.
        """

    @hookspec
    def slamkit_keyframe_inserted(self, event: KeyFrameInserted) -> None:
        """Local mapping inserted a keyframe and finished processing it (points created, fused, local BA).

        Inserted keyframes minus culled keyframes (``slamkit_keyframe_culled``) is the map's keyframe count,
        as long as tracking did not reset the map.
        """

    @hookspec
    def slamkit_points_culled(self, event: PointsCulled) -> None:
        """Local mapping's recent-point culling removed map points (fired only when it removed some)."""

    @hookspec
    def slamkit_keyframe_culled(self, event: KeyFrameCulled) -> None:
        """Local mapping's keyframe culling removed a redundant keyframe (with its pose relative to its parent)."""

    @hookspec
    def slamkit_loop_checked(self, event: LoopChecked) -> None:
        """Loop closing processed a keyframe: its candidates and the verdict (a closed loop or why not)."""

    @hookspec
    def slamkit_loop_closed(self, event: LoopClosed) -> None:
        """Loop closing accepted and corrected a loop (after ``slamkit_loop_checked`` of the same keyframe)."""

    @hookspec
    def slamkit_maps_merged(self, event: MapsMerged) -> None:
        """Two maps of the Atlas were merged.

        Specified now so listeners can rely on it; nothing fires it yet: the Atlas's map merging (ORB-SLAM3,
        a later issue) will.
        """

    @hookspec
    def slamkit_run_finished(self, event: RunFinished) -> None:
        """The run ended (done, failed or interrupted): its status and every map at the end.

        Fired exactly once per run, also after a failure or Ctrl-C, after every other event of the run. Plugins
        write their results here and drop the run's state.
        """
