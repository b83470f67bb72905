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
        0.593167, 0.969367, 0.427067, 0.631017, 0.607583, 0.160717, 0.0908277, -0.027862, -0.271527,
        -0.161306, -0.305757, 0.383919
    ]),
    scale=np.array([
        0.333553, 1.80106, 0.304324, 0.184331, 0.181234, 0.130401, 0.14247, 1.49098, 1.23905,
        1.00353, 1.19969, 0.321983
    ]),
    weights=np.array([
        0.604587, -0.811201, 1.33729, 0.993607, 0.0638541, 0.387492, 0.0137336, 0.528257, 0.226398,
        0.322565, -0.278566, 0.281508
    ]),
    bias=np.array(-0.998109),
)
