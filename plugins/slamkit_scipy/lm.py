"""A Levenberg-Marquardt driver shared by the solvers (Nielsen's damping update, as g2o's LM).

Each problem supplies three callables over its own state type X:
  linearize(x) -> (system, g, cost, hmax): the Gauss-Newton system at x (with IRLS weights), the gradient
      g = J^T W r flattened, the robust cost at x, and max diag(H) for the initial damping (a float, or a
      zero-argument callable giving it: the driver reads it at its first linearization only);
  solve(system, lam) -> h: the step solving (H + lam I) h = -g;
  retract(x, h) -> x': the updated state; cost(x) -> float the robust cost (same kernel weights rule).
One iteration is one linearization followed by up to ``max_trials`` damped solves until a step lowers
the cost (g2o's OptimizationAlgorithmLevenberg does the same with 10 trials).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np

from slamkit.interfaces import AbortToken

X = TypeVar("X")


@dataclass(frozen=True)
class LMSettings:
    """tau: initial damping = tau * max diag(H) (Nielsen/g2o: 1e-5); lambda_init: an absolute initial damping
    instead (g2o's setUserLambdaInit); max_trials: damped solves per iteration; rel_tol: stop when an
    accepted step lowers the cost by less than rel_tol * cost."""

    tau: float = 1e-5
    lambda_init: float | None = None
    max_trials: int = 10
    rel_tol: float = 1e-10


@dataclass
class LMOutcome(Generic[X]):
    """x: final state; cost_initial/cost_final: robust costs; iterations run; aborted by the token."""

    x: X
    cost_initial: float
    cost_final: float
    iterations: int
    aborted: bool
    converged: bool


def levenberg_marquardt(
    x: X,
    linearize: Callable[[X], tuple[Any, np.ndarray, float, float | Callable[[], float]]],
    solve: Callable[[Any, float], np.ndarray],
    retract: Callable[[X, np.ndarray], X],
    cost: Callable[[X], float],
    iterations: int,
    settings: LMSettings,
    abort: AbortToken | None = None,
) -> LMOutcome[X]:
    """Run up to ``iterations`` LM iterations from x (linearize also returns max diag(H) for the damping, read once:
    a callable is called only then)."""
    lam = -1.0
    nu = 2.0
    f0 = f = float("nan")
    done = 0
    converged = False
    stale = True  # the linear system must be rebuilt at x
    system: Any = None
    g = np.zeros(0)
    for _ in range(iterations):
        if abort is not None and abort.is_set():
            return LMOutcome(x, f0 if done else cost(x), f if done else cost(x), done, True, False)
        if stale:
            system, g, f, hmax = linearize(x)
            if done == 0:
                f0 = f
            stale = False
        if lam < 0.0:
            if settings.lambda_init is not None:
                lam = settings.lambda_init
            else:
                lam = settings.tau * max(hmax() if callable(hmax) else hmax, 1e-12)
        accepted = False
        decrease = 0.0
        for _trial in range(settings.max_trials):
            h = solve(system, lam)
            if not np.all(np.isfinite(h)):
                lam *= nu
                nu *= 2.0
                continue
            predicted = float(h @ (lam * h - g))
            if predicted <= settings.rel_tol * f:
                break  # the model promises less than the tolerance: converged (no step would count)
            x_new = retract(x, h)
            f_new = cost(x_new)
            rho = (f - f_new) / predicted if predicted > 0.0 else -1.0
            if rho > 0.0 and np.isfinite(f_new):
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                accepted = True
                decrease = f - f_new
                x, f = x_new, f_new
                stale = True
                break
            lam *= nu
            nu *= 2.0
        done += 1
        if not accepted or decrease <= settings.rel_tol * max(f, 1e-300):
            # no damped step lowers the cost, or the decrease is negligible: converged to precision
            converged = True
            break
    if done == 0:
        f0 = f = cost(x)
    return LMOutcome(x, f0, f, done, False, converged)
