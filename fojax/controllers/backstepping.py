"""Backstepping sliding mode control (BSMC) and its fractional-order variant (FOBSMC).

The paper compares against BSMC [9], [10] and FOBSMC [17] without giving their laws
or gains. Both are written here in the standard backstepping form of Bouabdallah &
Siegwart ("Backstepping and sliding-mode techniques applied to an indoor micro
quadrotor", IEEE ICRA 2005) with a sliding surface as the second backstepping error
(as in Bouadi & Tadjine, "Sliding mode control based on backstepping approach for an
UAV type-quadrotor", 2007), on the nominal double integrator ``e1'' = a + d`` that
the cascade of :mod:`fojax.controllers.cascade` leaves per axis.

BSMC, per axis, with ``e1 = q - q_r``, ``e2 = q' - q_r'``:

    z1 = e1,                 virtual rate q'_d = q_r' - lambda z1
    s  = z2 = q' - q'_d = e2 + lambda e1                                  (B1)
    a  = -z1 - lambda e2 - k s - q_s sw(s)                                (B2)

``V = z1^2/2 + s^2/2`` gives ``V' = -lambda z1^2 - k s^2 - q_s |s| + s d`` (with
``sw = sign``): the ``-z1`` term is the backstepping cross term. A disturbance with
``|d| < q_s`` is rejected: ``s`` reaches 0 in finite time and ``e1`` then decays as
``exp(-lambda t)``. With a boundary layer (``sat``, width ``w``) a constant ``d``
leaves ``|e1| = |d| / (1 + k lambda + q_s lambda / w)`` at steady state while that
lies in the layer (:meth:`BSMC.steady_state_error_bound`).

FOBSMC replaces the integer-order surface term ``lambda e1`` by its fractional
counterpart, as the AFONFTSMC does (``D^(gamma - 1)`` a Riemann-Liouville integral of
order ``1 - gamma``, :mod:`fojax.fractional`):

    s = e2 + lambda D^(gamma-1) e1                                        (F1)
    a = -e1 - lambda D^gamma e1 - k s - q_s sw(s)                         (F2)

``D^gamma e1`` is the time derivative of ``D^(gamma-1) e1``, read from the same
fractional memory, so ``s' = a + lambda D^gamma e1 + d`` exactly and the reaching law
gives ``s s' = -k s^2 - q_s |s| + s (d - e1)``; ``gamma -> 1`` is BSMC.

Gains (ours: no published ones): ``lambda`` the AFONFTSMC's surface slope ``c1
|e|^(p/q - 1)`` at the settling band (0.05 m, 0.05 rad), ``k`` its ``hbar_2``, ``q_s``
its ``hbar_1``, its boundary layers, and ``gamma = 0.9``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from fojax.controllers.base import ControlLaw, FractionalMemory, LawOutput, switching
from fojax.controllers.gains import Bounds, GainField, GainSpec, per_axis
from fojax.controllers.registry import register

Array = jax.Array

__all__ = ["BSMC", "BSMCGains", "FOBSMC", "FOBSMCGains"]

# fmt: off
_BSMC_FIELDS = [
    GainField("surface", per_axis(0.133, 3.29, 26.3), Bounds(0.0),
              doc="``lambda``, slope of the surface (B1), 1/s."),
    GainField("reaching", per_axis(0.2204, 0.8876, 5.8670), Bounds(0.0),
              doc="``k``, proportional reaching gain, 1/s."),
    GainField("switching", per_axis(2.6044, 16.1251, 156.4373), Bounds(0.0, include_low=True),
              doc="``q_s``, switching gain, m/s^2 or rad/s^2."),
    GainField("boundary_layer", per_axis(0.05, 0.05, 0.2), Bounds(0.0), role="smoothing",
              doc="width ``w`` of ``sat``/``tanh`` switching (unused by ``sign``)."),
]
BSMC_GAINS = GainSpec("BSMCGains", _BSMC_FIELDS, "BSMC")
FOBSMC_GAINS = GainSpec(
    "FOBSMCGains",
    [
        *_BSMC_FIELDS,
        GainField("order", [0.9] * 6, Bounds(0.0, 1.0, symbol="gamma"), integer_order=1.0,
                  doc="``gamma``: the surface (F1) holds ``D^(gamma-1) e1`` (1: ``e1``)."),
    ],
    "FOBSMC",
)
# fmt: on
BSMCGains = BSMC_GAINS.type
FOBSMCGains = FOBSMC_GAINS.type


def _steady_state_error(gains, disturbance, kind: str) -> Array:
    """Steady-state ``|e1|`` ``(..., 6)`` of (B1)-(B2) under a constant disturbance.

    At an equilibrium ``e2 = 0``, ``s = lambda e1`` and (B2) gives
    ``|d| = (1 + k lambda) |e1| + q_s sw(lambda |e1|)``, monotone in ``|e1|``:
    ``sign``: ``max(|d| - q_s, 0) / (1 + k lambda)``; ``sat``: ``|d| / (1 + k lambda +
    q_s lambda / w)`` inside the layer, the ``sign`` value beyond it; ``tanh``: the
    upper bound ``min(|d| / (1 + k lambda), (w / lambda) artanh(|d| / q_s))``.
    """
    d = jnp.abs(jnp.asarray(disturbance))
    q, k = jnp.asarray(gains.switching), jnp.asarray(gains.reaching)
    lam, w = jnp.asarray(gains.surface), jnp.asarray(gains.boundary_layer)
    outside = jnp.maximum(d - q, 0.0) / (1.0 + k * lam)
    if kind == "sign":
        return outside
    if kind == "sat":
        inside = d / (1.0 + k * lam + q * lam / w)
        return jnp.where(lam * inside <= w, inside, outside)
    ratio = jnp.where(q > 0, d / jnp.where(q > 0, q, 1.0), jnp.inf)
    layer = jnp.where(ratio < 1.0, w / lam * jnp.arctanh(jnp.minimum(ratio, 0.999999)), jnp.inf)
    return jnp.minimum(d / (1.0 + k * lam), layer)


def _reach(kind: str, g, e1, e2, surface, surface_term_rate) -> Array:
    """``a = -e1 - lambda (surface term)' - k s - q_s sw(s)`` (B2)/(F2), ``(6,)``."""
    sw = switching(kind, surface, g.boundary_layer)
    return -e1 - g.surface * surface_term_rate - g.reaching * surface - g.switching * sw


