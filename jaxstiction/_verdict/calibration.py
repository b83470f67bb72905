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
        -0.342992, -0.224817, -0.512862, 0.415201
    ]),
    scale=np.array([
        0.326914, 1.66433, 0.284129, 0.157667, 0.144856, 0.12594, 0.140406, 1.34933, 1.26641,
        1.03882, 1.18583, 0.338359
    ]),
    weights=np.array([
        0.634856, -0.98667, 1.93671, 1.14951, 0.0912656, 0.595406, 0.148177, 0.32591, 0.416412,
        0.611393, -0.14508, 0.299469
    ]),
    bias=np.array(-1.31849),
)
