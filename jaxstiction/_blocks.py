r"""The block library: valve, actuator and sensor physics as composable Modules.

Every block is an `eqx.Module` whose fields are its parameters, with

- `init(u0) -> state`: the state of a block at rest at input `u0`;
- `step(state, u) -> (state, out)`: one sample, usable inside `lax.scan`;
- `initial_states(u_open, count) -> states`: a batch (leading axis) of candidate
  initial states when the state at the start of a record is unknown (a stuck valve
  may have stopped anywhere, after travelling up or down), built from the opening
  input samples `u_open`; the default is `init(u_open[0])` alone;
- `__call__(u, state=None)`: the block run over a whole signal.

Blocks on the **input side** sit between the controller output OP and the process
input (order in a real loop: actuator lag / rate limit → stiction or deadband →
travel limits → inherent characteristic → dead time). Blocks on the **output side**
act on the process output (`side = "output"`): external sinusoid, narrow-band
disturbance, drift, sensor quantisation. All valve quantities are in % of span.

[`jaxstiction.BLOCKS`][] maps each name to its class; [`jaxstiction.make_block`][]
builds one from a name and parameters (as in a nominal-model file).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
from jaxtyping import Array, Float


def _levels(u_open, count: int):
    """Running maximum and minimum of the opening samples `u_open` at up to `count`
    of the samples where each reaches a new extreme: the input levels whose first
    crossing gives the distinct first slip times there. Every one of them when there
    are at most `count` such samples (the last repeated to fill `count`), else
    `count` spread evenly over them."""
    u = jnp.asarray(u_open)
    n = u.shape[0]

    def at_new_extremes(run):
        new = jnp.concatenate([jnp.ones((1,), bool), run[1:] != run[:-1]])
        k = jnp.sum(new)
        pos = jnp.nonzero(new, size=n, fill_value=n - 1)[0]
        i = jnp.arange(count)
        spread = jnp.round(i * (k - 1) / max(count - 1, 1)).astype(i.dtype)
        return run[pos[jnp.where(k <= count, jnp.minimum(i, k - 1), spread)]]

    return at_new_extremes(jax.lax.cummax(u)), at_new_extremes(jax.lax.cummin(u))


def _stops(u_open, count: int, S, J):
    """Where a stopped two-parameter valve may have stopped (`us`) and which way it
    last travelled (`d`), so that its first slip is every distinct one the opening
    samples allow: after rising (d = +1) it slips up past the running max M with
    us = M - J, or down past the running min m with us = m + S; after falling,
    us = m + J (down) or M - S (up)."""
    up, dn = _levels(u_open, count)
    one = jnp.ones_like(up)
    return jnp.concatenate([up - J, dn + S, dn + J, up - S]), jnp.concatenate([one, one, -one, -one])


def _exceeds(a, b, scale):
    """`a > b`, decided as exact arithmetic would where the two are equal up to
    rounding: a slip threshold met exactly (a quantised OP; the candidate initial
    states of `_stops`, built to slip just past a level the input reaches) must not
    slip or stick by the last bit, which would depend on OP's units and zero. The
    margin, 1e-12 of `scale`, is far above rounding and far below any valve's
    resolution."""
    return a > b + 1e-12 * scale


def _f(x) -> Array:
    """A parameter as an inexact JAX array (integers would truncate S, J)."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(jnp.result_type(float))
    return x


class AbstractBlock(eqx.Module):
    """A block of the loop: parameters are fields; `init`/`step` run it in `lax.scan`."""

    side: ClassVar[str] = "input"

    def init(self, u0):
        """State of the block at rest at input `u0`."""
        raise NotImplementedError

    def step(self, state, u):
        """One sample: `(new_state, output)`."""
        raise NotImplementedError

    def initial_states(self, u_open, count: int):
        """A batch of candidate initial states (leading axis) for an unknown start,
        from the opening input samples `u_open` (see the module docstring)."""
        return jax.tree.map(lambda t: jnp.asarray(t)[None], self.init(jnp.asarray(u_open)[0]))

    @eqx.filter_jit  # compiled once per block structure, not once per eager call
    def __call__(self, u: Float[Array, " time"], state=None) -> Float[Array, " time"]:
        """The block's output over a whole signal `u`, from `state` (default: at rest
        at `u[0]`)."""
        u = _f(u)
        if state is None:
            state = self.init(u[0])
        _, y = jax.lax.scan(lambda s, ut: self.step(s, ut), state, u)
        return y


