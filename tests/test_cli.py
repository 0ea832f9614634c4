"""The `ndtom` command: info, map, demo, the error messages and exit codes (in-process,
sharing the session's Taichi), plus two real subprocesses."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parent))
import io_fixtures as fx  # noqa: E402
import test_pipeline_bags as pb  # noqa: E402

import ndtom_ti  # noqa: E402
from ndtom_ti import MapMemoryError, NdtOmMap  # noqa: E402
from ndtom_ti.cli import app, default_output  # noqa: E402
from ndtom_ti.mapfile import read_header  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    return {
        "ros1": pb.write_plane_bag(root, "ros1"),
        "mcap": pb.write_plane_bag(root, "mcap"),
        "early": pb.write_plane_bag(root, "ros1", name="early", early_cloud=True),
        "two": pb.write_plane_bag(root, "sqlite3", name="two", second_topic=True),
        "notf": pb.write_plane_bag(root, "ros1", name="notf", with_tf=False),
        "fields": pb.write_plane_bag(root, "ros1", name="fields", bad_fields=True),
        "zeros": pb.write_plane_bag(root, "mcap", name="zeros", no_return=300),
    }


def run(*args: object):
    r = CliRunner(env={"COLUMNS": "250"}).invoke(app, [str(a) for a in args])
    assert "Traceback" not in r.output, r.output
    return r


def assert_user_error(r, *texts: str, code: int = 2) -> None:
    assert r.exit_code == code, r.output
    assert "Error:" in r.output, r.output
    for t in texts:
        assert t in r.output, (t, r.output)


# ---------------------------------------------------------------------------- help, info
def test_help_and_version() -> None:
    r = run("--help")
    assert r.exit_code == 0
    for cmd in ("info", "map", "demo", "export"):
        assert cmd in r.output
    r = run("map", "--help")
    assert r.exit_code == 0
    for opt in (
        "--resolution",
        "--output",
        "--cloud-topic",
        "--fixed-frame",
        "--poses",
        "--pose-topic",
        "--sensor-frame",
        "--every",
        "--every-distance",
        "--start",
        "--end",
        "--max-scans",
        "--max-range",
        "--min-range",
        "--no-occupancy",
        "--miss-model",
        "--arch",
        "--config",
    ):
        assert opt in r.output, opt
    r = run("--version")
    assert r.exit_code == 0 and ndtom_ti.__version__ in r.output


def test_info_shows_topics_frames_and_pose_sources(bags) -> None:
    r = run("info", bags["ros1"])
    assert r.exit_code == 0, r.output
    for text in (
        "/points",
        "sensor_msgs/msg/PointCloud2",
        "/tf_static",
        "mappable (frame lidar)",
        "map",
        "base",
        "lidar",
        "[static]",
        "[5 transforms",
        "tf: map -> base -> lidar",
        "Ready: ndtom map",
        "ROS1",
    ):
        assert text in r.output, text
    r = run("info", bags["two"])
    assert r.exit_code == 0
    assert "/points_front" in r.output and "Cannot map with the defaults" in r.output
    assert "--cloud-topic" in r.output
    r = run("info", bags["notf"])
    assert r.exit_code == 0 and "TF frames: none" in r.output and "no usable poses" in r.output


def test_usage_errors_are_one_error_line_and_a_hint(bags, tmp_path: Path) -> None:
    """A missing -r or an option out of its range: the Error:/Hint: form of every other
    bad option (exit 2), not Click's usage text."""
    for args, texts in (
        (("map", bags["ros1"]), ("Missing option '-r' / '--resolution'", "Hint: give the cell size in metres")),
        (
            ("map", bags["ros1"], "-r", "0.5", "--every", "0"),
            ("'--every'", "greater than or equal to 1", "Hint: `ndtom map --help`"),
        ),
        (("bogus",), ("No such command 'bogus'", "Hint: `ndtom --help` lists the commands")),
    ):
        r = run(*args)
        assert_user_error(r, *texts)
        assert "Usage:" not in r.output and "Try '" not in r.output, r.output
    assert not list(tmp_path.iterdir())


def test_info_of_a_map_file_and_of_nothing(bags, tmp_path: Path) -> None:
    out = tmp_path / "m.ndtom"
    assert run("map", bags["ros1"], "-r", pb.RES, "-o", out, "--no-progress").exit_code == 0
    r = run("info", out)
    assert r.exit_code == 0 and "Map file" in r.output and "0.25 m" in r.output
    assert "scans inserted" in r.output and "/points" in r.output
    # "Gaussians" is the summary's count; the records (all cells with points) are named and told apart
    gaussians = NdtOmMap.load(out).metadata["summary"]["gaussians"]
    assert re.search(rf"Gaussians\W+{gaussians:,} \(cells of >= 3 points, occupied\)", r.output), r.output
    assert "Gaussian records" in r.output and "fewer points or in free cells" in r.output
    assert "frame origin" not in r.output  # the plane's poses start near their frame's origin
    assert_user_error(run("info", tmp_path / "nothing.bag"), "does not exist")
    m = NdtOmMap.load(out)
    m.metadata["frame_origin"] = "east"  # a damaged or hand-made file is shown, not a crash
    m.save(out)
    del m
    r = run("info", out)
    assert r.exit_code == 0 and "frame origin" in r.output and "'east' (not three numbers" in r.output, r.output


