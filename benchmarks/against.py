"""This tree against another version, side by side: a loss of speed flagged before it lands.

Run from the repository root (a seeded plain script, not a test; the service part needs ``wrk``)::

    python -m benchmarks.against main                     # the working tree against main
    python -m benchmarks.against bf3bd4d --rounds 5 --scale 0.3
    python -m benchmarks.against HEAD~3 --no-service      # the index alone (a minute)

REF is checked out into a temporary worktree; both trees are then measured the same way,
taking turns in a shuffled order each round (a noisy neighbour hits both alike), each run in
processes of its own, with numba's cache of its own tree:

- **the index**: ``QuadTree.query`` and ``QuadTree.diff`` p50 over a panning path of full-HD
  screens on the long document and the clustered board (the public API, which every version
  has), a tree built in memory;
- **the service**: ``/viewport`` and ``/diff`` under wrk on one worker of each tree's server,
  the long document imported into each: the server's CPU per answer.

Each measure's ratio is this tree's over REF's (times: above 1 is slower), the median over
rounds. The exit status is 1 when any ratio is above ``--tolerance`` (1.10): the two losses
that went unseen for weeks (a third of the index's speed, half the service's) are far past it,
while the same tree against itself stays within ~5% here.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import statistics
import subprocess
import sys
import tempfile
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from spatial import scenes

from .load import interleave, run_wrk, write_wrk_script
from .machine import cpu_model
from .servers import ROOT, Server
from .service_bench import import_scene, measured, request_paths, write_ndjson

# What a child process measures in its tree: the boxes and the path come from files, so both
# trees see the same scene; only the public API, which every version has.
INDEX_PROBE = """
import json, sys, time
import numpy as np
from spatial import QuadTree
boxes, path = np.load(sys.argv[1]), np.load(sys.argv[2])
tree = QuadTree.bulk_load(boxes)
views = [tuple(r) for r in path.tolist()]
for v in views[:20]:
    tree.query(v)  # untimed: numba's cache loaded
def p50(call):
    times = []
    for i in range(1, len(views)):
        t = time.perf_counter_ns()
        call(i)
        times.append(time.perf_counter_ns() - t)
    return float(np.median(times)) / 1000
