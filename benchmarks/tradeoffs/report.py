"""The report's pieces: Markdown tables, number formats, plots, the header and --update's splice."""

from __future__ import annotations

import argparse
import os
import platform
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..machine import cpu_model, versions
from ..spatial_bench import source_hash


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]], align: str) -> list[str]:
    """Markdown table; ``align`` has one ``l`` or ``r`` per column."""
    rule = ["---:" if a == "r" else "---" for a in align]
    return ["| " + " | ".join(header) + " |", "|" + "|".join(rule) + "|"] + [
        "| " + " | ".join(r) + " |" for r in rows
    ]


def pct(share: float, digits: int = 1) -> str:
    return f"{100 * share:.{digits}f}%"


def kb(nbytes: float) -> str:
    return f"{nbytes / 1e3:,.1f}"


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig: Any, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)


SCENE_COLOURS = {
    "doc": "tab:blue",
    "whiteboard": "tab:orange",
    "clustered": "tab:red",
    "uniform": "tab:green",
}


def header(args: argparse.Namespace, argv: list[str], seconds: float, native32: bool | None) -> list[str]:
    u = platform.uname()
    pkgs = versions(("numpy", "numba", "matplotlib"))
    coords = {None: "not measured", True: "available", False: "NOT available (measured float64 for both)"}
    return [
        "# Vantage trade-offs: accuracy against cost",
        "",
        f"- command: `{shlex.join(['python', '-m', 'benchmarks.tradeoffs', *argv])}`",
        f"- machine: {u.system} {u.release} {u.machine}, CPU {cpu_model()}, nproc {len(os.sched_getaffinity(0))}",
        f"- python {platform.python_version()}; {pkgs}",
        f'- spatial sources sha256 {source_hash()}; `QuadTree(coords="float32")` {coords[native32]}',
        f"- seed {args.seed}, scale {args.scale:g} (1 = 2000 pages / 1M items per scene), "
        f"steps {args.steps}, build repeats {args.repeat}; run time {seconds / 60:.1f} min",
        "",
        "Every accuracy figure is against the exact answer: brute force over the float64 boxes, "
        "`x0 <= qx1 and x1 >= qx0 and y0 <= qy1 and y1 >= qy0` (touching counts). Times are medians "
        "(p50) of calls interleaved step by step in a seeded shuffled order, on a shared 2-core "
        "machine: read the ratios more than the absolute microseconds.",
        "",
    ]


def splice(old: list[str], new: list[str]) -> list[str]:
    """``old`` report lines with each of ``new``'s sections (from a '## ' heading to the next)
    in place of the old section of the same number, or before the recommendations if it had none."""

    def sections(lines: list[str]) -> tuple[list[str], list[list[str]]]:
        head: list[str] = []
        parts: list[list[str]] = []
        for line in lines:
            if line.startswith("## "):
                parts.append([])
            (parts[-1] if parts else head).append(line)
        return head, parts

    def key(part: list[str]) -> str:
        return part[0].split()[1] if part[0].split()[1][:1].isdigit() else part[0]

    head, parts = sections(old)
    for part in sections(new)[1]:
        at = next((i for i, p in enumerate(parts) if key(p) == key(part)), None)
        if at is None:
            at = next((i for i, p in enumerate(parts) if not key(p)[:1].isdigit()), len(parts))
            parts.insert(at, part)
        else:
            parts[at] = part
    return head + [line for part in parts for line in part]
