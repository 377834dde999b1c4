"""Zoomed out, aggregates stand in for what is too small to draw: every answer at a level of
detail is checked against brute force (items of the band's size, aggregates containing the
rest); diffs across pans and zooms equal the difference of the two answers; edits keep it so,
over HTTP and the stream; and an answer stays within its entry budget."""

import itertools

import numpy as np
import oracle
import orjson
import pytest
from service import receive
from test_panning import Held, _boxes, _edit, _param
from test_panning import _edits_around as _edits_around_positions

from spatial import scenes

SCREEN_PX = (1280, 800)


def _view(boxes: np.ndarray, centre: int, scale: float) -> list[float]:
    """A SCREEN_PX screen at ``scale`` centred on item ``centre``."""
    cx, cy = (boxes[centre, :2] + boxes[centre, 2:]) / 2
    hw, hh = SCREEN_PX[0] / scale / 2, SCREEN_PX[1] / scale / 2
    return [float(cx - hw), float(cy - hh), float(cx + hw), float(cy + hh)]


def _zooms(boxes: np.ndarray, steps: int, seed: int) -> list[tuple[list[float], float]]:
    """A path of (viewport, scale): pans and zooms from page level down past the whole document."""
    rng = np.random.default_rng(seed)
    scale, centre, out = 1.0, int(rng.integers(len(boxes))), []
    for _ in range(steps):
        move = rng.random()
        if move < 0.4:
            scale = float(np.clip(scale * 2 ** rng.uniform(-2, 1.5), 1e-4, 2))
        elif move < 0.6:
            centre = int(rng.integers(len(boxes)))
        view = _view(boxes, centre, scale)
        if move >= 0.6:  # a pan of a third of a screen
            dx, dy = (view[2] - view[0]) / 3 * rng.choice((-1, 1)), (view[3] - view[1]) / 3
            view = [view[0] + dx, view[1] + dy, view[2] + dx, view[3] + dy]
        out.append((view, scale))
    return out


def _edits_around(rect, current: dict) -> list[tuple[str, tuple | None]]:
    """test_panning's edits around ``rect`` for the items ``current`` holds now, by their ids
    (it names them ``i<position>``, which after a deletion is another item, or none)."""
    ids = list(current)
    edits = []
    for name, box in _edits_around_positions(rect, np.array(list(current.values()))):
        if name.startswith("i") and name[1:].isdigit():
            name = ids[int(name[1:])]
        edits.append((name, box))
    return edits


def _viewport(c, doc, rect, scale) -> dict:
    params = {**dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)), "scale": scale, "min_px": 1}
    return c.get(f"/documents/{doc}/viewport", params=params).json()


def test_every_zoom_shows_each_item_or_an_aggregate_holding_it(document):
    c, doc, boxes = document
    ids = [f"i{i}" for i in range(len(boxes))]
    for rect, scale in _zooms(boxes, 30, seed=1):
        body = _viewport(c, doc, rect, scale)
        assert body["band"] is not None and 2.0 ** body["band"] >= 1 / scale
        oracle.check_shown(boxes, ids, rect, 2.0 ** body["band"], body["items"])
        assert body["truncated"] is False


def test_diffs_across_pans_and_zooms_are_the_difference_of_the_two_answers(document):
    c, doc, boxes = document
    path = _zooms(boxes, 40, seed=2)
    for (old, old_scale), (new, new_scale) in itertools.pairwise(path):
        before, after = _viewport(c, doc, old, old_scale), _viewport(c, doc, new, new_scale)
        params = {
            "from": _param(old),
            "to": _param(new),
            "from_scale": old_scale,
            "scale": new_scale,
            "min_px": 1,
            "from_band": before["band"],
        }
        diff = c.get(f"/documents/{doc}/diff", params=params).json()
        assert diff["band"] == after["band"] and diff["reset"] is False
        held = {e["id"]: e for e in before["items"]}
        for item_id in diff["leave"]:
            held.pop(item_id)  # only what the client holds leaves
        held.update((e["id"], e) for e in diff["enter"])
        assert held == {e["id"]: e for e in after["items"]}
        ids_before, ids_after = set(map(_id, before["items"])), set(map(_id, after["items"]))
        assert set(diff["leave"]) == ids_before - ids_after
        entered = set(map(_id, diff["enter"]))
        assert ids_after - ids_before <= entered
        # sent again, held already: aggregates whose masks were made in another pixel grid
        assert all(i.startswith("~") for i in entered - (ids_after - ids_before))


