"""Map quality in dynamic scenes against exact ground truth: NDT-OM with the NDT miss model,
NDT-OM with the paper's eq. (12), and OctoMap (when pyoctomap is installed) on the same scans.

    python benchmarks/quality.py --scene hall yard --seed 7 --res 0.1 0.2 0.4 --out quality

Scenes are made by shared/tools/simworld.py (60 scans one second apart by default; a static
twin of each scene, same seed, for the conflicting cells). Metrics: ndtom_ti.quality.
Writes quality.csv, one top view per scene (quality_<scene>.png) and prints a table.

Scene settings (vehicle speed, mount roll and pitch, range noise, scan stride) take a list
each; the grid is their cross product over seeds, scenes and resolutions:

    python benchmarks/quality.py --scene hall --seed 1001 1002 --speed 1 2 --pitch 0 5

or a given list of combinations, each starting from the defaults:

    python benchmarks/quality.py --seed 1001 --combo default speed=2 pitch=5 noise=0.05

A second table puts the three mappers side by side, with ndtom's ghosts over OctoMap's.
"""

from __future__ import annotations

import argparse
import gc
import json
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from itertools import product
from pathlib import Path

import numpy as np

import ndtom_ti
from ndtom_ti import MapConfig, NdtOmMap
from ndtom_ti import quality as q

ROOT = Path(__file__).resolve().parents[1]
SIMWORLD = ROOT.parent / "shared" / "tools" / "simworld.py"
MAPPERS = ("ndtom-ndt", "ndtom-paper", "octomap")


@dataclass(frozen=True)
class Settings:
    """The simulator's motion and sensor settings of a scene (simworld's defaults but the stride)."""

    speed: float = 1.0  # m/s
    roll: float = 0.0  # mount roll, degrees
    pitch: float = 0.0  # mount pitch, degrees
    noise: float = 0.02  # range noise std, m
    stride: int = 10  # every stride-th scan of the 10 Hz stream

    def tag(self) -> str:
        """File-name suffix naming the settings that differ from the defaults ('' for none)."""
        short = {"speed": "v", "roll": "r", "pitch": "p", "noise": "e", "stride": "k"}
        d = Settings()
        return "".join(f"_{short[k]}{getattr(self, k):g}" for k in short if getattr(self, k) != getattr(d, k))

    def label(self) -> str:
        return self.tag().lstrip("_").replace("_", " ") or "default"


def parse_combo(text: str) -> Settings:
    """'speed=2,pitch=5' (or 'default') -> Settings; unnamed settings keep their defaults."""
    if text == "default":
        return Settings()
    kw = {}
    for part in text.split(","):
        key, _, val = part.partition("=")
        if key not in Settings.__dataclass_fields__ or not val:
            raise ValueError(f"bad setting {part!r} (keys: {', '.join(Settings.__dataclass_fields__)})")
        kw[key] = int(val) if key == "stride" else float(val)
    return Settings(**kw)


def make_scene(
    simworld: Path, out: Path, scene: str, seed: int, scans: int, static: bool, settings: Settings = Settings()
) -> Path:
    name = f"{scene}_s{seed}_n{scans}{settings.tag()}{'_static' if static else ''}"
    npz = out / f"{name}.npz"
    if not npz.exists():
        st = settings
        args = [
            sys.executable,
            str(simworld),
            "--variant",
            scene,
            "--seed",
            str(seed),
            "--scans",
            str(scans),
            "--stride",
            str(st.stride),
            "--speed",
            f"{st.speed:g}",
            "--sigma",
            f"{st.noise:g}",
            "--mount-rpy",
            f"{st.roll:g},{st.pitch:g},0",
            "--no-bags",
            "--name",
            name,
            "--out",
            str(out),
        ]
        if static:
            args.append("--static")
        subprocess.run(args, check=True, capture_output=True)
    return npz


def read_scene(npz: Path) -> tuple[list[q.LabelledScan], float, tuple[np.ndarray, np.ndarray]]:
    z = np.load(npz)
    params = json.loads(str(z["params_json"]))
    n_static = len(z["static_lo"])
    scans = []
    for i in range(len(z["poses"])):
        a, b = z["scan_offsets"][i], z["scan_offsets"][i + 1]
        ret = ~z["no_return"][a:b]
        T = z["poses"][i]
        local = z["points"][a:b][ret].astype(np.float64)
        present = z["dyn_present"][i]
        scans.append(
            q.LabelledScan(
                points=local @ T[:3, :3].T + T[:3, 3],
                dynamic=z["hit_id"][a:b][ret] >= n_static,
                origin=T[:3, 3].copy(),
                T_world_sensor=T,
                dyn_lo=z["dyn_lo"][i][present],
                dyn_hi=z["dyn_hi"][i][present],
            )
        )
    return scans, float(params.get("range_sigma", 0.02)), (z["static_lo"], z["static_hi"])


