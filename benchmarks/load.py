"""Load generators for service_bench, each in a process of its own: wrk (HTTP) with a generated
Lua script, and benchmarks.stream_load (WebSocket). Both report one JSON line of one shape,
parsed here into a :class:`LoadResult`.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

# Each wrk thread has a Lua state of its own: setup() (main state) numbers the threads, init()
# (the thread's state) loads that thread's request paths from a file and pre-formats them, so
# request() only picks the next one. done() prints the summary as one JSON line.
LUA = r"""
local PATHS = "%(paths)s"
local counter = 0

function setup(thread)
  thread:set("tid", counter)
  counter = counter + 1
end

function init(args)
  reqs, i = {}, 0
  for path in io.lines(string.format(PATHS, tid)) do
    reqs[#reqs + 1] = wrk.format("GET", path, %(headers)s)
  end
end

function request()
  i = i %% #reqs + 1
  return reqs[i]
end

function done(summary, latency, requests)
  local e = summary.errors
  io.write(string.format(
    '{"requests":%%d,"bytes":%%d,"duration_us":%%d,' ..
    '"errors":{"connect":%%d,"read":%%d,"write":%%d,"status":%%d,"timeout":%%d},' ..
    '"latency_us":{"p50":%%d,"p90":%%d,"p99":%%d,"max":%%d}}\n',
    summary.requests, summary.bytes, summary.duration,
    e.connect, e.read, e.write, e.status, e.timeout,
    latency:percentile(50), latency:percentile(90), latency:percentile(99), latency.max))
end
"""


@dataclass
class LoadResult:
    """One load run: totals, and latencies in microseconds."""

    requests: int
    bytes: int
    duration_us: int
    errors: dict[str, int]
    p50_us: float
    p90_us: float
    p99_us: float
    max_us: float

    @property
    def rps(self) -> float:
        return self.requests / (self.duration_us / 1e6)

    @classmethod
    def from_output(cls, output: str, what: str) -> LoadResult:
        """The last JSON line of a load generator's stdout."""
        line = next((ln for ln in reversed(output.splitlines()) if ln.startswith("{")), None)
        if line is None:
            raise RuntimeError(f"{what}: no JSON summary in its output:\n{output[-2000:]}")
        d = json.loads(line)
        lat = d["latency_us"]
        return cls(
            d["requests"],
            d["bytes"],
            d["duration_us"],
            d["errors"],
            lat["p50"],
            lat["p90"],
            lat["p99"],
            lat["max"],
        )

    def check(self, what: str) -> None:
        """Fail loudly on any error or non-2xx answer: a fast wrong run must never look good."""
        bad = {k: v for k, v in self.errors.items() if v}
        if bad or not self.requests:
            raise RuntimeError(f"{what}: {self.requests} requests, errors {bad or 'none'}")


def write_wrk_script(
    directory: Path, name: str, per_thread: list[list[str]], headers: dict[str, str] | None = None
) -> Path:
    """A Lua script whose thread t cycles through ``per_thread[t]`` (request paths, in order),
    each request with ``headers``."""
    directory.mkdir(parents=True, exist_ok=True)
    for t, paths in enumerate(per_thread):
        (directory / f"{name}-{t}.txt").write_text("\n".join(paths) + "\n")
    script = directory / f"{name}.lua"
    lua_headers = "{" + ", ".join(f'["{k}"] = "{v}"' for k, v in (headers or {}).items()) + "}"
    script.write_text(LUA % {"paths": str(directory / f"{name}-%d.txt"), "headers": lua_headers})
    return script


def interleave(paths: list[list[str]], threads: int) -> list[list[str]]:
    """Panner k goes to thread k % threads; a thread's list alternates between its panners.

    wrk calls request() per thread, not per connection, so a thread's panners take turns; with
    stateless requests (each one a full viewport, or a from/to pair) the order does not matter.
    """
    out = []
    for t in range(threads):
        mine = paths[t::threads]
        out.append([p[s] for s in range(max(map(len, mine))) for p in mine if s < len(p)])
    return out


def wrk_command(url: str, script: Path, connections: int, threads: int, seconds: float) -> list[str]:
    wrk = shutil.which("wrk") or "/usr/bin/wrk"
    return [
        wrk,
        f"-t{threads}",
        f"-c{connections}",
        f"-d{seconds:g}s",
        "--latency",
        "--timeout",
        "30s",
        "-s",
        str(script),
        url,
    ]


def run_wrk(url: str, script: Path, connections: int, threads: int, seconds: float, what: str) -> LoadResult:
    cmd = wrk_command(url, script, connections, threads, seconds)
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 120)
    if done.returncode:
        raise RuntimeError(
            f"{what}: wrk exited with {done.returncode}:\n{done.stderr}\n{done.stdout[-2000:]}"
        )
    result = LoadResult.from_output(done.stdout, what)
    result.check(what)
    return result


def run_stream(
    url: str, paths_file: Path, seconds: float, limit: int, what: str, deflate: bool = False
) -> LoadResult:
    cmd = [
        sys.executable,
        "-m",
        "benchmarks.stream_load",
        "--url",
        url,
        "--paths",
        str(paths_file),
        "--seconds",
        f"{seconds:g}",
        "--limit",
        str(limit),
        *(["--deflate"] if deflate else []),
    ]
    root = Path(__file__).resolve().parent.parent
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 120, cwd=root)
    if done.returncode:
        raise RuntimeError(f"{what}: stream_load exited with {done.returncode}:\n{done.stderr[-4000:]}")
    result = LoadResult.from_output(done.stdout, what)
    result.check(what)
    return result
