"""The stiction probability's coefficients (a leaf: fitted numbers only).

Written by `python benchmarks/calibrate_probability.py --write` (fit seeds
0-399 of the realistic fleet and the labelled real records of
the plant development half and the ISDB); do not edit by hand.
"""

import numpy as np

from .probability import Calibration


CALIBRATION = Calibration(
    names=(
        "horch", "log_regularity", "share", "shape_op", "shape_pv", "stuck_pv", "ngi", "crossval",
        "evidence", "evidence_prediction", "evidence_estimation", "band",
    ),
    mean=np.array([
        0.619042, 0.859322, 0.428099, 0.688966, 0.609894, 0.183669, 0.116749, -0.0102032, -0.256826,
        -0.192647, -0.269705, 0.431943
    ]),
    scale=np.array([
        0.324433, 1.63083, 0.280758, 0.162016, 0.161133, 0.138027, 0.161407, 1.44906, 1.32018,
        1.04014, 1.32257, 0.337835
    ]),
    weights=np.array([
        0.562292, -1.11384, 1.94607, 1.04237, 0.344631, 0.822559, 0.380471, 0.202161, 0.509965,
        0.531381, -0.100006, 0.456246
    ]),
    bias=np.array(0.160801),
)
