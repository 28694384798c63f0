"""Adaptive nonsingular fast terminal sliding mode control (ANFTSMC).

Labbadi & Cherkaoui, "Robust adaptive nonsingular fast terminal sliding-mode tracking
control for an uncertain quadrotor UAV subjected to disturbances", ISA Transactions
99 (2020) 290-304: the paper's reference [26] and its integer-order predecessor. The
surface is the nonsingular fast terminal one of Yang & Yang ("Nonsingular fast
terminal sliding-mode control for nonlinear dynamical systems", Int. J. Robust
Nonlinear Control 21 (2011) 1865-1879). On the nominal double integrator
``e'' = a + d`` that the cascade of :mod:`fojax.controllers.cascade` leaves per axis
(``e = q - q_r``, model terms cancelled, eq. (13)):

    sigma = e + b sig^alpha(e) + b' sig^beta(e'),   1 < beta < 2, alpha > beta   (A1)
    a     = -1/(beta b') sig^(2-beta)(e') (1 + alpha b |e|^(alpha-1))
            - c sigma - K sw(sigma)                                              (A2)
    K     = a0 + a1 |e| + a2 |e'| + h                                            (A3)
    a0'   = mu0 |sigma| |e'|^(beta-1),  a1' = mu1 |sigma| |e| |e'|^(beta-1),
    a2'   = mu2 |sigma| |e'|^beta                                                (A4)

with ``sig^r(x) = |x|^r sign(x)``. The first term of (A2) cancels
``e' (1 + alpha b |e|^(alpha-1))`` in ``sigma'``, so
``sigma' = beta b' |e'|^(beta-1) (-c sigma - K sw(sigma) + d)``: the factor
``|e'|^(beta-1) >= 0`` only slows the reaching where ``e' = 0``, which is not an
invariant set off ``sigma = 0`` (Yang & Yang). The adaptive gains (A4), integrated by
forward Euler at the control step from 0, carry the same factor.

A constant disturbance ``d`` with ``K < |d|`` leaves an equilibrium ``e' = 0``,
``c sigma = d - K sign(sigma)``, where the adaptation (A4) stops (``|e'| = 0``), so
``|e| <= |sigma| <= max(|d| - h, 0) / c`` with ``sign``
(:meth:`ANFTSMC.steady_state_error_bound`, also for ``sat``/``tanh``;
``|e| <= |sigma|`` because ``e`` and ``b sig^alpha(e)`` share a sign).

Gains (Table 2 of the ISA paper): position
``b = 0.03``, ``b' = 0.8``, ``c = 1.21``, ``beta = 5/3``, ``alpha = 2``,
``mu = (0.5, 0.001, 0.01)``; attitude ``b = 8.7406``, ``b' = 0.4838``, ``c = 11.718``,
``beta = 1.0885``, ``alpha = 1.2``, ``mu = (0.0118, 6.29e-4, 0.01)``. The constant
``h`` of (A3) has no value there: ours (:data:`DEFAULT_SWITCHING`). Boundary layers
(``sat``/``tanh`` only): 0.05 position, 0.2 attitude, as the AFONFTSMC's.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from fojax._arrays import unstack
from fojax.controllers.base import ControlLaw, LawOutput, abs_power, signed_power, switching
from fojax.controllers.gains import Bounds, GainField, GainSpec, per_axis
from fojax.controllers.registry import register

Array = jax.Array

__all__ = ["ANFTSMC", "ANFTSMCGains", "DEFAULT_SWITCHING"]

DEFAULT_SWITCHING = (0.1, 0.1, 1.0)
"""Our ``h`` (x/y, z, attitude): not published; see ``docs/model.md``."""

_BETA_XY, _BETA_ATT = 5.0 / 3.0, 1.0885  # position, attitude
# fmt: off
GAINS = GainSpec(
    "ANFTSMCGains",
    [
        GainField("surface_b", per_axis(0.03, 0.03, 8.7406), Bounds(0.0),
                  doc="``b``, weight of ``sig^alpha(e)`` in (A1)."),
        GainField("surface_b_rate", per_axis(0.8, 0.8, 0.4838), Bounds(0.0),
                  doc="``b'``, weight of ``sig^beta(e')``."),
        GainField("beta", per_axis(_BETA_XY, _BETA_XY, _BETA_ATT), Bounds(1.0, 2.0),
                  doc="``beta`` (nonsingular)."),
        GainField("alpha_ratio", per_axis(2.0 / _BETA_XY, 2.0 / _BETA_XY, 1.2 / _BETA_ATT),
                  Bounds(1.0, symbol="alpha/beta"),
                  doc="``alpha / beta``, so that ``alpha > beta`` holds for every gain."),
        GainField("reaching", per_axis(1.21, 1.21, 11.718), Bounds(0.0),
                  doc="``c``, proportional reaching gain."),
        GainField("switching", per_axis(*DEFAULT_SWITCHING), Bounds(0.0, include_low=True),
                  doc="``h``, the constant part of the switching gain (A3)."),
        GainField("adaptation", [(0.5, 0.001, 0.01)] * 3 + [(0.0118, 6.29e-4, 0.01)] * 3,
                  Bounds(0.0, include_low=True),
                  doc="rates ``(mu0, mu1, mu2)`` of (A4).", search_high=5.0),
        GainField("boundary_layer", per_axis(0.05, 0.05, 0.2), Bounds(0.0), role="smoothing",
                  doc="width of ``sat``/``tanh`` switching (unused by ``sign``)."),
    ],
    "ANFTSMC",
)
# fmt: on
ANFTSMCGains = GAINS.type


@register
@dataclasses.dataclass(frozen=True)
class ANFTSMC(ControlLaw):
    """Adaptive NFTSMC, laws (A1)-(A4) of the module docstring.

    Args: ``dt``, ``horizon``, and
        switching: ``"sign"`` (default, the ISA paper's), ``"sat"`` or ``"tanh"``.
    """

    switching: str = "sign"

    name = "anftsmc"
    GAINS = GAINS

    def steady_state_error_bound(self, gains: ANFTSMCGains, disturbance: Array) -> Array:
        """``(..., 6)`` bound on the steady-state ``|e|`` under a constant disturbance
        ``d`` ``(..., 6)`` (m/s^2, rad/s^2) on the nominal double integrator.

        At an equilibrium ``e' = 0`` and ``c sigma + K sw(sigma) = d`` with ``K >= h``
        (the adaptive part is >= 0 and only lowers the bound), and ``|e| <= |sigma|``:
        ``sign``: ``max(|d| - h, 0) / c``; ``sat``: ``|d| / (c + h / w)`` when that lies
        in the layer ``|sigma| <= w``, the ``sign`` value otherwise; ``tanh``:
        ``min(|d| / c, w artanh(|d| / h))``. Near ``e' = 0`` the approach is slow
        (the ``sig^(2 - beta)(e')`` term), so the bound is reached from below.
        """
        d = jnp.abs(jnp.asarray(disturbance))
        h, c = jnp.asarray(gains.switching), jnp.asarray(gains.reaching)
        w = jnp.asarray(gains.boundary_layer)
        outside = jnp.maximum(d - h, 0.0) / c
        if self.switching == "sign":
            return outside
        if self.switching == "sat":
            inside = d / (c + h / w)
            return jnp.where(inside <= w, inside, outside)
        ratio = jnp.where(h > 0, d / jnp.where(h > 0, h, 1.0), jnp.inf)
        layer = jnp.where(ratio < 1.0, w * jnp.arctanh(jnp.minimum(ratio, 0.999999)), jnp.inf)
        return jnp.minimum(d / c, layer)

    def init(self, params: ANFTSMCGains, dtype: Any) -> Array:
        return jnp.zeros((6, 3), dtype)

    def step(self, params: ANFTSMCGains, adaptive: Array, e1: Array, e2: Array):
        g = params
        beta = g.beta
        alpha = beta * g.alpha_ratio
        sigma = (
            e1 + g.surface_b * signed_power(e1, alpha) + g.surface_b_rate * signed_power(e2, beta)
        )
        a0, a1, a2 = unstack(adaptive, axis=1)
        gain = a0 + a1 * jnp.abs(e1) + a2 * jnp.abs(e2)
        gain = gain + g.switching
        sw = switching(self.switching, sigma, g.boundary_layer)
        equivalent = (
            -signed_power(e2, 2.0 - beta) * (1.0 + alpha * g.surface_b * abs_power(e1, alpha - 1.0))
        ) / (beta * g.surface_b_rate)
        acceleration = equivalent - g.reaching * sigma - gain * sw
        rate_factor = abs_power(e2, beta - 1.0) * jnp.abs(sigma)
        regressor = jnp.stack(
            [rate_factor, rate_factor * jnp.abs(e1), rate_factor * jnp.abs(e2)], 1
        )
        new_adaptive = adaptive + self.dt * g.adaptation * regressor
        return new_adaptive, LawOutput(acceleration, sigma, adaptive)
