"""Settings of [`jaxstiction.screen`][] (a leaf)."""

from __future__ import annotations

import equinox as eqx

from .._checks import check_counts
from .._estimate.settings import SCREEN_ESTIMATE, Settings
from .._verdict.settings import VerdictSettings


class ScreenSettings(eqx.Module):
    """Settings of [`jaxstiction.screen`][].

    - `estimate`: [`jaxstiction.Settings`][] of every fit (default: the screen's
      lighter profile, Kano valve and nulls only; `Settings()` for the full
      estimator); `verdict`: [`jaxstiction.VerdictSettings`][].
    - `chunk`: at most this many loops per batched call; `samples_per_call`: fewer
      when `chunk` × bucket length would exceed it (memory grows with both).
    - `threads`: batched calls run at once, each on its own thread (0: one per CPU
      core, at most 8). XLA's CPU backend runs one call's work on one core at a time, so a
      second call in flight uses a second core; memory grows with the calls in
      flight. (Without a Dask scheduler.)
    """

    estimate: Settings = SCREEN_ESTIMATE
    verdict: VerdictSettings = VerdictSettings()
    chunk: int = eqx.field(static=True, default=2)
    samples_per_call: int = eqx.field(static=True, default=8000)
    threads: int = eqx.field(static=True, default=0)

    def __check_init__(self):
        check_counts(self, positive=("chunk", "samples_per_call"), nonnegative=("threads",))
