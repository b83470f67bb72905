"""The stiction probability's coefficients (a leaf: fitted numbers only).

Written by `python benchmarks/calibrate_probability.py --write`, which fits them
(`fit_calibration`) on the simulated realistic fleet and the labelled real records
it names in its output; do not edit by hand.
"""

import numpy as np

from .probability import Calibration


CALIBRATION = Calibration(
    names=("horch", "log_regularity", "share", "shape_op", "shape_pv", "stuck_pv", "ngi", "crossval",
           "evidence", "evidence_prediction", "evidence_estimation", "band"),
    mean=np.array([0.5847, 0.9774, 0.4256, 0.6285, 0.6052, 0.1609, 0.091, 0.3526, -0.2715, -0.1613, -0.3058,
                    0.3839]),
    scale=np.array([0.3434, 1.7608, 0.303, 0.1845, 0.1812, 0.1309, 0.1424, 1.1937, 1.239, 1.0035, 1.1997,
                     0.322]),
    weights=np.array([0.5954, -0.7087, 1.1455, 0.9901, -0.0785, 0.3576, 0.0147, 0.7377, 0.0414, 0.3461, -0.1742,
                       0.375]),
    bias=np.array(-1.0219),
)
