"""A simulation's numbers per mode: the table printed, the JSON written, the PNG plotted."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .users import ANSWERS, Mode, Sent, UserLog

__all__ = ["kinds_table", "plot", "summarise", "table"]


def _pct(values: np.ndarray, q: float) -> float | None:
    return float(np.percentile(values, q)) if values.size else None


def summarise(mode: Mode, logs: list[UserLog], seconds: float) -> dict[str, Any]:
    """One mode's figures over all its users. ``requests``, latency and ``bytes_per_request``
    are of answers (viewport, diff, stream: what a moved screen waits for); tile fetches are
    counted in ``by_route`` and ``by_kind``, and in the bytes on the wire."""
    sent = [r for log in logs for r in log.requests]
    requests = [r for r in sent if r.route in ANSWERS]
    frames = np.array([blank for log in logs for _, blank in log.frames]) if logs else np.zeros(0)
    latency = np.array([r.latency for r in requests]) * 1e3
    drawn = np.array([r.drawn for r in requests if r.drawn is not None]) * 1e3
    sizes = np.array([r.size for r in requests])
    wire = sum(r.wire for r in sent)

    def pct(q: float) -> float | None:
        return _pct(latency, q)

    return {
        "mode": mode.name,
        "transport": mode.transport,
        "overscan": mode.overscan,
        "lod": mode.lod,
        "tiles": mode.tiles,
        "users": len(logs),
        "users_zooming_out": sum(log.zooms_out for log in logs),
        "requests": len(requests),
        "requests_per_s": len(requests) / seconds,
        "by_route": {route: sum(r.route == route for r in sent) for route in sorted({r.route for r in sent})},
        "by_kind": {
            route: _kind([r for r in sent if r.route == route], seconds)
            for route in sorted({r.route for r in sent})
        },
        "latency_ms": {"p50": pct(50), "p95": pct(95), "p99": pct(99), "max": pct(100)},
        # until the answer and the tiles it named were in: the screen drawn
        "drawn_ms": {"p50": _pct(drawn, 50), "p99": _pct(drawn, 99)},
        "bytes_per_request": float(sizes.mean()) if sizes.size else None,
        "bytes_per_s": float(sizes.sum() / seconds),
        "wire_bytes": wire,  # every request's body as it came, tiles included
        "wire_bytes_per_s": wire / seconds,
        "wire_bytes_per_answer": wire / len(requests) if requests else None,
        "tiles_needed": sum(log.tiles_needed for log in logs),  # under the screen, as it changed
        "tiles_held": sum(log.tiles_held for log in logs),  # needed, held already: not fetched
        "tiles_empty": sum(log.tiles_empty for log in logs),  # fetched, holding no aggregate
        "bands": _bands(requests),
        "entered_mean": float(np.mean([r.entered for r in requests])) if requests else None,
        "left_mean": float(np.mean([r.left for r in requests])) if requests else None,
        "errors": sum(len(log.errors) for log in logs),
        "error_samples": [e for log in logs for e in log.errors][:5],
        "frames": int(frames.size),
        "blank_mean": float(frames.mean()) if frames.size else None,
        "blank_p95": float(np.percentile(frames, 95)) if frames.size else None,
        "frames_with_blank": float((frames > 0).mean()) if frames.size else None,
    }


def _kind(sent: list[Sent], seconds: float) -> dict[str, Any]:
    """One kind of request's figures."""
    latency = np.array([r.latency for r in sent]) * 1e3
    wire = sum(r.wire for r in sent)
    return {
        "requests": len(sent),
        "per_s": len(sent) / seconds,
        "latency_ms": {"p50": _pct(latency, 50), "p99": _pct(latency, 99)},
        "bytes": sum(r.size for r in sent),
        "wire_bytes": wire,
        "wire_bytes_per_request": wire / len(sent) if sent else None,
        "wire_bytes_per_s": wire / seconds,
    }


def _bands(answers: list[Sent]) -> dict[str, int]:
    """Answers per band they showed ("none": exact, no level of detail), finest first."""
    bands = sorted({r.band for r in answers}, key=lambda b: -np.inf if b is None else b)
    return {"none" if b is None else str(b): sum(r.band == b for r in answers) for b in bands}


def _num(value: float | None, fmt: str = ",.1f") -> str:
    return "–" if value is None else format(value, fmt)


def table(rows: list[dict[str, Any]]) -> str:
    """The Markdown table a person reads first: answers (req/s, latency, bytes/req); ``drawn``,
    until an answer's tiles were in too; ``wire bytes/req``, every body on the wire, tiles
    included, per answer."""
    num = _num
    lines = [
        "| mode | req/s | p50 ms | p95 ms | p99 ms | max ms | drawn p99 ms | bytes/req | wire bytes/req "
        "| entered | left | errors | blank mean | blank p95 | frames with blank |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lat = r["latency_ms"]
        lines.append(
            f"| {r['mode']} | {num(r['requests_per_s'])} | {num(lat['p50'])} | {num(lat['p95'])} | {num(lat['p99'])} "
            f"| {num(lat['max'])} | {num(r['drawn_ms']['p99'])} | {num(r['bytes_per_request'], ',.0f')} "
            f"| {num(r['wire_bytes_per_answer'], ',.0f')} | {num(r['entered_mean'])} "
            f"| {num(r['left_mean'])} | {r['errors']} | {num(r['blank_mean'], '.2%')} | {num(r['blank_p95'], '.1%')} "
            f"| {num(r['frames_with_blank'], '.1%')} |"
        )
    return "\n".join(lines)


def kinds_table(rows: list[dict[str, Any]]) -> str:
    """Each mode's requests by kind (viewport, diff, stream, tile): counts, latency, and the
    bytes of their bodies on the wire."""
    num = _num
    lines = [
        "| mode | kind | requests | per s | p50 ms | p99 ms | wire bytes/req | wire MB | wire MB/s |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        for kind, k in r["by_kind"].items():
            lat = k["latency_ms"]
            lines.append(
                f"| {r['mode']} | {kind} | {k['requests']:,} | {num(k['per_s'])} | {num(lat['p50'])} "
                f"| {num(lat['p99'])} | {num(k['wire_bytes_per_request'], ',.0f')} "
                f"| {num(k['wire_bytes'] / 1e6, ',.2f')} | {num(k['wire_bytes_per_s'] / 1e6, ',.2f')} |"
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
        times = np.sort([r.latency * 1e3 for log in logs for r in log.requests if r.route in ANSWERS])
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
