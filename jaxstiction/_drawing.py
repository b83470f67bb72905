"""The pictures' shared look: their resolution and size, the palette, and a figure
on its own Agg canvas, so that drawing never touches the user's matplotlib state
(no `pyplot`, no `matplotlib.use`, no `rcParams` edits) and needs no display."""

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure


DPI = 110
SIZE = (8.0, 4.5)  # inches; figures with two rows of panels are taller
C_MEAS = "0.15"
C_MODEL = "tab:red"
C_PAPER = "tab:blue"
C_CLEAN = "tab:green"
C_OPEN = "tab:red"
C_CLOSE = "tab:blue"
C_VAL = "gold"
BOX = dict(boxstyle="round,pad=0.4", facecolor="white", edgecolor="0.6", alpha=0.9)


def figure(size=SIZE) -> Figure:
    """A matplotlib `Figure` on its own Agg canvas (no `pyplot`, no global state)."""
    fig = Figure(figsize=size, dpi=DPI)
    FigureCanvasAgg(fig)
    return fig
