"""What every format module shares: the source it reads, the error it raises, box geometry."""

from __future__ import annotations

import math
import multiprocessing
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec

from ..items import bad_utf8

__all__ = [
    "ImportFailed",
    "Matrix",
    "Source",
    "apply",
    "bounds",
    "compose",
    "json_of",
    "processes",
    "rotated",
]

MAX_PROCESSES = 4  # processes a file is read by, at most


class ImportFailed(Exception):
    """A file cannot be imported; the message names the file, where in it, and the fix."""


@dataclass
class Source:
    """A file being read, and how: what the format modules get."""

    path: Path
    size: int
    columns: int = 1  # PDF pages side by side
    done: int = 0  # bytes read so far (an estimate for formats read whole)
    max_data_bytes: int = 4096  # the largest ``data`` (VANTAGE_MAX_DATA_BYTES), for modules that check
    scratch: Path | None = None  # where a module's processes may write files (None: the system's temp)

    @classmethod
    def of(cls, path: Path, **options: Any) -> Source:
        try:
            return cls(path, path.stat().st_size, **options)
        except OSError as error:
            raise ImportFailed(f"{path}: cannot read it ({error.strerror or error})") from None


def processes() -> int:
    """How many processes may read one file: one a core, at most ``MAX_PROCESSES``; 1 where
    a process cannot be forked (nothing to import again in each)."""
    if "fork" not in multiprocessing.get_all_start_methods():
        return 1
    return min(os.cpu_count() or 1, MAX_PROCESSES)


def json_of(source: Source, fix: str) -> Any:
    """The file's JSON value (after a UTF-8 byte order mark, if any).

    :raises ImportFailed: saying why it cannot be read, then ``fix``
    """
    data = source.path.read_bytes().removeprefix(b"\xef\xbb\xbf")
    try:
        return msgspec.json.decode(data)
    except (msgspec.DecodeError, UnicodeDecodeError) as error:
        bad = bad_utf8(data, error)
        why = f"not UTF-8 (a string holds the {bad})" if bad else f"not valid JSON ({error})"
    except RecursionError:
        why = "nested too deeply to read (arrays or objects over a thousand levels within each other)"
    raise ImportFailed(f"{why}: {fix}")


def bounds(points: Iterable[tuple[float, float]]) -> tuple[float, float, float, float]:
    """The axis-aligned box around ``points`` (at least one).

    >>> bounds([(3, 1), (-1, 4), (2, 2)])
    (-1, 1, 3, 4)
    """
    xs, ys = zip(*points, strict=True)
    return min(xs), min(ys), max(xs), max(ys)


def rotated(
    points: Iterable[tuple[float, float]], angle: float, cx: float, cy: float
) -> list[tuple[float, float]]:
    """``points`` turned by ``angle`` radians about ``(cx, cy)``, clockwise on a canvas whose
    y grows downward (as Excalidraw and tldraw turn them).

    >>> [tuple(round(v, 9) for v in p) for p in rotated([(1, 0)], math.pi / 2, 0, 0)]
    [(0.0, 1.0)]
    """
    if not angle:
        return list(points)
    c, s = math.cos(angle), math.sin(angle)
    return [(cx + (x - cx) * c - (y - cy) * s, cy + (x - cx) * s + (y - cy) * c) for x, y in points]


Matrix = tuple[float, float, float, float, float, float]  # a, b, c, d, e, f: x' = a x + c y + e


def compose(m: Matrix, n: Matrix) -> Matrix:
    """The transform that applies ``n``, then ``m`` (PDF's and tldraw's affine matrices).

    >>> compose((1, 0, 0, 1, 10, 0), (2, 0, 0, 2, 0, 0))  # scale by 2, then move right 10
    (2, 0, 0, 2, 10, 0)
    """
    a, b, c, d, e, f = m
    a2, b2, c2, d2, e2, f2 = n
    return (
        a * a2 + c * b2,
        b * a2 + d * b2,
        a * c2 + c * d2,
        b * c2 + d * d2,
        a * e2 + c * f2 + e,
        b * e2 + d * f2 + f,
    )


def apply(m: Matrix, point: tuple[float, float]) -> tuple[float, float]:
    """``point`` transformed by ``m``.

    >>> apply((2, 0, 0, 2, 10, 0), (1, 1))
    (12, 2)
    """
    x, y = point
    return m[0] * x + m[2] * y + m[4], m[1] * x + m[3] * y + m[5]
