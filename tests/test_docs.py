"""The API docs work without internet, and every example they show succeeds when sent as
"Try it out" sends it: path and query examples filled in, the body example as the body, with
its content type."""

import re

import msgspec
from service import client

# The documented operations in an order whose examples all succeed: each finds what the
# ones before it made (the document, item w17); a route missing here fails the test.
ORDER = [
    ("get", "/health"),
    ("post", "/documents"),
    ("get", "/documents"),
    ("post", "/documents/{doc}/items"),
    ("get", "/documents/{doc}"),
    ("get", "/documents/{doc}/items/{item}"),
    ("put", "/documents/{doc}/items/{item}"),
    ("patch", "/documents/{doc}/items/{item}"),
    ("get", "/documents/{doc}/viewport"),
    ("get", "/documents/{doc}/diff"),
    ("get", "/documents/{doc}/cells"),
    ("get", "/documents/{doc}/items"),
    ("get", "/documents/{doc}/search"),
    ("get", "/stats"),
    ("delete", "/documents/{doc}/items/{item}"),
    ("post", "/documents/{doc}/items"),  # w17 again, for the bulk delete's example
    ("delete", "/documents/{doc}/items"),
    ("delete", "/documents/{doc}"),
]


def _example(schema: dict, components: dict) -> object:
    """A body from the schema's examples, as Swagger UI fills one in."""
    if "$ref" in schema:
        schema = components[schema["$ref"].rsplit("/", 1)[1]]
    if "example" in schema:
        return schema["example"]
    props = schema.get("properties", {})
    return {
        name: (p.get("examples") or [p.get("example")])[0]
        for name, p in props.items()
        if name in schema.get("required", props)
    }


def test_every_documented_example_succeeds_as_try_it_out_sends_it(data_dir):
    with client() as c:
        schema = c.get("/openapi.json").json()
        components = schema["components"]["schemas"]
        documented = {(m, path) for path, ops in schema["paths"].items() for m in ops}
        assert documented == set(ORDER), f"add these to ORDER: {documented - set(ORDER)}"
        doc = None
        for method, path in ORDER:
            op = schema["paths"][path][method]
            params = {"doc": doc}
            query = {}
            for p in op.get("parameters", []):
                examples = p.get("examples") or p["schema"].get("examples")
                if p["in"] == "path" and p["name"] != "doc":
                    params[p["name"]] = examples[0]
                elif p["in"] == "query" and p.get("required"):
                    query[p["name"]] = examples[0]
            url = re.sub(r"\{(\w+)\}", lambda m: str(params[m.group(1)]), path)
            kwargs: dict = {"params": query}
            if "requestBody" in op:
                (kind, content), *_ = op["requestBody"]["content"].items()
                body = content.get("example", _example(content["schema"], components))
                raw = body if isinstance(body, str) else msgspec.json.encode(body)
                kwargs |= {"content": raw, "headers": {"content-type": kind}}
            answer = c.request(method.upper(), url, **kwargs)
            assert 200 <= answer.status_code < 300, (
                f"{method.upper()} {url}: {answer.status_code} {answer.text}"
            )
            if (method, path) == ("post", "/documents"):
                doc = answer.json()["id"]


def test_the_docs_need_no_internet():
    with client() as c:
        for page in ("/docs", "/redoc"):
            html = c.get(page).text
            assets = re.findall(r"""(?:src|href|url)\s*[=:]\s*['"]([^'"]+)['"]""", html)
            assert assets and not [a for a in assets if a.startswith(("http:", "https:", "//"))], html
            for asset in assets:
                if asset.startswith("/"):
                    assert c.get(asset).status_code == 200, asset
        assert c.get("/static/favicon.svg").status_code == 200


def test_try_it_out_on_the_import_route_imports_its_example_in_a_browser(data_dir):
    """Swagger UI itself, in Chromium: it sends a body the way it does (it JSON-encodes any
    example of a media type named *json*, NDJSON's included), so the route's first example must
    be one it sends as it is."""
    import httpx
    from browser import chromium_page

    from app.launch import launch

    server, url = launch(data_dir)
    try:
        doc = httpx.post(f"{url}/documents", json={"name": "tried"}).json()["id"]
        with chromium_page() as page:
            page.goto(f"{url}/docs")
            block = page.locator("[id$='import_items_documents__doc__items_post']")
            block.locator(".opblock-summary").first.click()
            block.get_by_role("button", name="Try it out").click()
            block.locator("input[placeholder='doc']").fill(doc)
            with page.expect_response(
                lambda r: f"/{doc}/items" in r.url and r.request.method == "POST"  # ?mode=upsert too
            ) as sent:
                block.get_by_role("button", name="Execute").click()
            assert sent.value.status == 200, sent.value.text()
        answer = httpx.get(f"{url}/documents/{doc}/viewport", params={"x0": 0, "y0": 0, "x1": 1e3, "y1": 1e3})
        assert [item["id"] for item in answer.json()["items"]] == ["w17"]
    finally:
        server.terminate()
        server.communicate(timeout=10)


def test_every_setting_is_documented():
    """Each field of app/config.py's Settings is named in the README, as VANTAGE_NAME or NAME."""
    from service import ROOT

    from app.config import Settings

    readme = (ROOT / "README.md").read_text()
    undocumented = [
        name
        for name in Settings.model_fields
        if f"`{name.upper()}`" not in readme and f"VANTAGE_{name.upper()}" not in readme
    ]
    assert not undocumented, f"settings the README does not name: {undocumented}"
