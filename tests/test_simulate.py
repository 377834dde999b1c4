"""The panning simulator: its paths and blank-area arithmetic by hand, and short bounded runs
against a real server, checked against what that server logged: the panning users, and the
users who zoom out to see the whole board and dive back in, with tiles."""

import re
import subprocess
import sys
from collections import Counter
from urllib.parse import parse_qs, urlsplit

import numpy as np
import orjson
import pytest

from app.client import Client
from app.demo import ndjson_lines
from app.launch import launch, stop
from app.simulate.coverage import blank_share
from app.simulate.motion import FPS, fit_scale, screen_rect, user_path
from app.simulate.policy import POLICY
from spatial import scenes

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
    from app.simulate.users import Mode, Sent, UserLog

    fast, slow = UserLog(), UserLog()
    for k in range(1, 101):  # latencies 1..100 ms, alternating between the two users
        log = fast if k % 2 else slow
        route = "diff" if k <= 70 else "viewport"
        log.requests.append(Sent(k * 0.01, k / 1000, 1000 + k, 500 + k, k % 3, k % 5, route, 3, k / 500))
    slow.requests += [Sent(0.5, 0.2, 3000, 1000, 0, 0, "tile", 3)] * 4  # tiles: not answers
    fast.frames += [(0.0, 0.0)] * 90 + [(0.0, 0.5)] * 10  # 10% of frames half blank
    slow.errors.append("timeout")
    figures = summarise(Mode("diff", 0.5, True), [fast, slow], seconds=2.0)
    assert figures["requests"] == 100 and figures["requests_per_s"] == 50 and figures["users"] == 2
    assert figures["by_route"] == {"diff": 70, "tile": 4, "viewport": 30}
    assert figures["by_kind"]["tile"]["wire_bytes"] == 4000 and figures["by_kind"]["diff"]["requests"] == 70
    assert figures["wire_bytes"] == sum(500 + k for k in range(1, 101)) + 4000
    assert figures["wire_bytes_per_answer"] == pytest.approx(figures["wire_bytes"] / 100)
    assert figures["drawn_ms"]["p50"] == pytest.approx(101.0) and figures["bands"] == {"3": 100}
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


def test_users_who_zoom_out_go_to_fit_look_and_dive_into_another_place():
    board = (0.0, 0.0, 1_000_000.0, 1_000_000.0)
    places = np.array([[900_000.0, 100_000.0]])  # the one place to dive into
    anchors = np.array([[100_000.0, 900_000.0]])
    path = user_path(3, board, anchors, seconds=12, zoom_out_every=4, places=places)
    np.testing.assert_array_equal(
        path, user_path(3, board, anchors, seconds=12, zoom_out_every=4, places=places)
    )
    fit = fit_scale(board, (1280, 800))
    assert fit == pytest.approx(800 / 1e6 * 0.95)
    at_fit = np.isclose(path[:, 2], fit)
    assert 1.0 * FPS <= at_fit.sum() <= 2 * 3.0 * FPS + 2  # one or two looks of 1-3 s
    first = np.flatnonzero(at_fit)[0]
    assert first < (4 + 1.2) * FPS  # the first look comes within --zoom-out-every, 1.2 s of zooming out
    rect = screen_rect(path[first], (1280, 800))
    assert rect[0] <= board[0] and rect[2] >= board[2]  # the whole board on screen
    after = np.flatnonzero(~at_fit[first:])[0] + first  # diving in: the dive ends near the place
    dive_end = after + np.argmax(path[after:, 2] >= path[0, 2] / 2.01)
    centre = screen_rect(path[dive_end], (1280, 800))
    assert np.hypot((centre[0] + centre[2]) / 2 - 900_000, (centre[1] + centre[3]) / 2 - 100_000) < 2000
    still = user_path(3, board, anchors, seconds=12)  # without looks: as before, never near Fit
    assert still[:, 2].min() >= still[0, 2] / 8 - 1e-12 and not np.isclose(still[:, 2], fit).any()


TILE_GET = re.compile(r'"GET (/documents/\w+/tiles/(-?\d+)/(-?\d+)/(-?\d+)/(-?\d+)\?version=\d+) HTTP')
ANSWER_GET = re.compile(r'"GET (/documents/\w+/(?:viewport|diff)\?\S+) HTTP')


