"""The screen's hard data-quality gates, as the benchmark scripts read them."""

import jax

import jaxstiction as js
from jaxstiction.internal import bucket_length, gate_measures, hard_gated as _hard_gated, pad


_measures = jax.jit(gate_measures)  # op by op, each record length would compile dozens of kernels


def hard_gated(op, pv, sp, settings=js.VerdictSettings()) -> bool:
    """Whether the screen's hard gates stop a record whatever the evidence (PV
    frozen, OP at a stop, or a record compressed or coarsely quantised by the
    historian): the library's `hard_gated` on the gate's own measures, the record
    padded to its length bucket as the screen pads it (one program per bucket)."""
    loop = pad(js.make_loop(op, pv, 1.0, sp=sp), bucket_length(len(pv)))
    return bool(_hard_gated(_measures(loop.op, loop.pv, loop.sp, loop.mask), settings))
