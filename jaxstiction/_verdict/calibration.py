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
        0.580993, 0.723041, 0.378877, 0.651852, 0.60056, 0.156441, 0.0972677, -0.0973902, -0.378424,
        -0.263019, -0.462546, 0.404222
    ]),
    scale=np.array([
        0.327007, 1.66342, 0.284151, 0.157584, 0.144805, 0.125937, 0.140824, 1.3496, 1.22641,
        0.986981, 1.17482, 0.333268
    ]),
    weights=np.array([
        0.579413, -0.931612, 1.8372, 1.0337, 0.204156, 0.715342, 0.361147, 0.192272, 0.243013,
        0.47392, 0.0985067, 0.421536
    ]),
    bias=np.array(-1.26695),
)
