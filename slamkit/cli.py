"""Command line: ``slamkit run | eval | report | bench | plugins | map info``.

``slamkit run [OVERRIDES...]`` is a Hydra application (all of Hydra's flags work: ``-m`` for multirun,
``--cfg job`` to print the config, ``+backend=gtsam``, ...). The other subcommands are plain argparse.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
from collections.abc import Sequence

from omegaconf import DictConfig

from slamkit import __version__
from slamkit.errors import SlamkitError
from slamkit.plugins import ComponentRegistry

#: The shell's convention for a process ended by SIGINT (128 + 2).
EXIT_INTERRUPTED = 130


def _one_line(exc: BaseException) -> str:
    """An error's message on one line; a Hydra config error's cause (e.g. "Key 'x' is not in struct") appended."""
    text = " ".join(str(exc).split())
    cause = exc.__cause__
    if cause is not None and str(cause).strip():
        first = str(cause).strip().splitlines()[0].strip()
        if first not in text:
            text = f"{text} ({first})"
    return text


def _run_hydra_app(hydra_args: Sequence[str]) -> int:
    """Run the Hydra app; a slamkit error (dataset, calibration, config value) or a Hydra config error (unknown key,
    bad override, missing config group option) is printed as one line and exits 2, with no traceback. Anything
    else is a bug and keeps its traceback."""
    import hydra
    from hydra.errors import HydraException

    from slamkit.app import run_job
    from slamkit.config import CONFIG_NAME, CONFIG_SEARCH_PATH, prepare_registry

    failures: list[tuple[SlamkitError, str]] = []

    @functools.wraps(run_job)  # Hydra names the job (and its log, app.log) after the wrapped function's module
    def job(cfg: DictConfig) -> object:
        # caught inside the job: Hydra would print its own line and a traceback before handing the error back
        try:
            return run_job(cfg)
        except SlamkitError as exc:
            from hydra.core.hydra_config import HydraConfig

            failures.append((exc, HydraConfig.get().runtime.output_dir))
            return None

    prepare_registry()
    app = hydra.main(config_path=CONFIG_SEARCH_PATH, config_name=CONFIG_NAME, version_base="1.3")(job)
    saved_argv, saved_full_error = sys.argv, os.environ.get("HYDRA_FULL_ERROR")
    user_wants_tracebacks = saved_full_error not in (None, "", "0")
    sys.argv = ["slamkit", *hydra_args]
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra then raises its config errors to us instead of printing them
    try:
        app()
    except HydraException as exc:
        if user_wants_tracebacks:
            raise
        print(f"slamkit run: {_one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        # the run directory already holds what was computed (metrics.json says "interrupted")
        print("slamkit run: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        sys.argv = saved_argv
        if saved_full_error is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = saved_full_error
    for error, out_dir in failures:
        if user_wants_tracebacks:
            raise error
        print(f"slamkit run: {_one_line(error)}{_kept_note(out_dir)}", file=sys.stderr)
    return 2 if failures else 0


def _kept_note(out_dir: str) -> str:
    """Where a run that failed after it started keeps what it computed ("" when it failed before the first frame)."""
    try:
        with open(os.path.join(out_dir, "metrics.json")) as f:
            started = json.load(f).get("stage") != "build"
    except (OSError, ValueError):
        return ""
    return f" (what was computed is in {out_dir})" if started else ""


def _plugins_command(args: argparse.Namespace) -> int:
    registry = ComponentRegistry.discover()
    rows = [
        {
            "kind": c.spec.kind,
            "name": c.spec.name,
            "distribution": c.distribution,
            "plugin": c.plugin,
            "target": c.spec.target,
            "description": c.spec.description,
        }
        for c in registry.components()
    ]
    failures = [{"plugin": f.plugin, "distribution": f.distribution, "reason": f.reason} for f in registry.failures]
    if args.json:
        print(json.dumps({"components": rows, "failures": failures}, indent=2))
    else:
        headers = ["kind", "name", "distribution", "target"]
        widths = [max([len(h)] + [len(r[h]) for r in rows]) for h in headers]
        print("  ".join(h.ljust(w) for h, w in zip(headers, widths, strict=True)))
        print("  ".join("-" * w for w in widths))
        for r in rows:
            print("  ".join(r[h].ljust(w) for h, w in zip(headers, widths, strict=True)))
        if failures:
            print("\nplugins that failed to load:")
            for f in registry.failures:
                print(f"  {f}")
    return 1 if failures and args.strict else 0


def _bench_run(argv: Sequence[str]) -> int:
    """``slamkit bench [--json FILE] [--runners a,b] [OVERRIDES...]`` (``slamkit bench optimizer`` is separate)."""
    from slamkit.bench.run import __doc__ as doc
    from slamkit.bench.run import add_bench_run_arguments, run_bench_command

    parser = argparse.ArgumentParser(
        prog="slamkit bench",
        description=(doc or "").split("\n\n")[0] + " See also: `slamkit bench optimizer`.",
    )
    add_bench_run_arguments(parser)
    args = parser.parse_args(list(argv))
    try:
        return run_bench_command(args)
    except SlamkitError as exc:
        print(f"slamkit bench: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("slamkit bench: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="slamkit", description="Feature-based visual SLAM, faithful to ORB-SLAM.")
    parser.add_argument("--version", action="version", version=f"slamkit {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser(
        "run",
        help="run SLAM on a sequence (a Hydra app: slamkit run dataset=euroc dataset.root=PATH +backend=gtsam)",
        add_help=False,
    )
    plugins = sub.add_parser("plugins", help="list every registered component: kind, name, distribution, target")
    plugins.add_argument("--json", action="store_true", help="print JSON instead of a table")
    plugins.add_argument("--strict", action="store_true", help="exit 1 when any plugin failed to load")
    plugins.set_defaults(func=_plugins_command)
    from slamkit.eval.cli import add_eval_parser

    add_eval_parser(sub)
    from slamkit.report.cli import add_report_parser

    add_report_parser(sub)
    from slamkit.map.mapfile_cli import add_map_parser

    add_map_parser(sub)
    bench = sub.add_parser(
        "bench",
        help="benchmarks: `slamkit bench [--json FILE] [--runners threaded,sequential] [OVERRIDES...]` runs a "
        "sequence and reports per-stage timings; `slamkit bench optimizer` compares the optimizer backends",
    )
    bench_sub = bench.add_subparsers(dest="bench_command", required=True)
    from slamkit.bench.optimizer import add_bench_optimizer_arguments, run_bench_optimizer

    bench_opt = bench_sub.add_parser(
        "optimizer", help="local BA and essential graph on every optimizer backend: wall time and final cost"
    )
    add_bench_optimizer_arguments(bench_opt)
    bench_opt.set_defaults(func=run_bench_optimizer)
    from slamkit.export.cli import add_export_parser

    add_export_parser(sub)
    ComponentRegistry.discover().add_cli_commands(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "run":
        return _run_hydra_app(argv[1:])
    if argv and argv[0] == "bench" and (len(argv) == 1 or argv[1] != "optimizer"):
        return _bench_run(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except SlamkitError as exc:
        print(f"slamkit {args.command}: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader went away (`slamkit report DIR | head`): stop quietly, as Unix tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    sys.exit(main())
