"""Trade 5: the overscan margin, measured end to end with the panning simulator (app.simulate)."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from .report import kb, md_table, pct, pyplot, save

ROOT = Path(__file__).resolve().parents[2]  # the repository: the simulator runs from there


OVERSCANS = (0.0, 0.1, 0.25, 0.5, 1.0)
SIM_PAGES, SIM_USERS, SIM_SECONDS = 200, 4, 4.0
BYTES_SLACK = 0.10  # the recommended margin may cost this much more bytes/s than none ...
BLANK_SLACK = 0.005  # ... and show blank in this many more frames than the best such margin


def simulate_command(out: str, seconds: float, seed: int) -> list[str]:
    return [
        sys.executable,
        "-m",
        "app.simulate",
        "--spawn",
        "--pages",
        str(SIM_PAGES),
        "--seconds",
        f"{seconds:g}",
        "--users",
        str(SIM_USERS),
        "--modes",
        "stream",
        "--lod",
        "on",
        "--overscan",
        ",".join(f"{m:g}" for m in OVERSCANS),
        "--seed",
        str(seed),
        "--out",
        out,
    ]


def trade_overscan(seconds: float, seed: int) -> tuple[list[dict[str, Any]], str]:
    """The simulator's per-mode summaries (see app/simulate/report.py) and the command line run."""
    with tempfile.TemporaryDirectory(prefix="tradeoffs-sim-") as tmp:
        cmd = simulate_command(tmp, seconds, seed)
        shown = shlex.join([".venv/bin/python", *cmd[1:-1], "<tmp>"])
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
        if done.returncode:
            raise SystemExit(f"FATAL: the simulator failed ({done.returncode}):\n{done.stderr[-3000:]}")
        result = json.loads((Path(tmp) / "result.json").read_text())
    return sorted(result["modes"], key=lambda m: m["overscan"]), shown


def section_overscan(modes: list[dict[str, Any]], command: str, seconds: float, plot: str) -> list[str]:
    def ms(value: float | None) -> str:
        return "–" if value is None else f"{value:,.1f}"

    table = md_table(
        [
            "overscan",
            "requests/s",
            "bytes/request",
            "KB/s",
            "latency p50 ms",
            "latency p95 ms",
            "entered/request",
            "blank mean",
            "blank p95",
            "frames with blank",
            "errors",
        ],
        [
            [
                f"{m['overscan']:g}",
                f"{m['requests_per_s']:,.1f}",
                f"{m['bytes_per_request'] or 0:,.0f}",
                kb(m["bytes_per_s"]),
                ms(m["latency_ms"]["p50"]),
                ms(m["latency_ms"]["p95"]),
                f"{m['entered_mean'] or 0:,.1f}",
                pct(m["blank_mean"] or 0, 2),
                pct(m["blank_p95"] or 0),
                pct(m["frames_with_blank"] or 0),
                str(m["errors"]),
            ]
            for m in modes
        ],
        "rrrrrrrrrrr",
    )
    return [
        "## 5. Overscan margin",
        "",
        "The client asks for the screen grown by a margin on each side (a share of the screen) and asks "
        "again only when the screen nears the margin's edge; a bigger margin means fewer, larger "
        "requests and less blank screen while an answer is on its way. Measured end to end with the "
        f"panning simulator: a spawned server with a generated {SIM_PAGES}-page document, {SIM_USERS} "
        f"virtual users scrolling, flinging, zooming and jumping at 60 frames/s for {seconds:g} s per "
        "margin, over the WebSocket stream with level of detail on (min_px 1):",
        "",
        f"    {command}",
        "",
        "Blank is the share of the screen outside the last rect the client received, per frame; "
        "*frames with blank* is the share of frames showing any. What stays blank at large margins "
        "is the first frames before the first answer and jumps to a far item, which no margin "
        "covers. Bytes are the stream's actual JSON; the simulator's screen is 1280x800.",
        "",
        *table,
        "",
        f"![overscan margin]({plot})",
        "",
    ]


