"""The panel's statistics (markdown), and the panel laid over a standalone HTML page."""

from __future__ import annotations

import html
import re

from .levels import Caps, fmt

__all__ = ["html_panel", "stats_markdown", "with_panel"]


def stats_markdown(snap: dict, drawn: dict, caps: Caps) -> str:
    """The statistics of the maps (``snap``: see :meth:`LevelCache.take`) and of what is drawn."""
    if snap.get("g") is None:
        return "No map loaded."
    st = snap["stats"]
    f = drawn["factor"]
    lines = [
        (
            f"**Map**: {'NDT-OM' if st['occupancy'] else 'Recursive NDT'}, "
            f"{snap['resolution']:g} m{' (native)' if f == 1 else f' ({f}x coarser)'}"
        ),
        f"**Scans**: {fmt(st['scans'])}, {fmt(st['points'])} points",
        (
            f"**Gaussians**: {fmt(drawn['gaussians_total'])} with p > {snap['threshold']:.2f}"
            + (f" between {drawn['clip'][0]:.2f} and {drawn['clip'][1]:.2f} m" if drawn.get("clip") else "")
            + f", {fmt(drawn['gaussians'])} drawn as {drawn['geometry']}"
        ),
        (
            f"**Level of detail** (auto): ellipsoids up to {fmt(caps.ellipsoids)} Gaussians, "
            f"splats up to {fmt(caps.splats)}, then a coarser level"
        ),
    ]
    if "known" in snap:
        lines.append(
            f"**Cells**: {fmt(snap['known'])} known, {fmt(snap['n_occupied'])} occupied "
            f"(p > {snap['threshold']:.2f}), {fmt(snap['n_free'])} free"
        )
    lines.append(
        f"**Free cells** drawn at most {fmt(caps.free_cells)}, occupied cells at most {fmt(caps.occupied_cells)}"
    )
    cs = snap.get("compare_stats")
    if cs is not None:
        if cs.get("gaussians") is None:
            lines.append("**Recursive NDT**: loaded (turn on *Conflicting cells* to compare)")
        else:
            lines.append(
                f"**Recursive NDT**: {fmt(cs['gaussians'])} Gaussians; **{fmt(cs['conflicts'])} conflicting cells**"
            )
    lines.append(f"**Memory**: {st['memory'] / 2**20:.1f} MiB")
    fo = snap.get("frame_origin")
    if fo is not None:
        lines.append(
            f"**Frame origin**: ({fo[0]:.2f}, {fo[1]:.2f}, {fo[2]:.2f}) m of the poses' frame is the map's "
            "(0, 0, 0); positions and heights here are the map's"
        )
    for note in drawn["notes"]:
        lines.append(f"**Note**: {note}")
    return "  \n".join(lines)


def _md_html(text: str) -> str:
    """The panel's markdown (``**bold**``, ``*italic*``, hard line breaks) as HTML."""
    out = html.escape(str(text))
    out = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", out)
    out = re.sub(r"\*(.+?)\*", r"<i>\1</i>", out)
    return out.replace("  \n", "<br>").replace("\n", "<br>")


def html_panel(label: str, legend: str, stats: str) -> str:
    """The legend (HTML) and statistics (markdown, ending with the notes) as one block of HTML."""
    return (
        '<details id="ndtom-panel" open style="position:fixed;top:8px;right:8px;z-index:1000;width:300px;'
        "max-height:90vh;overflow:auto;background:rgba(255,255,255,0.92);border:1px solid #ccc;"
        'border-radius:6px;padding:6px 8px;font:13px/1.4 sans-serif;color:#222">'
        f"<summary><b>{html.escape(label)}</b></summary>{legend}"
        f'<div style="font-size:0.85em;margin-top:4px">{_md_html(stats)}</div></details>'
    )


def with_panel(page: str, panel: str) -> str:
    """``page`` (viser's standalone HTML) with ``panel`` laid over the scene."""
    end = page.rfind("</body>")
    return page + panel if end < 0 else page[:end] + panel + page[end:]
