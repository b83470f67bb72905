"""The estimator: one loop from OP and PV to a [`jaxstiction.LoopFit`][].

`settings` (with the screen's presets) and `result` are leaves; the stages
`relax`, `gram`, `reduce`, `hammerstein` (spline candidates) and `physical` (the
Kano fit) sit below `estimate`, the one jitted entry point; `programs` keeps
exported `estimate` programs on disk, and `report` reads a fit out for people
([`jaxstiction.fit`][]).
"""
