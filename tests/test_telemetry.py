"""``VANTAGE_TELEMETRY``: with it on, every request, the hot viewport and diff routes included,
leaves an OpenTelemetry span through the configured provider; off (the default), none does.

OpenTelemetry's provider is global and set once per process, so each case runs in a fresh
interpreter.
"""

import pytest
from service import in_fresh_interpreter

SPANS = r"""
import json, sys
from fastapi.testclient import TestClient
from opentelemetry import trace
from opentelemetry.sdk.trace import TracerProvider
from opentelemetry.sdk.trace.export import SimpleSpanProcessor
from opentelemetry.sdk.trace.export.in_memory_span_exporter import InMemorySpanExporter

exporter = InMemorySpanExporter()
provider = TracerProvider()
provider.add_span_processor(SimpleSpanProcessor(exporter))
trace.set_tracer_provider(provider)

from app.config import Settings
from app.main import create_app

settings = Settings(data_dir=sys.argv[1], telemetry=sys.argv[2] == "on", allowed_hosts="127.0.0.1,testserver")
with TestClient(create_app(settings), base_url="http://127.0.0.1") as client:
    doc = client.post("/documents", json={"name": "traced"}).json()["id"]
    line = b'{"id": "a", "x0": 0, "y0": 0, "x1": 5, "y1": 5}\n'
    client.post(f"/documents/{doc}/items", content=line, headers={"content-type": "application/x-ndjson"})
    exporter.clear()
    paths = [
        "/health",
        f"/documents/{doc}/viewport?x0=0&y0=0&x1=10&y1=10",
        f"/documents/{doc}/diff?from=0,0,10,10&to=100,100,110,110",
    ]
    for path in paths:
        assert client.get(path).status_code == 200, path
spans = exporter.get_finished_spans()
print(json.dumps([
    {"path": s.attributes.get("url.path"), "status": s.attributes.get("http.response.status_code")}
    for s in spans
    if s.kind == trace.SpanKind.SERVER  # a request's own span, not the ones inside it
]))
"""


@pytest.mark.parametrize("telemetry", ["on", "off"])
def test_requests_are_traced_when_telemetry_is_on_and_only_then(tmp_path, telemetry):
    spans = in_fresh_interpreter(SPANS, str(tmp_path), telemetry, timeout=170)
    if telemetry == "off":
        assert spans == []
        return
    paths = sorted(span["path"].rsplit("/", 1)[-1] for span in spans)
    assert paths == ["diff", "health", "viewport"], spans
    assert {span["status"] for span in spans} == {200}
