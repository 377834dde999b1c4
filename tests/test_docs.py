"""The docs hold: the API docs work without internet, and every example they show succeeds when
sent as "Try it out" sends it (path and query examples filled in, the body example as the body,
with its content type); the README and the pages in docs/ run as written (every shell command,
the README's Python example), link only to what exists, and name every setting."""

import os
import re
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import msgspec
from service import ROOT, client

# The documented operations in an order whose examples all succeed: each finds what the
# ones before it made (the document, item w17); a route missing here fails the test.
ORDER = [
    ("get", "/health"),
    ("post", "/documents"),
    ("get", "/documents"),
    ("post", "/documents/{doc}/items"),
    ("post", "/documents/{doc}/uploads"),
    ("put", "/documents/{doc}/uploads/{upload}/parts/{number}"),
    ("get", "/documents/{doc}/uploads/{upload}"),
    ("post", "/documents/{doc}/uploads/{upload}/commit"),
    ("post", "/documents/{doc}/uploads"),  # another, for the delete's example
    ("delete", "/documents/{doc}/uploads/{upload}"),
    ("get", "/documents/{doc}"),
    ("get", "/documents/{doc}/items/{item}"),
    ("put", "/documents/{doc}/items/{item}"),
    ("patch", "/documents/{doc}/items/{item}"),
    ("get", "/documents/{doc}/viewport"),
    ("get", "/documents/{doc}/diff"),
    ("get", "/documents/{doc}/tiles/{band}/{z}/{tx}/{ty}"),
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
        doc = upload = None
        for method, path in ORDER:
            op = schema["paths"][path][method]
            params = {"doc": doc, "upload": upload}
            query = {}
            for p in op.get("parameters", []):
                examples = p.get("examples") or p["schema"].get("examples")
                if p["in"] == "path" and p["name"] not in params:
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
            elif (method, path) == ("post", "/documents/{doc}/uploads"):
                upload = answer.json()["id"]  # what the next routes' {upload} names


def test_the_docs_need_no_internet(data_dir):  # a store of its own, not ./data of the checkout
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


def test_every_setting_is_in_the_settings_table():
    """Each field of app/config.py's Settings has its row in docs/operating.md's settings table,
    as `VANTAGE_NAME`, and the table has no row for a setting that does not exist."""
    from app.config import Settings

    operating = (DOCS / "operating.md").read_text()
    section = operating[operating.index("\n## Settings\n") :]
    section = section[: section.index("\n## ", 1)]
    rows = re.findall(r"^\| `VANTAGE_(\w+)` \|", section, re.M)
    assert len(rows) > 20, "the settings table was not found"
    fields = {name.upper() for name in Settings.model_fields}
    assert not fields - set(rows), f"settings the table does not name: {sorted(fields - set(rows))}"
    assert not set(rows) - fields, f"the table names settings that do not exist: {sorted(set(rows) - fields)}"
    assert len(rows) == len(set(rows)), "a setting has two rows"


# -- the README and docs/ run as written ---------------------------------------------------------

DOCS = ROOT / "docs"
SHELLS = {"sh", "bash", "shell", "console"}  # the fences whose commands run
NOT_RUN = re.compile(r"^<!-- not run: (.*\S.*) -->$")  # on the line before a fence: skipped, and why
LOCAL_SERVER = re.compile(r"\b(?:localhost|127\.0\.0\.1):8000\b")  # ./run's server, in the docs
MIN_COMMANDS = 12  # fewer found means the extractor broke, not that the docs shrank this much
SHELL_TIMEOUT = 120  # seconds for all of them (they take a few)


def _pages() -> list[Path]:
    """The README, then the docs/ pages in the order it links them; every page is linked."""
    readme = (ROOT / "README.md").read_text()
    linked = list(dict.fromkeys(re.findall(r"\]\((docs/[\w.-]+\.md)\)", readme)))
    pages = [ROOT / "README.md", *(ROOT / page for page in linked)]
    unlinked = sorted(p.name for p in DOCS.glob("*.md") if p not in pages)
    assert not unlinked, f"pages the README does not link: {unlinked}"
    return pages


@dataclass
class Block:
    page: Path
    line: int  # of the opening fence, 1-based
    lang: str
    lines: list[str]
    skipped: str | None  # the reason given by a `<!-- not run: ... -->` line, or None


def _blocks(page: Path) -> list[Block]:
    """The fenced code blocks of ``page``."""
    blocks: list[Block] = []
    lines = page.read_text().splitlines()
    at = 0
    while at < len(lines):
        fence = re.match(r"^```(\w*)", lines[at])
        if not fence:
            at += 1
            continue
        end = next(i for i in range(at + 1, len(lines)) if lines[i].startswith("```"))
        marker = NOT_RUN.match(lines[at - 1].strip()) if at else None
        blocks.append(Block(page, at + 1, fence.group(1), lines[at + 1 : end], marker and marker.group(1)))
        at = end + 1
    return blocks


def _commands(block: Block) -> list[tuple[int, str]]:
    """``(line, command)`` for each command of a shell block: a line that is not blank or a
    comment, joined with the lines after it while it ends in ``\\`` or ``|`` (in a console
    block, only lines after a ``$`` prompt)."""
    commands: list[tuple[int, str]] = []
    lines = iter(enumerate(block.lines, start=block.line + 1))
    for number, line in lines:
        if block.lang == "console":
            if not line.startswith("$ "):
                continue
            line = line[2:]
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        command = [line]
        while re.search(r"(\\|\|)\s*$", command[-1]):
            command.append(next(lines)[1])
        commands.append((number, "\n".join(command)))
    return commands


def test_every_shell_command_in_the_docs_runs(tmp_path):
    """The shell blocks of the README and of every page it links run, in that order, in one bash
    session against a fresh server (``localhost:8000`` is that server), and every command exits
    0; ``curl`` fails on an HTTP error. A block that cannot run says why, just before its fence."""
    from service import serving

    blocks = [b for page in _pages() for b in _blocks(page) if b.lang in SHELLS and not b.skipped]
    commands = [(block.page, line, command) for block in blocks for line, command in _commands(block)]
    assert len(commands) >= MIN_COMMANDS, f"only {len(commands)} commands found in the docs' shell blocks"
    with serving(tmp_path / "data") as url:
        here = url.removeprefix("http://")
        script = [
            "set -o pipefail",
            # an HTTP error fails the command, and shows the server's answer where curl can (7.76+)
            'case "$(command curl --help all)" in *--fail-with-body*) fail=--fail-with-body;; *) fail=--fail;; esac',
            'curl() { command curl $fail --silent --show-error "$@"; }',
        ]
        for i, (_, _, command) in enumerate(commands):
            script += [
                f'echo "::started {i}" >&2',
                LOCAL_SERVER.sub(here, command),
                f'[ $? = 0 ] || {{ echo "::failed {i}" >&2; exit 1; }}',
                "echo",
            ]
        bin_dir = str(Path(sys.executable).parent)  # vantage, and the python the docs call python3
        work = tmp_path / "work"
        work.mkdir()
        with subprocess.Popen(
            ["bash", "-c", "\n".join(script)],
            cwd=work,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}"},
            start_new_session=True,  # a command that never ends is killed with everything it started
        ) as bash:
            try:
                out, err = bash.communicate(timeout=SHELL_TIMEOUT)
                why = "failed"
            except subprocess.TimeoutExpired:
                os.killpg(bash.pid, signal.SIGKILL)
                out, err = bash.communicate()
                why = f"did not end within {SHELL_TIMEOUT} s (does it start a server? mark its block not run)"
    if bash.returncode != 0:
        started = re.findall(r"::started (\d+)", err)
        page, line, command = commands[int(started[-1])] if started else (ROOT, 0, "(none)")
        raise AssertionError(
            f"{page.relative_to(ROOT)}:{line}: this command {why}:\n{command}\n\n{out[-2000:]}\n{err[-3000:]}"
        )


