"""The command line: ``python -m benchmarks.tradeoffs`` runs the trades asked for and writes the report."""

from __future__ import annotations

import argparse
import gc
import shlex
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tqdm import tqdm

from . import __doc__ as DESCRIPTION
from .aggregates import (
    AGG_ZOOM_OUT,
    AggResult,
    plot_aggregates,
    plot_zoom_out,
    section_aggregates,
    section_rules,
    trade_aggregates,
    trade_rules,
)
from .exact import plot_exact, section_exact, trade_exact
from .float32 import (
    MAGNITUDES,
    magnitude_scene,
    plot_float32,
    section_float32,
    trade_float32,
    trade_float32_scene,
)
from .lod import plot_lod, section_lod, trade_lod
from .overscan import SIM_SECONDS, plot_overscan, section_overscan, trade_overscan
from .recommendations import Results, section_recommendations
from .report import header, splice
from .scene import SCENE_KEYS, load_scene
from .shape import build_shape, plot_shape, section_shape, shapes, time_shapes
from .tiles import section_tiles, trade_tiles

TRADES = ("exact", "lod", "float32", "shape", "overscan", "aggregates")


def plot_path(out: Path, trade: str) -> Path:
    return out.parent / f"tradeoffs-{trade}.png"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.tradeoffs",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="scene size factor: 1.0 is 2000 pages / 1M items per scene (default %(default)s); "
        "below 1 the simulator also runs shorter",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="scenes, paths and shuffles (default %(default)s)"
    )
    parser.add_argument(
        "--steps",
        type=int,
        default=2000,
        help="panning path steps per scene (trades exact, float32, shape; default %(default)s)",
    )
    parser.add_argument("--repeat", type=int, default=3, help="builds per tree shape; the median is reported")
    parser.add_argument("--trades", default=",".join(TRADES), help=f"comma list of {', '.join(TRADES)}")
    parser.add_argument(
        "--scenes", default=",".join(SCENE_KEYS), help=f"comma list of {', '.join(SCENE_KEYS)}"
    )
    parser.add_argument(
        "--out",
        default="docs/TRADEOFFS.md",
        help="the report; plots go next to it as tradeoffs-<trade>.png (default %(default)s)",
    )
    parser.add_argument(
        "--update",
        action="store_true",
        help="replace only the sections of the trades run in the existing report, keeping its header, "
        "other sections and recommendations",
    )
    parser.add_argument(
        "--rules",
        action="store_true",
        help="with the aggregates trade, also compare the overview's merge rules (minutes more)",
    )
    args = parser.parse_args(argv)
    args.trade_list = [t.strip() for t in args.trades.split(",") if t.strip()]
    args.scene_list = [s.strip() for s in args.scenes.split(",") if s.strip()]
    if not set(args.trade_list) <= set(TRADES) or not set(args.scene_list) <= set(SCENE_KEYS):
        parser.error(f"--trades takes {', '.join(TRADES)}; --scenes takes {', '.join(SCENE_KEYS)}")
    if args.scale <= 0 or args.steps < 2 or args.repeat < 1:
        parser.error("--scale must be > 0, --steps >= 2, --repeat >= 1")
    return args