print(json.dumps({
    "query": p50(lambda i: tree.query(views[i])),
    "diff": p50(lambda i: tree.diff(views[i - 1], views[i])),
}))
"""

SCENES = {
    "document": lambda scale: scenes.long_document(pages=max(1, round(2000 * scale)))[0],
    "board": lambda scale: scenes.whiteboard(n=max(1, round(1_000_000 * scale)))[0],
}
PANNERS = 8  # wrk connections, each on its own path


def main(argv: list[str] | None = None) -> None:
    args = _parse(argv)
    with ExitStack() as stack:
        work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="against-")))
        other = _worktree(args.ref, work / "ref")
        stack.callback(subprocess.run, ["git", "worktree", "remove", "--force", str(other)], cwd=ROOT)
        trees = {"this tree": ROOT, args.ref: other}
        caches = {"this tree": None, args.ref: work / "numba-ref"}  # the ref's own, not the tree's
        rng = random.Random(args.seed)
        results: dict[str, dict[str, list[float]]] = {name: {} for name in trees}
        files = _scenes(work, args.scale, args.steps, args.seed)
        for round_ in range(args.rounds):
            for name in rng.sample(list(trees), len(trees)):
                for scene, (boxes, path) in files.items():
                    probe = _probe(trees[name], caches[name], boxes, path)
                    for measure, value in probe.items():
                        results[name].setdefault(f"index: {scene} {measure} p50 (us)", []).append(value)
            print(f"round {round_ + 1}/{args.rounds}: index measured", file=sys.stderr)
        if args.service:
            _service(stack, work, trees, caches, results, args, rng)
    _report(results, args)


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.against",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("ref", help="the version to compare with: a branch, tag or commit")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of both trees; medians are reported")
    parser.add_argument("--scale", type=float, default=0.3, help="scene size (1.0: 2000 pages, 1M notes)")
    parser.add_argument("--steps", type=int, default=1000, help="viewports of the panning path")
    parser.add_argument("--seconds", type=float, default=5.0, help="length of each wrk run")
    parser.add_argument("--tolerance", type=float, default=1.10, help="the largest ratio that passes")
    parser.add_argument("--no-service", dest="service", action="store_false", help="the index alone")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.rounds < 1 or args.scale <= 0 or args.steps < 10 or args.tolerance < 1:
        parser.error("--rounds >= 1, --scale > 0, --steps >= 10 and --tolerance >= 1")
    if args.service and shutil.which("wrk") is None:
        parser.error("the service part needs wrk on the PATH (apt-get install wrk), or --no-service")
    return args


def _worktree(ref: str, where: Path) -> Path:
    done = subprocess.run(
        ["git", "worktree", "add", "--detach", str(where), ref], cwd=ROOT, capture_output=True, text=True
    )
    if done.returncode:
        sys.exit(f"cannot check out {ref!r}: {done.stderr.strip()}")
    return where


def _scenes(work: Path, scale: float, steps: int, seed: int) -> dict[str, tuple[Path, Path]]:
    files = {}
    for name, make in SCENES.items():
        boxes = make(scale)
        path = scenes.panning_path(boxes, steps, seed=seed)
        files[name] = (work / f"{name}-boxes.npy", work / f"{name}-path.npy")
        np.save(files[name][0], boxes)
        np.save(files[name][1], path)
    return files


def _env(tree: Path, cache: Path | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = str(tree)
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return env


def _probe(tree: Path, cache: Path | None, boxes: Path, path: Path) -> dict[str, float]:
    done = subprocess.run(
        [sys.executable, "-c", INDEX_PROBE, str(boxes), str(path)],
        cwd=tree,
        env=_env(tree, cache),
        capture_output=True,
        text=True,
    )
    if done.returncode:
        sys.exit(f"the index probe failed in {tree}:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.splitlines()[-1])


def _service(
    stack: ExitStack,
    work: Path,
    trees: dict[str, Path],
    caches: dict[str, Path | None],
    results: dict[str, dict[str, list[float]]],
    args: argparse.Namespace,
    rng: random.Random,
) -> None:
    boxes, kinds = scenes.long_document(pages=max(1, round(2000 * args.scale)))
    ndjson = work / "document.ndjson"
    write_ndjson(boxes, kinds, ndjson)
    paths = [scenes.panning_path(boxes, args.steps, seed=args.seed + k) for k in range(PANNERS)]
    servers, scripts = {}, {}
    for name, tree in trees.items():
        # Each tree's own HTTP protocol, where it has one (one socket write a response)
        protocol = ["--http", "app.protocol:CorkedHttp"] if (tree / "app" / "protocol.py").exists() else []
        env = {**_env(tree, caches[name]), "VANTAGE_DATA_DIR": str(work / f"data-{len(servers)}")}
        server = stack.enter_context(
            Server(f"server-{len(servers)}", "app.main:app", env, work, protocol, tree)
        )
        server.start().wait_ready()
        doc, _ = import_scene(server, ndjson, len(boxes))
        servers[name] = server
        for mode in ("viewport", "diff"):
            per = [request_paths(mode, doc, path) for path in paths]
            scripts[name, mode] = write_wrk_script(
                work / f"wrk-{len(servers)}", mode, interleave(per, 2), None
            )
            run_wrk(server.url, scripts[name, mode], PANNERS, 2, 1.0, "warm-up")
    for round_ in range(args.rounds):
        for name in rng.sample(list(trees), len(trees)):
            for mode in ("viewport", "diff"):
                server = servers[name]
                run = measured(
                    server, lambda: run_wrk(server.url, scripts[name, mode], PANNERS, 2, args.seconds, mode)
                )
                results[name].setdefault(f"service: /{mode} server CPU an answer (us)", []).append(
                    run.server_cpu / run.load.rps * 1e6
                )
        print(f"round {round_ + 1}/{args.rounds}: service measured", file=sys.stderr)


def _report(results: dict[str, dict[str, list[float]]], args: argparse.Namespace) -> None:
    this, ref = results["this tree"], results[args.ref]
    lines = [
        f"## This tree against {args.ref}",
        f"{cpu_model()}; {args.rounds} rounds, scale {args.scale}; medians; ratio = this tree / {args.ref}",
        "",
        f"| measure | this tree | {args.ref} | ratio | |",
        "|---|---:|---:|---:|---|",
    ]
    slower = []
    for measure, values in this.items():
        ratios = [a / b for a, b in zip(values, ref[measure], strict=True)]
        ratio = statistics.median(ratios)
        verdict = "slower" if ratio > args.tolerance else ""
        if verdict:
            slower.append(measure)
        lines.append(
            f"| {measure} | {statistics.median(values):.2f} | {statistics.median(ref[measure]):.2f} "
            f"| {ratio:.2f}x | {verdict} |"
        )
    print("\n".join(lines))
    if slower:
        print(
            f"\nslower than {args.ref} by more than {args.tolerance:.2f}x: {', '.join(slower)}",
            file=sys.stderr,
        )
        sys.exit(1)


if __name__ == "__main__":
    main()
