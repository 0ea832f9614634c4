"""Kernel compiles: a cheaper Taichi front end, and who is told when a kernel compiles.

Taichi compiles a kernel at its first call in a process; with its offline cache warm it
still rebuilds the kernel's IR from the Python source to find the cached code. In Taichi
1.7.4 about half of that time went to source positions for error messages: every AST
node's text wrapped to 80 columns with a caret line (``get_pos_info``, 9.7 of 19.6 s of
the front end's time in a first scan, profiled). ``fast_frontend`` gives each node its
file, line and source line instead, which is what a compile error or warning needs, and
reads, wraps and dedents each function's source once per process rather than at each of its
inlined calls.
"""

from __future__ import annotations

import threading

from .kernels import families
from .taichi_import import WRITTEN_FOR, plain, replace_method_test

_done = False
_lock = threading.Lock()


def _pos_info(self, node) -> str:
    line = node.lineno + self.lineno_offset
    text = self.src[node.lineno - 1] if 0 < node.lineno <= len(self.src) else ""
    return f'File "{self.file}", line {line}, in {self.func.func.__name__}:\n{text}\n'


def _once_per_code(read):
    """``read(fn)`` remembered per code object: the source of a code object does not change
    within a process."""
    done: dict = {}

    def cached(fn):
        key = getattr(fn, "__code__", None)
        if key is None:
            return read(fn)
        if key not in done:
            done[key] = read(fn)
        return done[key]

    return cached


def _cached_source(getsourcefile, getsourcelines):
    # Taichi reads a function's source at every inlined call of it (tokenizing its whole
    # file's block each time: 310 reads, 0.46 s of a first scan's front end, profiled).
    lines = _once_per_code(getsourcelines)

    def sourcelines(fn):
        src, start = lines(fn)
        return list(src), start  # each caller its own list

    return _once_per_code(getsourcefile), sourcelines


class _RememberedTextwrap:
    """What Taichi's front end calls of ``textwrap``, remembered per argument: it re-wraps
    and dedents a function's source at every inlined call of it (329 times in a first
    scan), though the source does not change within a process."""

    def __init__(self, textwrap):
        self._tw = textwrap
        self._fill: dict = {}
        self._dedent: dict = {}

    def fill(self, text, **kwargs):
        key = (text, tuple(sorted(kwargs.items())))
        out = self._fill.get(key)
        if out is None:
            out = self._fill[key] = self._tw.fill(text, **kwargs)
        return out

    def dedent(self, text):
        out = self._dedent.get(text)
        if out is None:
            out = self._dedent[text] = self._tw.dedent(text)
        return out

    def __getattr__(self, name):  # anything else, as textwrap has it
        return getattr(self._tw, name)


def fast_frontend() -> bool:
    """Use the cheaper source positions in Taichi's front end (once per process). Only on
    the Taichi release it was written for, and not with NDTOM_PLAIN_COMPILE=1. Returns
    whether it is in use."""
    global _done
    with _lock:
        if _done:
            return True
        if plain():
            return False
        import taichi

        if tuple(getattr(taichi, "__version__", ())) != WRITTEN_FOR:
            return False
        try:
            from taichi.lang.ast import ast_transformer_utils as utils

            ctx = utils.ASTTransformerContext
        except (ImportError, AttributeError):
            return False
        if not callable(getattr(ctx, "get_pos_info", None)):
            return False
        ctx.get_pos_info = _pos_info
        from taichi.lang import kernel_impl

        replace_method_test(kernel_impl)  # (in place already when ndtom_ti was imported before Taichi)
        read = (getattr(kernel_impl, "getsourcefile", None), getattr(kernel_impl, "getsourcelines", None))
        if all(callable(f) for f in read):
            kernel_impl.getsourcefile, kernel_impl.getsourcelines = _cached_source(*read)
        tw = getattr(kernel_impl, "textwrap", None)
        if tw is not None and callable(getattr(tw, "fill", None)) and callable(getattr(tw, "dedent", None)):
            kernel_impl.textwrap = _RememberedTextwrap(tw)
        _done = True
        return True


# Who is told of each kernel variant's first call (kernels/families.py calls them).
on_compile = families.on_compile
