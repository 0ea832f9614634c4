"""The kernel families of a storage, built on first use and cached per frozen config.

Each family is a factory ``build(storage, cfg) -> Bound`` (kernels/trace.py,
kernels/update.py); a variant is compiled by Taichi at its first call, which on_compile's
listeners hear of (a map's first scan compiles its path's kernels and the tree path's:
ScanUpdate.compile_tree_path). Taichi kernels are shared by every KernelSet of a storage;
a KernelSet decides how they are launched.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace

from . import launch, trace, update
from .layout import Storage
from .trace import RaysConfig
from .update import FreeConfig, MergeConfig

# Kernels of every scan get the lighter call (launch.py); the rest keep Taichi's.
_PER_SCAN = {
    "prepare",
    "hits_count",
    "hits_sum",
    "hits_group",
    "hits_dense",
    "merge",
    "rays",
    "mark_gaussians",
    "block_apply",
    "apply_marked",
    "apply_free",
    "apply_free_all",
    "reset_rays",
}


# Told the name of each kernel variant just before its first call in this process (the call
# that compiles it, or loads it from Taichi's offline cache): the command line says so.
_listeners: list[Callable[[str], None]] = []


def on_compile(fn: Callable[[str], None]) -> Callable[[], None]:
    """Call ``fn(kernel_name)`` before each kernel variant's first call; returns a function
    that stops it."""
    _listeners.append(fn)

    def stop() -> None:
        if fn in _listeners:
            _listeners.remove(fn)

    return stop


class KernelSet:
    """The update kernels of one storage, by family and config: ``ks.merge(MergeConfig(...))``
    is a Bound kernel, called by keyword. ``fast``: launch the per-scan ones through
    launch.Launcher (default: where launch.enabled())."""

    def __init__(self, f: Storage, fast: bool | None = None):
        self.storage = f
        self.fast = launch.enabled() if fast is None else bool(fast)
        self._bound: dict = {}

    def _get(self, build, cfg):
        key = (build.__name__, cfg)
        b = self._bound.get(key)
        if b is None:
            cache = self.storage.__dict__.setdefault("kernel_cache", {})
            raw = cache.get(key)
            if raw is None:
                for fn in _listeners:
                    fn(build.__name__)
                raw = cache[key] = build(self.storage, cfg)
            b = raw.launched(launch.Launcher) if self.fast and build.__name__ in _PER_SCAN else raw
            self._bound[key] = b
        return b

    # ray traversal
    def rays(self, cfg: RaysConfig):
        return self._get(trace.rays, cfg)

    def mark_gaussians(self, bt: str):
        return self._get(trace.mark_gaussians, bt)

    def reset_rays(self):
        return self._get(trace.reset_rays, None)

    def reset_rays_all(self):
        return self._get(trace.reset_rays_all, None)

    def count_new_nodes(self, dedup: bool):
        return self._get(trace.count_new_nodes, bool(dedup))

    # occupancy update
    def prepare(self):
        return self._get(update.prepare, None)

    def hits_count(self):
        return self._get(update.hits_count, None)

    def hits_sum(self):
        return self._get(update.hits_sum, None)

    def hits_group(self):
        return self._get(update.hits_group, None)

    def hits_dense(self, bt: str):
        return self._get(update.hits_dense, bt)

    def merge(self, cfg: MergeConfig):
        return self._get(update.merge, cfg)

    def block_apply(self, cfg: FreeConfig):
        return self._get(update.block_apply, cfg)

    def apply_marked(self):
        return self._get(update.apply_marked, None)

    def apply_free(self, ndt: bool):
        return self._get(update.apply_free, bool(ndt))

    def apply_free_all(self, ndt: bool):
        return self._get(update.apply_free_all, bool(ndt))

    def ndt_refresh(self):
        return self._get(update.ndt_refresh, None)

    def erased_near(self):
        return self._get(update.erased_near, None)

    # queries, export, load (plain Taichi kernels, few arguments)
    @property
    def io(self) -> SimpleNamespace:
        from .io import io_kernels

        return io_kernels(self.storage)


def kernel_set(f: Storage, fast: bool | None = None) -> KernelSet:
    """The KernelSet of storage ``f`` (one per launch kind, kept on the storage)."""
    fast = launch.enabled() if fast is None else bool(fast)
    sets = f.__dict__.setdefault("kernel_sets", {})
    ks = sets.get(fast)
    if ks is None:
        ks = sets[fast] = KernelSet(f, fast)
    return ks
