"""Run any optimizer backend in one long-lived worker process (``optimizer.worker=process``).

GTSAM holds the GIL for the whole of a C++ call, so an inline local BA freezes tracking. ProcessOptimizer is an
Optimizer that forwards each call to a worker process which built the backend from its config node; problems and
results are plain arrays and pickle cheaply. The abort token of ``bundle_adjust`` is bridged to a
multiprocessing Event that the worker's backend checks between iterations. One request runs at a time (a lock
serialises callers). If the worker dies, the call raises OptimizerWorkerError with its exit code and, when it
could still report one, its traceback; an exception raised by the backend (ProblemError, ...) is re-raised in the
caller as itself. close() (also the context manager's exit, and an atexit hook) stops the worker cleanly.
"""

from __future__ import annotations

import atexit
import contextlib
import multiprocessing as mp
import threading
import traceback
import weakref
from collections.abc import Mapping
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from types import TracebackType
from typing import Any

from slamkit.errors import SlamkitError
from slamkit.interfaces import AbortToken
from slamkit.problems import (
    BundleProblem,
    BundleResult,
    EssentialGraphProblem,
    EssentialGraphResult,
    PoseOnlyProblem,
    PoseOnlyResult,
    Sim3Problem,
    Sim3Result,
)

__all__ = ["OptimizerWorkerError", "ProcessOptimizer"]

_POLL_S = 0.005  # how often the caller checks its abort token and the worker's health while waiting
_START_TIMEOUT_S = 120.0  # building the backend imports numpy/scipy/gtsam in a fresh interpreter
_METHODS = ("optimize_pose", "bundle_adjust", "optimize_sim3", "optimize_essential_graph")


class OptimizerWorkerError(SlamkitError):
    """The optimizer worker process died, could not start, or sent something unusable."""


def _pickles(obj: object) -> bool:
    import pickle

    try:
        pickle.dumps(obj)
    except Exception:
        return False
    return True


def _serve(node: dict[str, Any], conn: Connection, abort: Any) -> None:
    """Worker main loop: build the backend, then answer (method, problem) requests until ("close",)."""
    try:
        from slamkit.plugins import ComponentRegistry

        backend = ComponentRegistry.discover().instantiate("optimizer", node)
    except BaseException as exc:
        conn.send(("fatal", exc if _pickles(exc) else None, traceback.format_exc()))
        conn.close()
        return
    conn.send(("ready", str(getattr(backend, "name", type(backend).__name__))))
    while True:
        try:
            request = conn.recv()
        except EOFError:  # the parent went away
            return
        if request[0] == "close":
            conn.close()
            return
        method, problem = request
        try:
            if method == "bundle_adjust":
                result = backend.bundle_adjust(problem, abort=abort)
            else:
                result = getattr(backend, method)(problem)
            conn.send(("ok", result))
        except Exception as exc:
            conn.send(("error", exc if _pickles(exc) else None, traceback.format_exc()))


def _shutdown(conn: Connection, process: BaseProcess, lock: threading.Lock) -> None:
    """Ask the worker to exit, then make sure it did (atexit / weakref finalizer; must not hold the proxy)."""
    with lock:
        if process.is_alive():
            with contextlib.suppress(OSError, ValueError):
                conn.send(("close",))
            process.join(timeout=5.0)
        if process.is_alive():
            process.terminate()
            process.join(timeout=5.0)
        conn.close()


