"""The one place Taichi is initialised, and the process-wide pool of map storage."""

from __future__ import annotations

import contextlib
import io
import math
import numbers
import os
import threading
import warnings
from dataclasses import dataclass, replace
from typing import Any

ARCHS = ("auto", "cpu", "cuda")

# Taichi 1.7.4's CPU memory pool hands out memory past the end of every host chunk after
# its first (README "Memory"): the pool must never need a second chunk. The first chunk is
# sized to the budget before ti.init (hostpool.py; 1 GiB when that is not possible). All
# maps share one storage whose pool use is computed exactly (node counts and chunk sizes),
# and an update that could pass the budget is refused before any kernel allocates.
CPU_POOL_LIMIT_BYTES = 896 * 2**20  # the budget within Taichi's own 1 GiB chunk
CPU_POOL_HARD_MAX_BYTES = 960 * 2**20
CPU_DEFAULT_SHARE = 0.5  # default CPU budget: this share of the machine's memory
CUDA_DEFAULT_SHARE = 0.5  # default CUDA pool: this share of the device's memory
DEFAULT_MAX_MAPS = 8
MAX_THREADS = 1024  # init(cpu_max_num_threads=...)


def chunk_for(budget: int) -> int:
    """The one pool chunk a CPU budget needs: the budget, plus room for what Taichi takes
    from the pool besides nodes (its runtime; struct-for element lists, ~2% of the leaves'
    bytes): 1/16 and 128 MiB, in whole MiB."""
    return -(-(budget + budget // 16 + 128 * 2**20) // 2**20) * 2**20


class NoFreeSlotError(RuntimeError):
    """Every map slot of the process is taken (``init(max_maps=...)``)."""


class MapMemoryError(MemoryError):
    """A scan or load would take the map storage past its memory budget."""


@dataclass
class _State:
    arch: str | None = None
    pool_limit: int = CPU_POOL_LIMIT_BYTES
    pool_max: int = CPU_POOL_HARD_MAX_BYTES  # the most the budget may be raised to later
    pool_chunk: int = 1 << 30  # CPU: bytes of the pool's one chunk
    pool_note: str | None = None  # why the CPU budget is below the one asked for
    max_maps: int = DEFAULT_MAX_MAPS
    pinned: tuple = ()  # (thread id, cpu) of each pinned Taichi worker
    huge_pages: int = 0  # bytes of the CPU pool advised MADV_HUGEPAGE
    taichi: Any = None  # Taichi's runtime object that init() started (check_taichi)
    ready: bool = False  # init() done, its default storage built
    pid: int | None = None  # the process that started Taichi (a forked child has another)
    init_thread: Any = None  # the thread that started Taichi: the only one that may build trees


_state = _State()
_lock = threading.Lock()
# Held by init() to its end (the default storage built too): another thread's first map
# waits for it, as Taichi builds a tree's code only in the thread that called ti.init.
_init_lock = threading.RLock()
_storages: dict = {}  # Layout -> Storage shared by all maps of that layout
_used: set = set()  # the layouts whose storage has held a map


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
    device_memory_GB: CUDA only: the memory pool Taichi preallocates (default: half of
        the device's memory; 4 GiB when it cannot be read).
    memory_limit_GB: budget of Taichi's memory pool for all maps' sparse trees. On the
        CPU the default is half of the machine's memory (or of a lower cgroup limit), and
        Taichi's pool is made one chunk of that size before it starts (Taichi 1.7.4
        corrupts memory past its first chunk, see README "Memory"); where that cannot be
        done safely the budget stays within Taichi's 1 GiB chunk (0.875 GiB, at most
        0.9375) and ``pool_note()`` says why. Later calls may lower it, or raise it back
        up to the budget the pool was sized for. On CUDA it defaults to 90% of the device
        pool.
        On Linux the CPU pool is advised transparent huge pages (``huge_pages()``;
        the environment variable NDTOM_HUGE_PAGES=0 turns that off).
    max_maps: how many maps may exist at once (default 8); each has a slot in the
        shared storage, fixed when the first map is made.
    cpu_max_num_threads: Taichi's worker threads on the CPU, a positive integer (default:
        one per CPU).
    pin_threads: on the CPU under Linux, fix each of Taichi's worker threads to a CPU of
        its own (affinity.py: short loops then run on all of them). Default: off, as a
        library should leave its host process's threads alone, unless the environment
        variable NDTOM_PIN_THREADS is 1; the ``ndtom`` command turns it on
        (``--no-pin-threads`` to leave it off).

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
    # (Taichi's own errors for these are C++ ones: "vector::_M_default_append", pybind's TypeError;
    # and it starts every thread asked for at once)
    n = cpu_max_num_threads
    if n is not None and (isinstance(n, bool) or not isinstance(n, numbers.Integral) or not 1 <= n <= MAX_THREADS):
        raise ValueError(
            f"cpu_max_num_threads must be an integer from 1 to {MAX_THREADS} (threads), or None for Taichi's "
            f"default (one per CPU); got {n!r}"
        )
    with _init_lock:
        return _init(
            arch, device_memory_GB, memory_limit_GB, max_maps, offline_cache, cpu_max_num_threads, pin_threads, debug
        )