# ---------------------------------------------------------------------------- stiction


class Kano(AbstractBlock):
    r"""Kano's (2004) stiction model: `S` deadband + stickband, `J` slip jump (% span).

    State `(y, us, stp, d, u_prev, du_prev)`: valve position, input where the valve
    stopped, 1 when stuck, direction (+1 up / −1 down), previous input and move::

        du = u - u_prev
        if du*du_prev <= 0 and stp == 0: us = u_prev; stp = 1   # stops or reverses
        if stp == 0:              y = u - d*(S-J)/2             # moving
        elif -d*(u - us) > S:     d = -d; y = u - d*(S-J)/2; stp = 0
        elif  d*(u - us) > J:     y = u - d*(S-J)/2; stp = 0
        else:                     y unchanged                   # stuck

    A threshold met exactly (up to rounding) is not exceeded, whatever the units of
    the input (see `_exceeds`).
    """

    S: Float[Array, ""] = eqx.field(converter=_f)
    J: Float[Array, ""] = eqx.field(converter=_f)

    def init(self, u0):
        u0 = jnp.asarray(u0)
        one = jnp.ones_like(u0)
        return (u0, u0, one, one, u0, jnp.zeros_like(u0))

    def step(self, state, u):
        S, J = self.S, self.J
        y, us, stp, d, u_prev, du_prev = state
        du = u - u_prev
        stops = (du * du_prev <= 0) & (stp == 0)
        us = jnp.where(stops, u_prev, us)
        stp = jnp.where(stops, 1.0, stp)
        moving = stp == 0
        scale = jnp.abs(u) + jnp.abs(us) + S
        reverse = (~moving) & _exceeds(-d * (u - us), S, scale)
        same = (~moving) & (~reverse) & _exceeds(d * (u - us), J, scale)
        d = jnp.where(reverse, -d, d)
        go = moving | reverse | same
        y = jnp.where(go, u - d * (S - J) / 2, y)
        stp = jnp.where(reverse | same, 0.0, stp)
        return (y, us, stp, d, u, du), y

    def initial_states(self, u_open, count: int):
        # Every distinct first slip of the opening samples (see `_stops`), plus the
        # two moving states. The held position itself is a free level (see
        # LoopModel.initial_state).
        stops, dirs = _stops(u_open, count, self.S, self.J)
        u0 = jnp.asarray(u_open)[0]
        S, J = self.S, self.J
        one = jnp.ones((1,), stops.dtype)
        us = jnp.concatenate([stops, u0[None], u0[None]])
        d = jnp.concatenate([dirs, one, -one])
        k = us.shape[0]
        stp = jnp.concatenate([jnp.ones((k - 2,), stops.dtype), jnp.zeros((2,), stops.dtype)])
        # moving: the previous input a hair behind in the travel direction
        eps = 1e-9 * (1 + jnp.abs(u0))
        u_prev = jnp.where(stp == 0, u0 - d * eps, u0)
        du_prev = jnp.where(stp == 0, d * eps, 0.0)
        y = jnp.where(stp == 0, u0 - d * (S - J) / 2, u0)
        return (y, us, stp, d, u_prev, du_prev)


