"""The screen's hard data-quality gates, as the benchmark scripts read them."""

import jax
import numpy as np

import jaxstiction as js
from jaxstiction.internal import bucket_length, gate_measures, hard_gated as _hard_gated


_measures = jax.jit(gate_measures)  # op by op, each record length would compile dozens of kernels


def hard_gated(op, pv, sp, settings=js.VerdictSettings()) -> bool:
    """Whether the screen's hard gates stop a record whatever the evidence (PV
    frozen, OP at a stop, or a record compressed or coarsely quantised by the
    historian): the library's `hard_gated` on the gate's own measures."""
    n = len(pv)
    width = bucket_length(n)  # padded and masked, as the screen does: one program per length bucket

    def pad(x):
        x = np.asarray(x, float)
        return np.concatenate([x, np.full(width - n, x[-1])])

    g = _measures(pad(op), pad(pv), pad(sp), (np.arange(width) < n).astype(float))
    return bool(_hard_gated(g, settings))
