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
        0.623858, 0.825391, 0.423813, 0.686606, 0.606907, 0.181879, 0.117008, -0.0119813, -0.251506,
        -0.183084, -0.268485, 0.431856
    ]),
    scale=np.array([
        0.317229, 1.65145, 0.279795, 0.161886, 0.158223, 0.137744, 0.161536, 1.43305, 1.32281,
        1.04661, 1.31593, 0.336202
    ]),
    weights=np.array([
        0.565465, -0.995809, 1.79703, 0.996789, 0.28455, 0.785845, 0.447838, 0.292332, 0.354424,
        0.452059, 0.0652564, 0.451004
    ]),
    bias=np.array(0.219226),
)