class Choudhury(AbstractBlock):
    r"""Choudhury, Thornhill & Shah (2005) two-parameter stiction model (`S`, `J`).

    The valve sticks when the input velocity changes sign or becomes zero
    ($x_{ss} = x(t-1)$); a stuck valve slips when $|x - x_{ss}|$ exceeds `J` (input
    keeps the direction of the last travel) or `S` (input reverses); a moving valve
    sits at $x - \mathrm{sign}(v)(S-J)/2$. After the first stick event it gives the
    same output as [`jaxstiction.Kano`][]. State `(y, x_ss, stuck, v_old,
    direction, x_prev)`; direction 0 means unknown (first break-away needs `S`).
    """

    S: Float[Array, ""] = eqx.field(converter=_f)
    J: Float[Array, ""] = eqx.field(converter=_f)

    def init(self, u0):
        u0 = jnp.asarray(u0)
        zero = jnp.zeros_like(u0)
        return (u0, u0, jnp.ones_like(u0), zero, zero, u0)

    def step(self, state, x):
        S, J = self.S, self.J
        y, x_ss, stuck, v_old, direction, x_prev = state
        v_new = x - x_prev
        sgn = jnp.sign(v_new)
        stick = (stuck == 0) & (sgn != jnp.sign(v_old))
        x_ss = jnp.where(stick, x_prev, x_ss)
        stuck = jnp.where(stick, 1.0, stuck)
        disp = x - x_ss
        band = jnp.where(jnp.sign(disp) == direction, J, S)
        slip = (stuck == 1) & _exceeds(jnp.abs(disp), band, jnp.abs(x) + jnp.abs(x_ss) + S)
        move = (stuck == 0) | slip
        y = jnp.where(move, x - sgn * (S - J) / 2, y)
        direction = jnp.where(move, sgn, direction)
        stuck = jnp.where(slip, 0.0, stuck)
        return (y, x_ss, stuck, v_new, direction, x), y

    def initial_states(self, u_open, count: int):
        # as Kano: stuck where every distinct first slip of the opening samples happens
        xss, direction = _stops(u_open, count, self.S, self.J)
        u0 = jnp.asarray(u_open)[0]
        k = xss.shape[0]
        return (jnp.full((k,), u0), xss, jnp.ones((k,), xss.dtype), jnp.zeros((k,), xss.dtype), direction,
                jnp.full((k,), u0))


class He(AbstractBlock):
    r"""He, Wang, Pottmann & Qin (2007) semi-physical stiction model, in Kano's terms:
    static band $f_s = (S + J)/2$, kinetic band $f_d = (S - J)/2$.

    The residual force $u_r$ accumulates input moves; when $|u_r| > f_s$ the valve
    slips to $y + u_r - \mathrm{sign}(u_r) f_d$ and $u_r = \mathrm{sign}(u_r) f_d$.
    It equals Kano when $J = 0$ or when every move while travelling exceeds $J$; it
    re-sticks at low velocity where Kano keeps moving. State `(y, u_prev, u_r)`.
    """

    S: Float[Array, ""] = eqx.field(converter=_f)
    J: Float[Array, ""] = eqx.field(converter=_f)

    def init(self, u0):
        u0 = jnp.asarray(u0)
        return (u0, u0, jnp.zeros_like(u0))

    def step(self, state, u):
        fs, fd = (self.S + self.J) / 2, (self.S - self.J) / 2
        y, u_prev, u_r = state
        u_r = u_r + (u - u_prev)
        slip = _exceeds(jnp.abs(u_r), fs, jnp.abs(u) + fs)
        s = jnp.sign(u_r)
        y = jnp.where(slip, y + u_r - s * fd, y)
        u_r = jnp.where(slip, s * fd, u_r)
        return (y, u, u_r), y

    def initial_states(self, u_open, count: int):
        # residual force such that the valve slips when the input passes a level
        up, dn = _levels(u_open, count)
        u0 = jnp.asarray(u_open)[0]
        fs = (self.S + self.J) / 2
        ur = jnp.clip(jnp.concatenate([fs - (up - u0), -fs - (dn - u0)]), -fs, fs)
        k = ur.shape[0]
        # reachable states keep u_prev - y - u_r constant (0 from rest): y = u0 - u_r
        return (u0 - ur, jnp.full((k,), u0), ur)


class Deadband(AbstractBlock):
    r"""Deadband / backlash of total `width` (a play operator):
    $y(t) = \mathrm{clip}(y(t-1),\ u(t) - w/2,\ u(t) + w/2)$. Stiction with no slip
    jump: after the first stop it equals [`jaxstiction.Kano`][] with `S = width`,
    `J = 0`. State `(y,)`, at rest centred on the input."""

    width: Float[Array, ""] = eqx.field(converter=_f)

    def init(self, u0):
        return (jnp.asarray(u0),)

    def step(self, state, u):
        (y,) = state
        y = jnp.clip(y, u - self.width / 2, u + self.width / 2)
        return (y,), y

    def initial_states(self, u_open, count: int):
        # resting where the input leaves the band at a level of the opening samples
        up, dn = _levels(u_open, count)
        return (jnp.concatenate([up - self.width / 2, dn + self.width / 2]),)


