"""Live mapping as a user runs it: pacing at the recording's rate, waiting for the first
browser, the summary and the saved map at the end and on Ctrl-C or SIGTERM.

No test measures wall-clock time: pacing runs on an injected clock whose sleep only
advances it, and signals are sent by the scan source itself at a known scan.
"""

from __future__ import annotations

import os
import signal
import threading
from dataclasses import dataclass

import numpy as np
import pytest

from ndtom_ti import NdtOmMap
from ndtom_ti.demo import make_scans

pytest.importorskip("viser", reason="the viewer needs viser: pip install ndtom_ti[viewer]")

from ndtom_ti.viewer import MapViewer, cli

RES = 0.5


@dataclass
class StampedScan:
    points: np.ndarray
    T_world_sensor: np.ndarray
    stamp_ns: int


def _scans(stamps_s, n_points=300):
    base = make_scans(len(stamps_s), rings=4, per_ring=n_points // 4)
    return [
        StampedScan(s.points, s.T_world_sensor, int(1_700_000_000e9) + round(t * 1e9)) for s, t in zip(base, stamps_s)
    ]


class FakeClock:
    """Time that only moves when the code sleeps (or a test says so)."""

    def __init__(self):
        self.t = 100.0
        self.slept = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> bool:
        self.slept.append(seconds)
        self.t += seconds
        return False  # not stopping


@pytest.fixture
def viewer():
    v = MapViewer(verbose=False, environment_map=False)
    yield v
    v.close()


def test_scans_play_at_the_recordings_rate_times_speed(viewer):
    stamps = [0.0, 0.1, 0.3, 0.35, 10.35, 10.45]  # a 10 s gap in the recording
    for speed, expected in ((1.0, [0.1, 0.2, 0.05, 2.0, 0.1]), (2.0, [0.05, 0.1, 0.025, 1.0, 0.05])):
        clock = FakeClock()
        lm = viewer.live(
            _scans(stamps),
            NdtOmMap(RES),
            speed=speed,
            max_gap_s=2.0,
            clock=clock,
            sleep=clock.sleep,
            refresh_interval=0.05,
        )
        lm.play()
        assert lm.wait(timeout=60) and lm.error is None and lm.scans_done == len(stamps)
        # the long gap is shortened to max_gap_s; everything else is the recording's own pace
        assert np.allclose(clock.slept, expected, atol=1e-9), clock.slept
        assert np.allclose(lm.waits, expected, atol=1e-9)
        lm.stop()


def test_late_scans_go_at_once_without_a_catch_up_burst(viewer):
    clock = FakeClock()
    stamps = [0.0, 0.1, 0.2, 0.3, 1.3, 1.4]

    def slow_insert(rep, item):  # mapping takes 0.25 s of the clock per scan: slower than 10 scans/s
        clock.t += 0.25

    lm = viewer.live(_scans(stamps), NdtOmMap(RES), speed=1.0, clock=clock, sleep=clock.sleep, on_scan=slow_insert)
    lm.play()
    assert lm.wait(timeout=60) and lm.scans_done == len(stamps)
    # scans 1-3 are late (no wait); the 1 s gap after scan 3 is kept from when scan 3 went
    # (0.75 s still to wait), and scan 5 is late again
    assert np.allclose(clock.slept, [0.75], atol=1e-9), clock.slept
    lm.stop()


def test_max_speed_and_the_speed_slider(viewer):
    clock = FakeClock()
    lm = viewer.live(_scans([0.0, 1.0, 2.0]), NdtOmMap(RES), speed=float("inf"), clock=clock, sleep=clock.sleep)
    assert viewer.controls.rate.label == "Speed (x recording)"
    lm.play()
    assert lm.wait(timeout=60) and clock.slept == []  # max: no pacing
    lm.stop()
    clock = FakeClock()
    lm = viewer.live(_scans([0.0, 1.0, 2.0]), NdtOmMap(RES), speed=1.0, clock=clock, sleep=clock.sleep)
    viewer.controls.rate.value = 4.0  # the slider in the page
    assert lm.speed == 4.0
    lm.play()
    assert lm.wait(timeout=60) and np.allclose(clock.slept, [0.25, 0.25])
    lm.stop()
    with pytest.raises(ValueError, match="speed"):
        viewer.live(_scans([0.0]), NdtOmMap(RES), speed=0.0)


def test_parse_rate():
    assert cli.parse_rate("1") == 1.0 and cli.parse_rate("2") == 2.0 and cli.parse_rate("0.5x") == 0.5
    assert cli.parse_rate("max") is None and cli.parse_rate(" MAX ") is None
    for bad in ("0", "-1", "fast", "nan", ""):
        with pytest.raises(ValueError, match="--rate"):
            cli.parse_rate(bad)


# ---------------------------------------------------------------------------- the live command


@pytest.fixture
def no_serving(monkeypatch):
    """After mapping the command would serve until Ctrl-C: record that it would, and return."""
    served = []
    # private: the command's wait for Ctrl-C after mapping has no public hook
    monkeypatch.setattr(cli, "_serve_until_stopped", lambda viewer, stop: served.append(viewer.url))
    return served


def test_mapping_waits_for_the_first_browser(monkeypatch, tmp_path, no_serving, capsys):
    scans = _scans([0.0, 0.01, 0.02])
    seen = []

    def browser_connects(viewer, stop):
        lm = viewer.live_mapper
        seen.append((lm.scans_done, lm.playing))  # nothing mapped while nobody watches
        return True

    monkeypatch.setattr(cli, "_wait_for_browser", browser_connects)  # private: a browser connecting, no public hook
    out = tmp_path / "w.ndtom"
    assert cli.live_command(scans, RES, "127.0.0.1", 0, save=out, speed=None) == 0
    assert seen == [(0, False)]
    text = capsys.readouterr().out
    assert "Waiting for a browser at http://127.0.0.1:" in text and "--no-wait" in text
    assert NdtOmMap.load(out).scans_inserted == 3
    assert len(no_serving) == 1  # after a complete run the viewer keeps showing the map

    # --no-wait: mapping starts at once, nobody is waited for
    seen.clear()
    assert cli.live_command(scans, RES, "127.0.0.1", 0, save=out, speed=None, wait_for_browser=False) == 0
    assert seen == []


def test_wait_for_browser_returns_on_a_client_or_a_stop():
    # the command's private wait, alone: a real page connecting is test_viewer_browser's
    class Server:
        def __init__(self, answers):
            self.answers = list(answers)

        def get_clients(self):
            return self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]

    class V:
        pass

    v = V()
    v.server = Server([{}, {}, {7: object()}])
    assert cli._wait_for_browser(v, threading.Event()) is True
    v.server = Server([{}])
    stop = threading.Event()
    stop.set()
    assert cli._wait_for_browser(v, stop) is False


