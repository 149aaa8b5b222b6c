"""slamkit.optim: backend-independent parts of optimization.

validation (checks every backend runs before solving), synthetic (seeded problems with known truth for tests
and benchmarks), costs (the robust cost of an estimate, identical for every backend), worker (run any backend
in a worker process) and factory (build the configured optimizer).
"""

from slamkit.optim.validation import (
    validate_bundle_problem,
    validate_essential_graph_problem,
    validate_pose_problem,
    validate_sim3_problem,
)

__all__ = [
    "validate_bundle_problem",
    "validate_essential_graph_problem",
    "validate_pose_problem",
    "validate_sim3_problem",
]
