"""The paper's adaptive fractional-order nonsingular fast terminal sliding mode control.

Position loop eqs. (12)-(28), attitude loop eqs. (37)-(47) of Labbadi & Cherkaoui,
read as in ``docs/model.md``, as a law of the cascade (:mod:`fojax.controllers.cascade`).
Axes are ordered ``(x, y, z, phi, theta, psi)``; every gain is a ``(6,)`` array (one
value per axis), the adaptation rates ``(6, 3)``.

Sliding surface per axis (16)-(18), (37)-(39), with ``e1`` the tracking error and
``e2`` its rate:

    S = e2 + D^(gamma1 - 1)[c1 sig^(p/q)(e1)] + I^gamma2[c2 sig^phi(e1)]

The printed ``D^(gamma1 - 1)`` has a negative order for ``0 < gamma1 < 1``: it is the
Riemann-Liouville fractional integral of order ``1 - gamma1``, so that its time
derivative is ``D^gamma1`` as in the equivalent control (23). The time derivative of
each fractional term is read from the same fractional memory (``D^gamma1 f = d/dt
D^(gamma1 - 1) f`` and ``d/dt I^gamma2 g``), so the equivalent control cancels exactly
the derivative of ``S`` as defined. Reaching law (24), (42)-(44) with the adaptive
bound ``b0 + b1 |e1| + b2 |e2|``:

    a = -D^gamma1[c1 sig^(p/q)(e1)] - d/dt I^gamma2[c2 sig^phi(e1)]
        - hbar1 sw(S) - hbar2 S - (b0 + b1 |e1| + b2 |e2| + mu) sw(S)

and the adaptive laws (25)-(27), (45)-(47), read as ``b_dot = eta (|S|, |e1| |S|,
|e2| |S|)`` (the printed laws lose the absolute values and the products), integrated
by forward Euler at the control step from zero.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from fojax._arrays import unstack
from fojax.controllers.base import (
    ControlLaw,
    FractionalMemory,
    LawOutput,
    signed_power,
    switching,
)
from fojax.controllers.gains import Bounds, GainField, GainSpec, per_axis
from fojax.controllers.registry import register

Array = jax.Array

__all__ = ["AFONFTSMC", "AFONFTSMCGains", "paper_gains"]

_POSITIVE = Bounds(0.0)
# fmt: off
GAINS = GainSpec(
    "AFONFTSMCGains",
    [
        GainField("surface_c1", per_axis(0.1797, 4.4265, 35.5118), _POSITIVE,
                  doc="``c_i1``, weight of the ``p/q`` term of the surface."),
        GainField("surface_c2", per_axis(0.1769, 3.7049, 3.9926), _POSITIVE,
                  doc="``c_i2``, weight of the ``phi`` term."),
        GainField("reaching_h1", per_axis(2.6044, 16.1251, 156.4373), _POSITIVE,
                  doc="``hbar_i1``, switching gain."),
        GainField("reaching_h2", per_axis(0.2204, 0.8876, 5.8670), _POSITIVE,
                  doc="``hbar_i2``, proportional reaching gain."),
        GainField("power", [3.0] * 6, _POSITIVE, doc="``phi_i``, exponent of the I^gamma2 term."),
        GainField("ratio", [11.0 / 10.0] * 6, Bounds(1.0, 2.0, symbol="p/q"),
                  doc="``p_i / q_i`` (nonsingular surface)."),
        GainField("gamma1", [0.99] * 6, Bounds(0.0, 1.0), integer_order=1.0,
                  doc="``gamma_i1``, fractional order (1: ``D^(gamma1 - 1)`` the identity)."),
        GainField("gamma2", [0.01] * 6, Bounds(0.0, 1.0), integer_order=0.0,
                  doc="``gamma_i2``, fractional order (0: ``I^gamma2`` the identity)."),
        GainField("adaptation", [[0.01] * 3] * 6, Bounds(0.0, include_low=True),
                  doc="rates ``(eta_i0, eta_i1, eta_i2)`` of the adaptive laws.",
                  search_high=0.1),
        GainField("mu", [1e-3] * 6, _POSITIVE, role="constant",
                  doc="``mu``, the reaching law's small constant."),
        GainField("boundary_layer", per_axis(0.05, 0.05, 0.2), _POSITIVE, role="smoothing",
                  doc="width of ``sat``/``tanh`` switching (unused by ``sign``)."),
    ],
    "AFONFTSMC",
)
# fmt: on
"""The paper's gains of Section V (the same values for x and y, and for the three
attitude axes; the printed ``p_i/q_i = 11/10``, ``phi_i = 3``, ``gamma_i1 = 0.99``,
``gamma_i2 = 0.01``, ``eta = 0.01``), ``mu = 1e-3``. Boundary layer (``sat``/``tanh``
only): 0.05 for position, 0.2 for attitude. In a boundary layer the switching term is
a gain ``h1 / width`` on ``S``; the discrete loop at ``dt`` stays free of a period-2
limit cycle while ``h1 dt / width < 2``, which the paper's attitude ``h1 = 156.4``
breaks below a width of 0.078 at 1 ms."""

AFONFTSMCGains = GAINS.type


def paper_gains(dtype: Any = None) -> AFONFTSMCGains:
    """The paper's gains of Section V (:data:`GAINS`)."""
    return GAINS.default(dtype)