def test_the_readmes_python_examples_run_as_written(tmp_path):
    """Each Python block of the README, in an interpreter of its own, against a fresh server
    (``localhost:8000`` is that server)."""
    from service import serving

    blocks = [b for b in _blocks(ROOT / "README.md") if b.lang == "python"]
    assert len(blocks) >= 2, "the README's Python examples were not found"
    with serving(tmp_path) as url:
        for block in blocks:
            source = LOCAL_SERVER.sub(url.removeprefix("http://"), "\n".join(block.lines))
            done = subprocess.run(
                [sys.executable, "-c", source], capture_output=True, text=True, timeout=120, cwd=ROOT
            )
            assert done.returncode == 0, f"README.md:{block.line}:\n{done.stderr[-3000:]}"


def _anchors(page: Path) -> set[str]:
    """The ``#anchors`` GitHub makes of ``page``'s headings."""
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.M | re.S)  # no headings in code
    headings = re.findall(r"^#{1,6} +(.+?) *$", text, re.M)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in headings}


def test_every_link_between_the_pages_leads_somewhere():
    """Relative links and images in the README and docs/ name files that exist, and a
    ``#anchor`` names a heading of its page."""
    broken = []
    for page in [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]:
        text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.M | re.S)
        targets = re.findall(r"\]\(([^)\s]+)\)", text) + re.findall(r'<img src="([^"]+)"', text)
        for target in targets:
            if re.match(r"^[a-z]+:", target):
                continue  # http:, https:, mailto:
            path, _, anchor = target.partition("#")
            linked = (page.parent / path).resolve() if path else page
            if not linked.exists():
                broken.append(f"{page.name}: {target} (no such file)")
            elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
                broken.append(f"{page.name}: {target} (no such heading)")
    assert not broken, "\n".join(broken)
