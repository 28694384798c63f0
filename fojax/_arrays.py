"""Array helpers of the batch-last layout.

A value of one draw keeps its own axes first and a batch's axes last (``(3,)`` for one
draw, ``(3, draws)`` for a batch). Reading the entries of such a value one by one with
``x[i]`` is free in the forward pass but costs the reverse pass one padded cotangent
per entry, each padded back to the whole array and summed (``k`` pads and ``k - 1``
additions of the whole array per read value). :func:`unstack` reads them with one
``lax.split``, whose reverse is one concatenation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

Array = jax.Array


def unstack(x: Array, sizes: tuple[int, ...] | None = None, axis: int = 0) -> tuple:
    """The pieces of ``x`` along ``axis``: its entries (``sizes=None``, each without
    that axis) or consecutive parts of the given ``sizes`` (each keeping it)."""
    if sizes is None:
        parts = lax.split(x, (1,) * x.shape[axis], axis=axis)
        return tuple(part.squeeze(axis) for part in parts)
    return tuple(lax.split(x, tuple(sizes), axis=axis))


def as_time(t) -> Array:
    """``t`` as an array of a floating dtype (integers become the default float)."""
    t = jnp.asarray(t)
    if not jnp.issubdtype(t.dtype, jnp.floating):
        t = t.astype(jnp.result_type(float))
    return t
