"""Map file size and save/load time: formats 7 (compact: Gaussians rounded), 6, 5 and 4
(compressed) against format 3 (raw arrays), paired in one process on the same maps.

    ndtom map ../shared/data/norlab_outdoor_stationary_14.bag -r 0.2 -o norlab.ndtom
    python benchmarks/mapfile_size.py norlab.ndtom [more.ndtom ...] --repeats 5

For each map: known cells, Gaussians, bytes of each format and bytes per known cell, then
the median seconds of writing and of reading it (MapSnapshot.save / MapSnapshot.load:
the file alone, no Taichi) in each format, alternated, and their ratio to format 3's; in
brackets the median CPU seconds (threads included) and their ratio: what the time becomes
when other work holds the other core. --map also times
NdtOmMap.save and NdtOmMap.load (what `ndtom map` and a script pay: the map's arrays
taken out of Taichi, or put in).
"""

from __future__ import annotations

import argparse
import gc
import statistics
import tempfile
import time
from pathlib import Path

from ndtom_ti.mapfile import COMPACT_VERSION, RAW_VERSION, VERSION
from ndtom_ti.snapshot import MapSnapshot


def timed(fn) -> tuple[float, float]:
    """Wall and CPU seconds (the process's, its threads included) of ``fn()``."""
    gc.collect()
    t, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - t, time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="+", type=Path)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--map", action="store_true", help="also time NdtOmMap.save/load (starts Taichi)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for path in args.maps:
            s = MapSnapshot.load(path)
            files = {v: Path(tmp) / f"v{v}.ndtom" for v in sorted({RAW_VERSION, 4, 5, VERSION, COMPACT_VERSION})}
            times: dict[str, list[tuple[float, float]]] = {}
            m = None
            if args.map:
                import ndtom_ti

                ndtom_ti.init("cpu")
                m = ndtom_ti.NdtOmMap.from_snapshot(s)
            for _ in range(args.repeats):
                for v, f in files.items():  # alternated: drifts of the machine hit both alike
                    times.setdefault(f"save {v}", []).append(timed(lambda v=v, f=f, s=s: s.save(f, version=v)))
                    times.setdefault(f"load {v}", []).append(timed(lambda f=f: MapSnapshot.load(f)))
                    if m is not None:
                        times.setdefault(f"map save {v}", []).append(
                            timed(lambda v=v, f=f, m=m: m.snapshot().save(f, version=v))
                        )
                        times.setdefault(f"map load {v}", []).append(
                            timed(lambda f=f: ndtom_ti.NdtOmMap.load(f).close())
                        )
            if m is not None:
                m.close()
            size = {v: f.stat().st_size for v, f in files.items()}
            med = {k: statistics.median(w for w, _ in t) for k, t in times.items()}
            cpu = {k: statistics.median(c for _, c in t) for k, t in times.items()}
            known = len(s.occ_index)
            rows.append((path.name, known, len(s.g_index), size, med))
            print(f"{path.name}: {known:,} known cells, {len(s.g_index):,} Gaussian records")
            for v in files:
                print(f"  format {v}: {size[v] / 2**20:.1f} MiB, {size[v] / max(known, 1):.2f} bytes a known cell")
            for what in ("save", "load", "map save", "map load"):
                if f"{what} {VERSION}" in med:
                    a, ac = med[f"{what} {RAW_VERSION}"], cpu[f"{what} {RAW_VERSION}"]
                    print(
                        f"  {what}: format {RAW_VERSION} {a:.3f} s [cpu {ac:.3f}], "
                        + ", ".join(
                            f"format {v} {med[f'{what} {v}']:.3f} s (ratio {med[f'{what} {v}'] / a:.2f})"
                            f" [cpu {cpu[f'{what} {v}']:.3f}, ratio {cpu[f'{what} {v}'] / ac:.2f}]"
                            for v in files
                            if v != RAW_VERSION
                        )
                        + f" (medians of {args.repeats})"
                    )


if __name__ == "__main__":
    main()