def test_map_compact_writes_a_smaller_rounded_map_that_info_names(bags, tmp_path: Path) -> None:
    """`ndtom map --compact` writes format 7 (Gaussians rounded), which `ndtom info` says and
    `ndtom_ti` loads; without it the map file is the lossless format 6."""
    from ndtom_ti.mapfile import read_header

    exact, small = tmp_path / "m.ndtom", tmp_path / "c.ndtom"
    for out, extra in ((exact, []), (small, ["--compact"])):
        assert (
            run("map", bags["ros1"], "-r", pb.RES, "-o", out, "--max-scans", "3", "--no-progress", *extra).exit_code
            == 0
        )
    assert read_header(exact)["version"] == 6 and read_header(small)["version"] == 7
    assert small.stat().st_size < exact.stat().st_size
    a, b = NdtOmMap.load(exact), NdtOmMap.load(small)
    assert len(a) == len(b) > 0
    r = run("info", small)
    assert r.exit_code == 0 and "compact: Gaussians rounded" in r.output, r.output
    assert "Gaussians rounded" not in run("info", exact).output


# ---------------------------------------------------------------------------- map
@pytest.mark.parametrize("kind", ["ros1", "mcap"])
def test_map_writes_the_right_map_with_its_settings(bags, tmp_path: Path, kind: str) -> None:
    out = tmp_path / "site.ndtom"
    r = run("map", bags[kind], "-r", pb.RES, "-o", out)
    assert r.exit_code == 0, r.output
    for text in (
        "Mapping summary",
        "5 of 5 clouds read",
        "scans skipped",
        "Gaussians",
        "known cells",
        "memory",
        "time per scan",
        "median",
        "p95",
        "Map written to",
    ):
        assert text in r.output, text
    assert not list(tmp_path.glob(".*tmp"))  # no temporary files left
    m = NdtOmMap.load(out)
    md = m.metadata
    assert md["source"] == str(bags[kind].resolve()) and md["cloud_topic"] == "/points"
    assert md["pose_source"] == "tf: map -> base -> lidar" and md["ndtom_ti_version"] == ndtom_ti.__version__
    assert md["options"]["every"] == 1 and md["options"]["arch"] == ndtom_ti.current_arch()
    assert md["complete"] is True and md["summary"]["scans_used"] == 5 and md["resolution"] == pb.RES
    assert m.resolution == pb.RES and m.occupancy_enabled and m.scans_inserted == 5
    pb.check_plane_map(m)
    del m


