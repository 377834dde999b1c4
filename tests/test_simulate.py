"""The panning simulator: its paths and blank-area arithmetic by hand, and a short bounded run
against a server it spawns, checked against what that server logged."""

import re
import subprocess
import sys

import numpy as np
import orjson
import pytest

from app.simulate.coverage import blank_share
from app.simulate.motion import FPS, screen_rect, user_path

BOUNDS = (0.0, 0.0, 612.0, 100_000.0)  # a long document: one page column
ANCHORS = np.column_stack([np.full(50, 306.0), np.linspace(100, 99_900, 50)])


@pytest.mark.parametrize(
    ("screen", "held", "blank"),
    [
        ((0, 0, 100, 100), (-10, -10, 110, 110), 0.0),  # inside the margin
        ((0, 0, 100, 100), (0, 0, 100, 100), 0.0),  # exactly what was fetched
        ((0, 0, 100, 100), (50, 0, 300, 100), 0.5),  # scrolled right, half not there yet
        ((0, 0, 100, 100), (50, 50, 300, 300), 0.75),  # a corner
        ((0, 0, 100, 100), (0, 80, 100, 300), 0.8),  # a fling down outran the data
        ((0, 0, 100, 100), (100, 0, 200, 100), 1.0),  # touching is not covering
        ((0, 0, 100, 100), (500, 500, 600, 600), 1.0),  # a jump
        ((0, 0, 100, 100), None, 1.0),  # nothing received yet
    ],
)
def test_blank_share_by_hand(screen, held, blank):
    assert blank_share(screen, held) == pytest.approx(blank)


def test_paths_are_seeded_and_move_like_people():
    path = user_path(7, BOUNDS, ANCHORS, seconds=60)
    assert path.shape == (60 * FPS, 3)
    np.testing.assert_array_equal(path, user_path(7, BOUNDS, ANCHORS, seconds=60))
    assert not np.array_equal(path, user_path(8, BOUNDS, ANCHORS, seconds=60))
    centres = np.array([screen_rect(c, (1280, 800)) for c in path])
    cx, cy = (centres[:, 0] + centres[:, 2]) / 2, (centres[:, 1] + centres[:, 3]) / 2
    assert (
        (cx >= BOUNDS[0] - 1e-6).all() and (cx <= BOUNDS[2] + 1e-6).all() and (cy <= BOUNDS[3] + 1e-6).all()
    )
    base = 1280 / 612 * 0.95  # the document's width fits the screen
    assert path[0, 2] == pytest.approx(base, rel=0.1)  # within one frame of a zoom, if it starts with one
    assert (path[:, 2] >= base / 8 - 1e-9).all() and (path[:, 2] <= base * 4 + 1e-9).all()
    step = np.hypot(np.diff(cx), np.diff(cy)) * path[1:, 2]  # screen pixels per frame
    assert (step == 0).mean() > 0.05  # pauses (and zooms around the centre)
    assert (step > 5000).any()  # a jump to a search result
    assert ((step > 60) & (step < 5000)).any()  # a fling: over 3,600 px/s
    assert len(np.unique(np.round(path[:, 2], 9))) > 10  # zooms


@pytest.mark.slow(seconds=13)
def test_a_short_run_against_a_spawned_server_matches_its_log(tmp_path):
    out = tmp_path / "sim"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "app.simulate",
            "--spawn",
            "--pages",
            "60",
            "--seconds",
            "1.5",
            "--users",
            "2",
            "--overscan",
            "0,0.5",
            "--lod",
            "on",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert "| mode | req/s |" in run.stdout and "stream overscan=0.5 lod=on" in run.stdout
    result = orjson.loads((out / "result.json").read_bytes())
    modes = result["modes"]
    assert len(modes) == 6 and {m["transport"] for m in modes} == {"poll", "diff", "stream"}
    for m in modes:
        assert m["errors"] == 0 and m["requests"] > 0, m
        assert m["frames"] == 2 * round(1.5 * FPS) and 0 <= m["blank_mean"] <= 1
        assert m["latency_ms"]["p50"] <= m["latency_ms"]["p99"] <= m["latency_ms"]["max"]
    routes = {"viewport": 0, "diff": 0, "stream": 0}
    for m in modes:
        for route, count in m["by_route"].items():
            routes[route] += count
    log = (out / "server.log").read_text()
    doc = result["document"]
    assert (
        len(re.findall(rf'"GET /documents/{doc}/viewport\?', log)) == routes["viewport"] + 1
    )  # + the anchors
    assert len(re.findall(rf'"GET /documents/{doc}/diff\?', log)) == routes["diff"]
    answers = re.findall(r"stream of \w+ closed: \d+ messages received, (\d+) answers sent", log)
    assert len(answers) == 2 * 2 and sum(map(int, answers)) == routes["stream"]  # two users, two stream modes
    assert (out / "plot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_target_that_is_not_loopback_is_refused(tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "app.simulate", "--url", "http://10.255.255.1:8000", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode != 0 and "not a loopback address" in run.stderr


def test_the_figures_of_a_mode_are_computed_from_what_its_users_saw():
    from app.simulate.report import summarise
    from app.simulate.users import Mode, UserLog

    fast, slow = UserLog(), UserLog()
    for k in range(1, 101):  # latencies 1..100 ms, alternating between the two users
        log = fast if k % 2 else slow
        log.requests.append((k * 0.01, k / 1000, 1000 + k, k % 3, k % 5, "diff" if k <= 70 else "viewport"))
    fast.frames += [(0.0, 0.0)] * 90 + [(0.0, 0.5)] * 10  # 10% of frames half blank
    slow.errors.append("timeout")
    figures = summarise(Mode("diff", 0.5, True), [fast, slow], seconds=2.0)
    assert figures["requests"] == 100 and figures["requests_per_s"] == 50 and figures["users"] == 2
    assert figures["by_route"] == {"diff": 70, "viewport": 30}
    assert figures["latency_ms"] == pytest.approx({"p50": 50.5, "p95": 95.05, "p99": 99.01, "max": 100.0})
    assert figures["bytes_per_request"] == pytest.approx(1050.5) and figures["bytes_per_s"] == pytest.approx(
        52_525
    )
    assert figures["entered_mean"] == pytest.approx(np.mean([k % 3 for k in range(1, 101)]))
    assert figures["errors"] == 1 and figures["frames"] == 100
    assert figures["blank_mean"] == pytest.approx(0.05) and figures["frames_with_blank"] == pytest.approx(0.1)
    assert figures["blank_p95"] == pytest.approx(0.5)


def test_without_its_extra_the_simulator_says_what_to_install():
    hide = (
        "import sys; sys.modules['matplotlib'] = None; from app.cli import main; main(['simulate', '--help'])"
    )
    run = subprocess.run([sys.executable, "-c", hide], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "pip install 'vantage-canvas[simulate]'" in run.stderr
    assert "matplotlib" in run.stderr and "httpx" not in run.stderr.split("needs")[1].split(":")[0]