class FOBSMCParams(NamedTuple):
    """The gains and the fractional weights of ``(D^(gamma-1), D^gamma)``."""

    gains: Any
    weights: Any


@register
@dataclasses.dataclass(frozen=True)
class FOBSMC(FractionalMemory, ControlLaw):
    """Fractional-order backstepping sliding mode control, laws (F1)-(F2).

    Args: ``dt``, ``horizon``, and
        switching: ``"sign"`` (default, as the paper's comparison), ``"sat"`` or ``"tanh"``
            with the gains' ``boundary_layer``.
        fractional_method: ``"soe"`` (accurate default), ``"oustaloup"`` (CRONE) or
            ``"gl"`` (:mod:`fojax.fractional`).
        fractional_options: extra options of the operator, ``(name, value)`` pairs.

    ``memory`` (:class:`FractionalMemory`): ``D^(gamma-1) e1`` and its time derivative
    ``D^gamma e1`` from one memory, the integral of order ``1 - gamma`` and its rate.
    """

    switching: str = "sign"
    fractional_method: str = "soe"
    fractional_options: tuple = ()

    name = "fobsmc"
    GAINS = FOBSMC_GAINS

    def steady_state_error_bound(self, gains: FOBSMCGains, disturbance: Array) -> Array:
        """``(..., 6)`` steady-state ``|e1|`` under a constant disturbance ``d``: 0.

        No equilibrium with ``e1 != 0`` exists: the fractional integral
        ``D^(gamma-1) e1`` of a constant error grows like ``t^(1 - gamma)``, so a
        constant ``d`` is rejected asymptotically (a power-law tail, slower than
        BSMC's exponential one) with any switching function, provided the loop is
        stable; with ``sign`` and ``q_s > |d|`` the sliding mode ``s = 0`` is reached
        in finite time and ``e1`` then decays as the Mittag-Leffler function
        ``E_(2-gamma)(-lambda t^(2-gamma))``.
        """
        d = jnp.abs(jnp.asarray(disturbance))
        return jnp.zeros(jnp.broadcast_shapes(d.shape, (6,)), d.dtype)

    @staticmethod
    def disturbance_error_tail(gains: FOBSMCGains, disturbance: Array, t: Array) -> Array:
        """``(..., 6)`` the power-law tail ``|e1(t)|`` under a constant ``d`` with ``sat``
        switching inside the layer (a linear loop), for large ``t``:
        ``|d| t^(gamma - 1) / ((k + q_s / w) lambda Gamma(gamma))``.

        From the final-value behaviour of ``E(s) = d / (s (s^2 + 1 + lambda s^gamma +
        K s + K lambda s^(gamma - 1)))``, ``K = k + q_s / w``, where
        ``K lambda s^(gamma - 1)`` dominates as ``s -> 0``.
        """
        d = jnp.abs(jnp.asarray(disturbance))
        gamma = jnp.asarray(gains.order)
        gain = jnp.asarray(gains.reaching) + jnp.asarray(gains.switching) / jnp.asarray(
            gains.boundary_layer
        )
        tail = jnp.asarray(t) ** (gamma - 1.0) / jnp.exp(jax.scipy.special.gammaln(gamma))
        return d * tail / (gain * jnp.asarray(gains.surface))

    def prepare(self, gains: FOBSMCGains, dtype: Any) -> FOBSMCParams:
        return FOBSMCParams(gains, self.memory.coefficients(1.0 - gains.order, dtype))

    def init(self, params: FOBSMCParams, dtype: Any) -> Any:
        return self.memory.init((6,), dtype)

    def step(self, params: FOBSMCParams, state: Any, e1: Array, e2: Array):
        g = params.gains
        state, (integral, derivative) = self.memory.step(params.weights, state, e1)
        surface = e2 + g.surface * integral
        return state, LawOutput(_reach(self.switching, g, e1, e2, surface, derivative), surface)


