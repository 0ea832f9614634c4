"""The one place Taichi is initialised, and the process-wide pool of map storage."""

from __future__ import annotations

import math
import numbers
import os
import threading
from dataclasses import dataclass

ARCHS = ("auto", "cpu", "cuda")

# Taichi 1.7.4's CPU memory pool hands out memory past the end of every 1 GiB host chunk
# after its first (README "Memory"): the pool must never need a second chunk. All maps
# share one storage whose pool use is computed exactly (node counts and chunk sizes), and
# an update that could pass the budget is refused before any kernel allocates.
CPU_POOL_LIMIT_BYTES = 896 * 2**20
CPU_POOL_HARD_MAX_BYTES = 960 * 2**20
DEFAULT_MAX_MAPS = 8


class MapMemoryError(MemoryError):
    """A scan or load would take the map storage past its memory budget."""


@dataclass
class _State:
    arch: str | None = None
    pool_limit: int = CPU_POOL_LIMIT_BYTES
    max_maps: int = DEFAULT_MAX_MAPS
    pinned: tuple = ()  # (thread id, cpu) of each pinned Taichi worker


_state = _State()
_lock = threading.Lock()
_storages: dict = {}  # Layout -> Storage shared by all maps of that layout


def init(
    arch: str = "auto",
    *,
    device_memory_GB: float | None = None,
    memory_limit_GB: float | None = None,
    max_maps: int | None = None,
    offline_cache: bool = True,
    cpu_max_num_threads: int | None = None,
    pin_threads: bool | None = None,
    debug: bool = False,
) -> str:
    """Initialise Taichi for ndtom_ti and return the arch in use ("cpu" or "cuda").

    arch: "auto" picks CUDA when a CUDA device is present, else the CPU; the environment
        variable NDTOM_ARCH overrides "auto".
    device_memory_GB: CUDA only: the memory pool Taichi preallocates (default 4 GiB).
    memory_limit_GB: budget of Taichi's memory pool for all maps' sparse trees. On the CPU
        it may not exceed 0.9375 GiB (Taichi 1.7.4 allocator bug, see README "Memory");
        default 0.875. On CUDA it defaults to 90% of the device pool.
    max_maps: how many maps may exist at once (default 8); each has a slot in the
        shared storage, fixed when the first map is made.
    pin_threads: on the CPU under Linux, fix each of Taichi's worker threads to a CPU of
        its own (affinity.py: short loops then run on all of them). Default: on, unless
        the environment variable NDTOM_PIN_THREADS is 0.

    Calling it again with the same arch (or "auto") is a no-op; another arch is an error
    because Taichi cannot change arch without destroying every existing map.
    """
    if arch not in ARCHS:
        raise ValueError(f"arch must be one of {ARCHS}, got {arch!r}")
    for name, gib in (("device_memory_GB", device_memory_GB), ("memory_limit_GB", memory_limit_GB)):
        if gib is None:
            continue
        if isinstance(gib, bool) or not isinstance(gib, numbers.Real):  # "1" * 2**30 would build a string
            raise TypeError(f"{name} must be a number of GiB, got {gib!r} ({type(gib).__name__})")
        if not (math.isfinite(gib) and gib > 0):
            raise ValueError(f"{name} must be a positive number of GiB, got {gib!r}")
    with _lock:
        if _state.arch is not None:
            if arch not in ("auto", _state.arch):
                raise RuntimeError(
                    f"ndtom_ti is already initialised with arch={_state.arch!r}; a process "
                    f"has one arch (re-initialising Taichi would destroy every map). "
                    f"Start a new process to use arch={arch!r}."
                )
            if memory_limit_GB is not None:
                _state.pool_limit = _check_limit(memory_limit_GB, _state.arch, None)
            if max_maps is not None and max_maps != _state.max_maps:
                if _storages:
                    raise RuntimeError("max_maps can only be set before the first map is made")
                _state.max_maps = _check_max_maps(max_maps)
            return _state.arch

        import taichi as ti

        if arch == "auto":
            arch = os.environ.get("NDTOM_ARCH", "auto")
            if arch not in ARCHS:
                raise ValueError(f"NDTOM_ARCH must be one of {ARCHS}, got {arch!r}")
        if max_maps is not None:
            _state.max_maps = _check_max_maps(max_maps)
        kwargs = dict(offline_cache=offline_cache, debug=debug, log_level=ti.WARN)
        if cpu_max_num_threads:
            kwargs["cpu_max_num_threads"] = cpu_max_num_threads
        pool_gb = device_memory_GB or 4.0
        if arch == "cuda" or (arch == "auto" and _cuda_driver_present()):
            try:
                ti.init(arch=ti.cuda, device_memory_GB=pool_gb, **kwargs)
            except Exception as exc:  # noqa: BLE001 - Taichi raises various types here
                if arch == "cuda":
                    raise RuntimeError(f"CUDA was requested but could not be initialised: {exc}") from exc
            if ti.lang.impl.current_cfg().arch == ti.cuda:
                _state.arch = "cuda"
            elif arch == "cuda":
                raise RuntimeError("CUDA was requested but no CUDA device is available; use arch='cpu'.")
        if _state.arch is None:
            ti.init(arch=ti.cpu, **kwargs)
            _state.arch = "cpu"
            if pin_threads is None:
                pin_threads = os.environ.get("NDTOM_PIN_THREADS", "1") not in ("0", "")
            if pin_threads:
                from .affinity import pin_pool
                from .kernels.ndt import cpu_threads

                _state.pinned = tuple(pin_pool(cpu_threads()))
        _state.pool_limit = _check_limit(memory_limit_GB, _state.arch, pool_gb)
        return _state.arch


