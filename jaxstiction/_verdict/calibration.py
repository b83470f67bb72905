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
        0.618235, 0.86774, 0.427589, 0.68818, 0.610042, 0.183128, 0.116861, -0.0110009, -0.257994,
        -0.194275, -0.269083, 0.432035
    ]),
    scale=np.array([
        0.323625, 1.62788, 0.281443, 0.16217, 0.161133, 0.138577, 0.161379, 1.44874, 1.32294,
        1.04245, 1.32282, 0.337898
    ]),
    weights=np.array([
        0.605349, -1.12627, 1.92885, 1.04636, 0.326264, 0.806564, 0.373828, 0.202099, 0.433589,
        0.545073, -0.0387088, 0.498717
    ]),
    bias=np.array(0.170065),
)