@register
@dataclasses.dataclass(frozen=True)
class BSMC(ControlLaw):
    """Backstepping sliding mode control, laws (B1)-(B2) of the module docstring.

    Args: ``dt``, ``horizon``, and
        switching: ``"sign"`` (default, as the paper's comparison), ``"sat"`` or
            ``"tanh"`` with the gains' ``boundary_layer``.
    """

    switching: str = "sign"

    name = "bsmc"
    GAINS = BSMC_GAINS

    def steady_state_error_bound(self, gains: BSMCGains, disturbance: Array) -> Array:
        """``(..., 6)`` steady-state ``|e1|`` under a constant disturbance ``d``
        ``(..., 6)`` (m/s^2, rad/s^2) on the nominal double integrator.

        ``sign``: ``max(|d| - q_s, 0) / (1 + k lambda)``, so 0 when ``q_s > |d|`` (the
        sliding mode rejects it); ``sat``: ``|d| / (1 + k lambda + q_s lambda / w)`` while
        that lies in the layer; ``tanh``: an upper bound (see ``_steady_state_error``).
        Continuous time; the 1 kHz loop adds a chattering band of order ``q_s dt^2``.
        """
        return _steady_state_error(gains, disturbance, self.switching)

    def step(self, params: BSMCGains, state: Any, e1: Array, e2: Array):
        g = params
        surface = e2 + g.surface * e1
        return state, LawOutput(_reach(self.switching, g, e1, e2, surface, e2), surface)
