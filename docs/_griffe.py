"""A griffe extension for the API pages (mkdocs.yml: mkdocstrings' `extensions`).

The pages load jaxstiction by inspection (`force_inspection`), because the jitted
entry points (`estimate = eqx.filter_jit(...)`) and the `Class.__init__.__doc__`
assignments exist only at run time. Inspection gives a class attribute the
docstring of its value's type (`validate = 1/3` would read "Convert a string or
number to a floating point number"); this drops such borrowed docstrings, so an
attribute is described by its class's docstring, as written.
"""

import inspect

import griffe


class DropBorrowedDocstrings(griffe.Extension):
    def on_attribute_instance(self, *, node, attr, **kwargs):
        if attr.docstring is None:
            return
        obj = getattr(node, "obj", None)
        if obj is None or isinstance(obj, type):
            return
        own = getattr(type(obj), "__doc__", None)
        if not isinstance(own, str) or inspect.cleandoc(own) == attr.docstring.value:
            attr.docstring = None

    def on_function_instance(self, *, node, func, **kwargs):
        # a class without its own `__init__` docstring would show object's
        # "Initialize self.  See help(type(self)) for accurate signature."
        if func.name == "__init__" and func.docstring is not None:
            if func.docstring.value == inspect.cleandoc(object.__init__.__doc__):
                func.docstring = None
