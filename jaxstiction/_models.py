r"""The loop model: an input chain of blocks, a linear process, a noise model, offsets.

$$PV(t) = \text{pv\_offset} + \frac{B(q)}{A(q)} q^{-\text{delay}}
\big(x(t) - \text{op\_offset}\big) + \frac{C(q)}{D(q)} e(t),\qquad
x = \text{chain}(OP),$$

followed by the output-side blocks (external oscillation, drift, quantisation).
Polynomials are coefficient arrays in $q^{-1}$ from $q^0$: `b = [b0, b1, ...]`,
`a = [1, a1, ...]`. Every estimator, scenario, nominal-model file and plot uses this
one model.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._blocks import _f, AbstractBlock, run_chain
from ._filters import lfilter, steady_state
from ._linalg import lstsq
from ._misc import chunked_vmap, first_min
from ._spline import scale_input, spline_basis


class LinearProcess(eqx.Module):
    r"""$G(q) = q^{-\text{delay}} B(q)/A(q)$; `delay` is a static whole number of
    samples (estimators fold their delay into leading zeros of `b`)."""

    b: Float[Array, " nb"] = eqx.field(converter=_f)
    a: Float[Array, " na"] = eqx.field(converter=_f)
    delay: int = eqx.field(static=True, default=0)

    def polynomials(self):
        """`(b, a)` with the delay folded into `b`, both padded to one length."""
        b = jnp.concatenate([jnp.zeros((self.delay,), self.b.dtype), self.b])
        n = max(b.shape[0], self.a.shape[0])
        b = jnp.concatenate([b, jnp.zeros((n - b.shape[0],), b.dtype)])
        a = jnp.concatenate([self.a, jnp.zeros((n - self.a.shape[0],), self.a.dtype)])
        return b, a

    @property
    def gain(self):
        """Static gain $B(1)/A(1)$."""
        return jnp.sum(self.b) / jnp.sum(self.a)


class NoiseModel(eqx.Module):
    r"""$H(q) = C(q)/D(q)$, both monic: `c = [1, c1, ...]`, `d = [1, d1, ...]`;
    `variance` is that of the white innovations $e$."""

    c: Float[Array, " nc"] = eqx.field(converter=_f, default=(1.0,))
    d: Float[Array, " nd"] = eqx.field(converter=_f, default=(1.0,))
    variance: Float[Array, ""] = eqx.field(converter=_f, default=1.0)

    def impulse(self, k: int):
        """The first `k` terms $h_0 = 1, h_1, \\ldots$ of the impulse response of $H$."""
        imp = jnp.zeros((k,), self.c.dtype).at[0].set(1.0)
        return lfilter(self.c, self.d, imp)


class SplineValve(AbstractBlock):
    r"""The paper's two-branch cubic-spline valve (6)–(9) as a block.

    OP is scaled to $u \in [-1, 1]$ with `lo`, `hi`; the direction $h$ is the literal
    rule (5) when `threshold == 0`, otherwise the robust rule (the direction changes
    only once $u$ has moved more than `threshold` from its running extreme);
    $\hat x = h f_1(u) + (1 - h) f_2(u)$ with `beta` = ascent then descent
    coefficients on [`jaxstiction.internal.spline_basis`][]. State `(h, extreme, u_prev)`.
    """

    beta: Float[Array, " p"]
    knots: Float[Array, " m"]
    knot_mask: Float[Array, " m2"]
    lo: Float[Array, ""]
    hi: Float[Array, ""]
    threshold: Float[Array, ""]

    def init(self, u0):
        u = scale_input(jnp.asarray(u0), self.lo, self.hi)
        return (jnp.ones_like(u), u, u)

    def step(self, state, op):
        h, ext, u_prev = state
        u = scale_input(op, self.lo, self.hi)
        ext = jnp.where(h > 0, jnp.maximum(ext, u), jnp.minimum(ext, u))
        down = (h > 0) & (u < ext - self.threshold)
        up = (h == 0) & (u > ext + self.threshold)
        h_rob = jnp.where(down, 0.0, jnp.where(up, 1.0, h))
        ext = jnp.where(down | up, u, ext)
        h_lit = jnp.where(u >= u_prev, 1.0, 0.0)
        h = jnp.where(self.threshold > 0, h_rob, h_lit).astype(u.dtype)
        basis = spline_basis(u[None], self.knots, self.knot_mask)[0]
        p = basis.shape[0]
        x = h * (basis @ self.beta[:p]) + (1 - h) * (basis @ self.beta[p:])
        return (h, ext, u), x

    def initial_states(self, u_open, count: int):
        u = scale_input(jnp.asarray(u_open)[0], self.lo, self.hi)
        return (jnp.array([1.0, 0.0], u.dtype), jnp.stack([u, u]), jnp.stack([u, u]))

    @staticmethod
    def linear(lo, hi, num_knots: int, dtype=None):
        """The spline valve that passes the scaled input through: $\\hat x = u$."""
        dtype = dtype or jnp.result_type(float)
        p = num_knots + 2
        beta1 = jnp.zeros((p,), dtype).at[num_knots - 1].set(1.0)  # the `u` column
        return SplineValve(
            beta=jnp.concatenate([beta1, beta1]),
            knots=jnp.linspace(-1.0, 1.0, num_knots, dtype=dtype),
            knot_mask=jnp.zeros((num_knots - 2,), dtype),
            lo=jnp.asarray(lo, dtype),
            hi=jnp.asarray(hi, dtype),
            threshold=jnp.zeros((), dtype),
        )


class InitialState(eqx.Module):
    """The state a simulation starts from.

    - `chain`: one state per input-side block;
    - `hold`, `held`: when `held`, the chain output is held at `hold` until it first
      changes (a stuck valve resting at an unknown position);
    - `filter`: the process filter's state (direct form II transposed), in PV units;
    - `output`: one state per output-side block.
    """

    chain: tuple
    hold: Float[Array, ""]
    held: Array
    filter: Float[Array, " s"]
    output: tuple


class LoopModel(eqx.Module):
    """A control loop's model (see the module docstring).

    **Fields:** `chain` (input-side blocks, OP → valve position), `process`
    ([`jaxstiction.LinearProcess`][]), `noise` ([`jaxstiction.NoiseModel`][]),
    `op_offset`, `pv_offset`, `output` (output-side blocks).
    """

    chain: tuple
    process: LinearProcess
    noise: NoiseModel = eqx.field(default_factory=NoiseModel)
    op_offset: Float[Array, ""] = eqx.field(converter=_f, default=0.0)
    pv_offset: Float[Array, ""] = eqx.field(converter=_f, default=0.0)
    output: tuple = ()

    def __check_init__(self):
        for blk in tuple(self.chain) + tuple(self.output):
            if not isinstance(blk, AbstractBlock):
                raise ValueError(f"every block of a LoopModel must be an AbstractBlock, got {type(blk).__name__}")

    # ------------------------------------------------------------------ pieces

    def _chain_init(self, op0):
        states, v = [], jnp.asarray(op0)
        for blk in self.chain:
            s = blk.init(v)
            states.append(s)
            _, v = blk.step(s, v)
        return tuple(states), v

    def valve(self, op, states=None) -> Float[Array, " time"]:
        """Process input before the offset: the input chain run over `op`."""
        return run_chain(tuple(self.chain), op, states)

    def _output(self, y, states=None):
        return run_chain(tuple(self.output), y, states)

    def rest_state(self, op) -> InitialState:
        """Everything at rest at the first input: the chain at `op[0]`, the process
        at steady state for the chain's first output."""
        op = _f(op)
        chain, x0 = self._chain_init(op[0])
        b, a = self.process.polynomials()
        filt = steady_state(b, a, x0 - self.op_offset)
        out = tuple(blk.init(self.pv_offset) for blk in self.output)
        zero = jnp.zeros((), op.dtype)
        return InitialState(chain, zero, jnp.asarray(False), filt, out)

    # ---------------------------------------------------------------- simulate

    def valve_path(self, op: Float[Array, " time"], initial: InitialState) -> Float[Array, " time"]:
        """Process input before the offset from `initial`: the chain's output, held at
        `initial.hold` (when `initial.held`) until it first changes."""
        x = self.valve(op, initial.chain)
        pre = jnp.cumprod(x == x[0]).astype(bool) & initial.held
        return jnp.where(pre, initial.hold, x)

    def simulate(self, op: Float[Array, " time"], initial: InitialState | None = None) -> Float[Array, " time"]:
        """Simulated PV for OP `op` (noise-free), from `initial` (default: at rest;
        see [`jaxstiction.LoopModel.initial_state`][] to estimate it from data)."""
        op = _f(op)
        if initial is None:
            initial = self.rest_state(op)
        return self.process_output(self.valve_path(op, initial), initial)

    def process_output(self, x: Float[Array, " time"], initial: InitialState) -> Float[Array, " time"]:
        """Simulated PV for the process input `x` (from
        [`jaxstiction.LoopModel.valve_path`][]), from `initial`'s process and output
        states: the part of `simulate` after the chain, for a caller that changes the
        process and keeps the valve."""
        b, a = self.process.polynomials()
        y = lfilter(b, a, x - self.op_offset, initial.filter) + self.pv_offset
        return self._output(y, initial.output)

    def initial_state(self, op, pv, weights, *, count: int = 16, window: int | None = None) -> InitialState:
        """Estimate the initial state from a record, as system-identification tools
        do before scoring a simulation.

        Every candidate state of the chain (each block's `initial_states` from the
        input up to the last sample of positive weight, the other blocks at rest;
        for a valve, up to `count` stopping points per direction, one per distinct
        first slip there) is run over
        `op`; for each, the level at which the chain output rests until it first
        moves and the process filter's state enter the simulation linearly and are
        found by least squares on the samples where `weights > 0` (typically the
        opening part of the record). The candidate with the smallest weighted error
        wins. Offsets and parameters are not touched.

        `window` (static): when `weights` are zero from that sample on, the search
        runs on the samples before it only: the same answer for less work.
        """
        states, errs = self.initial_candidates(op, pv, weights, count=count, window=window)
        return jax.tree.map(lambda t: t[first_min(errs)], states)

    def initial_candidates(self, op, pv, weights, *, count: int = 16, window: int | None = None):
        """`(states, errors)`: every candidate initial state that
        [`jaxstiction.LoopModel.initial_state`][] weighs (an `InitialState` with a
        leading axis, its hold level and filter state fitted) and its weighted sum of
        squared prediction errors (`inf` where not finite); `initial_state` picks the
        least. Same arguments."""
        op, pv, weights = _f(op), _f(pv), _f(weights)
        if window is not None and window < op.shape[0]:
            # every filter is causal: the samples after the last weighted one change nothing
            op, pv, weights = op[:window], pv[:window], weights[:window]
        # candidates from the input up to the last weighted sample (held after it)
        t = jnp.arange(op.shape[0])
        last = jnp.max(jnp.where(weights > 0, t, 0))
        cands = self._chain_candidates(jnp.where(t <= last, op, op[last]), count)
        b, a = self.process.polynomials()
        s = b.shape[0] - 1
        add = self._output(jnp.zeros_like(op)) if self.output else 0.0  # additive output blocks
        target0 = pv - self.pv_offset - add
        eye = jnp.eye(max(s, 1), dtype=op.dtype)[:s]
        free = jax.vmap(lambda z: lfilter(b, a, jnp.zeros_like(op), z), out_axes=1)(eye) if s else None

        def whiten(v):
            # prediction errors under the noise model: the maximum-likelihood fit
            # (coloured noise would otherwise pass for a start-up transient)
            return lfilter(self.noise.d, self.noise.c, v)

        wfree = None if free is None else jax.vmap(whiten, in_axes=1, out_axes=1)(free)

        def one(states):
            x = self.valve(op, states)
            pre = jnp.cumprod(x == x[0]).astype(op.dtype)
            forced = lfilter(b, a, (1 - pre) * (x - self.op_offset))
            hold = lfilter(b, a, pre)
            wcols = whiten(hold)[:, None] if free is None else jnp.concatenate([whiten(hold)[:, None], wfree], axis=1)
            r = whiten(target0 - forced)
            th = lstsq(wcols * weights[:, None], r * weights, 1e-12)
            err = jnp.sum(weights * (r - wcols @ th) ** 2)
            return jnp.where(jnp.isfinite(err), err, jnp.inf), th

        # vmapped (the scans then run once over a batch of candidates), in chunks
        # that bound memory on long records
        chunk = int(max(1, min(256, 2_000_000 // max(op.shape[0], 1))))
        if jax.tree.leaves(cands):
            errs, ths = chunked_vmap(lambda c: one(c), (cands,), chunk)
        else:  # memoryless chain (e.g. travel limits): one candidate
            errs, ths = jax.tree.map(lambda t: t[None], one(cands))
            cands = jax.tree.map(lambda t: jnp.asarray(t)[None], cands)
        k = errs.shape[0]
        out = tuple(jax.tree.map(lambda t: jnp.broadcast_to(t, (k,) + jnp.shape(t)), blk.init(self.pv_offset))
                    for blk in self.output)
        states = InitialState(cands, ths[:, 0] + self.op_offset, jnp.ones((k,), bool), ths[:, 1:], out)
        return states, errs

    def _chain_candidates(self, op, count: int):
        """Candidate initial states of the chain (leading axis): each block's own
        candidates in turn, the other blocks at rest (a union, not all combinations:
        in a loop model at most one block has a hidden memory worth searching)."""
        op = jnp.asarray(op)
        if not self.chain:
            return jnp.zeros((1,), op.dtype)  # one (empty) candidate
        rest, _ = self._chain_init(op[0])
        # each block's input over the searched samples, from the rest start
        inputs, v = [], op
        for blk, s0 in zip(self.chain, rest):
            inputs.append(v)
            _, v = jax.lax.scan(lambda s, x, b=blk: b.step(s, x), s0, v)
        groups = []
        for i, blk in enumerate(self.chain):
            cand = blk.initial_states(inputs[i], count)
            leaves = jax.tree.leaves(cand)
            k = leaves[0].shape[0] if leaves else 1
            states = tuple(
                cand if j == i else jax.tree.map(lambda t: jnp.broadcast_to(jnp.asarray(t), (k,) + jnp.shape(t)), r)
                for j, r in enumerate(rest)
            )
            groups.append(states)
        return jax.tree.map(lambda *xs: jnp.concatenate(xs), *groups)

    # ----------------------------------------------------------------- predict

    def predict(self, op, pv, k: int = 1, initial: InitialState | None = None) -> Float[Array, " time"]:
        r"""k-step-ahead prediction $\hat y(t \mid t-k)$ with the noise model:
        $\hat y = y - \bar H_k H^{-1} (y - y_{sim})$, where $\bar H_k$ is the first `k`
        terms of the impulse response of $H = C/D$. `k` is a static int ≥ 1; a very
        large `k` gives the simulation."""
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"`k` must be an int >= 1, got {k!r}")
        pv = _f(pv)
        v = pv - self.simulate(op, initial)
        e = lfilter(self.noise.d, self.noise.c, v)
        return pv - lfilter(self.noise.impulse(k), jnp.ones((1,), pv.dtype), e)


def pad_to(x, n: int):
    """`x` with zeros appended to length `n`."""
    return jnp.concatenate([x, jnp.zeros((n - x.shape[0],), x.dtype)])


def scaled_loop_model(chain, b, a, offset, noise_c, noise_d, mu, sy, *, sx=None, op_offset=None, variance=None,
                      lengths: tuple[int, int] | None = None, output=()) -> LoopModel:
    r"""The [`jaxstiction.LoopModel`][] in engineering units of a fit in scaled units,
    $y = (PV - \mu) / s_y$ from the input $x = (v - \text{op\_offset}) / s_x$ (the
    valve path $v$ of `chain`; `sx=None`: not scaled, and `op_offset=None`: 0).

    `b`, `a`, `offset`: the fitted polynomials and output offset (scaled units);
    `noise_c`, `noise_d`: its noise model, with the innovations' `variance` (scaled
    units; `None`: the `NoiseModel` default); `lengths`: `(len(b), len(a))` to pad
    the polynomials to, so that models of different orders stack."""
    b_dtype = b.dtype
    b = b * sy if sx is None else b * sy / sx
    if lengths is not None:
        b, a = pad_to(b, lengths[0]), pad_to(a, lengths[1])
    noise = (NoiseModel(c=noise_c, d=noise_d) if variance is None
             else NoiseModel(c=noise_c, d=noise_d, variance=variance * sy**2))
    return LoopModel(
        chain=tuple(chain),
        process=LinearProcess(b=b, a=a),
        noise=noise,
        op_offset=jnp.zeros((), b_dtype) if op_offset is None else op_offset,
        pv_offset=mu + sy * offset,
        output=tuple(output),
    )