def local_points(sc: q.LabelledScan) -> np.ndarray:
    T = sc.T_world_sensor
    return np.ascontiguousarray(((sc.points - T[:3, 3]) @ T[:3, :3]).astype(np.float32))


def build(scans, res: float, **kw) -> tuple[NdtOmMap, np.ndarray]:
    m = NdtOmMap(res, **kw)
    times = []
    for sc in scans:
        pts = local_points(sc)
        t0 = time.perf_counter()
        m.insert_scan(pts, sc.T_world_sensor)
        times.append(time.perf_counter() - t0)
    return m, np.array(times)


def build_octree(scans, res: float):
    import pyoctomap

    tree = pyoctomap.OcTree(res)
    times = []
    for sc in scans:
        t0 = time.perf_counter()
        tree.insertPointCloud(np.ascontiguousarray(sc.points), np.ascontiguousarray(sc.origin), -1.0)
        times.append(time.perf_counter() - t0)
    return tree, np.array(times)


def evaluate(
    scene: str,
    dyn: list,
    static: list,
    sigma: float,
    boxes,
    res: float,
    octomap: bool,
    seed: int = 7,
    settings: Settings = Settings(),
) -> tuple[list[dict], dict]:
    cand = q.mark_observed(q.ghost_candidates(dyn, res, 3.0 * sigma, boxes), dyn, res)
    ref = q.static_reference(dyn, res)
    rows, left = [], {}
    # Warm-up: kernels compile before the timed maps.
    for model in ("ndt", "paper"):
        w, _ = build(dyn[:2], res, config=MapConfig(miss_model=model))
        del w
    rcu, _ = build(static, res, occupancy=False)
    for mapper in MAPPERS:
        if mapper == "octomap":
            if not octomap:
                continue
            tree, times = build_octree(dyn, res)
            qual = q.score(q.octree_occupied(tree, res), cand, ref)
            conf = None
            del tree
        else:
            cfg = MapConfig(miss_model=mapper.split("-")[1])
            m, times = build(dyn, res, config=cfg)
            qual = q.score(q.ndtom_occupied(m), cand, ref)
            del m
            s, _ = build(static, res, config=cfg)
            conf = q.conflicting(rcu, s)[1]
            del s
        gc.collect()
        left[mapper] = qual.ghosts_left
        rows.append(
            {
                "scene": scene,
                "seed": seed,
                **asdict(settings),
                "resolution": res,
                "mapper": mapper,
                "scans": len(dyn),
                "ghosts_pct": 100 * qual.ghosts,
                "ghost_cells_observed": qual.ghost_cells,
                "static_kept_pct": 100 * qual.static_kept,
                "static_cells": qual.static_cells,
                "conflicting_static_pct": None if conf is None else 100 * conf,
                "ms_median": 1e3 * float(np.median(times[1:])),
                "ms_p95": 1e3 * float(np.percentile(times[1:], 95)),
            }
        )
    del rcu
    gc.collect()
    octo = next((r["ghosts_pct"] for r in rows if r["mapper"] == "octomap"), None)
    for r in rows:
        r["ghosts_vs_octomap"] = r["ghosts_pct"] / octo if octo and r["mapper"] != "octomap" else None
    return rows, {"candidates": cand, "static": ref, "left": left}


def top_view(path: Path, scene: str, res: float, detail: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mappers = list(detail["left"])
    fig, axes = plt.subplots(1, len(mappers), figsize=(5.5 * len(mappers), 5), squeeze=False)
    st = detail["static"]
    cand = detail["candidates"]
    obs = cand.cells[cand.observed]
    for ax, name in zip(axes[0], mappers):
        ax.scatter(st[:, 0] * res, st[:, 1] * res, s=0.2, c="0.75", lw=0, label="static surface (truth)")
        ax.scatter(obs[:, 0] * res, obs[:, 1] * res, s=2, c="tab:green", lw=0, label="left by moving objects")
        g = detail["left"][name]
        ax.scatter(g[:, 0] * res, g[:, 1] * res, s=3, c="tab:red", lw=0, label=f"ghosts kept ({len(g)})")
        ax.set_title(f"{scene}, {res:g} m: {name}")
        ax.set_aspect("equal")
        ax.legend(loc="upper right", fontsize=7, markerscale=4)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def print_table(rows: list[dict]) -> None:
    head = f"{'scene':6} {'res':>5} {'mapper':12} {'ghosts':>7} {'observed':>8} {'static kept':>11} {'conflicting':>11} {'ms/scan':>8}"
    print(head)
    print("-" * len(head))
    for r in rows:
        conf = "-" if r["conflicting_static_pct"] is None else f"{r['conflicting_static_pct']:.1f}%"
        print(
            f"{r['scene']:6} {r['resolution']:>5g} {r['mapper']:12} {r['ghosts_pct']:>6.1f}% {r['ghost_cells_observed']:>8} "
            f"{r['static_kept_pct']:>10.1f}% {conf:>11} {r['ms_median']:>8.1f}"
        )


def print_grid(rows: list[dict]) -> None:
    """One line per scene, seed, settings and resolution: the mappers side by side."""
    head = (
        f"{'scene':5} {'seed':>5} {'settings':14} {'res':>4} | {'ghosts % ndt / paper / octo':>27} {'ndt/octo':>8} | "
        f"{'static kept % ndt / paper / octo':>32} | {'conflicting % ndt / paper':>25}"
    )
    print(head)
    print("-" * len(head))
    keys = ("scene", "seed", *Settings.__dataclass_fields__, "resolution")
    groups: dict[tuple, dict] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), {})[r["mapper"]] = r
    for key, g in groups.items():
        st = Settings(**{k: key[2 + i] for i, k in enumerate(Settings.__dataclass_fields__)})
        ratio = g.get("ndtom-ndt", {}).get("ghosts_vs_octomap")
        print(
            f"{key[0]:5} {key[1]:>5} {st.label():14} {key[-1]:>4g} | {_side(g, MAPPERS, 'ghosts_pct'):>27} "
            f"{'-' if ratio is None else f'{ratio:.2f}x':>8} | {_side(g, MAPPERS, 'static_kept_pct'):>32} | "
            f"{_side(g, MAPPERS[:2], 'conflicting_static_pct'):>25}"
        )


