"""The fleet screen: every loop of a plant through one batched, jitted estimate and
verdict, then ranked.

`settings` is a leaf; `batch` fits chunks of loops (length buckets, threads,
Dask); `causes` names the causes of the loops not called sticky by the diagnosis;
`screen` reads, checks, runs and ranks; `html`, `figure` and `outputs` write the
screen's files.
"""
