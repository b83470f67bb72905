"""Mismatch diagnosis: locate, name, model and prove (see `diagnose`'s notes).

`settings` (with the verdict vocabulary) is a leaf; `locate`, `drift` and
`characteristic` are the tests; `candidates` the blocks on their grids;
`heldout` scores a model held out; `significance` measures every family against
its bootstrap; `proof` judges a held-out gain against its spread; `joint` refits
stiction with the linear part; `diagnose` runs the steps in order.
"""