def test_map_default_output_is_the_recording_name_in_the_current_folder(bags, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert default_output(bags["mcap"]) == tmp_path / "plane_mcap.ndtom"
    assert default_output(Path("/data/site.bag")) == tmp_path / "site.ndtom"
    r = run("map", bags["ros1"], "-r", pb.RES, "--max-scans", "2", "--no-occupancy", "--no-progress")
    assert r.exit_code == 0, r.output
    h = read_header(tmp_path / "plane.ndtom")
    assert h["scans_inserted"] == 2 and h["occupancy"] is False and h["metadata"]["options"]["max_scans"] == 2


def test_map_options_and_config_file(bags, tmp_path: Path) -> None:
    cfg = tmp_path / "map.toml"
    cfg.write_text("p_occupied = 0.7\nmax_range = 50.0\nmin_points = 4\n")
    out = tmp_path / "c.ndtom"
    r = run(
        "map",
        bags["ros1"],
        "-r",
        "0.5",
        "-o",
        out,
        "--config",
        cfg,
        "--max-range",
        "3.5",
        "--every",
        "2",
        "--no-progress",
    )
    assert r.exit_code == 0, r.output
    assert "3 of 5 clouds read" in r.output and "2 left out by --every" in r.output and "out of range" in r.output
    h = read_header(out)
    assert h["config"]["p_occupied"] == 0.7 and h["config"]["max_range"] == 3.5 and h["config"]["min_points"] == 4
    assert h["metadata"]["config_file"] == str(cfg.resolve()) and h["resolution"] == 0.5
    assert h["metadata"]["summary"]["dropped"]["range"] > 0
    js = tmp_path / "map.json"
    js.write_text('{"p_empty": 0.4}')
    assert (
        run("map", bags["ros1"], "-r", "0.5", "-o", out, "--config", js, "--max-scans", "1", "--no-progress").exit_code
        == 0
    )
    assert read_header(out)["config"]["p_empty"] == 0.4


def test_a_bad_option_value_names_its_commands_help(bags, tmp_path: Path) -> None:
    """The hint of an option the command refuses names that command's help, not `ndtom COMMAND --help`."""
    bad = tmp_path / "bad.json"
    bad.write_text('{"p_occupid": 0.7}')
    r = run("map", bags["ros1"], "-r", "0.5", "-o", tmp_path / "x.ndtom", "--config", bad, "--no-progress")
    assert_user_error(r, "unknown options ['p_occupid']", "Hint: `ndtom map --help` lists the options")


def test_miss_model_option_wins_over_the_config_file(bags, tmp_path: Path) -> None:
    cfg = tmp_path / "map.toml"
    cfg.write_text('miss_model = "ndt"\nsigma_s = 0.1\n')
    out = tmp_path / "m.ndtom"
    r = run("map", bags["ros1"], "-r", "0.5", "-o", out, "--config", cfg, "--max-scans", "2", "--no-progress")
    assert r.exit_code == 0, r.output
    assert read_header(out)["config"]["miss_model"] == "ndt" and read_header(out)["config"]["sigma_s"] == 0.1
    r = run(
        "map",
        bags["ros1"],
        "-r",
        "0.5",
        "-o",
        out,
        "--config",
        cfg,
        "--miss-model",
        "paper",
        "--max-scans",
        "2",
        "--no-progress",
    )
    assert r.exit_code == 0, r.output
    assert read_header(out)["config"]["miss_model"] == "paper"
    r = run("map", bags["ros1"], "-r", "0.5", "-o", out, "--miss-model", "octomap")
    assert r.exit_code == 2 and "octomap" in r.output


@pytest.mark.parametrize(
    "args, texts",
    [
        (["-r", "-1"], ["resolution must be a positive"]),
        (["-r", "nan"], ["resolution must be a positive"]),
        (["-r", "0.25", "--every", "2", "--every-distance", "1"], ["--every or --every-distance, not both"]),
        (["-r", "0.25", "--sensor-frame", "--pose-topic", "/odom"], ["give one pose source"]),
        (["-r", "0.25", "--start", "5", "--end", "1"], ["--end (1.0) is before --start (5.0)"]),
        (["-r", "0.25", "--min-range", "5", "--max-range", "2"], ["max_range must be > min_range"]),
        (["-r", "0.25", "--poses", "missing_poses.txt"], ["pose file", "does not exist"]),
        (["-r", "0.25", "--pose-topic", "/odm"], ["pose topic '/odm' is not in"]),
        (["-r", "0.25", "--config", "missing.toml"], ["config file", "does not exist"]),
        (["-r", "0.25", "--every", "0"], ["Invalid value for '--every'"]),
        (["-r", "0.25", "--arch", "tpu"], ["Invalid value for '--arch'"]),
        ([], ["Missing option '-r'"]),
    ],
    ids=[
        "negative-res",
        "nan-res",
        "every-and-distance",
        "two-pose-sources",
        "end-before-start",
        "ranges",
        "pose-file",
        "pose-topic",
        "config-file",
        "every-0",
        "arch",
        "no-res",
    ],
)
def test_bad_options_exit_2(bags, tmp_path: Path, args: list, texts: list) -> None:
    out = tmp_path / "x.ndtom"
    r = run("map", bags["ros1"], "-o", out, *args)
    assert r.exit_code == 2, r.output
    for t in texts:
        assert t in r.output, (t, r.output)
    assert not out.exists()


def test_bad_config_file_exits_2(bags, tmp_path: Path) -> None:
    for text, name, msg in (
        ("p_occupied = [", "a.toml", "not valid TOML"),
        ('{"resolution": 0.1}', "b.json", "unknown options ['resolution']"),
        ("p_occupied = 0.3", "c.toml", "p_occupied must be in (0.5, 1)"),
    ):
        f = tmp_path / name
        f.write_text(text)
        r = run("map", bags["ros1"], "-r", "0.25", "-o", tmp_path / "x.ndtom", "--config", f)
        assert_user_error(r, msg, "Hint:")
        assert not (tmp_path / "x.ndtom").exists()


def _empty_bag(root: Path) -> Path:
    return fx.write_bag(root / "empty.bag", "ros1", [])


def _truncated_bag(root: Path) -> Path:
    src = pb.write_plane_bag(root, "ros1", name="full")
    data = src.read_bytes()
    (root / "cut.bag").write_bytes(data[: len(data) // 2])
    return root / "cut.bag"


def _corrupt_bag(root: Path) -> Path:
    rng = np.random.default_rng(5)
    (root / "noise.bag").write_bytes(b"#ROSBAG V2.0\n" + rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
    return root / "noise.bag"


def _text_file(root: Path) -> Path:
    (root / "notes.bag").write_text("these are not the bags you are looking for\n")
    return root / "notes.bag"


def _plain_folder(root: Path) -> Path:
    (root / "folder").mkdir()
    (root / "folder" / "readme.txt").write_text("x")
    return root / "folder"


@pytest.mark.parametrize(
    "make, extra, texts",
    [
        (
            lambda r, b: b["ros1"],
            ["--cloud-topic", "/point"],
            ["cloud topic '/point' is not in", "Did you mean '/points'?", "Mappable topics: /points"],
        ),
        (lambda r, b: b["ros1"], ["--cloud-topic", "/tf"], ["/tf has type tf2_msgs/msg/TFMessage"]),
        (lambda r, b: b["two"], [], ["2 PointCloud2 topics: /points, /points_front", "--cloud-topic"]),
        (lambda r, b: b["notf"], [], ["no usable poses for /points (frame 'lidar')", "--sensor-frame", "--poses"]),
        (lambda r, b: b["ros1"], ["--fixed-frame", "odom"], ["fixed frame 'odom' is not in the TF tree"]),
        (lambda r, b: b["fields"], [], ["has no x/y/z field", "fields present: range", "x, y, z fields"]),
        (lambda r, b: _empty_bag(r), [], ["has no topic to map", "the bag is empty"]),
        (lambda r, b: _truncated_bag(r), [], ["cut.bag", "truncated or corrupt", "rosbag reindex"]),
        (lambda r, b: _corrupt_bag(r), [], ["noise.bag", "truncated or corrupt"]),
        (lambda r, b: _text_file(r), [], ["is not a ROS bag"]),
        (lambda r, b: _plain_folder(r), [], ["is a folder but not a ROS2 bag", "readme.txt"]),
        (lambda r, b: r / "missing.bag", [], ["missing.bag does not exist"]),
    ],
    ids=[
        "misspelled-topic",
        "not-a-cloud-topic",
        "several-topics",
        "no-poses",
        "bad-fixed-frame",
        "unknown-fields",
        "empty",
        "truncated",
        "corrupt",
        "not-a-bag",
        "folder",
        "missing",
    ],
)
def test_bad_recordings_exit_2_without_a_map(bags, tmp_path: Path, make, extra: list, texts: list) -> None:
    bag = make(tmp_path, bags)
    out = tmp_path / "out.ndtom"
    r = run("map", bag, "-r", pb.RES, "-o", out, *extra)
    assert_user_error(r, *texts, "Hint:")
    assert not out.exists() and not list(tmp_path.glob(".out.ndtom*"))


def test_no_poses_error_lists_each_source_on_a_line_of_its_own(bags, tmp_path: Path) -> None:
    r = run("map", bags["notf"], "-r", pb.RES, "-o", tmp_path / "out.ndtom")
    assert_user_error(r, "no usable poses for /points (frame 'lidar')")
    lines = r.output.splitlines()
    assert any(line.startswith("  - TF:") for line in lines), r.output
    assert any(line.startswith("Map in the sensor frame") for line in lines), r.output
    assert max(len(line) for line in lines) < 200, r.output


def test_info_failures_speak_of_what_was_given(tmp_path: Path) -> None:
    """A corrupt or missing .ndtom is a map file's fault, not a bag's; and after `ndtom
    info` fails its hint does not suggest `ndtom info` again."""
    (tmp_path / "bad.ndtom").write_bytes(b"garbage here")
    r = run("info", tmp_path / "bad.ndtom")
    assert_user_error(r, "not an ndtom_ti map file")
    assert "ROS bag" not in r.output and "ndtom info BAG" not in r.output, r.output
    r = run("info", tmp_path / "missing.ndtom")
    assert_user_error(r, "no map file at")
    assert "bag" not in r.output.lower().replace("also takes recordings", ""), r.output
    r = run("info", tmp_path / "missing.bag")
    assert_user_error(r, "missing.bag does not exist", "Hint: `ndtom info` takes a ROS1 .bag file")
    assert "ndtom info BAG" not in r.output, r.output


def test_clouds_before_the_first_transform_are_skipped_and_counted(bags, tmp_path: Path) -> None:
    out = tmp_path / "early.ndtom"
    r = run("map", bags["early"], "-r", pb.RES, "-o", out)
    assert r.exit_code == 0, r.output
    assert "5 of 6 clouds read" in r.output and "1 no pose at stamp" in r.output
    assert "note: no pose at stamp: cloud #0" in r.output and "before the first" in r.output
    assert read_header(out)["metadata"]["summary"]["skipped"] == {"no pose at stamp": 1}


def test_no_scan_left_is_an_error(bags, tmp_path: Path) -> None:
    out = tmp_path / "none.ndtom"
    r = run("map", bags["ros1"], "-r", pb.RES, "-o", out, "--start", "100")  # past the end: said so first
    assert_user_error(r, "t_start (--start) 100 s is past the end", "s long (seconds from its first message")
    assert not out.exists()
    r = run("map", bags["ros1"], "-r", pb.RES, "-o", out, "--start", "0.3", "--end", "0.31")  # between two clouds
    assert_user_error(r, "no scans were mapped", "outside time window", "no map written")
    assert not out.exists()


@pytest.mark.parametrize(
    "where, texts",
    [
        (lambda t: t / "no" / "such" / "folder" / "m.ndtom", ["folder", "does not exist"]),
        (lambda t: t / "afile.txt" / "m.ndtom", ["is not a folder"]),
        (lambda t: t, ["is a folder"]),
    ],
    ids=["missing-folder", "parent-is-file", "output-is-folder"],
)
def test_unwritable_output_fails_before_mapping(bags, tmp_path: Path, monkeypatch, where, texts) -> None:
    (tmp_path / "afile.txt").write_text("x")
    import ndtom_ti.pipeline

    def no_mapping(*a, **k):
        raise AssertionError("mapping started")

    monkeypatch.setattr(ndtom_ti.pipeline, "map_recording", no_mapping)
    r = run("map", bags["ros1"], "-r", pb.RES, "-o", where(tmp_path))
    assert_user_error(r, "map file", *texts)


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_read_only_folder(bags, tmp_path: Path) -> None:  # pragma: no cover - needs a non-root user
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        assert_user_error(run("map", bags["ros1"], "-r", pb.RES, "-o", ro / "m.ndtom"), "cannot write", code=1)
    finally:
        ro.chmod(0o755)


def test_ctrl_c_saves_what_was_mapped(bags, tmp_path: Path, monkeypatch) -> None:
    orig = NdtOmMap.insert_scan
    calls = {"n": 0}

    def insert(self, points, T):
        calls["n"] += 1
        if calls["n"] == 2:
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of the second insert
        return orig(self, points, T)

    monkeypatch.setattr(NdtOmMap, "insert_scan", insert)
    out = tmp_path / "partial.ndtom"
    r = run("map", bags["ros1"], "-r", pb.RES, "-o", out)
    assert r.exit_code == 130, r.output
    assert "Interrupted: saved the 2 scans mapped so far" in r.output and "Mapping summary" in r.output
    m = NdtOmMap.load(out)
    assert m.scans_inserted == 2 and m.metadata["complete"] is False
    assert m.metadata["summary"]["stopped"] == "interrupted"
    del m


def test_a_run_stopped_early_keeps_the_map_it_would_replace(bags, tmp_path: Path, monkeypatch) -> None:
    """Run again into a finished map's file and press Ctrl-C: the scans mapped so far go beside
    it (NAME.partial.ndtom), and the finished map stays as it was."""
    out = tmp_path / "keep.ndtom"
    assert run("map", bags["ros1"], "-r", pb.RES, "-o", out).exit_code == 0
    before = out.read_bytes()
    orig = NdtOmMap.insert_scan
    calls = {"n": 0}

    def insert(self, points, T):
        calls["n"] += 1
        if calls["n"] == 2:
            os.kill(os.getpid(), signal.SIGINT)
        return orig(self, points, T)

    monkeypatch.setattr(NdtOmMap, "insert_scan", insert)
    r = run("map", bags["ros1"], "-r", pb.RES, "-o", out)
    assert r.exit_code == 130, r.output
    partial = tmp_path / "keep.partial.ndtom"
    assert f"saved the 2 scans mapped so far to {partial}" in r.output, r.output
    assert f"{out}, the map there before this run, is unchanged" in r.output
    assert out.read_bytes() == before and NdtOmMap.load(out).metadata["complete"] is True
    m = NdtOmMap.load(partial)
    assert m.scans_inserted == 2 and m.metadata["complete"] is False
    del m
    monkeypatch.setattr(NdtOmMap, "insert_scan", orig)
    assert run("map", bags["ros1"], "-r", pb.RES, "-o", out).exit_code == 0  # a finished run replaces it
    assert NdtOmMap.load(out).metadata["complete"] is True


def test_small_cli_inputs(bags, tmp_path: Path, monkeypatch) -> None:
    """--start nan is refused as a time; a map of a ROS2 bag named by its metadata.yaml is named
    after the bag folder; a ROS2 folder whose metadata.yaml is missing points to reindexing."""
    from ndtom_ti.cli.mapping import default_output

    r = run("map", bags["mcap"], "-r", pb.RES, "--start", "nan", "-o", tmp_path / "m.ndtom")
    assert_user_error(r, "--start must be a number of seconds")
    monkeypatch.chdir(tmp_path)
    assert default_output(bags["mcap"] / "metadata.yaml") == tmp_path / (bags["mcap"].name + ".ndtom")
    bare = tmp_path / "bare_ros2"
    bare.mkdir()
    for f in bags["mcap"].iterdir():
        if f.suffix == ".mcap":
            (bare / f.name).write_bytes(f.read_bytes())
    assert_user_error(run("info", bare), "has no metadata.yaml", "ros2 bag reindex")


def test_a_map_that_cannot_be_written_is_written_elsewhere(bags, tmp_path: Path, monkeypatch) -> None:
    """The save fails at the end (a full disk, a dangling link): the map goes to the current
    folder instead of being lost with the run."""
    out = tmp_path / "full" / "m.ndtom"
    out.parent.mkdir()
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    save = NdtOmMap.save

    def full_disk(self, path, **kw):
        if Path(path).parent == out.parent:
            raise OSError(28, "No space left on device")
        return save(self, path, **kw)

    monkeypatch.setattr(NdtOmMap, "save", full_disk)
    r = run("map", bags["ros1"], "-r", pb.RES, "-o", out)
    assert r.exit_code == 1, r.output
    rescued = list(here.glob("m.rescued-*.ndtom"))
    assert len(rescued) == 1 and f"it was written to {rescued[0]} instead" in r.output, r.output
    m = NdtOmMap.load(rescued[0])
    assert m.scans_inserted == pb.N_CLOUDS and m.metadata["complete"] is True
    del m


def test_no_output_replaces_a_recording_or_a_map(bags, tmp_path: Path) -> None:
    """Outputs of every command (an export, a page, the demo's map) refuse a recording, a file
    inside a ROS2 bag's folder and, unless they are a map themselves, a map file."""
    m = tmp_path / "m.ndtom"
    assert run("map", bags["ros1"], "-r", pb.RES, "-o", m).exit_code == 0
    rec = tmp_path / "rec.bag"
    rec.write_bytes(bags["ros1"].read_bytes())
    other = tmp_path / "other.ndtom"
    other.write_bytes(m.read_bytes())
    meta = bags["mcap"] / "metadata.yaml"
    before = meta.read_bytes()
    assert_user_error(run("export", m, "-o", meta), "inside the ROS2 bag", "choose another path")
    assert_user_error(run("export", m, "-f", "ply", "-o", rec), "it is a ROS1 bag")
    assert_user_error(run("export", m, "-f", "ply", "-o", other), "it is an ndtom map file")
    assert meta.read_bytes() == before and rec.read_bytes() == bags["ros1"].read_bytes()
    demo = tmp_path / "d"
    demo.mkdir()
    (demo / "demo.ndtom").write_bytes(rec.read_bytes())
    assert_user_error(run("demo", "--out", demo, "--scans", 2), "it is a ROS1 bag")
    assert (demo / "demo.ndtom").read_bytes() == rec.read_bytes()


def test_pose_child_frame_goes_with_a_pose_topic(bags, tmp_path: Path) -> None:
    r = run(
        "map", bags["ros1"], "-r", pb.RES, "--sensor-frame", "--pose-child-frame", "base", "-o", tmp_path / "m.ndtom"
    )
    assert_user_error(r, "--pose-child-frame goes with poses from a pose topic, not with --sensor-frame")


def test_the_map_file_does_not_replace_other_files(bags, tmp_path: Path) -> None:
    """-o naming another recording, a file of another kind, or another format's suffix is
    refused before any work: the map would destroy the file, or not be what the name says."""
    other = tmp_path / "other.bag"
    other.write_bytes(bags["ros1"].read_bytes())
    r = run("map", bags["ros1"], "-r", pb.RES, "-o", other)
    assert_user_error(r, "it is a ROS1 bag", "choose another path")
    assert other.read_bytes() == bags["ros1"].read_bytes()
    notes = tmp_path / "notes.txt"
    notes.write_text("calibration notes\n")
    assert_user_error(run("map", bags["ros1"], "-r", pb.RES, "-o", notes), "it is a file of another kind")
    assert notes.read_text() == "calibration notes\n"
    assert_user_error(run("map", bags["ros1"], "-r", pb.RES, "-o", tmp_path / "new.bag"), "is named as a recording")
    for name in ("cloud.ply", "map.bt", "grid.PGM"):
        target = tmp_path / name
        r = run("map", bags["ros1"], "-r", pb.RES, "-o", target)
        assert_user_error(r, "maps are written in ndtom's own format", "ndtom export")
        assert not target.exists()
    disguised = tmp_path / "rec.ndtom"  # a recording, whatever its name
    disguised.write_bytes(bags["ros1"].read_bytes())
    assert_user_error(run("map", bags["ros1"], "-r", pb.RES, "-o", disguised), "it is a ROS1 bag")
    empty = tmp_path / "empty.ndtom"
    empty.touch()  # an empty file (as `touch` leaves) is no loss
    assert run("map", bags["ros1"], "-r", pb.RES, "-o", empty).exit_code == 0


def refuse_scan(monkeypatch, fail_at: int) -> None:
    """Make the ``fail_at``-th scan inserted one the memory budget refuses."""
    orig = NdtOmMap.insert_scan
    calls = {"n": 0}

    def insert(self, points, T):
        calls["n"] += 1
        if calls["n"] == fail_at:
            raise MapMemoryError("this update could take Taichi's memory pool to 999 MiB, past the budget (test)")
        return orig(self, points, T)

    monkeypatch.setattr(NdtOmMap, "insert_scan", insert)


@pytest.mark.parametrize("fail_at", [3, 1])
def test_memory_budget_saves_what_was_mapped_and_exits_1(bags, tmp_path: Path, monkeypatch, fail_at) -> None:
    refuse_scan(monkeypatch, fail_at)
    out = tmp_path / "mem.ndtom"
    r = run("map", bags["ros1"], "-r", pb.RES, "-o", out)
    assert_user_error(r, f"scan {fail_at} was refused", "memory pool", "coarser resolution", code=1)
    if fail_at == 3:
        assert "Saved the 2 scans mapped before it" in r.output
        h = read_header(out)
        assert h["scans_inserted"] == 2 and h["metadata"]["complete"] is False
    else:
        assert "Nothing was mapped; no map written" in r.output and not out.exists()


def test_taichi_arch_cannot_change_in_a_process(bags, tmp_path: Path) -> None:
    other = "cuda" if ndtom_ti.current_arch() == "cpu" else "cpu"
    r = run("map", bags["ros1"], "-r", pb.RES, "-o", tmp_path / "a.ndtom", "--arch", other)
    assert_user_error(r, "already initialised", "--arch")
    assert not (tmp_path / "a.ndtom").exists()


# ---------------------------------------------------------------------------- demo
def test_demo_maps_the_synthetic_room(tmp_path: Path) -> None:
    out = tmp_path / "demo_out"
    r = run("demo", "--out", out)
    assert r.exit_code == 0, r.output
    for text in (
        "Demo scene",
        "Mapping summary",
        "20 of 20 clouds read",
        "Against the ground truth",
        "left where the box was taken away",
        "Map written to",
        f"Next: ndtom view {out / 'demo.ndtom'}",
        "ndtom export",
    ):
        assert text in r.output, text
    # points/s leaves out the first scan, which compiles the kernels (it read "0.00 M points/s")
    rate = float(re.search(r"([\d.]+) M points/s after the first scan", r.output).group(1))
    assert rate > 0.05, r.output
    m = NdtOmMap.load(out / "demo.ndtom")
    check = m.metadata["ground_truth_check"]
    assert check["left_in_vanished"] == 0 and check["on_surface"] > 0.98
    assert m.resolution == 0.2 and m.scans_inserted == 20 and len(m) == check["gaussians"]
    del m
    (tmp_path / "file").write_text("x")
    assert_user_error(run("demo", "--out", tmp_path / "file"), "is a file, not a folder")
    # the same for the sweep's --out (a raw "[Errno 17] File exists" before; experiments share the check)
    assert_user_error(run("sweep", "--synthetic", "--out", tmp_path / "file"), "is a file, not a folder")


@pytest.mark.parametrize("fail_at", [1, 4])
def test_demo_refused_by_the_memory_budget_hints_in_its_own_options(tmp_path: Path, monkeypatch, fail_at) -> None:
    """The demo has no --memory-limit or --max-range: its hint names neither, and with no
    scan mapped there is no ground-truth table of "nan%" (what -r 0.001 printed)."""
    refuse_scan(monkeypatch, fail_at)
    r = run("demo", "--out", tmp_path / "d", "--scans", "6", "--no-progress")
    assert_user_error(r, f"scan {fail_at} was refused", "coarser resolution (-r 0.4)", code=1)
    assert "--memory-limit" not in r.output and "--max-range" not in r.output and "--max-scans" not in r.output
    assert "nan" not in r.output
    assert ("Against the ground truth" in r.output) == (fail_at > 1)


# ---------------------------------------------------------------------------- real processes
def _ndtom() -> list[str]:
    exe = shutil.which("ndtom")
    return [exe] if exe else [sys.executable, "-m", "ndtom_ti"]


def test_python_m_ndtom_ti_help() -> None:
    p = subprocess.run(
        [sys.executable, "-m", "ndtom_ti", "--help"], capture_output=True, text=True, cwd=ROOT, timeout=120
    )
    assert p.returncode == 0, p.stderr
    assert "Usage:" in p.stdout and "map" in p.stdout and "export" in p.stdout


def test_real_ndtom_map_exit_codes(bags, tmp_path: Path) -> None:
    env = {**os.environ, "NDTOM_ARCH": "cpu"}
    out = tmp_path / "real.ndtom"
    p = subprocess.run(
        [*_ndtom(), "map", str(bags["ros1"]), "-r", str(pb.RES), "-o", str(out), "--arch", "cpu"],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    assert "Map written to" in p.stdout and read_header(out)["scans_inserted"] == 5
    assert "Traceback" not in p.stderr
    p = subprocess.run(
        [*_ndtom(), "map", str(bags["notf"]), "-r", "0.25", "-o", str(tmp_path / "bad.ndtom")],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert p.returncode == 2 and "Error: no usable poses" in p.stderr and "Traceback" not in p.stderr


def test_tables_written_to_a_file_are_not_folded_at_80_columns(tmp_path: Path) -> None:
    """Output to a file or CI log (no terminal, no COLUMNS): table cells keep their words
    whole on one line, not folded at Rich's default 80 columns."""
    m = NdtOmMap(0.5)
    m.insert_scan(np.random.default_rng(0).normal(size=(500, 3)) + [3.0, 0.0, 0.0], np.eye(4))
    path = m.save(tmp_path / "m.ndtom")
    del m
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    with open(tmp_path / "log.txt", "w") as log:
        subprocess.run(
            [sys.executable, "-m", "ndtom_ti", "info", str(path)], stdout=log, env=env, check=True, timeout=120
        )
    text = (tmp_path / "log.txt").read_text()
    assert "(every cell with points: the Gaussians, and those of fewer points or in free cells)" in text, text
    assert max(len(line) for line in text.splitlines()) <= 160


@pytest.mark.skipif(shutil.which("script") is None, reason="needs util-linux's script (a terminal for the bar)")
def test_the_bar_says_when_kernels_compile(tmp_path: Path) -> None:
    # A fresh process compiles (or loads from Taichi's cache) each kernel at its first call; the
    # first scan waits for that, and the terminal must say so, not sit at 0 scans in silence.
    out = tmp_path / "demo"
    cmd = " ".join(shlex.quote(str(a)) for a in [*_ndtom(), "demo", "--scans", "2", "--out", out, "--arch", "cpu"])
    p = subprocess.run(
        ["script", "-qec", cmd, "/dev/null"],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "COLUMNS": "150"},
    )
    assert p.returncode == 0, p.stdout[-3000:]
    assert "compiling kernels, once per process" in p.stdout, p.stdout[-3000:]
    assert "Warning" not in p.stdout, p.stdout[-3000:]


def test_no_return_points_are_counted_not_mapped(bags, tmp_path: Path) -> None:
    """(0, 0, 0) points (a driver's beams with no return) are left out and counted: as hits
    they put an occupied Gaussian where the sensor was at every scan."""
    out = tmp_path / "zeros.ndtom"
    r = run("map", bags["zeros"], "-r", pb.RES, "-o", out, "--no-progress")
    assert r.exit_code == 0, r.output
    assert "1,500 at (0, 0, 0) (no return)" in r.output, r.output
    m = NdtOmMap.load(out)
    assert m.metadata["summary"]["dropped"]["no_return"] == 300 * pb.N_CLOUDS
    g = m.gaussians(min_points=1)
    for k in range(pb.N_CLOUDS):
        assert np.linalg.norm(g["mean"] - pb.T_map_lidar(k)[:3, 3], axis=1).min() > 1.0
    pb.check_plane_map(m)


def test_two_cloud_topics_into_one_map(tmp_path: Path) -> None:
    bag, _ = pb.write_two_lidar_bag(tmp_path)
    r = run("map", bag, "-r", pb.RES, "-o", tmp_path / "two.ndtom", "--no-progress")
    assert_user_error(r, "2 PointCloud2 topics: /points, /points2")
    r = run(
        "map", bag, "-r", pb.RES, "--cloud-topic", "/points,/points2", "-o", tmp_path / "two.ndtom", "--no-progress"
    )
    assert r.exit_code == 0, r.output
    assert "8 of 8 clouds read" in r.output and "/points,/points2" in r.output
