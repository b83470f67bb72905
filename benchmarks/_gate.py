"""The screen's hard data-quality gates, as the benchmark scripts read them."""

import jax
import numpy as np

import jaxstiction as js
from jaxstiction.internal import gate_measures, hard_gated as _hard_gated


_measures = jax.jit(gate_measures)  # op by op, each record length would compile dozens of kernels


def hard_gated(op, pv, sp, settings=js.VerdictSettings()) -> bool:
    """Whether the screen's hard gates stop a record whatever the evidence (PV
    frozen, OP at a stop, or a record compressed or coarsely quantised by the
    historian): the library's `hard_gated` on the gate's own measures."""
    g = _measures(np.asarray(op, float), np.asarray(pv, float), np.asarray(sp, float), np.ones(len(pv)))
    return bool(_hard_gated(g, settings))
