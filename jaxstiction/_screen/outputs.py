"""The screen's files in a folder: `summary.csv`, one picture per loop and
`report.html`."""

from __future__ import annotations

import os
from pathlib import Path

from .html import write_html, write_summary_csv
from .screen import ScreenReport


def write_screen_outputs(report: ScreenReport, out_dir: str | os.PathLike) -> list[Path]:
    """Write `summary.csv`, one picture per loop (`loops/NAME.png`; with `--whatif`,
    one more per sticky loop, `whatif/NAME.png`) and a static `report.html` (ranked
    loops with verdict, band and thumbnails) into `out_dir`."""
    from .figure import write_screen_loop_figure  # matplotlib, only when pictures are written

    out = Path(out_dir)
    (out / "loops").mkdir(parents=True, exist_ok=True)
    written = [write_summary_csv(report.loops, out / "summary.csv")]
    for r in report.loops:
        if "figure" in r:
            r["picture"] = f"loops/{_safe(r['name'])}.png"
            written.append(write_screen_loop_figure(r, out / r["picture"]))
        if "whatif_figure" in r:  # `screen --whatif`: as is, repaired and compensated side by side
            from .._whatif.figure import write_whatif_figure

            r["whatif_picture"] = f"whatif/{_safe(r['name'])}.png"
            written.append(write_whatif_figure(r["name"], float(r.get("Ts") or 1.0), r["whatif_figure"],
                                               r["whatif"], out / r["whatif_picture"]))
    written.append(write_html(report, out / "report.html"))
    return written


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
