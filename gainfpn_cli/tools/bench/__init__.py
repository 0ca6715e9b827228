"""``gainfpn bench``: the speed/accuracy trade, measured on simulated bursts.

Every point runs the real pipeline (read, motion, solve, write) on a burst
with known truth, in a fresh process so that its peak memory is its own
(the solver's worker processes included). Points that isolate the solver
(flow-error sensitivity, parallel efficiency) call it directly with the true
motion. Reference points in the same run: the paper's published
configuration, a flat-field calibration from as many uniformly lit frames,
and the temporal-noise floor (the true gains).
"""

from .measure import OUTPUTS, background_rms, run
from .points import BurstSpec, Point, plan
from .report import markdown, plot

__all__ = ["OUTPUTS", "BurstSpec", "Point", "background_rms", "markdown", "plan", "plot", "run"]