def _init(
    arch: str,
    device_memory_GB: float | None,
    memory_limit_GB: float | None,
    max_maps: int | None,
    offline_cache: bool,
    cpu_max_num_threads: int | None,
    pin_threads: bool | None,
    debug: bool,
) -> str:
    """init() past its checks of the arguments, holding _init_lock."""
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
                if _used:
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
        kwargs = {"offline_cache": offline_cache, "debug": debug, "log_level": ti.WARN}
        if cpu_max_num_threads is not None:
            kwargs["cpu_max_num_threads"] = int(cpu_max_num_threads)
        pool_gb = device_memory_GB
        if arch == "cuda" or (arch == "auto" and _cuda_driver_present()):
            if pool_gb is None:  # sized from the device (no bug there: one exact preallocation)
                total = _cuda_device_memory()
                pool_gb = max(0.5, round(CUDA_DEFAULT_SHARE * total / 2**30 * 4) / 4) if total else 4.0
            try:
                _quiet(ti.init, arch=ti.cuda, device_memory_GB=pool_gb, **kwargs)
            except Exception as exc:  # Taichi raises various types here
                if arch == "cuda":
                    raise RuntimeError(f"CUDA was requested but could not be initialised: {exc}") from exc
            from taichi.lang import impl

            if impl.current_cfg().arch == ti.cuda:
                _state.arch = "cuda"
            elif arch == "cuda":
                raise RuntimeError("CUDA was requested but no CUDA device is available; use arch='cpu'.")
        if _state.arch is None:
            _init_cpu(ti, memory_limit_GB, kwargs)
            _state.arch = "cpu"
            if pin_threads is None:
                pin_threads = os.environ.get("NDTOM_PIN_THREADS", "0") not in ("0", "")
            if pin_threads:
                from .affinity import pin_pool
                from .kernels.ndt import cpu_threads

                _state.pinned = tuple(pin_pool(cpu_threads()))
        if _state.arch == "cuda":
            _state.pool_limit = _check_limit(memory_limit_GB, _state.arch, pool_gb)
            _state.pool_max = 1 << 62
        # Taichi adds a tree's code (its struct module) only from the thread that called
        # ti.init: its default tree is materialized now, not by the first kernel launch,
        # which may be a worker thread's (a reader's first known_cells() or save()).
        from taichi.lang import impl

        from .compiling import fast_frontend

        fast_frontend()
        _state.init_thread = threading.current_thread()
        impl.get_runtime().materialize()
        _state.taichi = impl.get_runtime()
        _state.pid = os.getpid()
        if hasattr(os, "register_at_fork"):
            os.register_at_fork(after_in_child=_keep_taichi_in_child)
    # Likewise the maps' storage (its trees are built when the first map is made, maybe in a
    # worker thread): built now for the default layout. An unused one gives way to another
    # layout or max_maps (storage()).
    storage(None)
    _state.ready = True
    return _state.arch


def _quiet(fn, *args, **kwargs):
    """Call ``fn`` without its prints: ti.init prints "[Taichi] Starting on arch=..." to
    stdout, which a library's user did not ask for (its warnings still go to the log)."""
    with contextlib.redirect_stdout(io.StringIO()):
        return fn(*args, **kwargs)


