"""How many bytes a map's Gaussian records hold that no lossless coding can drop.

    ndtom map ../shared/data/balm_hall_every4 -r 0.2 -o balm.ndtom
    python benchmarks/record_entropy.py balm.ndtom [more.ndtom ...]

For each float64 column of the records of more than one point (means relative to their
cell, scatter terms), the entropy of each bit of the 64 across the records; the sum over
the low 40 mantissa bits is what a coder modelling bits or bytes one at a time must keep
(format 6 codes byte planes). Spread over the known cells, with format 6's own bytes for
the rest of the file, it says whether a lossless file can reach a given size per known cell.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ndtom_ti.snapshot import MapSnapshot

LOW_BITS = 40


def bit_entropy(col: np.ndarray) -> np.ndarray:
    """[64] entropy in bits of each bit of a float64 column, bit 0 the lowest."""
    u = np.ascontiguousarray(col).view(np.uint64)
    p = np.array([((u >> np.uint64(k)) & np.uint64(1)).mean() for k in range(64)])
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -(p * np.log2(p) + (1 - p) * np.log2(1 - p))
    return np.nan_to_num(h)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="+", type=Path)
    args = ap.parse_args()
    print("map | known cells | records (of >1 point) | bits a record: all 64 / low 40 | low 40 a known cell, B")
    for path in args.maps:
        s = MapSnapshot.load(path)
        known = s.known_cell_count()
        multi = s.g_n > 1
        cols = [s.g_mean_rel[multi, a] for a in range(3)] + [s.g_scatter[multi, k] for k in range(6)]
        hs = [bit_entropy(c) for c in cols]
        full = sum(h.sum() for h in hs)
        low = sum(h[:LOW_BITS].sum() for h in hs)
        per_cell = low / 8 * multi.sum() / max(known, 1)
        print(f"{path.name} | {known:,} | {len(s.g_n):,} ({multi.sum():,}) | {full:.0f} / {low:.0f} | {per_cell:.2f}")


if __name__ == "__main__":
    main()
