"""Valve and loop physics blocks (DESIGN §3), each a pure JAX function.

Every stateful block is written as a one-sample `step(state, u, params) -> (state, out)`
usable inside `lax.scan`, plus a whole-signal wrapper. All valve quantities are in %
of span. Parameters are JAX scalars so the wrappers can be `vmap`ped over them.
"""

import functools as ft

import jax
import jax.numpy as jnp
import jax.random as jr
from jaxtyping import Array, Float, PRNGKeyArray


def _inexact(x) -> Array:
    """`x` as a JAX array, cast to the default float dtype if it is not inexact.

    (Integer inputs such as a staircase of whole percents must not truncate `S`, `J`.)
    """
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(jnp.result_type(float))
    return x


@ft.partial(jax.jit, static_argnums=0)
def _scan_block(step, state, u, *params):
    """Run a one-sample `step(state, u_t, *params) -> (state, out)` over a signal.

    Jitted with the (module-level) `step` static only so that eager calls of the
    wrappers reuse one compilation per step and shape instead of re-tracing a fresh
    closure each time; inside a caller's `jit`/`vmap` it is simply inlined.
    """
    _, y = jax.lax.scan(lambda s, ut: step(s, ut, *params), state, u)
    return y


def kano_init(u0):
    """Initial Kano state for a valve resting (stuck) at input `u0`.

    State is `(y, us, stp, d, u_prev, du_prev)`: valve position, input where the valve
    stopped, 1 when stuck, direction (+1 up / -1 down), previous input and previous
    move.
    """
    u0 = jnp.asarray(u0)
    one = jnp.ones_like(u0)
    return (u0, u0, one, one, u0, jnp.zeros_like(u0))


def kano_step(state, u, S, J):
    """One sample of Kano's (2004) stiction model; transcription of DESIGN §3.

    **Arguments:**

    - `state`: the tuple from [`jaxstiction.kano_init`][] or a previous step.
    - `u`: controller output at this sample (% of span).
    - `S`: deadband + stickband (% of span).
    - `J`: slip jump (% of span).

    **Returns:** `(new_state, valve_position)`.
    """
    y, us, stp, d, u_prev, du_prev = state
    du = u - u_prev
    stops = (du * du_prev <= 0) & (stp == 0)
    us = jnp.where(stops, u_prev, us)
    stp = jnp.where(stops, 1.0, stp)
    moving = stp == 0
    reverse = (~moving) & (-d * (u - us) > S)
    same = (~moving) & (~reverse) & (d * (u - us) > J)
    d = jnp.where(reverse, -d, d)
    y_move = u - d * (S - J) / 2
    go = moving | reverse | same
    y = jnp.where(go, y_move, y)
    stp = jnp.where(reverse | same, 0.0, stp)
    return (y, us, stp, d, u, du), y


def kano(u: Float[Array, " time"], S, J, *, state=None) -> Float[Array, " time"]:
    """Valve position from controller output through Kano's stiction model.

    The valve starts stuck at `u[0]` unless `state` is given. `S`, `J` may be traced
    (e.g. `vmap` over a grid of them).
    """
    u = _inexact(u)
    S = jnp.asarray(S, u.dtype)
    J = jnp.asarray(J, u.dtype)
    if state is None:
        state = kano_init(u[0])
    return _scan_block(kano_step, state, u, S, J)


# --------------------------------------------------------------------------------------
# Choudhury, Thornhill & Shah (2005)
# --------------------------------------------------------------------------------------


def choudhury_init(u0):
    """Initial Choudhury state for a valve resting (stuck) at input `u0`.

    State is `(y, x_ss, stuck, v_old, direction, x_prev)`: valve position, input where
    the valve stuck, 1 when stuck, previous input velocity, direction of the last
    travel (`0` = unknown, so the first break-away needs the full `S` either way) and
    previous input.
    """
    u0 = jnp.asarray(u0)
    zero = jnp.zeros_like(u0)
    return (u0, u0, jnp.ones_like(u0), zero, zero, u0)