def _init_cpu(ti, memory_limit_GB: float | None, kwargs: dict) -> None:
    """ti.init on the CPU with the pool's one chunk sized to the budget, or Taichi's own
    1 GiB chunk and the budget within it when that cannot be done safely (pool_note)."""
    from . import hostpool

    mem = hostpool.physical_memory()
    if memory_limit_GB is None:
        want = int(CPU_DEFAULT_SHARE * mem)
    else:
        want = _positive_limit(memory_limit_GB)
        if want > mem:
            raise ValueError(
                f"memory_limit_GB={memory_limit_GB} is more than this machine's {mem / 2**30:.1f} GiB of memory; "
                "give a smaller budget"
            )
    legacy = min(want, CPU_POOL_LIMIT_BYTES if memory_limit_GB is None else CPU_POOL_HARD_MAX_BYTES)
    before = hostpool.anonymous_mappings()  # the pool chunk is the mapping ti.init adds
    if want <= CPU_POOL_HARD_MAX_BYTES:  # fits Taichi's own first chunk
        _quiet(ti.init, arch=ti.cpu, **kwargs)
        _huge_pages(before)
        _state.pool_limit, _state.pool_max, _state.pool_chunk = want, CPU_POOL_HARD_MAX_BYTES, 1 << 30
        return
    why = None
    try:
        cell = hostpool.chunk_size_cell()
    except (hostpool.GuardFailed, OSError, ValueError) as exc:
        cell, why = None, str(exc)
    chunk = chunk_for(want)
    if cell is not None and not hostpool.address_space_for(chunk):
        cell, why = None, f"Taichi could not map a {chunk / 2**30:.1f} GiB pool (Linux refuses that address space)"
    if cell is not None:
        cell.value = chunk
        try:
            _quiet(ti.init, arch=ti.cpu, **kwargs)
        except RuntimeError as exc:  # Linux refused a mapping that large: Taichi's own chunk
            cell.value = hostpool.DEFAULT_CHUNK
            why = f"Taichi could not map a {chunk / 2**30:.1f} GiB pool ({str(exc).strip().splitlines()[-1][:120]})"
            _quiet(ti.init, arch=ti.cpu, **kwargs)
        else:
            new = [n for a, n in hostpool.anonymous_mappings().items() if a not in before and n >= chunk]
            if new:
                _huge_pages(before)
                _state.pool_limit = _state.pool_max = want
                _state.pool_chunk = chunk
                return
            why = f"no {chunk / 2**30:.1f} GiB pool chunk appeared after Taichi started"
    else:
        _quiet(ti.init, arch=ti.cpu, **kwargs)
    _huge_pages(before)
    _state.pool_limit, _state.pool_max, _state.pool_chunk = legacy, CPU_POOL_HARD_MAX_BYTES, 1 << 30
    _state.pool_note = (
        f"the CPU map budget is {legacy / 2**30:.3f} GiB instead of {want / 2**30:.1f} GiB: {why}; Taichi 1.7.4 "
        "corrupts memory past its first 1 GiB pool chunk, so maps stay within it (README \"Memory\")"
    )
    warnings.warn(_state.pool_note, RuntimeWarning, stacklevel=3)


def _huge_pages(before: dict) -> None:
    """Transparent huge pages for the CPU pool Taichi mapped since ``before`` (unless
    NDTOM_HUGE_PAGES=0): a scan's first touches of new nodes then fault once per 2 MiB,
    and the tree walks of merge and eq. (12) miss the TLB less (docs/performance.md)."""
    from . import hostpool

    if os.environ.get("NDTOM_HUGE_PAGES", "1") not in ("0", ""):
        _state.huge_pages = hostpool.advise_huge_pages(before)


def huge_pages() -> int:
    """Bytes of the CPU pool advised for transparent huge pages (0: none)."""
    return _state.huge_pages


def pool_note() -> str | None:
    """Why the CPU budget is below the one asked for (None when it is not)."""
    return _state.pool_note


def pool_chunk() -> int:
    """Bytes of the CPU pool's one chunk (what the budget may be raised to fits in it)."""
    return _state.pool_chunk


