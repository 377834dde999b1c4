"""The report's closing section: each trade's advice, per scene type."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from .exact import ExactRow, advise_exact
from .float32 import CoordRow, SceneCoordRow, advise_coords
from .lod import LodRow, advise_lod
from .overscan import advise_overscan, overscan_elsewhere
from .scene import Scene
from .shape import ShapeRow, advise_shape


@dataclass
class Results:
    scenes: list[Scene]
    exact: list[ExactRow]
    lod: list[LodRow]
    coords: list[CoordRow]
    coords_scenes: list[SceneCoordRow]
    shape: list[ShapeRow]
    overscan: list[dict[str, Any]]


def section_recommendations(res: Results) -> list[str]:
    names = {
        "doc": "Long document",
        "whiteboard": "Whiteboard",
        "clustered": "Clustered board",
        "uniform": "Uniform / dense",
    }
    lines = [
        "## Recommendations",
        "",
        "Rules of thumb from the tables above, per scene type; rerun this script after changing "
        "the index and they follow the new numbers.",
        "",
    ]
    for scene in res.scenes:
        lines.append(f"**{names[scene.key]}** ({scene.title}, {len(scene.boxes):,} items)")
        lines.append("")
        exact = next((r for r in res.exact if r.scene is scene), None)
        lod = [r for r in res.lod if r.scene is scene]
        shape = [r for r in res.shape if r.scene is scene]
        if exact:
            lines.append(f"- exact vs candidates: {advise_exact(exact)}")
        if lod:
            lines.append(f"- level of detail: {advise_lod(lod)}")
        coords = next((r for r in res.coords_scenes if r.scene is scene), None)
        if coords:
            lines.append(f"- coordinates: {advise_coords(coords, res.coords)}")
        if shape:
            lines.append(f"- tree shape: {advise_shape(shape)}")
        if res.overscan and scene.key == "doc":
            lines.append(f"- overscan: {advise_overscan(res.overscan)}")
        lines.append("")
    if res.overscan and any(s.key != "doc" for s in res.scenes):
        lines += [overscan_elsewhere(res.overscan), ""]
    return lines
