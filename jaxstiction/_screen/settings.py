"""Settings of [`jaxstiction.screen`][] (a leaf)."""

from __future__ import annotations

import equinox as eqx

from .._checks import check_counts
from .._estimate.settings import SCREEN_ESTIMATE, Settings
from .._verdict.settings import VerdictSettings
from .._whatif.settings import WhatIfSettings


class ScreenSettings(eqx.Module):
    """Settings of [`jaxstiction.screen`][].

    - `estimate`: [`jaxstiction.Settings`][] of every fit (default: the screen's
      lighter profile, Kano valve and nulls only; `Settings()` for the full
      estimator); `verdict`: [`jaxstiction.VerdictSettings`][].
    - `chunk`: at most this many loops per batched call; `samples_per_call`: fewer
      when `chunk` × bucket length would exceed it (memory grows with both). 0 (the
      default) sizes each from the machine (`auto_batch`): on a CPU, 2 loops and
      8000 samples per call (the fastest on 2 cores, where XLA runs a call on one
      core); on a GPU or TPU, as many loops as a quarter of the device's memory
      holds, at most 1024 (on an NVIDIA H200, with one polish start in the Kano
      search, 1500-sample loops cost 0.090, 0.027 and 0.012 s each at 64, 256 and
      1024 loops per call). A `chunk` given is used as
      it is, cut by `samples_per_call` only when that is given too. The results do
      not depend on the chunk.
    - `threads`: batched calls run at once, each on its own thread (0: one per CPU
      core, at most 8). XLA's CPU backend runs one call's work on one core at a time, so a
      second call in flight uses a second core; memory grows with the calls in
      flight. (Without a Dask scheduler.)
    - `whatif`: [`jaxstiction.WhatIfSettings`][] to give every sticky loop a
      `whatif` object (what a repair would buy, `screen --whatif`); `None` (the
      default): none.
    """

    estimate: Settings = SCREEN_ESTIMATE
    verdict: VerdictSettings = VerdictSettings()
    chunk: int = eqx.field(static=True, default=0)
    samples_per_call: int = eqx.field(static=True, default=0)
    threads: int = eqx.field(static=True, default=0)
    whatif: WhatIfSettings | None = None

    def __check_init__(self):
        check_counts(self, nonnegative=("chunk", "samples_per_call", "threads"))
