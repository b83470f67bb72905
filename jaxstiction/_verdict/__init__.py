"""The stiction verdict of a fitted loop and its cause when it is not stiction.

`settings` is a leaf; `verdict` judges a [`jaxstiction.LoopFit`][] (pure JAX, vmapped
with `estimate`). Below the diagnosis and the screen, so that both can hold one
stiction policy.
"""
