"""The paper's evaluation (ndtom_ti.evaluation) on small inputs, and the error-refinement
baseline (ndtom_ti.evaluation.er_baseline).

Synthetic data: simworld halls of 5 scans 1 s apart (stride 10) at 0.5 m, static and
dynamic (same poses, same ray pattern and noise: the static hall is the control).
Real data: 4 clouds of the TUM bag at 0.2 m. About 25 s in all on 2 cores.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, SIMWORLD
from typer.testing import CliRunner

from ndtom_ti import evaluation as ex
from ndtom_ti.cli import app
from ndtom_ti.evaluation.er_baseline import UPDATE_RULE, ErrorRefinementMap
from ndtom_ti.evaluation.metrics import batch_ndt, mean_l2_score
from ndtom_ti.evaluation.sources import make_simworld

RES = 0.5
N_SCANS = 5
TUM = DATA / "tum_fr2_pioneer_slam2_10f.bag"


def need_simworld() -> None:
    if not SIMWORLD.exists():
        pytest.skip(f"simworld not found at {SIMWORLD}")


@pytest.fixture(scope="module")
def static_run(tmp_path_factory):
    """Static hall generated on the fly (the ``sim:static`` source), all outputs, with a
    one-resolution Fig. 5 sweep."""
    need_simworld()
    out = tmp_path_factory.mktemp("exp_static")
    s = ex.run_experiments(
        "sim:static", RES, out, sim_scans=N_SCANS, sim_stride=10, tools_dir=SIMWORLD.parent, sweep=[1.0]
    )
    return s, out


@pytest.fixture(scope="module")
def dynamic_npz(tmp_path_factory):
    need_simworld()
    return make_simworld(tmp_path_factory.mktemp("sim_dyn"), n_scans=N_SCANS, stride=10, tools_dir=SIMWORLD.parent)


@pytest.fixture(scope="module")
def dynamic_run(tmp_path_factory, dynamic_npz):
    out = tmp_path_factory.mktemp("exp_dynamic")
    return ex.run_experiments(dynamic_npz, RES, out, plots=False), out


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


# ---------------------------------------------------------------------------- ER baseline
def _er_loop(points_per_scan, r, eps_min):
    """The documented rule, one point at a time (the reference of the vectorised code)."""
    st: dict = {}
    for pts in points_per_scan:
        for x in pts:
            k = tuple(np.floor(x / r).astype(np.int64))
            q = x - (np.array(k) + 0.5) * r
            c = st.setdefault(k, [0, np.zeros(3), np.zeros((3, 3))])
            c[0] += 1
            if c[0] == 1:
                c[1], c[2] = q.copy(), np.zeros((3, 3))
            else:
                eps = max(1.0 / c[0], eps_min)
                e = q - c[1]
                c[1] = c[1] + eps * e
                c[2] = c[2] + eps * (np.outer(e, e) - c[2])
    return st


def test_er_baseline_is_the_documented_rule(rng):
    r, eps_min = 0.5, 0.1
    scans = [rng.normal(0.0, 1.0, (1500, 3)) for _ in range(3)]  # negative indices too
    er = ErrorRefinementMap(r, eps_min=eps_min)
    for s in scans:
        er.insert_world(s)
    ref = _er_loop(scans, r, eps_min)
    g = er.gaussians()
    keep = {k: v for k, v in ref.items() if v[0] >= 3}
    assert len(g["index"]) == len(keep) == len(er) > 100
    order = np.lexsort(g["index"].T[::-1])
    assert (order == np.arange(len(order))).all()  # sorted by cell index, like gaussians()
    for i, k in enumerate(map(tuple, g["index"])):
        n, mu, C = keep[k]
        assert g["n"][i] == n
        np.testing.assert_allclose(g["mean"][i], mu + (np.array(k) + 0.5) * r, rtol=0, atol=1e-12)
        np.testing.assert_allclose(g["cov"][i], C, rtol=0, atol=1e-12)
    assert "eps_min" in UPDATE_RULE and "Yguel" in UPDATE_RULE


def test_er_baseline_is_not_exact(rng):
    """Its mean is the running mean while 1/k >= eps_min, but its covariance never is the
    batch one, and with the learning-rate floor it forgets: it scores below 1."""
    r = 1.0
    pts = rng.uniform(0.0, 4.0, (20_000, 3))
    batch = batch_ndt(pts, r)
    exact_mean = ErrorRefinementMap(r, eps_min=1e-9)
    exact_mean.insert_world(pts)
    g = exact_mean.gaussians()
    np.testing.assert_array_equal(g["index"], batch["index"])
    np.testing.assert_allclose(g["mean"], batch["mean"], rtol=0, atol=1e-9)
    assert np.abs(g["cov"] - batch["cov"]).max() > 1e-6
    floor = ErrorRefinementMap(r, eps_min=0.05)
    for part in np.array_split(pts, 4):
        floor.insert_world(part)
    assert mean_l2_score(floor.gaussians(), batch) < 0.999


# ---------------------------------------------------------------------------- the experiments
def test_rcu_equals_batch_er_scores_lower(static_run):
    s, out = static_run
    rows = read_csv(out / "fig1_vs_batch.csv")
    assert len(rows) == N_SCANS == s["scans"]
    assert min(float(r["score_rcu"]) for r in rows) >= 0.999
    assert s["fig1_min_score"]["rcu"] >= 0.999
    assert s["fig1_final_score"]["er"] < s["fig1_final_score"]["rcu"] - 0.005
    assert 0.5 < s["fig1_final_score"]["er"] < 1.0
    # RCU has every batch cell and no other (they are the same map)
    assert all(int(r["rcu_gaussians"]) == int(r["batch_gaussians"]) for r in rows)
    # the exact multi-resolution claim rides along: coarsened RCU == batch at 3 r
    assert s["fig4d"]["rcu_coarse_vs_batch_score"] >= 0.999


def test_ndtom_differs_from_batch_only_where_occupancy_removed_cells(static_run, dynamic_run):
    for s, _ in (static_run, dynamic_run):
        nb, c = s["ndtom_vs_batch"], s["conflicting_cells"]
        # every NDT-OM Gaussian is a batch cell; the batch cells it lacks are the conflicting ones
        assert nb["shared"] == nb["ndtom_gaussians"]
        assert nb["batch_missing_in_ndtom"] == c["count"]
        assert nb["shared"] + nb["batch_missing_in_ndtom"] == nb["batch_gaussians"]
        # cells never erased hold the batch Gaussian (same points -> similarity ~1) ...
        assert nb["min_similarity_shared_same_n"] >= 0.9999
        # ... and the others were erased once and refilled: few of them
        assert nb["shared_refilled"] < 0.05 * nb["shared"]
        assert s["fig1_final_score"]["ndtom"] < s["fig1_final_score"]["rcu"]
        # the score lost is the removed cells (plus refilled ones): batch score <= 1 - removed share
        assert s["fig1_final_score"]["ndtom"] <= 1.0 - c["count"] / nb["batch_gaussians"] + 1e-9


def test_conflicting_cells_static_vs_dynamic(static_run, dynamic_run, dynamic_npz):
    """Static hall: conflicting cells are not zero. A 32-beam lidar on a moving vehicle
    grazes the floor and shelf boards: a horizontal-surface cell that gets no endpoint in a
    scan while that scan's rays to farther floor pass through it loses log-odds; the floor
    (z = 0) also lies on a cell boundary, so half its noisy points fill the cell layer above
    it, which those rays cross. Measured here (5 scans, 0.5 m): 7.6% of NDT-OM's Gaussians,
    ~90% of them horizontal planes, and 0.74% other (the threshold: < 2%). The dynamic hall
    (same poses and rays) adds conflicting cells where moving objects were."""
    st, dy = static_run[0]["conflicting_cells"], dynamic_run[0]["conflicting_cells"]
    assert st["fraction_of"] == "ndtom_gaussians"
    assert math.isclose(st["fraction"], st["count"] / st["ndtom_gaussians"])
    assert st["horizontal"] + st["other"] == st["count"]
    assert st["fraction"] < 0.12
    assert st["horizontal"] >= 0.8 * st["count"]
    assert st["other_fraction"] < 0.02
    assert st["with_dynamic_points"] == 0

    assert dy["count"] > 0
    assert dy["with_dynamic_points"] >= 10
    assert dy["other"] > st["other"]  # moving boxes have vertical sides

    # ground truth: the pallet that vanishes halfway leaves cells NDT-OM has emptied
    z = np.load(dynamic_npz)
    names = [str(n) for n in z["dyn_names"]]
    pid = len(z["static_lo"]) + names.index("pallet_removed")
    off = z["scan_offsets"]
    cells = set()
    for i in range(N_SCANS):
        a, b = off[i], off[i + 1]
        keep = ~z["no_return"][a:b]
        p = z["points"][a:b][keep].astype(np.float64)
        T = z["poses"][i]
        w = p[z["hit_id"][a:b][keep] == pid] @ T[:3, :3].T + T[:3, 3]
        k = np.floor(w / RES).astype(np.int64)
        cells |= set(map(tuple, k[k[:, 2] >= 1].tolist()))  # above the floor layer
    conf = {(int(r["i"]), int(r["j"]), int(r["k"])) for r in read_csv(dynamic_run[1] / "conflicting_cells.csv")}
    assert len(cells) >= 5
    assert len(cells & conf) >= 0.5 * len(cells)


def test_outputs_exist_and_parse(static_run):
    _, out = static_run
    j = json.loads((out / "summary.json").read_text())
    for key in (
        "fig1_final_score",
        "fig2_mean_score",
        "fig3_final",
        "conflicting_cells",
        "fig4d",
        "time_per_scan_ms",
        "ndtom_vs_batch",
        "er_update_rule",
        "fig5",
        "files",
    ):
        assert key in j, key
    for key in ("fig1_final_score", "fig2_mean_score", "time_per_scan_ms"):
        assert set(j[key]) == {"rcu", "ndtom", "ndtom_ndt", "er"}
    assert {"count", "fraction"} <= set(j["conflicting_cells"])
    assert {"fine_resolution", "fine_gaussians", "coarse_resolution", "coarse_gaussians"} <= set(j["fig4d"])
    d = j["fig4d"]
    assert d["coarse_resolution"] == pytest.approx(3 * RES) and 0 < d["coarse_gaussians"] < d["fine_gaussians"]
    assert all(0.0 < j["fig2_mean_score"][m] <= 1.0 for m in ("rcu", "ndtom", "ndtom_ndt", "er"))
    # The NDT miss model beside the paper's mapper: its own conflicting cells.
    c = j["conflicting_cells"]
    assert 0 <= c["count_ndt_miss_model"] and 0.0 <= c["fraction_ndt_miss_model"] < 1.0
    f3 = j["fig3_final"]
    assert f3["mean_logodds_occupied"] > 0 > f3["mean_logodds_empty"]
    assert f3["occupied_cells"] > 0 and f3["empty_cells"] > 0

    columns = {
        "fig1_vs_batch.csv": [
            "scan",
            "batch_gaussians",
            "score_rcu",
            "score_ndtom",
            "score_ndtom_ndt",
            "score_er",
            "ms_ndtom",
        ],
        "fig2_self_test.csv": ["cloud", "cloud_gaussians", "score_rcu", "score_ndtom", "score_er", "coverage_rcu"],
        "fig3_logodds.csv": ["scan", "mean_logodds_occupied", "mean_logodds_empty", "occupied_cells", "empty_cells"],
        "fig4b_conflicting.csv": [
            "scan",
            "conflicting",
            "ndtom_gaussians",
            "rcu_gaussians",
            "fraction",
            "fraction_ndt",
        ],
        "conflicting_cells.csv": ["i", "j", "k", "x", "y", "z", "rcu_n", "ndtom_logodds", "horizontal"],
        "fig5_sweep.csv": ["mapper", "resolution", "ms_median"],
    }
    for name, cols in columns.items():
        rows = read_csv(out / name)
        assert rows and set(cols) <= set(rows[0]), name
        assert name in j["files"]
    assert len(read_csv(out / "fig2_self_test.csv")) == N_SCANS
    assert int(read_csv(out / "fig4b_conflicting.csv")[-1]["conflicting"]) == j["conflicting_cells"]["count"]
    mappers = {r["mapper"] for r in read_csv(out / "fig5_sweep.csv")}
    assert "ndtom" in mappers and ("octomap" in mappers) == (j["fig5"]["baseline"] == "octomap")
    pngs = [
        "fig1_vs_batch.png",
        "fig2_self_test.png",
        "fig3_logodds.png",
        "fig4b_conflicting.png",
        "fig4_maps.png",
        "fig5_time_per_scan.png",
    ]
    for name in pngs:
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, name
        assert name in j["files"]
    assert "Fig. 1" in ex.format_summary(j)


def test_tum_rcu_equals_batch(tmp_path):
    if not TUM.exists():
        pytest.skip(f"{TUM} not available")
    s = ex.run_experiments(TUM, 0.2, tmp_path, max_scans=4, plots=False)
    assert s["scans"] == 4 and s["source_kind"] == "recording"
    assert s["fig1_min_score"]["rcu"] >= 0.99
    assert s["fig1_final_score"]["er"] < s["fig1_final_score"]["rcu"]
    assert s["ndtom_vs_batch"]["min_similarity_shared_same_n"] >= 0.999


def test_command_prints_summary(dynamic_npz, tmp_path):
    res = CliRunner().invoke(
        app,
        [
            "experiments",
            str(dynamic_npz),
            "-r",
            "1.0",
            "--out",
            str(tmp_path),
            "--max-scans",
            "2",
            "--every",
            "2",
            "--no-plots",
            "--coarsen",
            "2",
        ],
    )
    assert res.exit_code == 0, res.output
    text = res.output
    assert "Fig. 1 score vs batch" in text and "Fig. 4b" in text and "Fig. 4d: 1 m -> 2 m" in text
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["scans"] == 2 and s["fig4d"]["factor"] == 2 and s["fig5"] is None


def test_given_scans_and_bad_options(tmp_path, rng):
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 1.0]
    pts = rng.uniform(-3.0, 3.0, (3000, 3)).astype(np.float32)
    s = ex.run_experiments([(pts, T), (pts[::-1].copy(), T)], 1.0, tmp_path, plots=False)
    assert s["source_kind"] == "scans" and s["scans"] == 2
    assert s["fig1_min_score"]["rcu"] >= 0.999
    far = T.copy()  # georeferenced poses: mapped relative to the first one, rounded (the same figures)
    far[:3, 3] += [512_345.0, 5_412_345.0, 0.0]
    said: list = []
    s2 = ex.run_experiments(
        [(pts, far), (pts[::-1].copy(), far)], 1.0, tmp_path / "far", plots=False, progress=said.append
    )
    assert any("mapped relative to [512300.0, 5412300.0, 0.0]" in line for line in said), said
    assert s2["scans"] == 2 and s2["fig1_min_score"] == s["fig1_min_score"]
    with pytest.raises(ValueError, match="coarsen"):
        ex.run_experiments([(pts, T)], 1.0, tmp_path, coarsen=1)
    with pytest.raises(ValueError, match="resolution"):
        ex.run_experiments([(pts, T)], -1.0, tmp_path)
    with pytest.raises(ValueError, match="sim:dynamic"):
        ex.load_scans("sim:yard")
