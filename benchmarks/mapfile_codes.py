"""Map file save/load time of several checkouts of ndtom_ti (say, before format 4, main and
a branch), each in its own process, alternated round by round, medians.

    ndtom map ../shared/data/balm_hall_every4 -r 0.2 -o balm.ndtom
    python -c "from ndtom_ti.snapshot import MapSnapshot; \\
               MapSnapshot.load('balm.ndtom').save('balm_v3.ndtom', version=3)"
    git worktree add --detach /tmp/pre4 1333084~1
    python benchmarks/mapfile_codes.py balm_v3.ndtom --code pre4=/tmp/pre4 --code new=. --rounds 7

MAP must be of format 3 (raw arrays), which every version reads. Each process loads it,
then times ``MapSnapshot.save`` / ``MapSnapshot.load`` of its own format (wall and CPU of
the process, threads included), and with --map ``NdtOmMap.save`` / ``NdtOmMap.load``
(starts Taichi). Ratios are against the first --code.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = r"""
import gc, json, os, statistics, sys, time
from ndtom_ti.snapshot import MapSnapshot
src, out, reps, with_map = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4] == "1"
s = MapSnapshot.load(src)
f = os.path.join(out, "t.ndtom")
res = {}
def timed(key, fn):
    gc.collect()
    t, c = time.perf_counter(), time.process_time()
    fn()
    res.setdefault(key, []).append(time.perf_counter() - t)
    res.setdefault(key + " cpu", []).append(time.process_time() - c)
s.save(f); MapSnapshot.load(f)  # warm
for _ in range(reps):
    timed("snap save", lambda: s.save(f))
    timed("snap load", lambda: MapSnapshot.load(f))
size = os.path.getsize(f)
if with_map:
    import ndtom_ti
    ndtom_ti.init("cpu")
    m = ndtom_ti.NdtOmMap.from_snapshot(s)
    m.save(f); ndtom_ti.NdtOmMap.load(f).close()
    for _ in range(reps):
        timed("map save", lambda: m.save(f))
        timed("map load", lambda: ndtom_ti.NdtOmMap.load(f).close())
print(json.dumps({"size": size, **{k: statistics.median(v) for k, v in res.items()}}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("maps", nargs="+", type=lambda p: Path(p).resolve())
    ap.add_argument("--code", action="append", required=True, help="NAME=DIR: a checkout (its root on PYTHONPATH)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=5, help="timings a process, their median taken")
    ap.add_argument("--map", action="store_true", help="also time NdtOmMap.save/load (starts Taichi)")
    args = ap.parse_args()
    codes = dict(c.split("=", 1) for c in args.code)
    for path in args.maps:
        got: dict[str, list[dict]] = {c: [] for c in codes}
        for r in range(args.rounds):
            for c in list(codes) if r % 2 == 0 else list(reversed(codes)):  # alternated: drifts hit all alike
                with tempfile.TemporaryDirectory() as tmp:
                    env = {**os.environ, "PYTHONPATH": str(Path(codes[c]).resolve())}
                    cmd = [sys.executable, "-c", CHILD, str(path), tmp, str(args.repeats), "1" if args.map else "0"]
                    p = subprocess.run(cmd, env=env, cwd=tmp, capture_output=True, text=True, check=False)
                    if p.returncode:
                        sys.exit(f"{c}: {p.stderr[-2000:]}")
                    got[c].append(json.loads(p.stdout.strip().splitlines()[-1]))
        print(f"{path.name} (medians of {args.rounds} rounds of {args.repeats})")
        keys = [k for k in got[next(iter(codes))][0] if k != "size"]
        base = {k: statistics.median(x[k] for x in got[next(iter(codes))]) for k in keys}
        for c in codes:
            med = {k: statistics.median(x[k] for x in got[c]) for k in keys}
            cells = "  ".join(f"{k} {1e3 * med[k]:.1f} ms ({med[k] / base[k]:.2f}x)" for k in keys)
            print(f"  {c}: {got[c][0]['size'] / 2**20:.2f} MiB  {cells}")


if __name__ == "__main__":
    main()
