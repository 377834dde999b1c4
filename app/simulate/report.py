"""A simulation's numbers per mode: the table printed, the JSON written, the PNG plotted."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .users import Mode, UserLog

__all__ = ["plot", "summarise", "table"]


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
    """Small multiples: a row per transport; its latency distribution, and the blank share of
    the screen over the run (the spikes are first loads and jumps), a line per overscan and
    level of detail."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    transports = list(dict.fromkeys(mode.transport for mode, _ in runs))
    fig, axes = plt.subplots(len(transports), 2, figsize=(11, 2.6 * len(transports) + 0.8), squeeze=False)
    for mode, logs in runs:
        latency, blank = axes[transports.index(mode.transport)]
        # Colour says the margin, the line says the level of detail.
        style = {"color": "tab:orange" if mode.overscan == 0 else "tab:blue", "ls": "-" if mode.lod else "--"}
        label = f"overscan {mode.overscan:g}, LOD {'on' if mode.lod else 'off'}"
        times = np.sort([r[1] * 1e3 for log in logs for r in log.requests])
        if times.size:
            latency.plot(times, np.arange(1, times.size + 1) / times.size, label=label, **style)
        frames = sorted(f for log in logs for f in log.frames)
        if frames:
            t, share = np.array(frames).T
            window = max(1, len(share) // 300)  # the users' frames, averaged over ~1/300 of the run
            smooth = np.convolve(share, np.ones(window) / window, "valid") * 100
            blank.plot(t[window - 1 :], smooth, label=label, lw=1, **style)
    for row, transport in enumerate(transports):
        latency, blank = axes[row]
        latency.set_xscale("log")
        latency.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        latency.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        latency.set_ylim(0, 1.02)
        latency.set_ylabel(f"{transport}\nshare of answers")
        blank.set_ylabel("blank screen (%)")
        for ax in (latency, blank):
            ax.grid(alpha=0.3)
        latency.legend(fontsize=7, loc="lower right")
    axes[-1][0].set_xlabel("latency (ms, log scale): the share of answers at most this long")
    axes[-1][1].set_xlabel("seconds into the run")
    fig.suptitle("Vantage panning simulation: a row per transport")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