class ProcessOptimizer:
    """An Optimizer whose backend lives in a worker process built from ``node`` (a composed optimizer config
    node with ``_target_``, without the ``worker`` key). ``start_method``: multiprocessing start method; "spawn"
    (default) gives the worker a fresh interpreter, safe whatever threads the caller runs."""

    def __init__(self, node: Mapping[str, Any], start_method: str = "spawn") -> None:
        ctx: Any = mp.get_context(start_method)
        self._node = dict(node)
        self._abort = ctx.Event()
        self._conn, child = ctx.Pipe(duplex=True)
        self._process = ctx.Process(
            target=_serve, args=(self._node, child, self._abort), name="slamkit-optimizer", daemon=True
        )
        self._lock = threading.Lock()
        self._process.start()
        child.close()
        self._finalizer = weakref.finalize(self, _shutdown, self._conn, self._process, self._lock)
        atexit.register(self._finalizer)
        message = self._receive(timeout_s=_START_TIMEOUT_S, what="starting the backend")
        if message[0] != "ready":  # pragma: no cover - _receive raises on anything else
            raise OptimizerWorkerError(f"optimizer worker sent {message[0]!r} instead of 'ready'")
        self.name: str = message[1]

    # ---- plumbing -----------------------------------------------------------------------------------

    @property
    def pid(self) -> int | None:
        """The worker's process id."""
        return self._process.pid

    def _died(self, what: str) -> OptimizerWorkerError:
        self._process.join(timeout=1.0)
        code = self._process.exitcode
        return OptimizerWorkerError(
            f"the optimizer worker (pid {self._process.pid}, target {self._node.get('_target_')}) died while "
            f"{what}: exit code {code}" + (f" (killed by signal {-code})" if code is not None and code < 0 else "")
        )

    def _receive(self, timeout_s: float | None, what: str, abort: AbortToken | None = None) -> tuple[Any, ...]:
        waited = 0.0
        while True:
            if abort is not None and abort.is_set():
                self._abort.set()
            try:
                if self._conn.poll(_POLL_S):
                    message: tuple[Any, ...] = self._conn.recv()
                    break
            except (EOFError, OSError):
                raise self._died(what) from None
            if not self._process.is_alive() and not self._conn.poll(0):
                raise self._died(what)
            waited += _POLL_S
            if timeout_s is not None and waited > timeout_s:
                raise OptimizerWorkerError(f"the optimizer worker did not answer within {timeout_s:.0f} s while {what}")
        if message[0] in ("error", "fatal"):
            exc, tb = message[1], message[2]
            if message[0] == "fatal":
                self._process.join(timeout=5.0)
            if isinstance(exc, BaseException):
                raise exc from OptimizerWorkerError(f"raised in the optimizer worker:\n{tb}")
            raise OptimizerWorkerError(f"the optimizer worker failed while {what}:\n{tb}")
        return message

    def _call(self, method: str, problem: object, abort: AbortToken | None = None) -> Any:
        with self._lock:
            if not self._process.is_alive():
                raise self._died(f"idle (before {method})")
            self._abort.clear()
            try:
                self._conn.send((method, problem))
            except (OSError, ValueError):
                raise self._died(f"receiving {method}") from None
            return self._receive(None, f"running {method}", abort)[1]

    # ---- Optimizer ----------------------------------------------------------------------------------

    def optimize_pose(self, problem: PoseOnlyProblem) -> PoseOnlyResult:
        """Motion-only BA in the worker."""
        result: PoseOnlyResult = self._call("optimize_pose", problem)
        return result

    def bundle_adjust(self, problem: BundleProblem, abort: AbortToken | None = None) -> BundleResult:
        """BA in the worker; ``abort`` (any token with is_set) is forwarded to the worker's backend."""
        result: BundleResult = self._call("bundle_adjust", problem, abort)
        return result

    def optimize_sim3(self, problem: Sim3Problem) -> Sim3Result:
        """Relative Sim3 in the worker."""
        result: Sim3Result = self._call("optimize_sim3", problem)
        return result

    def optimize_essential_graph(self, problem: EssentialGraphProblem) -> EssentialGraphResult:
        """Essential-graph optimization in the worker."""
        result: EssentialGraphResult = self._call("optimize_essential_graph", problem)
        return result

    # ---- lifetime -----------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the worker (idempotent)."""
        self._finalizer()

    def __enter__(self) -> ProcessOptimizer:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
