"""Small shared helpers with no better home."""

import jax
import jax.numpy as jnp


def chunked_vmap(f, args, chunk: int):
    """`jax.vmap(f)(*args)` evaluated `chunk` members at a time (`lax.map` over
    chunks), so a large grid never materialises all its intermediates at once.
    Memory is that of one chunk; the result equals the plain `vmap`."""
    n = jax.tree.leaves(args)[0].shape[0]
    if n <= chunk:
        return jax.vmap(f)(*args)
    k = -(-n // chunk)
    pad = k * chunk - n

    def prep(x):
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x
        return x.reshape((k, chunk) + x.shape[1:])

    out = jax.lax.map(lambda a: jax.vmap(f)(*a), jax.tree.map(prep, args))
    return jax.tree.map(lambda y: y.reshape((k * chunk,) + y.shape[2:])[:n], out)
