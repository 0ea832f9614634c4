"""Export a map's Gaussians: PLY (points for viewers), npz (all arrays), CSV (one row each).

Every writer takes the dict of :meth:`NdtOmMap.gaussians` (``index``, ``mean``, ``cov``,
``n``, ``p_occ``, ``logodds``) and writes atomically (a temporary file in the target
folder, renamed over the target), so a failed export never leaves a half-written file.

- PLY: binary little endian; one vertex per Gaussian at its mean, properties
  ``x y z`` (float32), ``p_occ`` (float32), ``n`` (int32) and the covariance terms
  ``cov_xx cov_xy cov_xz cov_yy cov_yz cov_zz`` (float32, m^2).
- npz: ``index`` (K, 3) int64, ``mean`` (K, 3) float64, ``cov`` (K, 3, 3) float64,
  ``n`` (K,) int64, ``p_occ`` and ``logodds`` (K,) float64, ``resolution`` (scalar) and
  ``metadata`` (the map's metadata as a JSON string).
- CSV: a header line, then one row per Gaussian:
  ``i,j,k,x,y,z,n,p_occ,logodds,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import IO, Any

import numpy as np

from .atomic import atomic_write

__all__ = ["COV_TERMS", "FORMATS", "PLY_PROPERTIES", "export_map", "write_csv", "write_npz", "write_ply"]

FORMATS = ("ply", "npz", "csv")
COV_TERMS = ("cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz")
_COV_IJ = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
PLY_PROPERTIES = (
    ("x", "float", "<f4"), ("y", "float", "<f4"), ("z", "float", "<f4"),
    ("p_occ", "float", "<f4"), ("n", "int", "<i4"),
    *((name, "float", "<f4") for name in COV_TERMS),
)  # fmt: skip


def _cov6(cov: np.ndarray) -> np.ndarray:
    cov = np.asarray(cov, np.float64).reshape(-1, 3, 3)
    return np.stack([cov[:, a, b] for a, b in _COV_IJ], axis=1)


def write_ply(g: dict, path: str | Path, *, comment: str | None = None) -> Path:
    """Binary little-endian PLY: one vertex per Gaussian (see the module doc)."""
    k = len(g["n"])
    dt = np.dtype([(name, code) for name, _, code in PLY_PROPERTIES])
    v = np.zeros(k, dt)
    mean = np.asarray(g["mean"], np.float64).reshape(-1, 3)
    v["x"], v["y"], v["z"] = mean[:, 0], mean[:, 1], mean[:, 2]
    v["p_occ"] = g["p_occ"]
    v["n"] = g["n"]
    c6 = _cov6(g["cov"])
    for j, name in enumerate(COV_TERMS):
        v[name] = c6[:, j]
    lines = ["ply", "format binary_little_endian 1.0"]
    if comment:
        lines += [f"comment {line}" for line in comment.splitlines()]
    lines.append(f"element vertex {k}")
    lines += [f"property {ptype} {name}" for name, ptype, _ in PLY_PROPERTIES]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii", errors="replace")

    def write(fh: IO[bytes]) -> None:
        fh.write(header)
        fh.write(v.tobytes())

    return atomic_write(path, write)


def write_npz(g: dict, path: str | Path, *, resolution: float | None = None, metadata: dict | None = None) -> Path:
    """All arrays of the Gaussians (see the module doc), uncompressed npz."""
    arrays: dict[str, Any] = {
        "index": np.asarray(g["index"], np.int64).reshape(-1, 3),
        "mean": np.asarray(g["mean"], np.float64).reshape(-1, 3),
        "cov": np.asarray(g["cov"], np.float64).reshape(-1, 3, 3),
        "n": np.asarray(g["n"], np.int64),
        "p_occ": np.asarray(g["p_occ"], np.float64),
        "logodds": np.asarray(g["logodds"], np.float64),
    }
    if resolution is not None:
        arrays["resolution"] = np.float64(resolution)
    if metadata is not None:
        arrays["metadata"] = np.array(json.dumps(metadata, default=str))
    return atomic_write(path, lambda fh: np.savez(fh, **arrays))


CSV_COLUMNS = ("i", "j", "k", "x", "y", "z", "n", "p_occ", "logodds", *COV_TERMS)


def write_csv(g: dict, path: str | Path) -> Path:
    """One row per Gaussian with a header line (see the module doc)."""
    idx = np.asarray(g["index"], np.int64).reshape(-1, 3)
    mean = np.asarray(g["mean"], np.float64).reshape(-1, 3)
    n = np.asarray(g["n"], np.int64)
    p = np.asarray(g["p_occ"], np.float64)
    lo = np.asarray(g["logodds"], np.float64)
    c6 = _cov6(g["cov"])

    def write(fh: IO[bytes]) -> None:
        fh.write((",".join(CSV_COLUMNS) + "\n").encode())
        # repr of float64 round-trips exactly
        for r in range(len(n)):
            row = [*map(str, idx[r].tolist()), *map(repr, mean[r].tolist()), str(int(n[r])), repr(float(p[r])),
                   repr(float(lo[r])), *map(repr, c6[r].tolist())]
            fh.write((",".join(row) + "\n").encode())

    return atomic_write(path, write)


def export_map(m: Any, path: str | Path, fmt: str | None = None, *, min_probability: float = 0.5,
               min_points: int | None = None) -> tuple[Path, int]:
    """Write the Gaussians of map ``m`` with ``p_occ > min_probability`` (0 exports every
    Gaussian, occupied or not) to ``path`` as ``fmt`` ('ply', 'npz' or 'csv'; default: from
    the suffix). Returns (path, number of Gaussians written)."""
    fmt = (fmt or Path(path).suffix.lstrip(".")).lower()
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if not 0.0 <= float(min_probability) < 1.0:
        raise ValueError(f"min_probability must be in [0, 1), got {min_probability}")
    g = m.gaussians(min_points=min_points, min_probability=float(min_probability))
    if fmt == "ply":
        from . import __version__

        comment = (f"ndtom_ti {__version__} NDT-OM Gaussians: resolution {m.resolution:g} m, "
                   f"p_occ > {float(min_probability):g}; covariances in m^2")
        out = write_ply(g, path, comment=comment)
    elif fmt == "npz":
        out = write_npz(g, path, resolution=m.resolution, metadata=m.metadata)
    else:
        out = write_csv(g, path)
    return out, len(g["n"])
