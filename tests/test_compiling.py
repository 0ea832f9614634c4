"""The cheaper Taichi front end (ndtom_ti.compiling): compile errors still point at the
source line, and each function's source is read once per process."""

import os
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import ndtom_ti
    import taichi as ti
    from taichi.lang import kernel_impl

    ndtom_ti.init("cpu")
    from ndtom_ti import compiling

    assert compiling.fast_frontend()
    assert kernel_impl.getsourcelines.__module__ == "ndtom_ti.compiling"

    @ti.func
    def twice(x):
        return x * 2

    @ti.kernel
    def uses(a: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        for i in range(a.shape[0]):
            a[i] = twice(twice(twice(a[i])))

    import numpy as np

    a = np.ones(4, np.int32)
    uses(a)
    assert (a == 8).all(), a

    @ti.kernel
    def broken(a: ti.types.ndarray(dtype=ti.i32, ndim=1)):
        for i in range(a.shape[0]):
            a[i] = no_such_name  # noqa: F821

    try:
        broken(a)
    except Exception as e:
        print("ERROR", type(e).__name__, str(e))
    """
)


def _run(path, text: str, plain: str):
    """``text`` as a script at ``path``, in a fresh process, with NDTOM_PLAIN_COMPILE=plain."""
    path.write_text(text)
    env = {**os.environ, "NDTOM_PLAIN_COMPILE": plain}
    return subprocess.run([sys.executable, str(path)], capture_output=True, text=True, env=env, timeout=300)


@pytest.mark.parametrize("plain", ["0", "1"])
def test_compile_errors_name_the_source_line(tmp_path, plain):
    script = tmp_path / "k.py"
    p = _run(script, SCRIPT, plain)
    if plain == "1":
        # the plain front end: fast_frontend refuses, the assert says so
        assert p.returncode != 0 and "assert compiling.fast_frontend()" in p.stderr
        return
    assert p.returncode == 0, p.stderr
    err = [ln for ln in p.stdout.splitlines() if ln.startswith("ERROR")]
    assert err, p.stdout
    out = p.stdout[p.stdout.index("ERROR") :]
    assert "no_such_name" in out
    assert str(script) in out  # the file, and the line's own text
    assert "a[i] = no_such_name" in out


def test_source_read_once_per_function():
    import ndtom_ti
    from ndtom_ti import compiling

    ndtom_ti.init("cpu")
    if not compiling.fast_frontend():
        pytest.skip("not the Taichi release the cheaper front end was written for")
    from taichi.lang import kernel_impl

    calls = []

    def lines(fn):
        calls.append(fn)
        return ["def f():\n", "    pass\n"], 1

    def files(fn):
        return "f.py"

    # private: the memo alone, on stand-in readers (fast_frontend installs it over Taichi's own)
    sourcefile, sourcelines = compiling._cached_source(files, lines)

    def f():
        pass

    g = type(f)(f.__code__, f.__globals__)  # another function object of the same code
    first = sourcelines(f)
    first[0].append("mutated")  # callers get their own list
    assert sourcelines(g) == (["def f():\n", "    pass\n"], 1)
    assert len(calls) == 1
    assert sourcefile(f) == "f.py"
    assert kernel_impl.getsourcelines.__module__ == "ndtom_ti.compiling"


def test_source_wrapped_and_dedented_once_as_textwrap_does():
    import ndtom_ti
    from ndtom_ti import compiling

    ndtom_ti.init("cpu")
    if not compiling.fast_frontend():
        pytest.skip("not the Taichi release the cheaper front end was written for")
    from taichi.lang import kernel_impl

    assert isinstance(kernel_impl.textwrap, compiling._RememberedTextwrap)
    calls = []

    class Counting:  # textwrap, counting its calls
        def fill(self, text, **kw):
            calls.append(text)
            return textwrap.fill(text, **kw)

        def dedent(self, text):
            calls.append(text)
            return textwrap.dedent(text)

    tw = compiling._RememberedTextwrap(Counting())
    lines = ["\tx = 1  ", "    if a:\t# c", "", "   ", "        y = [1,\t2]"]
    for _ in range(3):
        assert [tw.fill(ln, tabsize=4, width=9999) for ln in lines] == [
            textwrap.fill(ln, tabsize=4, width=9999) for ln in lines
        ]
        assert tw.fill(lines[0], tabsize=8, width=9999) == textwrap.fill(lines[0], tabsize=8, width=9999)
        text = "    def f():\n        return 1\n"
        assert tw.dedent(text) == textwrap.dedent(text)
    assert len(calls) == len(lines) + 2  # each argument once
    assert compiling._RememberedTextwrap(textwrap).TextWrapper is textwrap.TextWrapper  # the rest as it is


CLASS_TEST = textwrap.dedent(
    """
    import ndtom_ti
    import taichi as ti
    from taichi.lang import kernel_impl

    ndtom_ti.init("cpu")
    from ndtom_ti import taichi_import

    taichis = taichi_import.taichis
    assert kernel_impl._inside_class is taichi_import.inside_class
    seen = []

    def both(level):  # one frame more than Taichi's own call: level + 1
        seen.append((taichis(level + 1), taichi_import.inside_class(level + 1)))
        return seen[-1][1]

    kernel_impl._inside_class = both

    @ti.kernel
    def plain():
        pass

    def make():
        @ti.kernel
        def nested():
            pass

    make()

    @ti.data_oriented
    class A:
        @ti.kernel
        def m(self):
            pass

        @ti.kernel
        def m2(self,
               x: ti.i32):
            pass

    class B:
        x = (1,
             2)

        @ti.kernel
        def m(self):
            pass

    A().m()
    print("SEEN", seen)
    assert all(a == b for a, b in seen) and sum(a for a, _ in seen) == 3, seen
    """
)


def test_method_kernels_are_told_from_functions_as_taichi_does(tmp_path):
    # The cheaper test of whether ti.kernel decorates a method gives Taichi's answer. (From a
    # file: both read the decorated line from the source.)
    out = _run(tmp_path / "kernels_in_classes.py", CLASS_TEST, "0")
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]


METHODS = textwrap.dedent(
    """
    import ndtom_ti  # before Taichi: its method test is replaced while Taichi is imported
    import taichi as ti
    from taichi.lang import kernel_impl

    print("TEST", kernel_impl._inside_class.__module__)
    ndtom_ti.init("cpu")

    @ti.data_oriented
    class Cells:
        def __init__(self):
            self.x = ti.field(ti.i32, 4)

        @ti.func
        def get(self, i):
            return self.x[i]

        @ti.kernel
        def fill(self, v: ti.i32):
            for i in self.x:
                self.x[i] = v

        @ti.kernel
        def total(self) -> ti.i32:
            s = 0
            for i in range(4):
                s += self.get(i)
            return s

    @ti.kernel
    def plain_kernel(v: ti.i32) -> ti.i32:
        return v + 1

    c = Cells()
    c.fill(3)
    print("SUM", c.total(), plain_kernel(4))
    """
)


@pytest.mark.parametrize("plain", ["0", "1"])
def test_methods_and_functions_told_apart_as_taichi_does(tmp_path, plain):
    p = _run(tmp_path / "m.py", METHODS, plain)
    assert p.returncode == 0, p.stderr
    expect = "taichi.lang.kernel_impl" if plain == "1" else "ndtom_ti.taichi_import"
    assert f"TEST {expect}" in p.stdout, p.stdout
    assert "SUM 12 5" in p.stdout, p.stdout
