"""The service's promises, each held by a test that fails when the code breaks it: imports are
all or nothing across decoding batches; nothing is shown before the store has it; the stream
answers only the newest of queued viewports."""

import orjson
from service import NDJSON, client, expected, ids_of, ndjson, receive

import app.items
import app.stores.base
from app.config import get_settings
from app.session import Session
from spatial import scenes

SCREEN = (0.0, 0.0, 700.0, 900.0)


def test_an_import_longer_than_a_batch_whose_last_line_is_bad_stores_nothing(document, monkeypatch):
    c, doc, boxes = document
    monkeypatch.setattr(app.items, "LINES_PER_BATCH", 10)  # 35 lines: three whole batches decode first
    moved = ndjson(boxes[:34] + 1000.0)
    bad = b'{"id": "last", "x0": 1, "y0": 0, "x1": 0, "y1": 1}\n'
    answer = c.post(f"/documents/{doc}/items", content=moved + bad, headers=NDJSON)
    assert answer.status_code == 422 and answer.json()["detail"].startswith("line 35: x0=1.0 > x1=0.0"), (
        answer.text
    )
    assert c.get(f"/documents/{doc}").json()["version"] == 1
    shown = c.get(
        f"/documents/{doc}/viewport", params=dict(zip(("x0", "y0", "x1", "y1"), SCREEN, strict=True))
    ).json()
    assert ids_of(shown["items"]) == expected(boxes, SCREEN)  # the first 34 never moved
    assert c.get(f"/documents/{doc}/items/i0").json()["x0"] == boxes[0, 0]


def _fill_the_store(c, pages: int) -> None:
    """Cap the store's file at the pages it has, plus ``pages``: a larger write fails as a
    full disk would, inside SQLite."""
    db = c.app.state.registry.store._db
    db.execute(f"PRAGMA max_page_count = {db.execute('PRAGMA page_count').fetchone()[0] + pages}")


def test_a_write_the_store_refuses_is_never_shown(document, monkeypatch):
    c, doc, _boxes = document
    monkeypatch.setattr(app.stores.base, "CHUNK", 1000)  # the import below fails after a few of its 20 chunks
    with c.websocket_connect(f"/documents/{doc}/stream") as ws:
        ws.send_text(orjson.dumps({"seq": 1, "viewport": SCREEN}).decode())
        assert receive(ws)["version"] == 1
        _fill_the_store(c, 50)  # ~200 kB: the import below compresses to ~800 kB
        big = ndjson(scenes.uniform(20_000, seed=8)[0] + 1e6)
        answer = c.post(f"/documents/{doc}/items", content=big, headers=NDJSON)
        assert answer.status_code == 507 and "store is full" in answer.json()["detail"], answer.text
        assert c.get(f"/documents/{doc}").json()["version"] == 1
        far = c.get(f"/documents/{doc}/viewport", params={"x0": 1e6, "y0": 1e6, "x1": 2e6, "y1": 2e6}).json()
        assert far["count"] == 0  # none of the refused import is shown
        item = {"x0": 1, "y0": 1, "x1": 2, "y1": 2, "data": {"text": "x" * 4000}}
        for k in range(1000):  # single edits until one no longer fits either
            put = c.put(f"/documents/{doc}/items/n{k}", json=item)
            if put.status_code != 201:
                break
            assert receive(ws)["type"] == "edit"  # a committed edit is pushed
        assert put.status_code == 507, put.text
        version = c.get(f"/documents/{doc}").json()["version"]
        assert c.get(f"/documents/{doc}/items/n{k}").status_code == 404
        ws.send_text(orjson.dumps({"seq": 2, "viewport": SCREEN}).decode())
        view = receive(ws)  # the refused edit was never pushed: the next message answers seq 2
        assert (view["type"], view["seq"], view["version"]) == ("view", 2, version)
        assert f"n{k}" not in ids_of(view["enter"])
    with client() as again:  # a restart shows what the store holds: what was shown, nothing of the import
        assert again.get(f"/documents/{doc}").json()["version"] == version
        far = again.get(
            f"/documents/{doc}/viewport", params={"x0": 1e6, "y0": 1e6, "x1": 2e6, "y1": 2e6}
        ).json()
        assert far["count"] == 0