def plot_overscan(modes: list[dict[str, Any]], path: Path) -> None:
    plt = pyplot()
    fig, (req, traffic, blank) = plt.subplots(1, 3, figsize=(14, 4.2))
    margins = [m["overscan"] for m in modes]
    req.plot(margins, [m["requests_per_s"] for m in modes], "o-", color="tab:blue")
    req.set_ylabel("requests per second (all users)")
    req.set_title("requests")
    traffic.plot(margins, [m["bytes_per_s"] / 1e3 for m in modes], "o-", color="tab:green", label="KB/s")
    traffic.set_ylabel("KB per second (all users)")
    traffic.set_ylim(bottom=0)
    per_request = traffic.twinx()
    per_request.plot(
        margins,
        [(m["bytes_per_request"] or 0) / 1e3 for m in modes],
        "s--",
        color="tab:gray",
        label="KB per request",
    )
    per_request.set_ylabel("KB per request")
    per_request.set_ylim(bottom=0)
    traffic.legend(handles=traffic.lines + per_request.lines, fontsize=8)
    traffic.set_title("bytes")
    blank.plot(
        margins,
        [100 * (m["blank_mean"] or 0) for m in modes],
        "o-",
        color="tab:red",
        label="blank share of the screen (mean)",
    )
    blank.set_ylabel("blank share of the screen, mean over frames (%)")
    blank.set_ylim(bottom=0)
    frames = blank.twinx()
    frames.plot(
        margins,
        [100 * (m["frames_with_blank"] or 0) for m in modes],
        "s--",
        color="tab:orange",
        label="frames showing any blank",
    )
    frames.set_ylabel("frames showing any blank (%)")
    frames.set_ylim(bottom=0)
    blank.legend(handles=blank.lines + frames.lines, fontsize=8)
    blank.set_title("blank screen")
    for ax in (req, traffic, blank):
        ax.set_xlabel("overscan margin (share of the screen per side)")
        ax.grid(alpha=0.3)
    fig.suptitle("Overscan margin: requests and bytes against blank screen (stream, LOD on)")
    save(fig, path)


def pick_overscan(modes: list[dict[str, Any]]) -> dict[str, Any]:
    """The smallest margin within BLANK_SLACK of the fewest blank frames, among those whose bytes/s
    stay within BYTES_SLACK of no margin's: blank is what a person sees, bytes/s what it costs."""
    zero = modes[0]
    cheap = [m for m in modes if m["bytes_per_s"] <= (1 + BYTES_SLACK) * zero["bytes_per_s"]] or [zero]
    fewest = min(m["frames_with_blank"] or 0 for m in cheap)
    return next(m for m in cheap if (m["frames_with_blank"] or 0) <= fewest + BLANK_SLACK)


def advise_overscan(modes: list[dict[str, Any]]) -> str:
    m, zero = pick_overscan(modes), modes[0]
    return (
        f"**overscan {m['overscan']:g}**: the smallest margin within {pct(BLANK_SLACK)} of the fewest frames "
        f"with blank among margins costing at most {pct(BYTES_SLACK, 0)} more bytes/s than none: "
        f"{pct(m['frames_with_blank'] or 0)} of frames show blank (vs {pct(zero['frames_with_blank'] or 0)} with "
        f"no margin), {m['requests_per_s']:,.0f} requests/s instead of {zero['requests_per_s']:,.0f}, "
        f"{kb(m['bytes_per_s'])} KB/s instead of {kb(zero['bytes_per_s'])}, but {kb(m['bytes_per_request'] or 0)} "
        f"KB per request instead of {kb(zero['bytes_per_request'] or 0)} (measured on a long document)."
    )


def overscan_elsewhere(modes: list[dict[str, Any]]) -> str:
    zero, last = modes[0], modes[-1]
    area = (1 + 2 * last["overscan"]) ** 2
    return (
        f"On the document, bytes/s go from {kb(zero['bytes_per_s'])} KB/s at margin 0 to "
        f"{kb(last['bytes_per_s'])} at {last['overscan']:g} ({last['bytes_per_s'] / zero['bytes_per_s']:.2f}x), "
        f"far less than the {area:g}x area each request covers: the stream sends each item once, as it enters. "
        f"What grows is the burst: a jump or a zoom fetches the whole grown rect, (1 + 2 x margin)^2 "
        f"screens of items ({kb(zero['bytes_per_request'] or 0)} -> {kb(last['bytes_per_request'] or 0)} KB "
        "per request here). The simulator runs a long document only; on a whiteboard or a dense canvas, "
        "with more items per screen (trade 2's exact column), those bursts grow in proportion, so "
        "prefer the smaller of the margins that clear the blank there."
    )
