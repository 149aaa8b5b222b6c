"""Record the local/global BA problems of a real run, for ``slamkit bench optimizer --problems DIR``.

Usage: ``python benchmarks/capture_ba_problems.py OUTDIR [slamkit run overrides...]``, e.g.
``python benchmarks/capture_ba_problems.py /tmp/ba_room runner=sequential`` or, on fr1_xyz,
``... /tmp/ba_fr1 runner=sequential dataset=tum_rgbd dataset.root=... dataset.use_depth=false``.

Every BundleProblem the configured optimizer receives (local BA of each keyframe, the initial map's global BA,
global BA after a loop) is pickled to OUTDIR/ba_NNNN.pkl before the optimizer solves it; the run itself is
unchanged (the wrapper forwards to the backend). Works with the sequential runner (the threaded runner's
worker process, if any, is not wrapped).
"""

from __future__ import annotations

import pickle
import sys
from pathlib import Path
from typing import Any


def main(argv: list[str]) -> int:
    """Patch every registered optimizer class's bundle_adjust to pickle its problem, then ``slamkit run``."""
    if not argv:
        print(__doc__)
        return 2
    out = Path(argv[0])
    out.mkdir(parents=True, exist_ok=True)
    from slamkit.cli import main as slamkit_main
    from slamkit.plugins import ComponentRegistry

    counter = [0]
    registry = ComponentRegistry.discover()
    for comp in registry.components("optimizer"):
        module_name, _, cls_name = comp.spec.target.rpartition(".")
        cls = getattr(__import__(module_name, fromlist=[cls_name]), cls_name)
        original = cls.bundle_adjust

        def recording(self: Any, problem: Any, abort: Any = None, _original: Any = original) -> Any:
            (out / f"ba_{counter[0]:04d}.pkl").write_bytes(pickle.dumps(problem, protocol=pickle.HIGHEST_PROTOCOL))
            counter[0] += 1
            return _original(self, problem, abort)

        cls.bundle_adjust = recording
    code = slamkit_main(["run", *argv[1:]])
    print(f"{counter[0]} bundle problems written to {out}")
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
