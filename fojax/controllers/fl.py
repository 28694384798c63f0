"""Feedback linearization (FL): cancel the nominal model, then a PD law per axis.

The paper's FL comparison [37] is not specified; this is the textbook form
(Slotine & Li, *Applied Nonlinear Control*, 1991, Ch. 6; for quadrotors e.g.
Voos, "Nonlinear control of a quadrotor micro-UAV using feedback-linearization",
IEEE ICM 2009): with the model terms cancelled by the cascade of
:mod:`fojax.controllers.cascade`, each axis is the double integrator ``e1'' = a + d``
and

    a = -k_p e1 - k_d e2                                                (FL)

with ``e1 = q - q_r``, ``e2 = q' - q_r'``. Closed loop ``e1'' + k_d e1' + k_p e1 = d``:
a constant disturbance ``d`` leaves the steady-state error ``e1 = d / k_p``
(:meth:`FL.steady_state_error`); FL has no robust term.

``ControlInfo.surfaces`` holds the PD error ``e2 + (k_p / k_d) e1`` (the combination
the law feeds back, ``a = -k_d (e2 + (k_p/k_d) e1)``); ``adaptive`` is zero.

Default gains (ours: no published FL gains exist for this comparison): real
closed-loop poles ``p_slow`` and ``p_fast`` per axis group, ``k_p = p_slow p_fast`` and
``k_d = p_slow + p_fast``: ``p_slow`` = the AFONFTSMC's surface slope
``c1 |e|^(p/q - 1)`` at the settling band (0.133, 3.29, 26.3 for x/y, z, attitude),
``p_fast`` = (4, 10, 80) rad/s, so that FL's undisturbed transient is comparable with
the AFONFTSMC's while the position poles stay below the attitude loop's.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from fojax.controllers.base import ControlLaw, LawOutput
from fojax.controllers.gains import Bounds, GainField, GainSpec, per_axis
from fojax.controllers.registry import register

Array = jax.Array

__all__ = ["DEFAULT_POLES", "FL", "FLGains"]

DEFAULT_POLES = {"slow": (0.133, 3.29, 26.3), "fast": (4.0, 10.0, 80.0)}
"""Closed-loop poles (rad/s) of the default gains per axis group (x/y, z, attitude)."""

_SLOW, _FAST = DEFAULT_POLES["slow"], DEFAULT_POLES["fast"]
_KP = per_axis(*(s * f for s, f in zip(_SLOW, _FAST, strict=True)))
_KD = per_axis(*(s + f for s, f in zip(_SLOW, _FAST, strict=True)))
# fmt: off
GAINS = GainSpec(
    "FLGains",
    [
        GainField("proportional", _KP, Bounds(0.0), doc="``k_p``, 1/s^2."),
        GainField("derivative", _KD, Bounds(0.0),
                  doc="``k_d``, 1/s (positive gains: a Hurwitz closed loop)."),
    ],
    "FL",
)
# fmt: on
FLGains = GAINS.type


@register
@dataclasses.dataclass(frozen=True)
class FL(ControlLaw):
    """Feedback linearization + PD (see the module docstring). Args: ``dt``, ``horizon``."""

    name = "fl"
    GAINS = GAINS

    @staticmethod
    def steady_state_error(gains: FLGains, disturbance: Array) -> Array:
        """``(..., 6)`` steady-state error ``d / k_p`` under a constant disturbance
        ``d`` ``(..., 6)`` (m/s^2, rad/s^2) on the nominal double integrator."""
        return jnp.asarray(disturbance) / jnp.asarray(gains.proportional)

    def step(self, params: FLGains, state: Any, e1: Array, e2: Array):
        kp, kd = params.proportional, params.derivative
        acceleration = -kp * e1 - kd * e2
        surface = e2 + kp / kd * e1
        return state, LawOutput(acceleration, surface)
