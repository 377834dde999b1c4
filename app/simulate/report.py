"""A simulation's numbers per mode: the table printed, the JSON written, the PNG plotted."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .users import Mode, UserLog

__all__ = ["plot", "summarise", "table"]

COLOURS = {"poll": "tab:red", "diff": "tab:blue", "stream": "tab:green"}


def summarise(mode: Mode, logs: list[UserLog], seconds: float) -> dict[str, Any]:
    """One mode's figures over all its users."""
    requests = [r for log in logs for r in log.requests]
    frames = np.array([blank for log in logs for _, blank in log.frames]) if logs else np.zeros(0)
    latency = np.array([r[1] for r in requests]) * 1e3
    sizes = np.array([r[2] for r in requests])

    def pct(q: float) -> float | None:
        return float(np.percentile(latency, q)) if latency.size else None

    return {
        "mode": mode.name,
        "transport": mode.transport,
        "overscan": mode.overscan,
        "lod": mode.lod,
        "users": len(logs),
        "requests": len(requests),
        "requests_per_s": len(requests) / seconds,
        "by_route": {
            route: sum(r[5] == route for r in requests) for route in sorted({r[5] for r in requests})
        },
        "latency_ms": {"p50": pct(50), "p95": pct(95), "p99": pct(99), "max": pct(100)},
        "bytes_per_request": float(sizes.mean()) if sizes.size else None,
        "bytes_per_s": float(sizes.sum() / seconds),
        "entered_mean": float(np.mean([r[3] for r in requests])) if requests else None,
        "left_mean": float(np.mean([r[4] for r in requests])) if requests else None,
        "errors": sum(len(log.errors) for log in logs),
        "error_samples": [e for log in logs for e in log.errors][:5],
        "frames": int(frames.size),
        "blank_mean": float(frames.mean()) if frames.size else None,
        "blank_p95": float(np.percentile(frames, 95)) if frames.size else None,
        "frames_with_blank": float((frames > 0).mean()) if frames.size else None,
    }


def table(rows: list[dict[str, Any]]) -> str:
    """The Markdown table a person reads first."""

    def num(value: float | None, fmt: str = ",.1f") -> str:
        return "–" if value is None else format(value, fmt)

    lines = [
        "| mode | req/s | p50 ms | p95 ms | p99 ms | max ms | bytes/req | entered | left | errors "
        "| blank mean | blank p95 | frames with blank |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lat = r["latency_ms"]
        lines.append(
            f"| {r['mode']} | {num(r['requests_per_s'])} | {num(lat['p50'])} | {num(lat['p95'])} | {num(lat['p99'])} "
            f"| {num(lat['max'])} | {num(r['bytes_per_request'], ',.0f')} | {num(r['entered_mean'])} "
            f"| {num(r['left_mean'])} | {r['errors']} | {num(r['blank_mean'], '.2%')} | {num(r['blank_p95'], '.1%')} "
            f"| {num(r['frames_with_blank'], '.1%')} |"
        )
    return "\n".join(lines)


def plot(runs: list[tuple[Mode, list[UserLog]]], path: Path) -> None:
    """Latency over time and blank area over time, one line per mode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, bottom) = plt.subplots(2, 1, figsize=(11, 7), sharex=True)
    for mode, logs in runs:
        # Colour says the transport, the line says the overscan, paleness says LOD off.
        style = {"color": COLOURS[mode.transport], "alpha": 1.0 if mode.lod else 0.45}
        requests = sorted(r[:2] for log in logs for r in log.requests)
        if requests:
            t, latency = np.array(requests).T
            top.plot(
                t, latency * 1e3, "." if mode.overscan else "x", markersize=2.5, label=mode.name, **style
            )
        frames = sorted(f for log in logs for f in log.frames)
        if frames:
            t, blank = np.array(frames).T
            window = max(1, len(blank) // 200)  # smooth over ~1/200 of the run
            smooth = np.convolve(blank, np.ones(window) / window, "valid") * 100
            bottom.plot(t[window - 1 :], smooth, "-" if mode.overscan else ":", label=mode.name, **style)
    top.set_ylabel("latency (ms)")
    top.set_yscale("log")
    top.legend(fontsize=7, ncol=2)
    bottom.set_ylabel("blank share of the screen (%)")
    bottom.legend(fontsize=7, ncol=2)
    bottom.set_xlabel("seconds into the run")
    fig.suptitle("Vantage panning simulation")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