def _cuda_device_memory() -> int:
    """Total memory of CUDA device 0 in bytes, from the driver (0 when it cannot be read)."""
    import ctypes
    import ctypes.util

    try:
        cuda = ctypes.CDLL(ctypes.util.find_library("cuda") or "libcuda.so.1")
        dev, size = ctypes.c_int(), ctypes.c_size_t()
        if cuda.cuInit(0) or cuda.cuDeviceGet(ctypes.byref(dev), 0):
            return 0
        if cuda.cuDeviceTotalMem_v2(ctypes.byref(size), dev):
            return 0
        return int(size.value)
    except (OSError, AttributeError):
        return 0


def _cuda_driver_present() -> bool:
    import ctypes.util

    return ctypes.util.find_library("cuda") is not None


def _positive_limit(limit_gb) -> int:
    if isinstance(limit_gb, bool) or not isinstance(limit_gb, (int, float)) or not limit_gb > 0:
        raise ValueError(f"memory_limit_GB must be a positive number of GiB, got {limit_gb!r}")
    return int(limit_gb * 2**30)


def _check_limit(limit_gb: float | None, arch: str, pool_gb: float | None) -> int:
    if arch == "cuda":
        if limit_gb is None:
            return int(0.9 * (pool_gb or 4.0) * 2**30)
        return _positive_limit(limit_gb)
    limit = _positive_limit(limit_gb)
    if limit > _state.pool_max:
        raise ValueError(
            f"memory_limit_GB={limit_gb} is above the {_state.pool_max / 2**30:.4f} GiB the CPU pool of this "
            "process can hold safely: Taichi 1.7.4's CPU pool corrupts memory once it grows "
            "past its first chunk, whose size is fixed when Taichi starts. Pass memory_limit_GB to "
            "the first ndtom_ti.init of the process, or use a coarser resolution or a smaller max_range."
        )
    return limit


def current_arch() -> str | None:
    return _state.arch


def pinned_threads() -> list[tuple[int, int]]:
    """(thread id, cpu) of the Taichi workers fixed to a CPU by init (empty if none)."""
    return list(_state.pinned)


def ensure_init() -> str:
    return _state.arch if _state.ready and _state.arch is not None else init()


def pool_limit() -> int:
    return _state.pool_limit


def _check_max_maps(n) -> int:
    if isinstance(n, bool) or int(n) != n or not 1 <= n <= 64:
        raise ValueError(f"max_maps must be an integer in [1, 64], got {n!r}")
    return int(n)


def storage(layout):
    """The storage shared by all maps of ``layout`` (None: the default layout), built by
    init() for the default layout, else on first use."""
    from ndtom_ti.kernels.layout import Layout, Storage

    ensure_init()
    check_taichi()
    layout = replace(layout, owner=None) if layout is not None else Layout()  # (owners: per slot)
    with _lock:
        st = _storages.get(layout)
        if st is not None and st.slots != _state.max_maps and layout not in _used:
            del _storages[layout]  # built by init(), never used: init(max_maps=...) came since
            st = None
        if st is None:
            _check_fits(layout, _state.max_maps)  # before init()'s storage gives way: a refusal leaves it
            if threading.current_thread() is not _state.init_thread:
                raise RuntimeError(
                    f"a map of a new grid layout ({layout}) was made in thread {threading.current_thread().name!r}; "
                    f"Taichi builds a layout's fields only in the thread that started it "
                    f"({_state.init_thread.name!r}, by ndtom_ti.init or the first map): make the first map of this "
                    "layout there (it may be closed at once), then use maps of it from any thread"
                )
            unused = [key for key in _storages if key not in _used]
            for key in unused:  # init()'s default storage gives way to the layout of the first map
                del _storages[key]
            if _storages:
                raise ValueError(
                    "all maps in a process share one grid layout (Taichi's pool cannot hold "
                    f"two safely); this process uses {next(iter(_storages))}, not {layout}"
                )
            st = _storages[layout] = Storage(layout, _state.max_maps)
        return st


def _forked() -> bool:
    """Whether this process was forked from the one that started Taichi here."""
    return _state.pid is not None and os.getpid() != _state.pid


