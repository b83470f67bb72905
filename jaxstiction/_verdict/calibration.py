"""The stiction probability's coefficients (a leaf: fitted numbers only).

Written by `python benchmarks/calibrate_probability.py --write` (fit seeds
0-399 of the realistic fleet and the labelled real records of
the plant development half and the ISDB); do not edit by hand.

Not weighed (weight 0, taken at 0): crossval, evidence, evidence_prediction,
evidence_estimation, band: the model-based evidence, which does not carry from
simulated loops to real ones.
"""

import numpy as np

from .probability import Calibration


CALIBRATION = Calibration(
    names=(
        "horch", "log_regularity", "share", "shape_op", "shape_pv", "stuck_pv", "ngi", "crossval",
        "evidence", "evidence_prediction", "evidence_estimation", "band",
    ),
    mean=np.array([
        0.619042, 0.859322, 0.428099, 0.688966, 0.609894, 0.183669, 0.116749, 0, 0, 0, 0, 0
    ]),
    scale=np.array([
        0.324433, 1.63083, 0.280758, 0.162016, 0.161133, 0.138027, 0.161407, 1, 1, 1, 1, 1
    ]),
    weights=np.array([
        0.503066, -0.880714, 1.7621, 1.1235, 0.337732, 1.01117, 0.321709, 0, 0, 0, 0, 0
    ]),
    bias=np.array(0.205748),
)
