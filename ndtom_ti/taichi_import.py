"""A cheaper ``import taichi``: Taichi 1.7.4 asks of every ``ti.func`` and ``ti.kernel`` it
defines (96 in its own import) whether it decorates a method, by reading the caller's
statement with ``inspect.getframeinfo``, which searches every loaded module for the frame's
file: ~80-90 ms of a 0.35 s import, measured. ``install`` replaces that test with a read of the
same line through ``linecache`` as soon as ``taichi.lang.kernel_impl`` is loaded, before
Taichi's own definitions run. This module imports no Taichi.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import itertools
import linecache
import os
import sys
import threading

# The Taichi release whose method test this replaces (compiling.py's other changes too).
WRITTEN_FOR = (1, 7, 4)
_MODULE = "taichi.lang.kernel_impl"
_lock = threading.Lock()
taichis = None  # Taichi's own method test, once replaced (tests compare the two)


def plain() -> bool:
    """NDTOM_PLAIN_COMPILE=1: Taichi's front end as Taichi ships it."""
    return os.environ.get("NDTOM_PLAIN_COMPILE", "") not in ("", "0")


def _statement_line(frame) -> str:
    lineno = frame.f_lineno
    if hasattr(frame.f_code, "co_positions") and frame.f_lasti >= 0:  # 3.11+: the statement's first line, as inspect's
        first = next(itertools.islice(frame.f_code.co_positions(), frame.f_lasti // 2, None), (None,))[0]
        lineno = lineno if first is None else first
    return linecache.getline(frame.f_code.co_filename, lineno, frame.f_globals).strip()


def inside_class(level_of_class_stackframe: int) -> bool:
    """Taichi's test of whether ti.kernel or ti.func decorates a method: the first line of the
    caller's statement opens a class or a data_oriented decorator."""
    kernel_impl = sys.modules.get(_MODULE)
    try:
        line = _statement_line(sys._getframe(level_of_class_stackframe))
    except (ValueError, AttributeError, TypeError):
        return False
    return any(pat.match(line) for pat in getattr(kernel_impl, "_KERNEL_CLASS_STACKFRAME_STMT_RES", ()))


def replace_method_test(kernel_impl) -> bool:
    """Puts ``inside_class`` in place of Taichi's own in ``kernel_impl``, on the release it was
    written for. Returns whether it is in place."""
    if getattr(kernel_impl, "_inside_class", None) is inside_class:
        return True
    if not (
        callable(getattr(kernel_impl, "_inside_class", None))
        and hasattr(kernel_impl, "_KERNEL_CLASS_STACKFRAME_STMT_RES")
    ):
        return False
    core = sys.modules.get("taichi._lib.core.taichi_python")
    if core is None:
        return False
    try:
        version = (core.get_version_major(), core.get_version_minor(), core.get_version_patch())
    except AttributeError:
        return False
    if version != WRITTEN_FOR:
        return False
    global taichis
    taichis = kernel_impl._inside_class
    kernel_impl._inside_class = inside_class
    return True


class _Finder(importlib.abc.MetaPathFinder):
    """Finds taichi.lang.kernel_impl as the path finder does, and has its loader replace the
    method test right after the module's own code ran. Leaves sys.meta_path once used."""

    def find_spec(self, name, path, target=None):
        if name != _MODULE:
            return None
        with _lock:
            if self in sys.meta_path:
                sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path, target)
        loader = getattr(spec, "loader", None)
        if loader is None or not callable(getattr(loader, "exec_module", None)):
            return spec  # (None: the other finders look)
        run = loader.exec_module

        def exec_module(module):
            run(module)
            replace_method_test(module)

        loader.exec_module = exec_module
        return spec


def install() -> None:
    """Before Taichi is imported (else nothing: compiling.fast_frontend replaces the test for
    the kernels defined later). Not with NDTOM_PLAIN_COMPILE=1."""
    if plain() or _MODULE in sys.modules:
        return
    with _lock:
        if not any(isinstance(f, _Finder) for f in sys.meta_path):
            sys.meta_path.insert(0, _Finder())