def choudhury_step(state, x, S, J):
    """One sample of the Choudhury, Thornhill & Shah (2005) two-parameter model.

    Follows the published flow chart: the valve sticks when the input velocity
    $v_{new} = x(t) - x(t-1)$ changes sign or becomes zero ($x_{ss} = x(t-1)$); a
    stuck valve slips when $|x - x_{ss}|$ exceeds the slip jump `J` (input keeps the
    direction the valve travelled in) or the deadband plus stickband `S` (input
    reverses); a moving or slipping valve sits at $x - \\mathrm{sign}(v_{new})(S-J)/2$.
    The direction test uses the direction of the last travel (the 2008 book form),
    which is what makes the model well behaved on noisy inputs.

    **Arguments:**

    - `state`: the tuple from [`jaxstiction.choudhury_init`][] or a previous step.
    - `x`: controller output at this sample (% of span).
    - `S`: deadband + stickband (% of span).
    - `J`: slip jump (% of span).

    **Returns:** `(new_state, valve_position)`.
    """
    y, x_ss, stuck, v_old, direction, x_prev = state
    v_new = x - x_prev
    sgn = jnp.sign(v_new)
    stick = (stuck == 0) & (sgn != jnp.sign(v_old))
    x_ss = jnp.where(stick, x_prev, x_ss)
    stuck = jnp.where(stick, 1.0, stuck)
    disp = x - x_ss
    band = jnp.where(jnp.sign(disp) == direction, J, S)
    slip = (stuck == 1) & (jnp.abs(disp) > band)
    move = (stuck == 0) | slip
    y = jnp.where(move, x - sgn * (S - J) / 2, y)
    direction = jnp.where(move, sgn, direction)
    stuck = jnp.where(slip, 0.0, stuck)
    return (y, x_ss, stuck, v_new, direction, x), y


def choudhury(u: Float[Array, " time"], S, J, *, state=None) -> Float[Array, " time"]:
    """Valve position from controller output through Choudhury's (2005) stiction model.

    The valve starts stuck at `u[0]` with unknown travel direction unless `state` is
    given. After the first stick event the output equals [`jaxstiction.kano`][] with the
    same `S`, `J` (Kano's model is the stochastic-input-safe form of this one); they can
    differ only before it, because Kano assumes an initial upward travel.
    """
    u = _inexact(u)
    S = jnp.asarray(S, u.dtype)
    J = jnp.asarray(J, u.dtype)
    if state is None:
        state = choudhury_init(u[0])
    return _scan_block(choudhury_step, state, u, S, J)


# --------------------------------------------------------------------------------------
# He, Wang, Pottmann & Qin (2007)
# --------------------------------------------------------------------------------------


def he_init(u0):
    """Initial He state: valve at `u0`, no residual force; `(y, u_prev, u_r)`."""
    u0 = jnp.asarray(u0)
    return (u0, u0, jnp.zeros_like(u0))


def he_step(state, u, fs, fd):
    """One sample of He et al.'s (2007) semi-physical two-parameter stiction model.

    The residual force $u_r$ accumulates input moves, $u_r \\leftarrow u_r + u(t) -
    u(t-1)$; if $|u_r| > f_s$ the valve slips to $y + u_r - \\mathrm{sign}(u_r) f_d$ and
    $u_r = \\mathrm{sign}(u_r) f_d$, otherwise it stays.

    **Arguments:**

    - `state`: the tuple from [`jaxstiction.he_init`][] or a previous step.
    - `u`: controller output at this sample (% of span).
    - `fs`: static friction band (% of span).
    - `fd`: kinetic friction band (% of span).

    **Returns:** `(new_state, valve_position)`.
    """
    y, u_prev, u_r = state
    u_r = u_r + (u - u_prev)
    slip = jnp.abs(u_r) > fs
    s = jnp.sign(u_r)
    y = jnp.where(slip, y + u_r - s * fd, y)
    u_r = jnp.where(slip, s * fd, u_r)
    return (y, u, u_r), y


def he_stiction(
    u: Float[Array, " time"], fs, fd, *, state=None
) -> Float[Array, " time"]:
    """Valve position from controller output through He et al.'s (2007) model.

    Maps to Kano's parameters as $S = f_s + f_d$, $J = f_s - f_d$: break-away, reversal
    band and the moving offset $(S-J)/2 = f_d$ are the same. The models differ in one
    respect: He's valve re-sticks whenever the input moves by less than
    $f_s - f_d = J$ in one sample (stick-slip at low velocity), while Kano's keeps
    moving until the input reverses or stops. So He equals Kano (after both have
    moved once) when $J = 0$, or when every input move while travelling exceeds $J$
    (e.g. staircases with steps larger than $J$). The valve starts at `u[0]`.
    """
    u = _inexact(u)
    fs = jnp.asarray(fs, u.dtype)
    fd = jnp.asarray(fd, u.dtype)
    if state is None:
        state = he_init(u[0])
    return _scan_block(he_step, state, u, fs, fd)


# --------------------------------------------------------------------------------------
# Deadband / backlash
# --------------------------------------------------------------------------------------


def deadband_init(u0):
    """Initial backlash state: valve centred on the input `u0`. State is `(y,)`."""
    return (jnp.asarray(u0),)


def deadband_step(state, u, width):
    """One sample of a deadband (backlash, play operator) of total `width`.

    $y(t) = \\mathrm{clip}(y(t-1),\\ u(t) - w/2,\\ u(t) + w/2)$: the valve follows the
    input at a lag of $w/2$ and stays put while a reversal is inside the band.

    **Returns:** `(new_state, valve_position)`.
    """
    (y,) = state
    y = jnp.clip(y, u - width / 2, u + width / 2)
    return (y,), y


