"""Shared fixtures: one Taichi init per session (arch from NDTOM_ARCH, default cpu)."""

import functools
import os
import subprocess
import sys
import textwrap
import weakref
from pathlib import Path

import numpy as np
import pytest

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
SHARED = Path(os.environ.get("NDTOM_SHARED", ROOT.parent / "shared"))
DATA = SHARED / "data"
SIMWORLD = SHARED / "tools" / "simworld.py"

sys.path.insert(0, str(TESTS))


# What the tests read from ../shared: without it they skip, one by one. CI sets
# NDTOM_REQUIRE_SHARED=1 (.ci/run): then a missing piece stops the run at once instead.
SHARED_NEEDED = (
    "data/balm_hall_every4",
    "data/luminar_embag_test.bag",
    "data/norlab_outdoor_stationary_14.bag",
    "data/tum_fr2_pioneer_slam2_10f.bag",
    "tools/simworld.py",
)


def pytest_configure(config):
    if os.environ.get("NDTOM_REQUIRE_SHARED", "") not in ("", "0"):
        missing = [p for p in SHARED_NEEDED if not (SHARED / p).exists()]
        if missing:
            raise pytest.UsageError(
                f"NDTOM_REQUIRE_SHARED is set but {SHARED} lacks {', '.join(missing)}: the tests of real "
                "recordings and simulated worlds would be skipped. Put the shared folder beside the "
                "repository (or set NDTOM_SHARED to it), or unset NDTOM_REQUIRE_SHARED."
            )
    import ndtom_ti

    ndtom_ti.init(os.environ.get("NDTOM_ARCH", "cpu"))


@pytest.fixture(autouse=True)
def close_maps(monkeypatch):
    """Closes every map a test made when it ends: maps share the process's few storage slots
    (``init(max_maps=...)``), and the next test must not wait for the collector to free them.
    Maps of module-scoped fixtures are made before this fixture and stay open."""
    from ndtom_ti import NdtOmMap

    made = weakref.WeakSet()
    init = NdtOmMap.__init__

    @functools.wraps(init)  # its signature and docstring stay inspectable
    def tracked(self, *args, **kwargs):
        init(self, *args, **kwargs)
        made.add(self)

    monkeypatch.setattr(NdtOmMap, "__init__", tracked)
    yield
    for m in list(made):
        m.close()


@pytest.fixture(scope="session")
def arch():
    import ndtom_ti

    return ndtom_ti.current_arch()


def _import_simworld():
    """The shared/tools/simworld module (skips the test where it is missing)."""
    if not SIMWORLD.exists():
        pytest.skip(f"simworld not found at {SIMWORLD}")
    if str(SIMWORLD.parent) not in sys.path:
        sys.path.insert(0, str(SIMWORLD.parent))
    import simworld

    return simworld


def _simworld(out: Path, *args: str) -> Path:
    """Run shared/tools/simworld.py into ``out`` and make the module importable."""
    _import_simworld()
    subprocess.run([sys.executable, str(SIMWORLD), *args, "--out", str(out)], check=True, capture_output=True)
    return out


@pytest.fixture(scope="session")
def sim_hall_dynamic(tmp_path_factory):
    """Synthetic hall, 24 scans 1 s apart, with moving and vanishing objects (npz only)."""
    out = _simworld(tmp_path_factory.mktemp("hall"), "--scans", "24", "--stride", "10", "--no-bags")
    import simworld

    return simworld.SimDataset(out / "hall.npz")


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def room_scans():
    """12 small scans of the demo room (16 rings x 360 beams), shared by the viewer tests."""
    from ndtom_ti.demo import make_scans

    return make_scans(12, rings=16, per_ring=360)


def cuda_device_present() -> bool:
    """Whether the CUDA driver reports a device (read through the driver, no Taichi init)."""
    import ctypes
    import ctypes.util

    try:
        cuda = ctypes.CDLL(ctypes.util.find_library("cuda") or "libcuda.so.1")
        count = ctypes.c_int(0)
        return cuda.cuInit(0) == 0 and cuda.cuDeviceGetCount(ctypes.byref(count)) == 0 and count.value > 0
    except (OSError, AttributeError):
        return False


def pytest_collection_modifyitems(config, items):
    """Tests marked ``gpu`` need a CUDA device: without one they are skipped, saying so."""
    gpu = [item for item in items if item.get_closest_marker("gpu") is not None]
    if gpu and not cuda_device_present():
        skip = pytest.mark.skip(reason="needs a CUDA GPU (none found by the CUDA driver)")
        for item in gpu:
            item.add_marker(skip)


def run_py(code: str, *args: str, timeout: int = 900) -> str:
    """Run ``code`` in a fresh CPU process (a process has one Taichi pool and one Taichi
    runtime) and return its stdout; a failure shows both streams' ends."""
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        capture_output=True,
        text=True,
        check=False,
        timeout=timeout,
        env={**os.environ, "NDTOM_ARCH": "cpu"},
    )
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    return out.stdout
