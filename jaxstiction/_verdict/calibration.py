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
        0.581345, 0.723417, 0.379195, 0.651853, 0.600487, 0.156326, 0.0969073, -0.0940925,
        -0.382207, -0.264033, -0.473646, 0.415201
    ]),
    scale=np.array([
        0.326914, 1.66433, 0.284129, 0.157667, 0.144856, 0.12594, 0.140406, 1.34933, 1.22349,
        0.990725, 1.16896, 0.338359
    ]),
    weights=np.array([
        0.596597, -0.960068, 1.87549, 1.05302, 0.20697, 0.698035, 0.32459, 0.201486, 0.257325,
        0.473678, 0.0674269, 0.377834
    ]),
    bias=np.array(-1.27669),
)
