"""CUDA against the CPU: tests marked ``gpu`` run only where the CUDA driver finds a device
(tests/conftest.py skips them elsewhere). The whole suite also runs on CUDA with NDTOM_ARCH=cuda."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import ndtom_ti
from ndtom_ti.demo import make_scans

# The same map made in a process of the other arch (Taichi has one arch per process).
_OTHER = """
import sys
import numpy as np
import ndtom_ti
from ndtom_ti.demo import make_scans

arch, out = sys.argv[1], sys.argv[2]
assert ndtom_ti.init(arch) == arch, ndtom_ti.current_arch()
m = ndtom_ti.NdtOmMap(0.2)
for s in make_scans(6, rings=16, per_ring=720):
    m.insert_scan(s.points, s.T_world_sensor)
k, g = m.known_cells(), m.gaussians(min_points=1, min_probability=0)
np.savez(out, k_index=k["index"], k_logodds=k["logodds"], **{"g_" + n: v for n, v in g.items()})
"""


def _rows(index: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(index.astype(np.int64)).view([("i", np.int64), ("j", np.int64), ("k", np.int64)])[:, 0]


@pytest.mark.gpu
def test_cuda_and_cpu_make_the_same_map(arch, tmp_path: Path) -> None:
    other = "cpu" if arch == "cuda" else "cuda"
    env = {**os.environ, "NDTOM_PIN_THREADS": "0"}
    p = subprocess.run(
        [sys.executable, "-c", _OTHER, other, str(tmp_path / "other.npz")],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
        check=False,
    )
    assert p.returncode == 0, p.stderr[-3000:]
    there = np.load(tmp_path / "other.npz")
    m = ndtom_ti.NdtOmMap(0.2)
    for s in make_scans(6, rings=16, per_ring=720):
        m.insert_scan(s.points, s.T_world_sensor)
    k, g = m.known_cells(), m.gaussians(min_points=1, min_probability=0)
    m.close()
    # A point or ray within rounding of a cell face may fall the other way (fused multiply-adds
    # on the GPU): allow a few cells in ten thousand, and the rest equal.
    here_k, there_k = _rows(k["index"]), _rows(there["k_index"])
    common, a, b = np.intersect1d(here_k, there_k, return_indices=True)
    assert len(k["index"]) > 10_000
    assert len(here_k) + len(there_k) - 2 * len(common) <= 1e-4 * len(here_k)
    close = np.abs(k["logodds"][a] - there["k_logodds"][b]) <= 1e-5
    assert (~close).sum() <= 1e-4 * len(common)
    here_g, there_g = _rows(g["index"]), _rows(there["g_index"])
    common, a, b = np.intersect1d(here_g, there_g, return_indices=True)
    assert len(g["n"]) > 1_000
    assert len(here_g) + len(there_g) - 2 * len(common) <= 1e-4 * len(here_g) + 1
    same_n = g["n"][a] == there["g_n"][b]
    assert (~same_n).sum() <= 1e-4 * len(common) + 1
    a, b = a[same_n], b[same_n]
    np.testing.assert_allclose(g["mean"][a], there["g_mean"][b], rtol=0, atol=1e-6)  # metres
    np.testing.assert_allclose(g["cov"][a], there["g_cov"][b], rtol=0, atol=1e-8)  # square metres