class AFONFTSMCParams(NamedTuple):
    """Per-run constants: the gains and the fractional weights of the surface memory."""

    gains: AFONFTSMCGains
    surface_weights: Any


class AFONFTSMCState(NamedTuple):
    """The law's memory.

    surface_memory: the fractional memory of the 12 surface signals, channels
        ``c1 sig^(p/q)(e1)`` for ``(x, y, z, phi, theta, psi)`` then
        ``c2 sig^phi(e1)`` for the same axes (:func:`fojax.fractional.integral_with_rate`:
        each channel gives its fractional integral and that integral's time derivative).
    adaptive: ``(6, 3)`` estimates ``(b0, b1, b2)`` per axis before the previous
        step's update; the update (25)-(27)/(45)-(47) is applied at the start of the
        next step from the three quantities below, so it reads stored values only.
    previous_surface, previous_error, previous_error_rate: ``(6,)`` ``S``, ``e1``,
        ``e2`` of the previous step (zeros before the first).
    """

    surface_memory: Any
    adaptive: Array
    previous_surface: Array
    previous_error: Array
    previous_error_rate: Array


@register
@dataclasses.dataclass(frozen=True)
class AFONFTSMC(FractionalMemory, ControlLaw):
    """The paper's control law (see the module docstring).

    Args:
        dt: control step (s). horizon: run length (s), sizes the fractional memory.
        fractional_method: ``"soe"`` (accurate default), ``"oustaloup"`` (the paper's
            CRONE filters, Remark 4) or ``"gl"`` (:mod:`fojax.fractional`).
        fractional_options: extra options of the operator, ``(name, value)`` pairs.
        switching: ``"sign"`` (the paper), ``"sat"`` or ``"tanh"``.

    ``memory``: the fractional memory of the 12 surface channels (:class:`FractionalMemory`).
    """

    fractional_method: str = "soe"
    fractional_options: tuple = ()
    switching: str = "sign"

    name = "afonftsmc"
    GAINS = GAINS

    @staticmethod
    def reaching_time_bound(gains: AFONFTSMCGains, initial_surface: Array) -> Array:
        """Finite-time bound of eq. (34) on reaching ``S = 0``, per axis ``(..., 6)``.

        Lemma 1 with ``V = S^2 / 2``, ``lambda_1 = sqrt(2) (hbar_1 + mu)``,
        ``lambda_2 = 2 hbar_2`` and ``V' <= -lambda_1 V^(1/2) - lambda_2 V``, (33), gives
        ``t_r <= (2 / lambda_2) ln((lambda_2 V0^(1/2) + lambda_1) / lambda_1)``
        ``= (1 / hbar_2) ln(1 + hbar_2 |S(0)| / (hbar_1 + mu))``. (34) as printed swaps
        ``lambda_1`` and ``lambda_2``; this is the form Lemma 1 gives. The adaptive
        estimation errors of the paper's ``V(t_0)`` are taken as zero (their true
        bounds are unknown), and the bound assumes the adaptive term dominates the
        disturbance, so it is a reference value, not a guarantee for every draw.
        """
        h1 = jnp.asarray(gains.reaching_h1) + jnp.asarray(gains.mu)
        h2 = jnp.asarray(gains.reaching_h2)
        return jnp.log1p(h2 * jnp.abs(initial_surface) / h1) / h2

    def prepare(self, gains: AFONFTSMCGains, dtype: Any) -> AFONFTSMCParams:
        # Channels 0-5, the p/q terms: integral of order 1 - gamma1 (the S term) and its
        # time derivative, the derivative of order gamma1. Channels 6-11, the phi terms:
        # integral of order gamma2 and its time derivative, the derivative of order
        # 1 - gamma2. All twelve share one memory (one array of modes); the orders are
        # (12,) or, over a batch, (12, 1) / (12, draws).
        integral_orders = jnp.concatenate([1.0 - gains.gamma1, gains.gamma2])
        return AFONFTSMCParams(gains, self.memory.coefficients(integral_orders, dtype))

    def init(self, params: AFONFTSMCParams, dtype: Any) -> AFONFTSMCState:
        zeros = jnp.zeros((6,), dtype)
        return AFONFTSMCState(
            surface_memory=self.memory.init((12,), dtype),
            adaptive=jnp.zeros((6, 3), dtype),
            previous_surface=zeros,
            previous_error=zeros,
            previous_error_rate=zeros,
        )

    def step(
        self, params: AFONFTSMCParams, state: AFONFTSMCState, error: Array, error_rate: Array
    ) -> tuple[AFONFTSMCState, LawOutput]:
        g = params.gains

        # Surfaces (16)-(18)/(37)-(39) and the fractional part of dS/dt: the 12 memory
        # channels c1 sig^(p/q)(e1), then c2 sig^phi(e1), as one array (the stacking done
        # on the errors, so that the powers are computed on the whole array).
        twice = jnp.concatenate([error, error])
        signals = jnp.concatenate([g.surface_c1, g.surface_c2]) * signed_power(
            twice, jnp.concatenate([g.ratio, g.power])
        )
        memory, (integral, rate) = self.memory.step(
            params.surface_weights, state.surface_memory, signals
        )
        p_integral, phi_integral = unstack(integral, (6, 6))
        surface = error_rate + p_integral + phi_integral

        # The adaptive update (25)-(27)/(45)-(47) owed by the previous step (Euler).
        magnitude = jnp.abs(state.previous_surface)
        regressor = jnp.stack(
            [
                jnp.ones_like(magnitude),
                jnp.abs(state.previous_error),
                jnp.abs(state.previous_error_rate),
            ],
            axis=1,
        )
        adaptive = state.adaptive + self.dt * g.adaptation * regressor * magnitude[:, None]

        # Reaching law (24)/(42)-(44) minus the fractional part of dS/dt.
        sw = switching(self.switching, surface, g.boundary_layer)
        b0, b1, b2 = unstack(adaptive, axis=1)
        bound = b0 + b1 * jnp.abs(error) + b2 * jnp.abs(error_rate)
        reaching = -g.reaching_h1 * sw - g.reaching_h2 * surface - (bound + g.mu) * sw
        p_rate, phi_rate = unstack(rate, (6, 6))
        acceleration = reaching - (p_rate + phi_rate)

        new_state = AFONFTSMCState(
            surface_memory=memory,
            adaptive=adaptive,
            previous_surface=surface,
            previous_error=error,
            previous_error_rate=error_rate,
        )
        return new_state, LawOutput(acceleration, surface, adaptive)
