"""Worker-process mode: same results as inline, errors carried back, abort forwarded, death reported, clean close."""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator

import numpy as np
import pytest

from slamkit.errors import ConfigError, ProblemError
from slamkit.optim.factory import build_optimizer
from slamkit.optim.synthetic import make_bundle_problem, make_essential_graph_problem, make_pose_problem
from slamkit.optim.worker import OptimizerWorkerError, ProcessOptimizer
from slamkit.plugins import ComponentRegistry

REGISTRY = ComponentRegistry.discover()
NAMES = [c.spec.name for c in REGISTRY.components("optimizer")]
BACKEND = "gtsam" if "gtsam" in NAMES else (NAMES[0] if NAMES else "")
pytestmark = pytest.mark.skipif(not NAMES, reason="no optimizer registered")


def _node(worker: str, **overrides: object) -> dict[str, object]:
    node = REGISTRY.get("optimizer", BACKEND).config_node()
    node.update(worker=worker, **overrides)
    return node


@pytest.fixture(scope="module")
def worker() -> Iterator[ProcessOptimizer]:
    opt = build_optimizer(_node("process"), REGISTRY)
    assert isinstance(opt, ProcessOptimizer)
    yield opt
    opt.close()


def test_worker_gives_the_inline_result(worker: ProcessOptimizer) -> None:
    inline = build_optimizer(_node("inline"), REGISTRY)
    assert worker.name == inline.name == BACKEND
    problem, _ = make_bundle_problem(np.random.default_rng(1), n_free=4, n_fixed=3, n_points=300, n_obs=1800)
    a, b = inline.bundle_adjust(problem), worker.bundle_adjust(problem)
    assert np.allclose(a.T_c_w, b.T_c_w, atol=1e-12) and np.array_equal(a.outlier, b.outlier)
    pose, _ = make_pose_problem(np.random.default_rng(2), n_points=100)
    assert np.allclose(inline.optimize_pose(pose).T_c_w, worker.optimize_pose(pose).T_c_w, atol=1e-12)
    graph, _ = make_essential_graph_problem(np.random.default_rng(3), n_keyframes=50, n_edges=60)
    assert np.allclose(
        inline.optimize_essential_graph(graph).S_c_w, worker.optimize_essential_graph(graph).S_c_w, atol=1e-12
    )


def test_backend_errors_come_back_as_themselves(worker: ProcessOptimizer) -> None:
    problem, _ = make_pose_problem(np.random.default_rng(4), n_points=50)
    problem.xyz_w[3, 0] = np.nan
    with pytest.raises(ProblemError, match=r"xyz_w: contains NaN or inf at index \(3, 0\)"):
        worker.optimize_pose(problem)
    # the worker is still serving
    problem.xyz_w[3, 0] = 1.0
    assert worker.optimize_pose(problem).T_c_w.shape == (4, 4)


def test_abort_token_reaches_the_worker(worker: ProcessOptimizer) -> None:
    problem, _ = make_bundle_problem(np.random.default_rng(5))
    token = threading.Event()
    timer = threading.Timer(0.05, token.set)
    timer.start()
    result = worker.bundle_adjust(problem, abort=token)
    timer.join()
    assert result.aborted
    assert result.iterations < problem.iterations_first + problem.iterations_second
    # the next call starts with a cleared token
    small, _ = make_bundle_problem(np.random.default_rng(6), n_free=3, n_fixed=2, n_points=100, n_obs=400)
    assert not worker.bundle_adjust(small).aborted


def test_dead_worker_is_reported_with_its_exit_code() -> None:
    opt = build_optimizer(_node("process"), REGISTRY)
    assert isinstance(opt, ProcessOptimizer) and opt.pid is not None
    os.kill(opt.pid, signal.SIGKILL)
    problem, _ = make_pose_problem(np.random.default_rng(7), n_points=50)
    with pytest.raises(OptimizerWorkerError, match=r"died .*exit code -9 \(killed by signal 9\)"):
        opt.optimize_pose(problem)
    opt.close()  # closing a dead worker is fine


@pytest.mark.skipif(BACKEND != "gtsam", reason="uses the gtsam plugin's config keys")
def test_bad_backend_config_fails_at_construction_with_the_backend_error() -> None:
    with pytest.raises(ConfigError, match=r"optimizer\.ordering = 'BOGUS'"):
        build_optimizer(_node("process", ordering="BOGUS"), REGISTRY)


def test_unknown_worker_mode_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"optimizer.worker = 'thread': expected one of inline, process"):
        build_optimizer(_node("thread"), REGISTRY)


def test_close_and_context_manager_stop_the_worker() -> None:
    with build_optimizer(_node("process"), REGISTRY) as opt:  # type: ignore[attr-defined]
        assert isinstance(opt, ProcessOptimizer)
        process = opt._process
        assert process.is_alive()
    assert not process.is_alive() and process.exitcode == 0
    opt.close()  # idempotent
    with pytest.raises(OptimizerWorkerError, match="died while idle"):
        opt.optimize_pose(make_pose_problem(np.random.default_rng(8), n_points=50)[0])
