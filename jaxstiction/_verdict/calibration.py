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
        0.580993, 0.723041, 0.378877, 0.651852, 0.60056, 0.156441, 0.0972677, -0.0973902, -0.370122,
        -0.290017, -0.377624, 0.403289
    ]),
    scale=np.array([
        0.327007, 1.66342, 0.284151, 0.157584, 0.144805, 0.125937, 0.140824, 1.3496, 1.22875,
        1.00973, 1.21168, 0.333304
    ]),
    weights=np.array([
        0.588238, -0.938144, 1.84023, 1.04814, 0.18789, 0.70365, 0.393027, 0.201919, 0.296197,
        0.427693, 0.0591943, 0.406459
    ]),
    bias=np.array(-1.26262),
)