def main(argv: list[str] | None = None) -> None:
    started = time.perf_counter()
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    trades = args.trade_list
    needs_scenes = {"exact", "lod", "float32", "shape", "aggregates"} & set(trades)
    keys = args.scene_list if needs_scenes else []
    sim_seconds = SIM_SECONDS if args.scale >= 1 else max(1.0, round(SIM_SECONDS * args.scale * 5) / 5)
    n32 = max(1000, round(1_000_000 * args.scale))
    total = (
        len(keys)
        + len(keys) * ("exact" in trades)
        + len(keys) * ("lod" in trades)
        + (len(MAGNITUDES) + len(keys)) * ("float32" in trades)
        + len(keys) * len(shapes()) * ("shape" in trades)
        + ("overscan" in trades)
        + len(keys) * ("aggregates" in trades)
    )
    bar = tqdm(total=total, desc="tradeoffs", unit="task", file=sys.stderr)
    res = Results([], [], [], [], [], [], [])
    native32: bool | None = None
    body: list[str] = []
    sim_command = ""
    aggs = AggResult([], [], {})
    for key in keys:
        bar.set_description(f"scene {key}")
        res.scenes.append(load_scene(key, args.scale, args.seed, args.steps))
        bar.update()
    if "exact" in trades:
        for scene in res.scenes:
            bar.set_description(f"exact: {scene.key}")
            res.exact.append(trade_exact(scene, args.seed))
            bar.update()
    if "lod" in trades:
        for scene in res.scenes:
            bar.set_description(f"lod: {scene.key}")
            res.lod += trade_lod(scene, args.seed)
            bar.update()
    if "float32" in trades:
        base, windows = magnitude_scene(n32, args.seed)
        for magnitude in MAGNITUDES:
            bar.set_description(f"float32: {magnitude:.0e}")
            row, native32 = trade_float32(base, windows, magnitude, args.seed)
            res.coords.append(row)
            gc.collect()
            bar.update()
        for scene in res.scenes:
            bar.set_description(f"float32: {scene.key}")
            res.coords_scenes.append(trade_float32_scene(scene, args.seed))
            gc.collect()
            bar.update()
    if "shape" in trades:
        for scene in res.scenes:
            trees, rows = [], []
            for shape in shapes():
                bar.set_description(f"shape: {scene.key} leaf {shape[0]} depth {shape[1]}")
                tree, row = build_shape(scene, shape, args.repeat)
                trees.append(tree)
                rows.append(row)
                bar.update()
            bar.set_description(f"shape: {scene.key} timing")
            time_shapes(scene, trees, rows, args.seed)
            res.shape += rows
            del trees
            gc.collect()
    if "overscan" in trades:
        bar.set_description("overscan: simulator")
        res.overscan, sim_command = trade_overscan(sim_seconds, args.seed)
        bar.update()
    if "aggregates" in trades:
        t0 = time.perf_counter()
        for scene in res.scenes:
            bar.set_description(f"aggregates: {scene.key}")
            rows, cost, pictures = trade_aggregates(scene, args.repeat, args.seed)
            bar.set_description(f"aggregates: {scene.key} tiles")
            aggs.tiles += trade_tiles(scene, args.seed)
            if args.rules:
                aggs.rules += trade_rules(scene, args.seed)
            aggs.rows += rows
            aggs.builds.append(cost)
            aggs.pictures.update(pictures)
            bar.update()
        aggs.seconds = time.perf_counter() - t0
    bar.close()

    def plot(trade: str, draw: Callable[[Any, Path], None], data: Any) -> str:
        path = plot_path(out, trade)
        draw(data, path)
        return path.name

    if res.exact:
        body += section_exact(res.exact, plot("exact", plot_exact, res.exact))
    if res.lod:
        body += section_lod(res.lod, plot("lod", plot_lod, res.lod))
    if res.coords:
        body += section_float32(
            res.coords, res.coords_scenes, n32, bool(native32), plot("float32", plot_float32, res.coords)
        )
    if res.shape:
        body += section_shape(res.shape, args.repeat, plot("shape", plot_shape, res.shape))
    if res.overscan:
        body += section_overscan(
            res.overscan, sim_command, sim_seconds, plot("overscan", plot_overscan, res.overscan)
        )
    if aggs.rows:
        picture = None
        if aggs.pictures:
            plot_zoom_out(aggs.pictures, out.parent / AGG_ZOOM_OUT)
            picture = AGG_ZOOM_OUT
        command = shlex.join(["python", "-m", "benchmarks.tradeoffs", *argv])
        body += section_aggregates(
            aggs, command, args.repeat, plot("aggregates", plot_aggregates, aggs), picture
        )
        body += section_tiles(aggs.tiles)
        if aggs.rules:
            body += section_rules(aggs.rules)
    if args.update and out.exists():
        report = splice(out.read_text().splitlines(), body)
    else:
        body += section_recommendations(res)
        report = header(args, argv, time.perf_counter() - started, native32) + body
    out.write_text("\n".join(report).rstrip() + "\n")
    print(f"wrote {out} and its plots in {time.perf_counter() - started:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