def _id(entry: dict) -> str:
    return entry["id"]


def test_a_diff_without_from_band_takes_the_band_the_old_view_gets(document):
    c, doc, boxes = document
    old, new = _view(boxes, 0, 0.01), _view(boxes, 0, 0.004)
    params = {"from": _param(old), "to": _param(new), "from_scale": 0.01, "scale": 0.004, "min_px": 1}
    implicit = c.get(f"/documents/{doc}/diff", params=params)
    band = _viewport(c, doc, old, 0.01)["band"]
    explicit = c.get(f"/documents/{doc}/diff", params={**params, "from_band": band})
    assert implicit.status_code == explicit.status_code == 200, (implicit.text, explicit.text)
    assert implicit.json() == explicit.json()
    assert implicit.json()["leave"]  # zooming out from the old band to a coarser one: some leave
    coarser = c.get(f"/documents/{doc}/diff", params={**params, "from_band": band + 1}).json()
    assert coarser != implicit.json()  # so from_band is read: the band taken is the old view's
    bad = c.get(f"/documents/{doc}/diff", params={"from": _param(old), "to": _param(new), "from_band": 3})
    assert bad.status_code == 422 and "from_band=3" in bad.json()["detail"]


def test_edits_reach_a_zoomed_out_stream_and_keep_its_aggregates_right(document):
    c, doc, boxes = document
    current, held, pushes = _boxes(boxes), Held(), 0
    everything = [
        float(boxes[:, 0].min()),
        float(boxes[:, 1].min()),
        float(boxes[:, 2].max()),
        float(boxes[:, 3].max()),
    ]
    with c.websocket_connect(f"/documents/{doc}/stream") as ws:
        for seq, scale in enumerate((0.02, 0.005)):
            ws.send_text(
                orjson.dumps({"seq": seq, "viewport": everything, "scale": scale, "min_px": 1}).decode()
            )
            answer = receive(ws)
            held.apply(answer)
            size = 2.0 ** answer["band"]
            held.check(current, everything, size)
            for item_id, box in _edits_around(everything, current):
                name = f"{item_id}-{seq}" if item_id in ("fresh", "far") else item_id
                assert name in current or box is not None, f"{name}: no such item to delete"
                version = _edit(c, doc, current, name, box)
                if item_id == "far":  # out of sight: nothing to push
                    continue
                pushed = receive(ws)
                assert (pushed["type"], pushed["version"]) == ("edit", version)
                held.apply(pushed)
                held.check(current, everything, size)
                pushes += 1
    assert pushes == 2 * 5  # every edit in sight was pushed, at each zoom
    assert any("agg" in e for e in held.items.values())


def test_diff_since_carries_edited_aggregates(document):
    c, doc, boxes = document
    current, held = _boxes(boxes), Held()
    path = _zooms(boxes, 12, seed=3)
    first = _viewport(c, doc, *path[0])
    held.apply({"reset": True, "leave": [], "enter": first["items"]})
    version, band = first["version"], first["band"]
    for step, ((old, old_scale), (new, new_scale)) in enumerate(itertools.pairwise(path)):
        if step % 2 == 0:
            for item_id, box in _edits_around(old, current):
                name = f"{item_id}-{step}" if item_id in ("fresh", "far") else item_id
                assert name in current or box is not None, f"{name}: no such item to delete"
                _edit(c, doc, current, name, box)
        params = {
            "from": _param(old),
            "to": _param(new),
            "from_scale": old_scale,
            "scale": new_scale,
            "min_px": 1,
            "from_band": band,
            "since": version,
        }
        answer = c.get(f"/documents/{doc}/diff", params=params).json()
        assert answer["reset"] is False
        held.apply(answer)
        held.check(current, new, 2.0 ** answer["band"])
        version, band = answer["version"], answer["band"]


