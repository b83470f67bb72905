"""`exported_call`, the on-disk cache of exported programs that spares a new process
tracing the what-if again: the same result as the plain call, saved once and loaded
by a new process (here: the in-memory table cleared) without exporting again, a
corrupt file rebuilt, a new entry for other shapes or other closed-over settings,
and the plain call when a function cannot be exported."""

import collections

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxstiction import _programs as programs


class _Thing(eqx.Module):
    x: jax.Array
    y: jax.Array
    label: str = eqx.field(static=True, default="a")


@eqx.filter_jit
def _f(t: _Thing, z, scale: float):
    return _Thing(x=jnp.cumsum(t.x) * scale + jnp.sum(z), y=t.y**2, label=t.label + "!"), jnp.max(t.x)


def _call(t, z, scale):
    return programs.exported_call("thing", lambda a, b: _f(a, b, scale), t, z, static=repr(scale))


def _same(a, b):
    for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        if isinstance(u, str):
            assert u == v
        else:
            np.testing.assert_array_equal(np.asarray(u), np.asarray(v))
    assert jax.tree.structure(a) == jax.tree.structure(b)


def test_exported_call_saves_loads_and_rebuilds(tmp_path, monkeypatch):
    monkeypatch.setattr(programs, "_loaded", collections.OrderedDict())
    t, z = _Thing(x=jnp.arange(5.0), y=jnp.ones(3)), jnp.asarray([1.0, 2.0])
    programs.use_folder(tmp_path)
    try:
        first = _call(t, z, 2.0)
        _same(first, _f(t, z, 2.0))
        (path,) = tmp_path.glob("thing-*.jaxexport")
        exports = []
        real = programs._export
        monkeypatch.setattr(programs, "_export", lambda *a: exports.append(1) or real(*a))
        monkeypatch.setattr(programs, "_loaded", collections.OrderedDict())
        _same(_call(t, z, 2.0), first)  # a new process: loaded, not exported
        assert exports == []
        path.write_bytes(b"not a program")
        monkeypatch.setattr(programs, "_loaded", collections.OrderedDict())
        _same(_call(t, z, 2.0), first)  # rebuilt
        assert exports == [1]
        # other closed-over settings, other shapes: other programs, right answers
        _same(_call(t, z, 3.0), _f(t, z, 3.0))
        longer = _Thing(x=jnp.arange(7.0), y=jnp.ones(3))
        _same(_call(longer, z, 2.0), _f(longer, z, 2.0))
        assert exports == [1, 1, 1] and len(list(tmp_path.glob("thing-*.jaxexport"))) == 3
    finally:
        programs.use_folder(None)


def test_exported_call_falls_back_to_the_plain_call(monkeypatch):
    monkeypatch.setattr(programs, "_loaded", collections.OrderedDict())

    def refuse(*a):
        raise RuntimeError("cannot export here")

    monkeypatch.setattr(programs, "_export", refuse)
    t, z = _Thing(x=jnp.arange(4.0), y=jnp.ones(2)), jnp.zeros(1)
    _same(_call(t, z, 1.5), _f(t, z, 1.5))
    assert not programs._loaded


def test_exported_call_keeps_only_the_latest_programs_in_memory(monkeypatch):
    monkeypatch.setattr(programs, "_loaded", collections.OrderedDict())
    monkeypatch.setattr(programs, "_KEEP", 2)
    z = jnp.zeros(1)
    for n in (3, 4, 5):
        t = _Thing(x=jnp.arange(float(n)), y=jnp.ones(2))
        _same(_call(t, z, 1.0), _f(t, z, 1.0))
    assert len(programs._loaded) == 2


def test_static_fields_of_the_arguments_key_the_program(monkeypatch):
    monkeypatch.setattr(programs, "_loaded", collections.OrderedDict())
    for label in ("a", "b"):  # same shapes, another static field: another program
        t = _Thing(x=jnp.arange(3.0), y=jnp.ones(2), label=label)
        out, _ = _call(t, jnp.zeros(1), 1.0)
        assert out.label == label + "!"
    assert len(programs._loaded) == 2