def _cuda_driver_present() -> bool:
    import ctypes.util

    return ctypes.util.find_library("cuda") is not None


def _check_limit(limit_gb: float | None, arch: str, pool_gb: float | None) -> int:
    if arch == "cuda":
        if limit_gb is None:
            return int(0.9 * (pool_gb or 4.0) * 2**30)
        return int(limit_gb * 2**30)
    if limit_gb is None:
        return CPU_POOL_LIMIT_BYTES
    limit = int(limit_gb * 2**30)
    if limit <= 0:
        raise ValueError(f"memory_limit_GB must be positive, got {limit_gb}")
    if limit > CPU_POOL_HARD_MAX_BYTES:
        raise ValueError(
            f"memory_limit_GB={limit_gb} is above the {CPU_POOL_HARD_MAX_BYTES / 2**30:.4f} GiB the CPU "
            "backend can hold safely: Taichi 1.7.4's CPU pool corrupts memory once it grows "
            "past its first 1 GiB chunk. Use a coarser resolution, a smaller max_range, or a "
            "CUDA device for larger maps."
        )
    return limit


def current_arch() -> str | None:
    return _state.arch


def pinned_threads() -> list[tuple[int, int]]:
    """(thread id, cpu) of the Taichi workers fixed to a CPU by init (empty if none)."""
    return list(_state.pinned)


def ensure_init() -> str:
    return _state.arch or init()


def pool_limit() -> int:
    return _state.pool_limit


def _check_max_maps(n) -> int:
    if isinstance(n, bool) or int(n) != n or not 1 <= n <= 64:
        raise ValueError(f"max_maps must be an integer in [1, 64], got {n!r}")
    return int(n)


def storage(layout):
    """The storage shared by all maps of ``layout`` (built on first use)."""
    from ndtom_ti.kernels.layout import Storage

    ensure_init()
    with _lock:
        st = _storages.get(layout)
        if st is None:
            if _storages:
                raise ValueError(
                    "all maps in a process share one grid layout (Taichi's pool cannot hold "
                    f"two safely); this process uses {next(iter(_storages))}, not {layout}"
                )
            st = _storages[layout] = Storage(layout, _state.max_maps)
        return st


def acquire_slot(layout):
    """(storage, slot) for a new map."""
    st = storage(layout)
    with _lock:
        if not st.free_slots:
            raise RuntimeError(
                f"{st.slots} maps exist already, the most this process allows at once; delete "
                "maps you no longer need (del m) or call ndtom_ti.init(max_maps=...) before "
                "making the first map"
            )
        return st, st.free_slots.pop()


def release_slot(st, slot: int) -> None:
    """Empty a dead map's slot (its nodes go back to Taichi's free lists) and free it."""
    try:
        st.kernels.clear_slot(slot)
    except Exception:  # noqa: BLE001 - interpreter shutdown: nothing to keep
        return
    st.leaf_count[slot] = 0
    st.occ_regions[slot] = 0
    st.gidx_regions[slot] = 0
    st.forget(slot)
    with _lock:
        st.free_slots.append(slot)
