"""Fuzzing: schemathesis from the OpenAPI schema against a real server, and hypothesis on the
NDJSON reader: every outcome a 2xx or a 4xx with a message, never a 5xx or a partial import."""

import io
import json

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from service import NDJSON, ndjson, spawn_server

from app.items import ItemError, decode_ndjson
from spatial import scenes

VALUES = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.floats(),
    st.text(max_size=5),
    st.lists(st.integers(), max_size=2),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)
ITEMISH = st.dictionaries(
    st.sampled_from(["id", "x0", "y0", "x1", "y1", "kind", "z", "data", "q"]), VALUES, max_size=9
)
LINES = st.one_of(
    st.binary(max_size=80),
    ITEMISH.map(lambda d: json.dumps(d).encode()),  # NaN, Infinity and huge integers included
    st.sampled_from(
        [b'{"id": "a", "x0": 0, "y0": 0, "x1": 1, "y1": 1}', b"{}", b"[]", b"null", b"\xff\xfe", b" "]
    ),
)


@given(st.lists(LINES, max_size=12))
@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
def test_the_ndjson_reader_accepts_or_names_the_line(lines):
    body = b"\n".join(lines) + b"\n"
    try:
        batches = list(decode_ndjson(io.BytesIO(body), 1 << 16, 4096))
    except ItemError as error:
        assert str(error).startswith("line ") and ": " in str(error)
        return
    assert sum(len(b.ids) for b in batches) == sum(1 for line in body.split(b"\n") if line.strip())


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    process, url = spawn_server(tmp_path_factory.mktemp("fuzz-data"))
    doc = httpx.post(f"{url}/documents", json={"name": "fuzzed"}).json()["id"]
    httpx.post(
        f"{url}/documents/{doc}/items", content=ndjson(scenes.uniform(300, seed=4)[0]), headers=NDJSON
    ).raise_for_status()
    yield url, doc
    process.terminate()
    process.communicate(timeout=10)


@schemathesis.serializer("application/x-ndjson")
def _ndjson_body(ctx, value) -> bytes:
    """The import's body is a string in the schema: send it as it is."""
    return value.encode("utf-8", "surrogatepass") if isinstance(value, str) else json.dumps(value).encode()


def test_no_request_the_schema_allows_gets_a_server_error(server):
    url, doc = server
    schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) == 23
    for operation in operations:
        deletes_the_document = operation.method.upper() == "DELETE" and operation.path == "/documents/{doc}"

        @given(case=operation.as_strategy())
        @settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
        def call(case):
            if case.path_parameters and "doc" in case.path_parameters and not deletes_the_document:
                case.path_parameters["doc"] = doc  # reach past the 404 into the real checks
            response = case.call(base_url=url)
            where = f"{case.method} {case.formatted_path}"
            assert response.status_code < 500, f"{where}: {response.status_code} {response.text[:300]}"
            if response.status_code >= 400:
                assert response.json()["detail"], f"{where}: a 4xx without a message"

        call()


def test_random_bytes_imported_get_a_4xx_and_change_nothing(server):
    url, doc = server
    before = httpx.get(f"{url}/documents/{doc}").json()

    @given(st.binary(min_size=1, max_size=300))
    @settings(max_examples=60, deadline=None)
    def post(body):
        answer = httpx.post(
            f"{url}/documents/{doc}/items", content=body + b"\n{", headers=NDJSON
        )  # never all valid
        assert answer.status_code == 422 and answer.json()["detail"].startswith("line ")

    post()
    after = httpx.get(f"{url}/documents/{doc}").json()
    assert (after["version"], after["items"]) == (before["version"], before["items"])
