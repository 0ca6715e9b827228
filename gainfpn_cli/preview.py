"""preview.png: the gain map as a person reads it (matplotlib, drawn off-screen).

The gain map in percent with its colour bar, the confidence map beside it, the
unestimated pixels in a legend colour, a labelled histogram of k, and a title
that says which burst, which models, the PRNU measured before and the residual
predicted after correction, and what the hold-out frame said.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError
from .metrics import robust_spread
from .report import Report
from .summary import after_text, holdout_text, prnu_text

#: Longest side (px) of the maps shown; a longer map is shown on every n-th pixel (not averaged,
#: so that the pixel-level pattern stays visible).
PREVIEW_PX = 1024
#: Colour of the pixels that could not be estimated (k = 1, confidence 0).
UNESTIMATED = "#b0b0b0"


def write_preview(path: Path, k: np.ndarray, confidence: np.ndarray, *, report: Report, name: str,
                  cfa: str | None = None, channels: tuple[str, ...] = ("Y",)) -> None:
    """Draw the first plane of ``k`` ``(H, W, C)`` and its confidence into ``path`` (PNG).

    ``report`` is the estimate's report (models, PRNU, predicted residual, hold-out); ``name``
    names the burst in the title.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import colors
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    deviation, conf, step = shown(k, confidence)
    est = conf > 0
    values = deviation[est]
    spread = 100.0 * robust_spread(1.0 + values / 100.0) if values.size else 0.0  # of k, relative
    limit = max(3.0 * spread, 0.05)  # +-3 robust sigma; 0.05 % for a flat map (k = 1)

    fig = Figure(figsize=(13.0, 4.8), dpi=100)  # placed by hand: a constrained layout takes twice as long
    grid = fig.add_gridspec(1, 3, width_ratios=[1.0, 1.0, 0.8], left=0.02, right=0.97, top=0.8, bottom=0.14,
                            wspace=0.25)
    gain_ax, conf_ax, hist_ax = (fig.add_subplot(grid[0, i]) for i in range(3))
    plane = "mosaic" if cfa else channels[0]
    sub = f", every {_ordinal(step)} pixel" if step > 1 else ""

    cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad=UNESTIMATED)
    image = gain_ax.imshow(np.ma.masked_array(deviation, ~est), cmap=cmap, vmin=-limit, vmax=limit,
                           interpolation="nearest")
    fig.colorbar(image, ax=gain_ax, shrink=0.85, label="k - 1 (%)")
    gain_ax.set_title(f"gain correction k ({plane}{sub})", fontsize=10)

    conf_map = matplotlib.colormaps["viridis"].with_extremes(bad=UNESTIMATED)
    image = conf_ax.imshow(np.ma.masked_array(conf, ~est), cmap=conf_map, norm=colors.Normalize(0, 1),
                           interpolation="nearest")
    fig.colorbar(image, ax=conf_ax, shrink=0.85, label="confidence")
    conf_ax.set_title("confidence", fontsize=10)
    for ax in (gain_ax, conf_ax):
        ax.set_xticks([])
        ax.set_yticks([])
    missing = 100.0 * (1.0 - est.mean())
    fig.legend(handles=[Patch(color=UNESTIMATED, label=f"not estimated (k = 1): {missing:.1f} % of pixels")],
               loc="lower left", fontsize=9, frameon=False)

    if values.size:
        hist_ax.hist(np.clip(values, -1.5 * limit, 1.5 * limit), bins=80, range=(-1.5 * limit, 1.5 * limit),
                     color="#3a6ea5")
    hist_ax.set_xlabel(f"k - 1 (%), clipped at +-{1.5 * limit:.2g}")
    hist_ax.set_ylabel("pixels")
    hist_ax.set_title(f"k of the estimated pixels\nrobust sigma {spread:.2f} %", fontsize=10)

    line1 = f"{name}: {len(report.inputs)} frames, motion {report.motion.model}, FPN model {report.fpn_models}"
    line2 = prnu_text(report.prnu_percent, report) + after_text(report)
    fig.suptitle(f"{line1}\n{line2}; {holdout_text(report.holdout)}", fontsize=11)

    from .files import atomic_output

    with atomic_output(path) as tmp:
        try:
            fig.savefig(tmp, format="png")
        except OSError as exc:
            raise InputError(f"{path}: cannot write PNG ({exc.strerror or exc})") from None


def shown(k: np.ndarray, confidence: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The first plane of ``k`` as ``k - 1`` in percent and its confidence, on every ``step``-th
    pixel so that neither side exceeds :data:`PREVIEW_PX` (picked, not averaged), and ``step``."""
    step = max(1, -(-max(k.shape[:2]) // PREVIEW_PX))
    deviation = 100.0 * (np.asarray(k[::step, ::step, 0], np.float64) - 1.0)
    return deviation, np.asarray(confidence[::step, ::step, 0], np.float64), step


def _ordinal(n: int) -> str:
    return f"{n}{'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')}"
