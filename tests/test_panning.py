"""Panning clients: the HTTP diff with ``since`` and the WebSocket stream, each replayed into the
set a client would hold and compared with brute force over the items as they are now."""

import itertools

import numpy as np
import oracle
import orjson
import pytest
from service import NDJSON, expected, receive
from starlette.websockets import WebSocketDisconnect

from spatial import scenes

SCREEN = (0.0, 0.0, 700.0, 900.0)


class Held:
    """What a client holds: apply ``leave`` then ``enter`` (an upsert), after a ``reset`` clear."""

    def __init__(self) -> None:
        self.items: dict[str, dict] = {}

    def apply(self, answer: dict) -> None:
        if answer["reset"]:
            self.items.clear()
        for item_id in answer["leave"]:
            self.items.pop(item_id, None)
        self.items.update((item["id"], item) for item in answer["enter"])

    def check(self, boxes: dict[str, tuple], rect, size: float = 0.0) -> None:
        """Holds exactly what brute force shows in ``rect`` (items of at least ``size``, and
        aggregates containing the smaller ones), with every box as it is now."""
        ids = list(boxes)
        array = np.array([boxes[i] for i in ids]).reshape(-1, 4)
        oracle.check_shown(array, ids, rect, size, list(self.items.values()))
        real = [i for i, item in self.items.items() if "agg" not in item]
        assert all(tuple(self.items[i][k] for k in ("x0", "y0", "x1", "y1")) == boxes[i] for i in real)


def _param(rect) -> str:
    return ",".join(map(repr, [float(v) for v in rect]))


def _boxes(boxes: np.ndarray) -> dict[str, tuple]:
    return {f"i{i}": tuple(box) for i, box in enumerate(boxes.tolist())}


def _edit(c, doc, current, item_id, box=None) -> int:
    """Move (or create) ``item_id`` to ``box``, or delete it; keeps ``current`` in step."""
    if box is None:
        answer = c.delete(f"/documents/{doc}/items/{item_id}")
        current.pop(item_id)
    else:
        answer = c.put(
            f"/documents/{doc}/items/{item_id}", json=dict(zip(("x0", "y0", "x1", "y1"), box, strict=True))
        )
        current[item_id] = tuple(map(float, box))
    assert answer.status_code in (200, 201), answer.text
    return answer.json()["version"]


def _edits_around(rect, boxes: np.ndarray) -> list[tuple[str, tuple | None]]:
    """Edits a viewer of ``rect`` must see: in, out, within, deleted, created; and one far away."""
    inside = sorted(expected(boxes, rect), key=lambda i: int(i[1:]))
    x0, y0, x1, y1 = rect
    return [
        (inside[0], (x0 - 500.0, y0 - 500.0, x0 - 490.0, y0 - 490.0)),  # moves out
        (inside[1], (x0 + 5.0, y0 + 5.0, x0 + 25.0, y0 + 9.0)),  # moves within
        (inside[2], None),  # deleted
        ("fresh", (x1 - 1.0, y1 - 1.0, x1 + 3.0, y1 + 3.0)),  # created, straddling the edge
        (f"i{len(boxes) - 1}", (x0 + 1.0, y0 + 1.0, x0 + 2.0, y0 + 2.0)),  # moves in
        ("far", (1e7, 1e7, 1e7 + 1, 1e7 + 1)),  # created out of sight
    ]


def test_diff_since_a_version_carries_the_edited_items(document):
    c, doc, boxes = document
    current, held = _boxes(boxes), Held()
    path = scenes.panning_path(boxes, 12, seed=4, screen=SCREEN[2:])
    view = c.get(
        f"/documents/{doc}/viewport",
        params=dict(zip(("x0", "y0", "x1", "y1"), path[0].tolist(), strict=True)),
    ).json()
    held.apply({"reset": True, "leave": [], "enter": view["items"]})
    version = view["version"]
    for step, (old, new) in enumerate(itertools.pairwise(path)):
        if step % 3 == 0:  # someone else edits around the client's view between its polls
            for item_id, box in _edits_around(old.tolist(), np.array(list(current.values()))):
                if item_id in current or box is not None:
                    _edit(c, doc, current, item_id, box)
        params = {"from": _param(old), "to": _param(new), "since": version}
        answer = c.get(f"/documents/{doc}/diff", params=params).json()
        assert answer["reset"] is False
        held.apply(answer)
        held.check(current, new.tolist())
        version = answer["version"]
    assert version > 1


def test_diff_since_before_an_import_or_from_the_future(document):
    c, doc, boxes = document
    rect = _param(SCREEN)
    c.post(
        f"/documents/{doc}/items",
        content=b'{"id": "i0", "x0": 1, "y0": 1, "x1": 2, "y1": 2}\n',
        headers=NDJSON,
    )
    answer = c.get(f"/documents/{doc}/diff", params={"from": rect, "to": rect, "since": 1}).json()
    assert answer["reset"] is True and answer["version"] == 2
    held = Held()
    held.apply(answer)
    current = _boxes(boxes) | {"i0": (1.0, 1.0, 2.0, 2.0)}
    held.check(current, SCREEN)
    future = c.get(f"/documents/{doc}/diff", params={"from": rect, "to": rect, "since": 3})
    assert future.status_code == 409 and "newer than the document's version 2" in future.json()["detail"]


