"""A lighter way to call the per-scan kernels.

Taichi 1.7's ``Kernel.__call__`` re-derives, on every call, how each argument is passed:
~13 us per numpy array on the project's 2-core VM, ~0.7 ms per scan over the update's
~55 array arguments. ``Launcher`` works that out once per argument signature (through
Taichi's own compile path) and then only hands over pointers and scalars. Anything it
was not built for (a non-contiguous array, a non-numpy argument, debug mode, a Taichi
without the internals it uses) goes through Taichi's ordinary call, unchanged.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from taichi.lang import impl, kernel_impl
from taichi.lang.util import cook_dtype
from taichi.types import ndarray_type, primitive_types
from taichi.types.utils import is_signed

_ARRAY, _INT, _UINT, _FLOAT = range(4)


# The Taichi release whose call path the Launcher reproduces: any other gets Taichi's call.
WRITTEN_FOR = (1, 7, 4)


def enabled() -> bool:
    """Whether kernels get a Launcher: only on the Taichi release it was written against
    (it uses that release's internals), not in Taichi's debug mode (its checks live in the
    ordinary call), and not with NDTOM_PLAIN_LAUNCH=1."""
    if os.environ.get("NDTOM_PLAIN_LAUNCH", "") not in ("", "0"):
        return False
    import taichi

    if tuple(getattr(taichi, "__version__", ())) != WRITTEN_FOR:
        return False
    try:
        return not impl.current_cfg().debug
    except Exception:  # noqa: BLE001 - no Taichi runtime yet
        return False


class Launcher:
    """Calls the Taichi kernel ``kernel`` (a ``@ti.kernel`` function) with positional
    arguments only, the same way Taichi would."""

    def __init__(self, kernel):
        self.kernel = kernel
        self._k: Any = getattr(kernel, "_primal", None)
        self._plans: dict = {}
        self._kinds = self._argument_kinds()

    def _argument_kinds(self):
        k = self._k
        needed = ("ensure_compiled", "compiled_kernels", "arguments")
        if not isinstance(k, kernel_impl.Kernel) or not all(hasattr(k, a) for a in needed):
            return None
        kinds = []
        for arg in k.arguments:
            ann = arg.annotation
            if isinstance(ann, ndarray_type.NdarrayType) and (
                ann.dtype is None or id(ann.dtype) in primitive_types.type_ids
            ):
                kinds.append(_ARRAY)
            elif id(ann) in primitive_types.real_type_ids:
                kinds.append(_FLOAT)
            elif id(ann) in primitive_types.integer_type_ids:
                kinds.append(_INT if is_signed(cook_dtype(ann)) else _UINT)
            else:
                return None  # templates, matrices, structs: Taichi's call
        return tuple(kinds)

    def __call__(self, *args):
        kinds = self._kinds
        if kinds is None or len(args) != len(kinds):
            return self.kernel(*args)
        sig = []
        for a, kd in zip(args, kinds):
            if kd == _ARRAY:
                if type(a) is not np.ndarray or not a.flags.c_contiguous:
                    return self.kernel(*args)
                sig.append((a.dtype.num, a.ndim))
        sig = tuple(sig)
        t_kernel = self._plans.get(sig)
        if t_kernel is None:
            # The first call of a signature runs through Taichi (its type checks, its
            # compile); the compiled kernel then serves the next calls.
            self.kernel(*args)
            t_kernel = self._k.compiled_kernels[self._k.ensure_compiled(*args)]
            prog: Any = impl.get_runtime().prog
            if not all(
                hasattr(o, a)
                for o, a in ((t_kernel, "make_launch_context"), (prog, "compile_kernel"), (prog, "launch_kernel"))
            ):
                self._kinds = None  # not the Taichi this was written for: its call from now on
                return None
            self._plans[sig] = t_kernel
            return None
        ctx = t_kernel.make_launch_context()
        for i, (a, kd) in enumerate(zip(args, kinds)):
            if kd == _ARRAY:
                ctx.set_arg_external_array_with_shape((i,), a.ctypes.data, a.nbytes, a.shape, 0)
            elif kd == _FLOAT:
                ctx.set_arg_float((i,), float(a))
            elif kd == _INT:
                ctx.set_arg_int((i,), int(a))
            else:
                ctx.set_arg_uint((i,), int(a))
        prog: Any = impl.get_runtime().prog
        prog.launch_kernel(prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel), ctx)
        return None