class SignalAt:
    """Scans that send ``sig`` to this process when scan ``at`` is read (the worker thread
    reads it; Python runs the handler in the main thread, where the command waits)."""

    def __init__(self, scans, at, sig):
        self.scans, self.at, self.sig = scans, at, sig
        self.read = 0

    def __iter__(self):
        for i, s in enumerate(self.scans):
            self.read = i + 1
            if i == self.at:
                os.kill(os.getpid(), self.sig)
            yield s


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_saves_what_was_mapped(sig, tmp_path, no_serving, capsys):
    # at half the recording's rate the scans are 0.2 s apart: the signal comes long before the end
    scans = SignalAt(_scans([0.1 * i for i in range(30)]), at=3, sig=sig)
    out = tmp_path / "s.ndtom"
    before = signal.getsignal(sig)
    saved = []

    def finish(m, summary):
        saved.append((summary.scans_used, summary.stopped, summary.complete))
        m.save(out)
        return 130 if summary.stopped == "interrupted" else 0

    code = cli.live_command(scans, RES, "127.0.0.1", 0, speed=0.5, wait_for_browser=False, finish=finish, total=30)
    assert code == 130
    n, stopped, complete = saved[0]
    assert stopped == "interrupted" and not complete and 3 <= n < 30
    m = NdtOmMap.load(out)
    assert m.scans_inserted == n and m.metadata["complete"] is False
    assert m.metadata["summary"]["scans_used"] == n
    assert no_serving == []  # an interrupted run closes the viewer
    assert signal.getsignal(sig) == before  # the handlers are put back
    assert "stopping after the scan in hand" in capsys.readouterr().err


def test_a_second_ctrl_c_during_the_save_waits_for_it(tmp_path, no_serving, capsys):
    scans = SignalAt(_scans([0.1 * i for i in range(30)]), at=2, sig=signal.SIGINT)
    out = tmp_path / "twice.ndtom"

    def finish(m, summary):
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C again while saving
        m.save(out)
        return 130

    assert cli.live_command(scans, RES, "127.0.0.1", 0, speed=0.5, wait_for_browser=False, finish=finish) == 130
    assert NdtOmMap.load(out).scans_inserted >= 2
    assert "saving the map, please wait" in capsys.readouterr().err


def test_demo_view_writes_its_map_and_the_summary(tmp_path, no_serving, monkeypatch):
    from typer.testing import CliRunner

    from ndtom_ti.cli import app

    monkeypatch.setattr("ndtom_ti.demo.make_scans", lambda n, **kw: make_scans(n, rings=8, per_ring=120))
    res = CliRunner().invoke(
        app,
        [
            "demo",
            "--view",
            "--no-wait",
            "--rate",
            "max",
            "--port",
            "0",
            "--scans",
            "4",
            "-r",
            "0.5",
            "--out",
            str(tmp_path / "d"),
        ],
    )
    assert res.exit_code == 0, res.output
    out = tmp_path / "d" / "demo.ndtom"
    assert "Mapping summary" in res.output and "4 of 4" in res.output and str(out) in res.output
    m = NdtOmMap.load(out)
    assert m.scans_inserted == 4 and m.metadata["command"] == "ndtom demo --view" and m.metadata["complete"]
    assert len(no_serving) == 1


def test_a_bad_scan_mid_run_stops_live_mapping_as_it_stops_ndtom_map(tmp_path, no_serving):
    """The one loop's behaviour (ndtom_ti.pipeline): a scan that cannot be inserted after
    others were stops mapping; the map keeps the scans before it, the summary says why,
    and the command fails (1), as `ndtom map` does."""
    scans = _scans([0.0, 0.01, 0.02, 0.03])
    bad = scans[2]
    scans[2] = StampedScan(bad.points, np.full((4, 4), np.nan), bad.stamp_ns)  # a pose with NaN
    out = tmp_path / "bad.ndtom"
    code = cli.live_command(scans, RES, "127.0.0.1", 0, save=out, speed=None, wait_for_browser=False, compare=False)
    assert code == 1
    m = NdtOmMap.load(out)
    summary = m.metadata["summary"]
    assert m.scans_inserted == 2 and m.metadata["complete"] is False and summary["stopped"] == "error"
    assert "scan 3 could not be inserted" in summary["error"] and "holds the 2 scans" in summary["error"]
    assert no_serving == []  # an incomplete run closes the viewer