@pytest.mark.parametrize("budget", [40, 400])
def test_an_answer_holds_no_more_entries_than_its_budget(data_dir, monkeypatch, budget):
    from service import client, ndjson

    monkeypatch.setenv("VANTAGE_LOD_BUDGET", str(budget))
    boxes, kinds = scenes.whiteboard(n=20_000, seed=4, clusters=20)
    with client() as c:
        doc = c.post("/documents", json={"name": "board"}).json()["id"]
        imported = c.post(
            f"/documents/{doc}/items",
            content=ndjson(boxes, kinds),
            headers={"content-type": "application/x-ndjson"},
        )
        assert imported.status_code == 200, imported.text
        ids = [f"i{i}" for i in range(len(boxes))]
        coarser = held_to_budget = 0
        for rect, scale in _zooms(boxes, 25, seed=5):
            body = _viewport(c, doc, rect, scale)
            most = budget * SCREEN_PX[0] * SCREEN_PX[1] / (1920 * 1080)
            top = (
                body["band"] == _viewport(c, doc, rect, 1e-12)["band"]
            )  # the top band answers whatever it holds
            assert len(body["items"]) <= max(1, most) or top
            held_to_budget += not top
            coarser += 2.0 ** body["band"] >= 2 / scale  # a coarser band than min_px asked for
            oracle.check_shown(boxes, ids, rect, 2.0 ** body["band"], body["items"])
        assert coarser > 0  # the budget did make some answers coarser
        assert held_to_budget > 0  # and some answers were held to it, below the top band


def test_ids_starting_with_a_tilde_are_refused(document):
    c, doc, _ = document
    answer = c.put(f"/documents/{doc}/items/~6.1", json={"x0": 0, "y0": 0, "x1": 1, "y1": 1})
    assert answer.status_code == 422 and "starts with '~'" in answer.json()["detail"]


def test_a_full_screen_answers_at_most_5000_entries_at_every_zoom_on_both_demos(demo):
    import httpx

    from app.demo import DEMOS

    url, docs = demo
    assert set(docs) == set(DEMOS), docs  # no documents: nothing checked
    for doc in docs.values():
        bounds = httpx.get(f"{url}/documents/{doc}").json()["bounds"]
        cx, cy = (bounds[0] + bounds[2]) / 2, (bounds[1] + bounds[3]) / 2
        fit = min(1920 / (bounds[2] - bounds[0]), 1080 / (bounds[3] - bounds[1]))
        scale = 1.0
        while scale >= fit / 2:
            for dx in (-0.3, 0.0, 0.3):  # across the document, as it is
                x = cx + dx * (bounds[2] - bounds[0])
                rect = [x - 960 / scale, cy - 540 / scale, x + 960 / scale, cy + 540 / scale]
                params = {
                    **dict(zip(("x0", "y0", "x1", "y1"), rect, strict=True)),
                    "scale": scale,
                    "min_px": 1,
                }
                body = httpx.get(f"{url}/documents/{doc}/viewport", params=params).json()
                assert len(body["items"]) <= 5000 and body["truncated"] is False, (doc, scale, body["band"])
            scale /= 2


def test_a_diff_starts_from_the_band_the_client_says_it_holds(document):
    """A client holding a coarser band than its old view would get (it zoomed, and its answer
    had not come yet) says so with ``from_band``: the diff takes it from there to the new view."""
    c, doc, boxes = document
    old, new = _view(boxes, 0, 0.01), _view(boxes, 5, 0.01)
    implied = _viewport(c, doc, old, 0.01)["band"]
    held = {e["id"] for e in _viewport(c, doc, old, 0.005)["items"]}  # what it holds: one band coarser
    assert _viewport(c, doc, old, 0.005)["band"] == implied + 1
    target = {e["id"] for e in _viewport(c, doc, new, 0.01)["items"]}
    params = {"from": _param(old), "to": _param(new), "from_scale": 0.01, "scale": 0.01, "min_px": 1}
    answer = c.get(
        f"/documents/{doc}/diff", params={**params, "from_band": implied + 1, "limit": 100_000}
    ).json()
    assert answer["reset"] is False  # a diff from what the client holds, not the whole view again
    after = held - set(answer["leave"]) | {e["id"] for e in answer["enter"]}
    assert after == target and held != target
