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
from jax.ad_checkpoint import checkpoint_name

Array = jax.Array

KEPT = "fojax_kept"
"""The name of values a checkpointed step keeps for its reverse pass
(:func:`reverse_pass_boundary`; the simulator's checkpoint policy saves them)."""


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


def reverse_pass_boundary(values):
    """``values`` unchanged, marked as a boundary of the reverse pass: a checkpointed
    step keeps them as residuals (named :data:`KEPT`) and their cotangents are computed
    once, into memory, before anything reads them.

    Without the boundary XLA's CPU backend fuses a cheap chain (an RK4 stage's
    arithmetic and its transpose) into every kernel that reads its result, recomputing
    it in each: measured, three kernels of 600-700 operations per draw-step recomputed
    the RK4 stages' cotangents (docs/performance.md, design choices). The forward pass is
    unaffected: outside ``grad`` both marks are the identity.
    """
    return _cotangent_barrier(jax.tree.map(lambda v: checkpoint_name(v, KEPT), values))


@jax.custom_jvp
def _cotangent_barrier(values):
    return values


@_cotangent_barrier.defjvp
def _cotangent_barrier_jvp(primals, tangents):
    # The barrier on the tangents transposes to a barrier on the cotangents; the
    # primal values pass untouched (forward mode keeps working).
    return primals[0], lax.optimization_barrier(tangents[0])
