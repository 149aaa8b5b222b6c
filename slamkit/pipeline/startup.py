"""One-off work before a timed run's clock starts, so the run's first frames do not pay for it.

Two things a live run in Python pays for that ORB-SLAM3's C++ does not, both measured on fr1_xyz in real time
(docs/BENCHMARKS.md, branch rtinit):

- **Loading the compiled kernels** (:func:`load_cached_kernels`). A ``@numba.njit(cache=True)`` kernel is not loaded
  when its module is imported but at its first call: numba reads the cache index, unpickles the object code and
  links it (20-170 ms a kernel on a 2-core Xeon, longer under load), holding up the thread that called it. In a run
  those first calls come on the frames after the map's initialisation (the two-keyframe BA, the first points'
  refresh, bag-of-words matching, motion-only BA): 0.5-0.9 s of loading on frames a real-time camera delivers every
  33 ms. ORB-SLAM3 links its code before it starts; this loads every signature the cache holds for this machine
  and this code now. Nothing is compiled here: a signature not in the cache (a fresh checkout, a changed kernel) is
  left to its first call, as before.
- **The cyclic garbage collector's full collections** (:func:`freeze_startup_heap`). After start-up the process
  holds ~150k objects the collector tracks (the modules of numpy, numba, scipy, hydra ...; the map adds ~5 per
  point); a full (generation-2) collection walks all of them, ~70-200 ms with the GIL held, which stops tracking
  whichever thread triggered it. ``gc.freeze()`` moves the objects alive at start-up into the permanent generation,
  which collections skip: a full collection then walks the map's objects only (12 ms instead of 217 ms at 300
  frames of fr1_xyz, measured under load). Reference counting still frees every object as before; only a reference
  cycle among the frozen start-up objects would no longer be reclaimed.

Neither changes any result.
"""

from __future__ import annotations

import gc
import logging
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from types import ModuleType
from typing import Any

log = logging.getLogger("slamkit.pipeline.startup")

#: The packages whose modules are searched for cached kernels: slamkit and its plugins (``slamkit_*``).
PACKAGE_PREFIXES = ("slamkit",)


@dataclass(frozen=True)
class KernelLoad:
    """What :func:`load_cached_kernels` did: ``loaded`` signatures read from the cache (over ``kernels`` kernels)
    in ``seconds`` (wall); ``skipped``: kernels whose cache could not be read (numba's internals changed)."""

    loaded: int
    kernels: int
    seconds: float
    skipped: int


def _dispatchers(modules: Iterable[ModuleType]) -> Iterator[Any]:
    """The numba dispatchers defined at the top level of ``modules``, each once."""
    from numba.core.dispatcher import Dispatcher

    seen: set[int] = set()
    for module in modules:
        for value in list(vars(module).values()):
            if isinstance(value, Dispatcher) and id(value) not in seen:
                seen.add(id(value))
                yield value


def _cached_signatures(dispatcher: Any) -> list[Any]:
    """The argument-type signatures the dispatcher's disk cache holds for this machine and this code (its index
    keys: (signature, codegen magic tuple, code hashes); numba's FunctionCache, read as its own ``load_overload``
    reads it), not yet loaded. Raises AttributeError when numba's cache internals are not the ones expected."""
    cache = dispatcher._cache
    if not getattr(cache, "_enabled", False):
        return []
    index = cache._cache_file._load_index()
    if not index:
        return []
    codegen = dispatcher.targetctx.codegen()
    wanted = []
    for key in index:
        sig = key[0]
        if cache._index_key(sig, codegen) != key:  # another CPU, numba build or version of the kernel's code
            continue
        if tuple(sig) in dispatcher.overloads:
            continue
        wanted.append(sig)
    return wanted


def load_cached_kernels(modules: Iterable[ModuleType] | None = None) -> KernelLoad:
    """Load every cached signature of the numba kernels of ``modules`` (default: every imported module of slamkit
    and its plugins) from numba's disk cache, so their first calls do not pay for it. Compiles nothing; changes
    no result. Returns what it did (logged at debug level)."""
    t0 = time.perf_counter()
    if modules is None:
        modules = [m for name, m in list(sys.modules.items()) if name.startswith(PACKAGE_PREFIXES) and m is not None]
    loaded = kernels = skipped = 0
    for dispatcher in _dispatchers(modules):
        try:
            signatures = _cached_signatures(dispatcher)
        except (AttributeError, TypeError, ValueError, OSError) as exc:  # numba internals or an unreadable index
            log.debug("kernel cache of %s not read: %s", getattr(dispatcher, "__name__", dispatcher), exc)
            skipped += 1
            continue
        if signatures:
            kernels += 1
        for sig in signatures:
            # Dispatcher.compile looks in the disk cache first: the key was just found there for this machine
            dispatcher.compile(sig)
            loaded += 1
    out = KernelLoad(loaded, kernels, time.perf_counter() - t0, skipped)
    log.debug("loaded %d cached signatures of %d kernels in %.2f s (%d caches not read)", *vars(out).values())
    return out


#: Whether :func:`freeze_startup_heap` froze objects that :func:`thaw_startup_heap` has not given back yet.
_frozen_here = False


def freeze_startup_heap() -> int:
    """Collect the garbage there is, then move every object the cyclic collector tracks into its permanent generation
    (``gc.freeze``), so later collections do not walk the start-up objects again (module docstring). Returns how many
    objects are frozen. Idempotent (a second call freezes only what was created since). A run that called it calls
    :func:`thaw_startup_heap` when it ends."""
    global _frozen_here
    gc.collect()
    gc.freeze()
    _frozen_here = True
    return gc.get_freeze_count()


def thaw_startup_heap() -> int:
    """Give the objects :func:`freeze_startup_heap` froze back to the cyclic collector (``gc.unfreeze``), when a run
    ends: a process that goes on after the run (an embedding application, a test session running many runs) would
    otherwise never reclaim a reference cycle among what was alive at each run's start (the previous run's map, if
    it was still referenced then). Does nothing when nothing was frozen here (a caller's own ``gc.freeze`` stays).
    Returns how many objects were given back."""
    global _frozen_here
    if not _frozen_here:
        return 0
    n = gc.get_freeze_count()
    gc.unfreeze()
    _frozen_here = False
    return n


__all__ = ["KernelLoad", "freeze_startup_heap", "load_cached_kernels", "thaw_startup_heap"]
