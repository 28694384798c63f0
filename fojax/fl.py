"""Feedback linearization (FL): cancel the nominal model, then a PD law per axis.

The paper's FL comparison [37] is not specified; this is the textbook form
(Slotine & Li, *Applied Nonlinear Control*, 1991, Ch. 6; for quadrotors e.g.
Voos, "Nonlinear control of a quadrotor micro-UAV using feedback-linearization",
IEEE ICM 2009): with the model terms cancelled by the cascade of
:mod:`fojax.cascade` (drag ``b x'`` in the position loop, coupling and drag
``F(eta')`` in the attitude loop, eq. (13) for thrust and attitude), each axis is the
double integrator ``e1'' = a + d`` and

    a = -k_p e1 - k_d e2                                                (FL)

with ``e1 = q - q_r``, ``e2 = q' - q_r'``. Closed loop ``e1'' + k_d e1' + k_p e1 = d``:
a constant disturbance ``d`` leaves the steady-state error ``e1 = d / k_p``
(:meth:`FL.steady_state_error`); FL has no robust term.

``ControlInfo.surfaces`` holds the PD error ``e2 + (k_p / k_d) e1`` (the combination
the law feeds back, ``a = -k_d (e2 + (k_p/k_d) e1)``); ``adaptive`` is zero.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from fojax.cascade import Cascade, CascadeParams, LawOutput, axes_gains, default_dtype
from fojax.controller import Bounds, check_bounds

Array = jax.Array


class FLGains(NamedTuple):
    """Gains of the FL controller, each ``(6,)`` over ``(x, y, z, phi, theta, psi)``.

    proportional: ``k_p`` (> 0), 1/s^2.
    derivative: ``k_d`` (> 0), 1/s.
    """

    proportional: Array
    derivative: Array


# Closed-loop poles of the defaults (rad/s), per axis group (x/y, z, attitude): a slow
# pole equal to the AFONFTSMC's surface slope at the settling band and a fast pole
# (see default_gains and docs/model.md, "Compared controllers").
DEFAULT_POLES = {"slow": (0.133, 3.29, 26.3), "fast": (4.0, 10.0, 80.0)}


def default_gains(dtype: Any = None) -> FLGains:
    """Our defaults (no published FL gains exist for this comparison).

    Real closed-loop poles ``p_slow`` and ``p_fast`` per axis group, ``k_p = p_slow
    p_fast`` and ``k_d = p_slow + p_fast``: ``p_slow`` = the AFONFTSMC's surface slope
    ``c1 |e|^(p/q - 1)`` at the settling band (0.133, 3.29, 26.3 for x/y, z,
    attitude), ``p_fast`` = (4, 10, 80) rad/s, chosen so that FL's undisturbed
    transient is comparable with the AFONFTSMC's while the position poles stay below
    the attitude loop's.
    """
    dtype = default_dtype(dtype)
    slow, fast = DEFAULT_POLES["slow"], DEFAULT_POLES["fast"]
    kp = [s * f for s, f in zip(slow, fast, strict=True)]
    kd = [s + f for s, f in zip(slow, fast, strict=True)]
    return FLGains(proportional=axes_gains(*kp, dtype), derivative=axes_gains(*kd, dtype))


GAINS_BOUNDS = {"proportional": Bounds(0.0), "derivative": Bounds(0.0)}
"""Positive gains: the closed loop ``s^2 + k_d s + k_p`` is then stable (Hurwitz)."""

GAINS_SHAPES = {name: (6,) for name in GAINS_BOUNDS}


def check_gains(gains: FLGains) -> None:
    """Raise ``ValueError`` naming every entry that is not finite, positive, ``(6,)``."""
    check_bounds(gains, GAINS_BOUNDS, GAINS_SHAPES, "FL")


@dataclasses.dataclass(frozen=True)
class FL(Cascade):
    """Feedback linearization + PD (see the module docstring).

    Args: those of :class:`fojax.cascade.Cascade` (``dt``, ``horizon``, command filter).
    """

    name = "fl"
    gains_type = FLGains
    gains_bounds = GAINS_BOUNDS

    @staticmethod
    def default_gains(dtype: Any = None) -> FLGains:
        return default_gains(dtype)

    @staticmethod
    def check_gains(gains: FLGains) -> None:
        check_gains(gains)

    @staticmethod
    def steady_state_error(gains: FLGains, disturbance: Array) -> Array:
        """``(..., 6)`` steady-state error ``d / k_p`` under a constant disturbance
        ``d`` ``(..., 6)`` (m/s^2, rad/s^2) on the nominal double integrator."""
        return jnp.asarray(disturbance) / jnp.asarray(gains.proportional)

    def _law(
        self, params: CascadeParams, axes: slice, law_state: Any, e1: Array, e2: Array
    ) -> tuple[Any, LawOutput]:
        kp = params.gains.proportional[axes]
        kd = params.gains.derivative[axes]
        acceleration = -kp * e1 - kd * e2
        surface = e2 + kp / kd * e1
        return law_state, LawOutput(acceleration, surface, jnp.zeros((3, 3), e1.dtype))