# ------------------------------------------------------------------- other input blocks


class ActuatorLag(AbstractBlock):
    r"""First-order actuator $x(t) = a\,x(t-1) + (1 - a)\,u(t)$, pole `a` in [0, 1)
    ($a = e^{-T_s/\tau}$; 0 passes the input through). At rest at the input."""

    a: Float[Array, ""] = eqx.field(converter=_f)

    def init(self, u0):
        return jnp.asarray(u0)

    def step(self, state, u):
        x = self.a * state + (1 - self.a) * u
        return x, x


class RateLimit(AbstractBlock):
    """Slew-rate limit: the output moves towards the input by at most `max_rate` per
    sample; where the limit is not active the output equals the input exactly."""

    max_rate: Float[Array, ""] = eqx.field(converter=_f)

    def init(self, u0):
        return jnp.asarray(u0)

    def step(self, state, u):
        du = u - state
        y = jnp.where(jnp.abs(du) > self.max_rate, state + jnp.sign(du) * self.max_rate, u)
        return y, y


class TravelLimits(AbstractBlock):
    """Mechanical travel limits of the stem: `clip(x, lo, hi)` (% of span)."""

    lo: Float[Array, ""] = eqx.field(converter=_f, default=-jnp.inf)
    hi: Float[Array, ""] = eqx.field(converter=_f, default=jnp.inf)

    def init(self, u0):
        return ()

    def step(self, state, u):
        return state, jnp.clip(u, self.lo, self.hi)


class EqualPercentage(AbstractBlock):
    r"""Inherent equal-percentage characteristic $100\,(R^{x/100} - 1)/(R - 1)$ with
    rangeability `R` (20–50 typically; `R = 1` is the linear valve)."""

    R: Float[Array, ""] = eqx.field(converter=_f)

    def init(self, u0):
        return ()

    def step(self, state, x):
        lin = self.R == 1
        R = jnp.where(lin, 2.0, self.R)
        f = (R ** (x / 100) - 1) / (R - 1) * 100
        return state, jnp.where(lin, x, f)


class DeadTime(AbstractBlock):
    """Dead time of `k` whole samples ($q^{-k}$); `k` is static (it sets the state
    length). At rest, the delay line holds the input."""

    k: int = eqx.field(static=True)

    def __check_init__(self):
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 0:
            raise ValueError(f"`k` must be a non-negative Python int, got {self.k!r}; pass e.g. 2.")

    def init(self, u0):
        return jnp.full((self.k,), u0, jnp.asarray(u0).dtype)

    def step(self, state, u):
        if self.k == 0:
            return state, u
        return jnp.concatenate([state[1:], jnp.asarray(u)[None]]), state[0]


# ------------------------------------------------------------------------ output side


class Sinusoid(AbstractBlock):
    r"""External oscillation added at the process output:
    $A \sin(2\pi t / P + \phi)$, `period` $P$ in samples, `phase` in radians."""

    side: ClassVar[str] = "output"
    amplitude: Float[Array, ""] = eqx.field(converter=_f)
    period: Float[Array, ""] = eqx.field(converter=_f)
    phase: Float[Array, ""] = eqx.field(converter=_f, default=0.0)

    def init(self, u0):
        return jnp.zeros_like(jnp.asarray(u0))

    def step(self, t, y):
        return t + 1, y + self.amplitude * jnp.sin(2 * jnp.pi * t / self.period + self.phase)


class Drift(AbstractBlock):
    r"""Slow drift added at the process output: a Gaussian random walk from 0,
    $w(t) = w(t-1) + \sigma\,\epsilon(t)$ ($w(0) = 0$), drawn from `key`."""

    side: ClassVar[str] = "output"
    step_std: Float[Array, ""] = eqx.field(converter=_f)
    key: Array = eqx.field(default_factory=lambda: jr.key_data(jr.key(0)))

    def init(self, u0):
        z = jnp.zeros_like(jnp.asarray(u0))
        return (z, z)

    def step(self, state, y):
        w, t = state
        eps = jr.normal(jr.fold_in(jr.wrap_key_data(self.key), t.astype(jnp.int32)), (), w.dtype)
        w = w + jnp.where(t > 0, self.step_std * eps, 0.0)
        return (w, t + 1), y + w


