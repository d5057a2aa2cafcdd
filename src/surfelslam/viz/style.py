"""Shared look of every surfelslam figure: colours, sizes, line widths, DPI."""

from __future__ import annotations

# Colours (matplotlib's tab10 subset, readable in print and for common colour-blindness types).
GT_COLOR = "#444444"  # ground truth: dark grey, dashed
EST_COLOR = "#1f77b4"  # estimate: blue
ERROR_COLOR = "#d62728"  # errors: red
SECONDARY_COLOR = "#ff7f0e"  # a second error series (RPE): orange
LOOP_COLOR = "#2ca02c"  # loop-closure edges: green
START_COLOR = "#2ca02c"
END_COLOR = "#9467bd"

GT_LINESTYLE = "--"
LINE_WIDTH = 1.2
THIN_LINE_WIDTH = 0.8
MARKER_SIZE = 12

DPI = 120
#: zlib level of the PNGs: 3 writes a 1600x1200 map figure in half the time of the default 6, about 10 % larger
PNG_COMPRESS_LEVEL = 3
TRAJECTORY_FIGSIZE_IN = (12.0, 6.5)  # top view + 3 time panels
ERRORS_FIGSIZE_IN = (10.0, 5.0)
#: Fixed margins (figure fractions) of the trajectory and ATE-error figures, instead of ``tight_layout`` (which lays
#: every tick label out once more: about a sixth of these figures' CPU). They are what ``tight_layout`` chose for
#: 300-frame runs (room300, TUM teddy), with room for tick labels a character or two wider.
TRAJECTORY_LAYOUT = {"left": 0.066, "right": 0.9875, "bottom": 0.088, "top": 0.9, "wspace": 0.15, "hspace": 0.122}
ERRORS_LAYOUT = {"left": 0.105, "right": 0.985, "bottom": 0.11, "top": 0.905, "hspace": 0.25}
TITLE_FONTSIZE = 11
LABEL_FONTSIZE = 9
GRID_ALPHA = 0.3
