"""Colours, names and texts the panels share (no state): joint colours by finger chain, short
joint labels, the joint list's option text, the help page."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .hotkeys import hotkey_table_markdown

STATIC = Path(__file__).resolve().parents[2] / "static"
#: radius (scene metres) of a joint sphere
JOINT_RADIUS_M = 0.0045


def load_colours() -> dict[str, Any]:
    try:
        return json.loads((STATIC / "colours.json").read_text())
    except (OSError, ValueError):
        return {
            "root": [240, 240, 240],
            "chains": [
                [230, 60, 60],
                [240, 160, 40],
                [70, 190, 80],
                [60, 140, 230],
                [190, 80, 220],
            ],
            "selected": [255, 255, 0],
            "handle_2d": [255, 255, 255],
            "occluded_mix": 0.35,
        }


def joint_colours(parents: np.ndarray, colours: dict[str, Any]) -> np.ndarray:
    """(J, 3) uint8: the root in ``root`` colour, each subtree of the root in its chain colour."""
    parents = np.asarray(parents)
    out = np.zeros((len(parents), 3), np.uint8)
    chains = colours["chains"]
    root_children = [int(c) for c in np.flatnonzero(parents == np.flatnonzero(parents < 0)[0])]
    for j in range(len(parents)):
        k = j
        while parents[k] >= 0 and k not in root_children:
            k = int(parents[k])
        out[j] = colours["root"] if parents[j] < 0 else chains[root_children.index(k) % len(chains)]
    return out


def short_name(name: str) -> str:
    """'index_tip' -> 'I-tip'; used for labels."""
    if "_" not in name:
        return name
    finger, part = name.split("_", 1)
    return f"{finger[0].upper()}-{part}"


def joint_option(names: list[str], k: int) -> str:
    """'4 I-tip (index_tip)': the *Joint* list shows the 3D label's name next to the full one."""
    name = names[k]
    short = short_name(name)
    return f"{k} {short} ({name})" if short != name else f"{k} {name}"


def load_help_markdown() -> str:
    try:
        return (STATIC / "help.md").read_text()
    except OSError:
        return "## Hotkeys\n\n" + hotkey_table_markdown()


def joint_legend(names: list[str], colours: np.ndarray, annotation: Any, selected: int) -> str:
    """HTML legend of the joints: each joint's colour (as drawn), its label and full name, and
    whether it is placed (● placed, ◐ an accepted guess, ⊘ marked outside the image, ○ not yet),
    occluded (greyed, "occluded") or selected (bold)."""
    rows = []
    for k, name in enumerate(names):
        r, g, b = (int(c) for c in colours[k])
        placed = bool(annotation.annotated[k])
        outside = bool(annotation.outside[k])
        occluded = not bool(annotation.visible[k]) and not outside
        mark = ("◐" if annotation.accepted[k] else "●") if placed else "⊘" if outside else "○"
        style = "opacity:0.45;" if occluded or outside else ""
        weight = "font-weight:bold;" if k == selected else ""
        note = " occluded" if occluded else " outside the image" if outside else ""
        rows.append(
            f'<tr style="{style}{weight}"><td style="color:rgb({r},{g},{b})">{mark}</td>'
            f"<td>{k}</td><td>{short_name(name)}</td><td>{name}{note}</td></tr>"
        )
    return (
        '<table class="handanno-legend" style="font-size:0.8em">'
        + "".join(rows)
        + "</table><div style='font-size:0.75em'>● placed · ◐ accepted guess (a drag places it "
        "yourself; the lift trusts it less) · ⊘ outside the image · ○ not placed (drawn as a "
        "small faded guess) · faded row / grey sphere: occluded · bold: selected</div>"
    )


def hand_diagram_svg(
    xy: np.ndarray,
    bones: np.ndarray,
    colours: np.ndarray,
    annotation: Any,
    selected: int,
    size_px: int = 160,
) -> str:
    """An SVG hand diagram: joints at ``xy`` (J, 2) (any unit, y down: a template hand seen from
    the camera) joined by ``bones`` (B, 2), each joint in its colour, filled when placed, hollow
    when not, faded when occluded, the selected one ringed and labelled. Shows where each joint
    goes and which are placed."""
    xy = np.asarray(xy, dtype=np.float64)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    scale = (size_px - 24) / max(float((hi - lo).max()), 1e-9)
    p = (xy - lo) * scale + 12
    parts = [
        f'<line x1="{p[a, 0]:.1f}" y1="{p[a, 1]:.1f}" x2="{p[b, 0]:.1f}" y2="{p[b, 1]:.1f}" '
        'stroke="#999" stroke-width="1.5"/>'
        for a, b in np.asarray(bones)
    ]
    for k in range(len(p)):
        r, g, b = (int(c) for c in colours[k])
        colour = f"rgb({r},{g},{b})"
        fill = colour if annotation.annotated[k] else "none"
        opacity = "0.4" if not annotation.visible[k] else "1"
        parts.append(
            f'<circle class="joint-{k}" cx="{p[k, 0]:.1f}" cy="{p[k, 1]:.1f}" r="4" '
            f'fill="{fill}" stroke="{colour}" stroke-width="1.5" opacity="{opacity}"/>'
        )
    s = int(selected)
    parts.append(
        f'<circle cx="{p[s, 0]:.1f}" cy="{p[s, 1]:.1f}" r="7" fill="none" stroke="#222" '
        'stroke-width="1.5"/>'
    )
    return (
        f'<svg class="handanno-hand" width="{size_px}" height="{size_px}" '
        f'viewBox="0 0 {size_px} {size_px}">' + "".join(parts) + "</svg>"
    )
