"""A per-thread hint to components that share their work among worker threads: keep it in the calling thread.

The ORB extractor deals an image's pyramid levels out to ``features.n_threads`` threads, which pays when the
extraction is on the critical path and the other core is idle (the sequential runner, tracking's own extraction).
When the extraction runs beside another busy thread instead — the threaded runner's frames extracted ahead of
tracking while local mapping works (slamkit/runtime/extract_ahead.py) — a second extraction thread only takes the
core from the thread everything waits for. The runner then wraps the extraction in :func:`single_threaded`, and a
component that would start worker threads asks :func:`is_single_threaded` first. The hint changes where work runs,
never its result (the ORB extractor's keypoints do not depend on its thread count).

The hint is thread-local: it holds for work started in the thread that entered the block, not in other threads.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

_local = threading.local()


@contextlib.contextmanager
def single_threaded() -> Iterator[None]:
    """Inside this block, work started by the current thread stays in it (nestable)."""
    depth = getattr(_local, "depth", 0)
    _local.depth = depth + 1
    try:
        yield
    finally:
        _local.depth = depth


def is_single_threaded() -> bool:
    """Whether the current thread is inside :func:`single_threaded`: a component should not hand its work to worker
    threads."""
    return getattr(_local, "depth", 0) > 0