def _keep_taichi_in_child() -> None:
    """In a child forked from a process running Taichi: Taichi's program, destroyed at the
    child's exit, waits for worker threads that fork did not copy, so a child that left by
    sys.exit or the end of its code never ended. One more reference keeps it alive to the
    end; the child's memory goes with the child."""
    if not _forked():
        return
    try:
        import ctypes

        from taichi.lang import impl

        prog = impl.get_runtime().prog
        if prog is not None:
            ctypes.pythonapi.Py_IncRef(ctypes.py_object(prog))
    except Exception:  # noqa: BLE001, S110 - a fork handler must not raise; the child runs on as before
        pass


def check_process() -> None:
    """RuntimeError in a process forked after ndtom_ti started Taichi: Taichi's worker threads
    do not survive fork, so a kernel there would hang (as would a lock another thread held)."""
    if _forked():
        raise RuntimeError(
            "this process was forked from one in which ndtom_ti had started Taichi, whose threads do not "
            "survive fork: a map here would hang at its first kernel. Start worker processes with "
            "multiprocessing's 'spawn' or 'forkserver' method (multiprocessing.get_context('spawn')), or "
            "make the first map only in the workers. A MapSnapshot (numpy only) works in a forked process"
        )


def check_taichi() -> None:
    """RuntimeError when Taichi was started again (``ti.init`` or ``ti.reset`` by other code in
    the process) after ndtom_ti started it: that frees every field, and a kernel on the maps'
    trees would then crash the process."""
    if _state.taichi is None:
        return
    check_process()
    from taichi.lang import impl

    if impl.get_runtime() is not _state.taichi:
        raise RuntimeError(
            "Taichi was initialised again (ti.init or ti.reset) after ndtom_ti started it, which freed the "
            "maps' fields: no map of this process can be used or made. Code that calls ti.init itself cannot "
            "share a process with ndtom_ti's maps: run it in a process of its own"
        )


def _check_fits(layout, slots: int) -> None:
    """ValueError when the fixed part of ``layout``'s storage (its top-level pointer arrays,
    built whole for every map slot) cannot fit in this machine's memory: Taichi would grow
    the process until Linux kills it, or fail half way and leave no map usable."""
    from . import hostpool

    need, mem = layout.fixed_bytes(slots), hostpool.physical_memory()
    if need > mem:
        why = f"more than this machine's {mem / 2**30:.1f} GiB of memory"
    elif _state.arch == "cpu" and not hostpool.address_space_for(need):
        why = f"more address space than this process may map (ulimit -v; {mem / 2**30:.1f} GiB of memory)"
    else:
        return
    raise ValueError(
        f"{layout} needs {need / 2**30:.1f} GiB for its top-level pointer arrays ({slots} map slots x "
        f"{math.prod(layout.l1)} regions) before any cell is stored, {why}; give a smaller l1 (at a coarser "
        "resolution fewer cells cover the same area), or fewer map slots with ndtom_ti.init(max_maps=...)"
    )


def acquire_slot(layout):
    """(storage, slot) for a new map."""
    st = storage(layout)
    with _lock:
        _used.add(st.layout)
        if not st.free_slots:
            raise NoFreeSlotError(
                f"{st.slots} maps are open already, the most this process allows at once; close "
                "the maps you no longer need (m.close(), or make them with `with NdtOmMap(...) as m:`) "
                "or call ndtom_ti.init(max_maps=...) before making the first map"
            )
        return st, st.free_slots.pop()


def release_slot(st, slot: int) -> None:
    """Empty a dead map's slot (its nodes go back to Taichi's free lists) and free it."""
    if _forked():
        return  # a forked child's copy of a map: a kernel would hang (check_taichi), its memory is its own
    try:
        import taichi as ti

        # Taichi 1.7.4's type check warns that every index of ti.deactivate is "not int32"
        # (they are i32; 14 multi-line warnings at its compile): not for the user's terminal.
        ti.set_logging_level(ti.ERROR)
        try:
            st.kernels.clear_slot(slot)
        finally:
            ti.set_logging_level(ti.WARN)
    except Exception:  # noqa: BLE001 - interpreter shutdown: nothing to keep
        return
    st.leaf_count[slot] = 0
    st.occ_regions[slot] = 0
    st.gidx_regions[slot] = 0
    st.forget(slot)
    with _lock:
        st.free_slots.append(slot)