def _answer(ws) -> dict:
    message = receive(ws)
    assert message["type"] in ("view", "edit"), message
    return message


def test_the_stream_answers_each_viewport_with_enter_and_leave(document):
    c, doc, boxes = document
    path = scenes.panning_path(boxes, 40, seed=5, screen=SCREEN[2:])
    held, current = Held(), _boxes(boxes)
    with c.websocket_connect(f"/documents/{doc}/stream") as ws:
        for seq, rect in enumerate(path.tolist()):
            ws.send_text(orjson.dumps({"seq": seq, "viewport": rect}).decode())
            answer = _answer(ws)
            assert (answer["type"], answer["seq"], answer["reset"]) == ("view", seq, seq == 0)
            held.apply(answer)
            held.check(current, rect)


def test_a_newer_viewport_supersedes_queued_ones(document):
    c, doc, boxes = document
    path = scenes.panning_path(boxes, 60, seed=6, screen=SCREEN[2:]).tolist()
    held = Held()
    with c.websocket_connect(f"/documents/{doc}/stream") as ws:
        for seq, rect in enumerate(path):  # a fling: sent without waiting for answers
            ws.send_text(orjson.dumps({"seq": seq, "viewport": rect}).decode())
        seqs = []
        while not seqs or seqs[-1] != len(path) - 1:
            answer = _answer(ws)
            held.apply(answer)
            seqs.append(answer["seq"])
    assert seqs == sorted(seqs) and len(seqs) == len(set(seqs)) <= len(path)
    held.check(_boxes(boxes), path[-1])


def test_the_stream_pushes_edits_to_what_the_client_shows(document):
    c, doc, boxes = document
    held, current = Held(), _boxes(boxes)
    with c.websocket_connect(f"/documents/{doc}/stream") as ws:
        ws.send_text(orjson.dumps({"seq": 1, "viewport": SCREEN}).decode())
        held.apply(_answer(ws))
        for item_id, box in _edits_around(SCREEN, boxes):
            version = _edit(c, doc, current, item_id, box)
            if item_id == "far":  # out of sight: nothing to push; the next view shows it is skipped
                continue
            answer = _answer(ws)
            assert (answer["type"], answer["seq"], answer["version"]) == ("edit", 1, version)
            assert len(answer["leave"]) + len(answer["enter"]) == 1  # just the edited item
            held.apply(answer)
            held.check(current, SCREEN)
        ws.send_text(orjson.dumps({"seq": 2, "viewport": SCREEN}).decode())
        answer = _answer(ws)
        assert answer["type"] == "view" and answer["enter"] == answer["leave"] == []


def test_the_stream_applies_level_of_detail_and_limits(document):
    c, doc, boxes = document
    everything = [
        float(boxes[:, 0].min()),
        float(boxes[:, 1].min()),
        float(boxes[:, 2].max()),
        float(boxes[:, 3].max()),
    ]
    held, current = Held(), _boxes(boxes)
    with c.websocket_connect(f"/documents/{doc}/stream") as ws:
        ws.send_text(orjson.dumps({"viewport": everything, "scale": 0.05, "min_px": 2}).decode())
        answer = _answer(ws)
        held.apply(answer)
        assert 2.0 ** answer["band"] >= 2 / 0.05
        held.check(current, everything, size=2.0 ** answer["band"])
        ws.send_text(orjson.dumps({"viewport": SCREEN, "limit": 5}).decode())
        cut = _answer(ws)
        assert cut["truncated"] is True and len(cut["enter"]) == 5 and cut["entered"] > 5
        ws.send_text(orjson.dumps({"viewport": SCREEN}).decode())
        again = _answer(ws)
        assert again["reset"] is True  # after a cut answer the client's set is incomplete
        held.apply(again)
        held.check(current, SCREEN)


@pytest.mark.parametrize(
    ("message", "why"),
    [
        (b"not json", "Invalid JSON"),
        (b'{"viewport": [0, 0, 1]}', "viewport"),
        (b'{"viewport": [5, 0, 1, 1]}', "x0=5.0 > x1=1.0"),
        (b'{"viewport": [0, 0, 1, 1], "scale": -1}', "scale"),
        (b'{"viewport": [0, 0, 1, 1], "zoom": 2}', "zoom"),
    ],
)
def test_a_bad_message_gets_an_error_and_the_stream_goes_on(document, message, why):
    c, doc, boxes = document
    with c.websocket_connect(f"/documents/{doc}/stream") as ws:
        ws.send_bytes(message)
        error = receive(ws)
        assert error["type"] == "error" and why in error["message"], error
        ws.send_text(orjson.dumps({"viewport": SCREEN}).decode())
        held = Held()
        held.apply(_answer(ws))
        held.check(_boxes(boxes), SCREEN)


def test_the_stream_of_an_unknown_document_says_so(document):
    c, _, _ = document
    with c.websocket_connect("/documents/nope/stream") as ws:
        assert "'nope' not found" in receive(ws)["message"]
        with pytest.raises(WebSocketDisconnect) as closed:
            receive(ws)
    assert closed.value.code == 4404
