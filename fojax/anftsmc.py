"""Adaptive nonsingular fast terminal sliding mode control (ANFTSMC).

Labbadi & Cherkaoui, "Robust adaptive nonsingular fast terminal sliding-mode tracking
control for an uncertain quadrotor UAV subjected to disturbances", ISA Transactions
99 (2020) 290-304: the paper's reference [26] and its integer-order predecessor. The
surface is the nonsingular fast terminal one of Yang & Yang ("Nonsingular fast
terminal sliding-mode control for nonlinear dynamical systems", Int. J. Robust
Nonlinear Control 21 (2011) 1865-1879). On the nominal double integrator
``e'' = a + d`` that the cascade of :mod:`fojax.cascade` leaves per axis
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

Gains (Table 2 of the ISA paper, as given in the project's paper notes): position
``b = 0.03``, ``b' = 0.8``, ``c = 1.21``, ``beta = 5/3``, ``alpha = 2``,
``mu = (0.5, 0.001, 0.01)``; attitude ``b = 8.7406``, ``b' = 0.4838``, ``c = 11.718``,
``beta = 1.0885``, ``alpha = 1.2``, ``mu = (0.0118, 6.29e-4, 0.01)``. The constant
``h`` of (A3) has no value there: ours (:data:`DEFAULT_SWITCHING`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from fojax.cascade import Cascade, CascadeParams, LawOutput, abs_power, axes_gains, default_dtype
from fojax.controller import Bounds, check_bounds, signed_power, switching

Array = jax.Array


class ANFTSMCGains(NamedTuple):
    """Gains of the ANFTSMC, each ``(6,)`` over ``(x, y, z, phi, theta, psi)``.

    surface_b: ``b`` (> 0), weight of ``sig^alpha(e)`` in (A1).
    surface_b_rate: ``b'`` (> 0), weight of ``sig^beta(e')``.
    beta: ``beta`` in ``(1, 2)`` (nonsingular).
    alpha_ratio: ``alpha / beta`` (> 1), so that ``alpha > beta`` holds for every
        gain in the box (``alpha = beta * alpha_ratio``).
    reaching: ``c`` (> 0), proportional reaching gain.
    switching: ``h`` (>= 0), the constant part of the switching gain (A3).
    adaptation: ``(6, 3)`` rates ``(mu0, mu1, mu2)`` (>= 0) of (A4).
    boundary_layer: width of ``sat``/``tanh`` switching (> 0; unused by ``sign``).
    """

    surface_b: Array
    surface_b_rate: Array
    beta: Array
    alpha_ratio: Array
    reaching: Array
    switching: Array
    adaptation: Array
    boundary_layer: Array


DEFAULT_SWITCHING = (0.1, 0.1, 1.0)
"""Our ``h`` (x/y, z, attitude): not published; see ``docs/model.md``."""


def default_gains(dtype: Any = None) -> ANFTSMCGains:
    """Table 2 of Labbadi & Cherkaoui (ISA Trans. 2020) and our ``h``.

    Boundary layers (``sat``/``tanh`` only): 0.05 position, 0.2 attitude, as the
    AFONFTSMC's.
    """
    dtype = default_dtype(dtype)
    position_mu = (0.5, 0.001, 0.01)
    attitude_mu = (0.0118, 6.29e-4, 0.01)
    beta_position, beta_attitude = 5.0 / 3.0, 1.0885
    return ANFTSMCGains(
        surface_b=axes_gains(0.03, 0.03, 8.7406, dtype),
        surface_b_rate=axes_gains(0.8, 0.8, 0.4838, dtype),
        beta=axes_gains(beta_position, beta_position, beta_attitude, dtype),
        alpha_ratio=axes_gains(
            2.0 / beta_position, 2.0 / beta_position, 1.2 / beta_attitude, dtype
        ),
        reaching=axes_gains(1.21, 1.21, 11.718, dtype),
        switching=axes_gains(*DEFAULT_SWITCHING, dtype),
        adaptation=jnp.asarray([position_mu] * 3 + [attitude_mu] * 3, dtype),
        boundary_layer=axes_gains(0.05, 0.05, 0.2, dtype),
    )


GAINS_BOUNDS = {
    "surface_b": Bounds(0.0),
    "surface_b_rate": Bounds(0.0),
    "beta": Bounds(1.0, 2.0),
    "alpha_ratio": Bounds(1.0, symbol="alpha/beta"),
    "reaching": Bounds(0.0),
    "switching": Bounds(0.0, include_low=True),
    "adaptation": Bounds(0.0, include_low=True),
    "boundary_layer": Bounds(0.0),
}
"""The constraints of (A1)-(A4): positive weights and gains, ``1 < beta < 2``,
``alpha > beta`` (as ``alpha / beta > 1``), non-negative ``h`` and rates."""

GAINS_SHAPES = {name: ((6, 3) if name == "adaptation" else (6,)) for name in GAINS_BOUNDS}


def check_gains(gains: ANFTSMCGains) -> None:
    """Raise ``ValueError`` naming every entry that breaks (A1)-(A4)'s constraints."""
    check_bounds(gains, GAINS_BOUNDS, GAINS_SHAPES, "ANFTSMC")


@dataclasses.dataclass(frozen=True)
class ANFTSMC(Cascade):
    """Adaptive NFTSMC, laws (A1)-(A4) of the module docstring.

    Args: those of :class:`fojax.cascade.Cascade`, and
        switching: ``"sign"`` (default, the ISA paper's), ``"sat"`` or ``"tanh"``.
    """

    switching: str = "sign"

    name = "anftsmc"
    gains_type = ANFTSMCGains
    gains_bounds = GAINS_BOUNDS

    @staticmethod
    def default_gains(dtype: Any = None) -> ANFTSMCGains:
        return default_gains(dtype)

    @staticmethod
    def check_gains(gains: ANFTSMCGains) -> None:
        check_gains(gains)

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

    def _init_law(self, params: CascadeParams, dtype: Any):
        return (jnp.zeros((3, 3), dtype), jnp.zeros((3, 3), dtype))

    def _law(self, params, axes, law_state, e1, e2):
        g = params.gains
        b, b_rate = g.surface_b[axes], g.surface_b_rate[axes]
        beta = g.beta[axes]
        alpha = beta * g.alpha_ratio[axes]
        adaptive = law_state
        sigma = e1 + b * signed_power(e1, alpha) + b_rate * signed_power(e2, beta)
        gain = (
            adaptive[:, 0]
            + adaptive[:, 1] * jnp.abs(e1)
            + adaptive[:, 2] * jnp.abs(e2)
            + g.switching[axes]
        )
        sw = switching(self.switching, sigma, g.boundary_layer[axes])
        equivalent = (
            -signed_power(e2, 2.0 - beta) * (1.0 + alpha * b * abs_power(e1, alpha - 1.0))
        ) / (beta * b_rate)
        acceleration = equivalent - g.reaching[axes] * sigma - gain * sw
        rate_factor = abs_power(e2, beta - 1.0) * jnp.abs(sigma)
        regressor = jnp.stack(
            [rate_factor, rate_factor * jnp.abs(e1), rate_factor * jnp.abs(e2)], 1
        )
        new_adaptive = adaptive + self.dt * g.adaptation[axes] * regressor
        return new_adaptive, LawOutput(acceleration, sigma, adaptive)