def _side(group: dict, mappers, field: str) -> str:
    vals = (group.get(m, {}).get(field) for m in mappers)
    return " / ".join("-" if v is None else f"{v:.1f}" for v in vals)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", nargs="+", default=["hall", "yard"], choices=["hall", "yard"])
    ap.add_argument("--seed", type=int, nargs="+", default=[7])
    ap.add_argument("--scans", type=int, default=60)
    ap.add_argument("--res", type=float, nargs="+", default=[0.2])
    d = Settings()
    ap.add_argument("--speed", type=float, nargs="+", default=[d.speed], help="vehicle speed, m/s")
    ap.add_argument("--roll", type=float, nargs="+", default=[d.roll], help="mount roll, degrees")
    ap.add_argument("--pitch", type=float, nargs="+", default=[d.pitch], help="mount pitch, degrees")
    ap.add_argument("--noise", type=float, nargs="+", default=[d.noise], help="range noise std, m")
    ap.add_argument("--stride", type=int, nargs="+", default=[d.stride], help="every K-th scan of the 10 Hz stream")
    ap.add_argument(
        "--combo",
        nargs="+",
        metavar="K=V[,K=V]",
        help="these combinations of settings (each from the defaults; 'default' for none) "
        "instead of the cross product of the lists",
    )
    ap.add_argument("--out", type=Path, default=Path("quality"))
    ap.add_argument("--simworld", type=Path, default=SIMWORLD, help="path of simworld.py")
    ap.add_argument("--no-octomap", action="store_true", help="skip OctoMap even when pyoctomap is installed")
    a = ap.parse_args(argv)
    if not a.simworld.exists():
        print(f"error: simworld.py not found at {a.simworld}; pass --simworld PATH", file=sys.stderr)
        return 2
    octomap = not a.no_octomap
    if octomap:
        try:
            import pyoctomap  # noqa: F401
        except ImportError:
            print("pyoctomap not installed: OctoMap skipped (pip install -e '.[bench]')", file=sys.stderr)
            octomap = False
    try:
        grid = (
            [parse_combo(c) for c in a.combo]
            if a.combo
            else [Settings(*v) for v in product(a.speed, a.roll, a.pitch, a.noise, a.stride)]
        )
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    a.out.mkdir(parents=True, exist_ok=True)
    ndtom_ti.init()
    rows, views = [], 0
    for scene, seed, st in product(a.scene, a.seed, grid):
        dyn, sigma, boxes = read_scene(make_scene(a.simworld, a.out, scene, seed, a.scans, False, st))
        static, _, _ = read_scene(make_scene(a.simworld, a.out, scene, seed, a.scans, True, st))
        for res in a.res:
            r, detail = evaluate(scene, dyn, static, sigma, boxes, res, octomap, seed, st)
            rows += r
            if res == a.res[0] and seed == a.seed[0]:
                top_view(a.out / f"quality_{scene}{st.tag()}.png", scene, res, detail)
                views += 1
        # Partial results survive a long grid stopped part way.
        write_csv(a.out / "quality.csv", rows)
    print_table(rows)
    print()
    print_grid(rows)
    print(f"wrote {a.out / 'quality.csv'} and {views} top views in {a.out}")
    return 0


def write_csv(path: Path, rows: list[dict]) -> None:
    import csv

    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


if __name__ == "__main__":
    raise SystemExit(main())