class NarrowBand(AbstractBlock):
    r"""Narrow-band external disturbance added at the process output: white noise
    through a resonator with poles $r e^{\pm 2\pi i/P}$,
    $w(t) = 2 r \cos(2\pi/P)\, w(t-1) - r^2 w(t-2) + \sigma \epsilon(t)$ from rest,
    with $\sigma$ set so that the stationary standard deviation of $w$ is `rms`;
    drawn from `key`. An oscillation of period `period` (samples) whose amplitude and
    phase wander over about $1/(1 - r)$ samples: no sinusoid fitted to one part of a
    record predicts another."""

    side: ClassVar[str] = "output"
    rms: Float[Array, ""] = eqx.field(converter=_f)
    period: Float[Array, ""] = eqx.field(converter=_f)
    r: Float[Array, ""] = eqx.field(converter=_f, default=0.99)
    key: Array = eqx.field(default_factory=lambda: jr.key_data(jr.key(0)))

    def init(self, u0):
        z = jnp.zeros_like(jnp.asarray(u0))
        return (z, z, z)

    def step(self, state, y):
        w1, w2, t = state
        c, r2 = jnp.cos(2 * jnp.pi / self.period), self.r**2
        # stationary variance of the AR(2) per unit innovation variance
        gain = (1 + r2) / ((1 - r2) * ((1 + r2) ** 2 - 4 * r2 * c**2))
        eps = jr.normal(jr.fold_in(jr.wrap_key_data(self.key), t.astype(jnp.int32)), (), w1.dtype)
        w = 2 * self.r * c * w1 - r2 * w2 + self.rms / jnp.sqrt(gain) * eps
        return (w, w1, t + 1), y + w


class Quantiser(AbstractBlock):
    r"""Sensor quantisation $q\,\mathrm{round}(y/q)$ (ties to even)."""

    side: ClassVar[str] = "output"
    step_size: Float[Array, ""] = eqx.field(converter=_f)

    def init(self, u0):
        return ()

    def step(self, state, y):
        return state, self.step_size * jnp.round(y / self.step_size)


BLOCKS: dict[str, type[AbstractBlock]] = {
    "kano": Kano,
    "choudhury": Choudhury,
    "he": He,
    "deadband": Deadband,
    "actuator_lag": ActuatorLag,
    "rate_limit": RateLimit,
    "travel_limits": TravelLimits,
    "equal_percentage": EqualPercentage,
    "dead_time": DeadTime,
    "sinusoid": Sinusoid,
    "drift": Drift,
    "narrow_band": NarrowBand,
    "quantiser": Quantiser,
}


def block_name(block: AbstractBlock) -> str:
    """The registry name of `block` (its class name in lower case if unregistered)."""
    for name, cls in BLOCKS.items():
        if type(block) is cls:
            return name
    return type(block).__name__.lower()


def make_block(name: str, **params) -> AbstractBlock:
    """Build a block of the library from its registry name and parameters,
    e.g. `make_block("kano", S=3.0, J=1.0)`.

    **Raises:** `ValueError` for an unknown name or wrong parameters (one line).
    """
    cls = BLOCKS.get(name)
    if cls is None:
        raise ValueError(f"unknown block {name!r}; known blocks: {', '.join(BLOCKS)}")
    try:
        return cls(**params)
    except TypeError as e:
        raise ValueError(f"block {name!r}: {e}") from None


def run_chain(blocks, u, states=None):
    """Run a chain of blocks over a signal; returns the output of the last block.

    `states` is a tuple with one initial state per block (default: each at rest at
    its own first input).
    """
    x = _f(u)
    if not blocks:
        return x

    def init_all(x0):
        out, v = [], x0
        for b in blocks:
            s = b.init(v)
            out.append(s)
            _, v = b.step(s, v)
        return tuple(out)

    if states is None:
        states = init_all(x[0])

    def step(ss, ut):
        new = []
        v = ut
        for b, s in zip(blocks, ss):
            s, v = b.step(s, v)
            new.append(s)
        return tuple(new), v

    _, y = jax.lax.scan(step, tuple(states), x)
    return y