class _Doc:
    """The smallest document a Session reads: a snapshot that never changes."""

    snapshot = None


def test_the_stream_answers_the_newest_of_queued_viewports_only(data_dir):
    session = Session(_Doc(), get_settings())  # type: ignore[arg-type]
    for seq, x in enumerate((0.0, 10.0, 20.0)):
        session.offer(orjson.dumps({"seq": seq, "viewport": [x, 0, x + 5, 5]}))
    job = session.take()
    assert job.view.rect == (20.0, 0.0, 25.0, 5.0) and (job.kind, job.seq) == ("view", 2)
    assert session.take() is None  # the two older ones are gone, not queued behind


def test_a_fling_over_a_socket_is_answered_for_its_last_view_not_in_turn(data_dir):
    """While an answer (the first is 100,000 items) is computed and sent, more viewports
    arrive: the answers skip the superseded ones and end with the last, never all in turn.
    (Whether the first view is answered, or superseded by the second before it is taken,
    depends on when the server reads them.)"""
    boxes = scenes.uniform(100_000, seed=9)[0]
    everything = [
        float(boxes[:, 0].min()),
        float(boxes[:, 1].min()),
        float(boxes[:, 2].max()),
        float(boxes[:, 3].max()),
    ]
    with client() as c:
        doc = c.post("/documents", json={"name": "a"}).json()["id"]
        assert c.post(f"/documents/{doc}/items", content=ndjson(boxes), headers=NDJSON).status_code == 200
        with c.websocket_connect(f"/documents/{doc}/stream") as ws:
            ws.send_text(orjson.dumps({"seq": 0, "viewport": everything, "limit": 100_000}).decode())
            for seq in range(1, 31):
                ws.send_text(orjson.dumps({"seq": seq, "viewport": [0, seq, 700, 900 + seq]}).decode())
            seqs = [receive(ws)["seq"]]
            while seqs[-1] != 30:
                seqs.append(receive(ws)["seq"])
    assert seqs == sorted(set(seqs)) and len(seqs) < 31, seqs  # superseded, not answered in turn


def test_only_a_pan_steps_small_change_is_answered_on_the_event_loop(document):
    """A stream answers on the event loop only what cannot stall it: a quick, complete last
    answer, the same level of detail and base, and a view that kept half of itself. A jump, a
    zoom or a new import may take milliseconds: those go to a worker thread."""
    c, doc, boxes = document
    session = Session(c.app.state.registry[doc], get_settings())

    def offered(seq: int, rect, scale=None, min_px=0.0):
        session.offer(orjson.dumps({"seq": seq, "viewport": rect, "scale": scale, "min_px": min_px}))
        return session.take()

    first = offered(1, [0, 0, 600, 800])
    assert not session.light(first)  # nothing answered yet: starts over
    session.answer(first)
    session.cost = 0.0001  # as a quick answer leaves it (the first, a whole page, may take longer)
    assert session.light(offered(2, [0, 300, 600, 1100]))  # kept 5/8 of itself
    assert not session.light(offered(3, [0, 500, 600, 1300]))  # kept 3/8
    assert not session.light(offered(4, [0, 5000, 600, 5800]))  # a jump
    assert not session.light(offered(5, [0, 0, 600, 800], scale=0.5, min_px=4))  # a zoom
    session.cost = 0.01
    assert not session.light(offered(6, [0, 10, 600, 810]))  # the last answer was slow
    session.cost = 0.0001
    moved = ndjson(boxes + 1.0)
    assert c.post(f"/documents/{doc}/items", content=moved, headers=NDJSON).status_code == 200
    assert not session.light(offered(7, [0, 10, 600, 810]))  # a new base: a reset