@pytest.mark.slow(seconds=15)
def test_users_zoomed_out_to_fit_ask_its_tiles_and_never_fetch_one_twice(tmp_path):
    boxes, kinds = scenes.clustered_board(n=3000, seed=3)
    with open(tmp_path / "server.log", "w") as log:
        server, url = launch(tmp_path / "data", "--log-level", "info", output=log)
        try:
            with Client(url) as vantage:
                doc = vantage.create_document("board")["id"]
                vantage.import_items(doc, b"".join(ndjson_lines(boxes, kinds)))
                bounds = vantage.describe(doc)["bounds"]
            run = subprocess.run(
                [sys.executable, "-m", "app.simulate", "--url", url, "--doc", doc, "--modes", "diff",
                 "--overscan", "0.5", "--lod", "on", "--tiles", "on", "--zoom-out-share", "1",
                 "--zoom-out-every", "1", "--users", "1", "--seconds", "4", "--out", str(tmp_path / "sim")],
                capture_output=True, text=True, timeout=120,
            )  # fmt: skip
            assert run.returncode == 0, run.stderr[-3000:]
            lines = (tmp_path / "server.log").read_text().splitlines()
            # the users' answers: after the simulator's own two (items to jump to, places to dive into)
            answers = [m[1] for line in lines if (m := ANSWER_GET.search(line))][2:]
            widest = min(answers, key=lambda a: float(parse_qs(urlsplit(a).query)["scale"][0]))
            with Client(url) as vantage:  # the view the user had when most zoomed out, asked again
                coarse = vantage.http.get(f"/documents/{doc}/viewport", params=_as_viewport(widest)).json()
        finally:
            stop(server)
    (m,) = orjson.loads((tmp_path / "sim" / "result.json").read_bytes())["modes"]
    assert m["errors"] == 0 and m["tiles"] and m["users_zooming_out"] == 1
    assert "| tile |" in run.stdout  # the table of requests by kind
    # It zoomed out to Fit (within the page's re-asking step of it), and the band there is
    # the coarsest it saw; it had been zoomed in, at finer ones.
    fit = fit_scale(bounds, (1280, 800))
    scale = float(parse_qs(urlsplit(widest).query)["scale"][0])
    assert fit * (1 - 1e-9) <= scale < fit * POLICY["lodStep"]
    sheet = coarse["tiles"]
    assert sheet is not None and coarse["aggregates"] > 0
    bands = [int(b) for b in m["bands"] if b != "none"]
    assert sheet["band"] == max(bands) and min(bands) < sheet["band"]
    # It asked for tiles zoomed out, and without once its tiles held no aggregate (zoomed in);
    # it fetched tiles of the Fit answer's band and level, within the range that answer
    # named; and never one tile twice, though it needed many again.
    assert len(answers) == m["requests"] and "tiles=true" in widest
    assert any("tiles=true" not in answer for answer in answers)
    fetched = [match.groups() for line in lines if (match := TILE_GET.search(line))]
    assert len(fetched) == m["by_route"]["tile"] > 0
    tx0, ty0, tx1, ty1 = sheet["range"]
    assert any(
        (int(b), int(z)) == (sheet["band"], sheet["z"]) and tx0 <= int(tx) <= tx1 and ty0 <= int(ty) <= ty1
        for _, b, z, tx, ty in fetched
    )
    twice = [tile for tile, n in Counter(t[0] for t in fetched).items() if n > 1]
    assert not twice, twice[:5]
    assert m["tiles_held"] > 0  # tiles needed again, found held


def _as_viewport(answer: str) -> dict:
    """The query of the tiled ``/viewport`` for the view a logged ``/viewport`` or ``/diff`` showed."""
    query = {k: v[0] for k, v in parse_qs(urlsplit(answer).query).items()}
    rect = query["to"].split(",") if "to" in query else [query[k] for k in ("x0", "y0", "x1", "y1")]
    return {
        **dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)),
        "scale": query["scale"],
        "min_px": 1,
        "tiles": "true",
    }