def deadband(u: Float[Array, " time"], width, *, state=None) -> Float[Array, " time"]:
    """Valve position through a deadband / backlash of total `width` (% of span).

    Stiction with no slip jump: after the first stop it equals
    [`jaxstiction.kano`][] with `S = width`, `J = 0`. The valve starts centred on `u[0]`
    (Kano instead starts on the upward branch).
    """
    u = _inexact(u)
    width = jnp.asarray(width, u.dtype)
    if state is None:
        state = deadband_init(u[0])
    return _scan_block(deadband_step, state, u, width)


# --------------------------------------------------------------------------------------
# Other blocks of the chain
# --------------------------------------------------------------------------------------


def dead_time(x: Float[Array, " time"], k: int) -> Float[Array, " time"]:
    """Delay a signal by `k` whole samples ($q^{-k}$), padding the start with `x[0]`.

    `k` is a static non-negative Python int (it fixes the shape of the padding).
    """
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise ValueError(
            f"`k` must be a non-negative Python int (static), got {k!r}; pass e.g. 2."
        )
    x = jnp.asarray(x)
    n = x.shape[0]
    if k == 0:
        return x
    k = min(k, n)
    return jnp.concatenate([jnp.full((k,), x[0], x.dtype), x[: n - k]])


def equal_percentage(x: Float[Array, "*shape"], R) -> Float[Array, "*shape"]:
    """Inherent equal-percentage valve characteristic, in % of span.

    $f(x) = 100\\,(R^{x/100} - 1)/(R - 1)$, with `x` the stem position in % of span and
    rangeability `R` (typically 20–50). `R = 1` is taken as its limit, the linear valve.
    """
    x = _inexact(x)
    R = jnp.asarray(R, x.dtype)
    lin = R == 1
    R_safe = jnp.where(lin, 2.0, R)
    f = (R_safe ** (x / 100) - 1) / (R_safe - 1) * 100
    return jnp.where(lin, x, f)


def travel_limits(x: Float[Array, "*shape"], lo, hi) -> Float[Array, "*shape"]:
    """Mechanical travel limits of the stem: `clip(x, lo, hi)` (% of span)."""
    return jnp.clip(x, lo, hi)


def actuator_lag_step(x_prev, u, a):
    """One sample of the first-order actuator lag; returns `(state, output)`."""
    x = a * x_prev + (1 - a) * u
    return x, x


def actuator_lag(u: Float[Array, " time"], a) -> Float[Array, " time"]:
    """First-order actuator lag $x_a(t) = a\\,x_a(t-1) + (1 - a)\\,u(t)$.

    `a` in $[0, 1)$ is the pole ($a = e^{-T_s/\\tau}$); the actuator starts at rest at
    `u[0]` (so `x_a(0) = u[0]`). `a = 0` passes `u` through unchanged.
    """
    u = _inexact(u)
    a = jnp.asarray(a, u.dtype)
    return _scan_block(actuator_lag_step, u[0], u, a)


def rate_limit_step(y_prev, u, max_rate):
    """One sample of the rate limiter; returns `(state, output)`."""
    du = u - y_prev
    y = jnp.where(jnp.abs(du) > max_rate, y_prev + jnp.sign(du) * max_rate, u)
    return y, y


def rate_limit(u: Float[Array, " time"], max_rate) -> Float[Array, " time"]:
    """Slew-rate limit: the output moves towards `u` by at most `max_rate` per sample.

    Starts at `u[0]`; where the limit is not active the output equals `u` exactly.
    """
    u = _inexact(u)
    max_rate = jnp.asarray(max_rate, u.dtype)
    return _scan_block(rate_limit_step, u[0], u, max_rate)


def quantize(y: Float[Array, "*shape"], q) -> Float[Array, "*shape"]:
    """Sensor quantisation $q\\,\\mathrm{round}(y/q)$ (ties to even, as NumPy)."""
    y = _inexact(y)
    return q * jnp.round(y / q)


def sinusoid(n: int, amplitude, period, phase=0.0) -> Float[Array, " time"]:
    """Sinusoidal disturbance $A \\sin(2\\pi t/P + \\phi)$ for $t = 0, \\ldots, n-1$.

    `period` is in samples and `phase` in radians; the result has the float dtype of
    the parameters (the default float dtype for Python scalars).
    """
    t = jnp.arange(n)
    return amplitude * jnp.sin(2 * jnp.pi * t / period + phase)


def random_walk(key: PRNGKeyArray, n: int, step_std) -> Float[Array, " time"]:
    """Slow drift: a Gaussian random walk starting at 0 with step std `step_std`.

    $w(0) = 0$, $w(t) = w(t-1) + \\sigma\\,\\epsilon(t)$, $\\epsilon \\sim N(0, 1)$.
    """
    dtype = jnp.result_type(step_std, 1.0)
    eps = jr.normal(key, (n,), dtype).at[0].set(0)
    return jnp.cumsum(step_std * eps)
