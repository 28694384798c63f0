"""What a controller is: the interface the simulator calls, and the control laws the
cascade (:mod:`fojax.controllers.cascade`) runs.

A *controller* is a static configuration object (a frozen dataclass, settled before
tracing) with three pure functions, which :func:`fojax.simulator.rollout` calls:

``prepare(gains, model) -> params``
    Everything derived from the gains and the nominal model that stays fixed during a
    run (fractional weights, for instance), as a pytree; differentiable in ``gains``.
``init(params, observation) -> state``
    The controller's state at ``t = 0``, a pytree of arrays.
``step(params, state, observation) -> (state, inputs, info)``
    One control update; ``inputs`` ``(4,)`` ``(u_F, tau_x, tau_y, tau_z)`` is held over
    the next plant step (zero-order hold), ``info`` a :class:`ControlInfo`.

Every controller of this package is a :class:`fojax.controllers.Cascade` around a
:class:`ControlLaw`: the cascade holds what the controllers share (position loop, eq.
(13), command filter, attitude loop), the law only how it turns the tracking errors of
the six axes into commanded error accelerations. A new controller is usually a new law
(see docs/extending.md); a controller that is not a cascade implements the three
functions above itself.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, ClassVar, NamedTuple, Protocol

import jax
import jax.numpy as jnp

from fojax import fractional
from fojax.controllers.gains import GainSpec

Array = jax.Array

__all__ = [
    "SWITCHING_FUNCTIONS",
    "ControlInfo",
    "ControlLaw",
    "Controller",
    "FractionalMemory",
    "LawOutput",
    "Observation",
    "check_positive",
    "signed_power",
    "switching",
]

SWITCHING_FUNCTIONS = ("sign", "sat", "tanh")


class Observation(NamedTuple):
    """What a controller sees at time ``t_k``.

    Shapes are those of one draw; a rollout over a batch of draws adds the batch's axes
    last (``state`` ``(12, draws)``). The reference is a function of time only, shared
    by every draw (``(4,)``), except in a union of scenarios, where it follows each
    draw's scenario (``(4, draws)``).

    time: ``()`` s.
    state: the plant state ``(x, y, z, phi, theta, psi, x', y', z', phi', theta', psi')``,
        a ``(12,)`` array or its four blocks of three (:class:`fojax.plant.StateBlocks`,
        what the rollout passes; :func:`fojax.plant.state_blocks` turns either into
        blocks). Blocks, because a ``(12,)`` array read entry by entry makes the reverse
        pass add twelve padded cotangents per step.
    reference: ``(4,)`` ``(x_r, y_r, z_r, psi_r)`` (m, rad).
    reference_velocity: ``(4,)`` its exact first time derivative.
    reference_acceleration: ``(4,)`` its exact second time derivative.
    """

    time: Array
    state: Array
    reference: Array
    reference_velocity: Array
    reference_acceleration: Array


class ControlInfo(NamedTuple):
    """Diagnostics returned with each control update (fixed shapes for every controller;
    a batch of draws adds its axes last).

    surfaces: ``(6,)`` sliding variables ``(S_x, S_y, S_z, S_phi, S_theta, S_psi)``
        (controllers without surfaces return their error measure or zeros).
    attitude_reference: ``(3,)`` ``(phi_r, theta_r, psi_r)`` that the attitude loop
        tracks at this step (rad): the position loop's command of eq. (13) after the
        command filter, and the reference yaw. Attitude errors and metrics are taken
        against it.
    adaptive: ``(6, 3)`` adaptive estimates ``(b0, b1, b2)`` per axis (zeros when the
        controller does not adapt).
    """

    surfaces: Array
    attitude_reference: Array
    adaptive: Array


class Controller(Protocol):
    """What :func:`fojax.simulator.rollout` needs from a controller.

    ``prepare`` receives the batch's shape (``()`` for one draw, ``(draws,)`` for a
    rollout over a batch, which adds its axes last to every per-draw array): gains are
    shared by the batch (each field with its declared shape) or given per draw (the
    batch's axes last).
    """

    name: str

    def prepare(self, gains: Any, model: Any, batch_shape: tuple[int, ...] = ()) -> Any: ...

    def init(self, params: Any, observation: Observation) -> Any: ...

    def step(
        self, params: Any, state: Any, observation: Observation
    ) -> tuple[Any, Array, ControlInfo]: ...


class LawOutput(NamedTuple):
    """What a control law returns for the six axes ``(x, y, z, phi, theta, psi)``.

    acceleration: ``(6,)`` (a batch's axes last: ``(6, draws)``; a tuple of six is
        stacked): the commanded *error* acceleration ``a_i`` of each axis (m/s^2,
        rad/s^2); the cascade adds the reference's acceleration and cancels the
        nominal model's terms.
    surface: ``(6,)`` the law's sliding variable (or error measure) per axis.
    adaptive: ``(6, 3)`` adaptive estimates before this update, or ``None``.
    """

    acceleration: Any
    surface: Any
    adaptive: Array | None = None


def check_positive(owner: Any, *names: str) -> None:
    """``ValueError`` unless each attribute ``names`` of ``owner`` is a finite number > 0."""
    for name in names:
        value = getattr(owner, name)
        if isinstance(value, bool) or not (
            isinstance(value, int | float) and math.isfinite(value) and value > 0
        ):
            raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


@dataclasses.dataclass(frozen=True)
class ControlLaw:
    """Base of the control laws (subclass it as a frozen dataclass).

    A law sees each axis ``i`` of ``(x, y, z, phi, theta, psi)`` as the double
    integrator ``e1_i'' = a_i + d_i`` that the cascade leaves once the nominal model is
    cancelled (``e1 = q - q_r``, ``e2 = q' - q_r'``, ``d`` the unknown disturbance), and
    chooses ``a_i``. A subclass declares

    * ``name``: the registry name (class attribute);
    * ``GAINS``: a :class:`fojax.controllers.GainSpec` (class attribute);

    and implements ``step``, and ``prepare``/``init`` when it precomputes from the gains
    or keeps a state:

    ``prepare(gains, dtype) -> params``: per-run constants (default: the gains);
    ``init(params, dtype) -> state``: the law's state at ``t = 0`` for one draw (default
    ``()``); the cascade broadcasts it over a batch;
    ``step(params, state, e1, e2) -> (state, LawOutput)``: ``e1``, ``e2`` are ``(6,)``
    arrays, one entry per axis.

    **One law for one draw and for a batch.** A rollout over a batch of draws runs the
    same ``step`` on arrays with the batch's axes last: ``e1`` and ``e2`` are then
    ``(6, draws)``, every gain field has a trailing axis (``(6, 1)`` when the gains are
    shared by the batch, ``(6, draws)`` when they are given per draw; ``(6, 3, 1)`` for
    a ``(6, 3)`` field) and the state's leaves have the batch's axes last. A law written
    with elementwise operations, indexing and stacking along its leading axes (``e1[2]``,
    ``adaptive[:, 0]``, ``jnp.stack(..., axis=1)``) and reductions over named leading
    axes runs unchanged on both: XLA then computes each ``(6, draws)`` array in one
    vectorised pass over the draws.

    Fields: ``dt`` (control step, s) and ``horizon`` (run length, s: sizes fractional
    memories); subclasses add their own options (``switching``, ``fractional_method``).
    """

    dt: float = 1e-3
    horizon: float = 80.0

    name: ClassVar[str]
    GAINS: ClassVar[GainSpec]

    def __post_init__(self) -> None:
        check_positive(self, "dt", "horizon")
        kind = getattr(self, "switching", None)
        if kind is not None and kind not in SWITCHING_FUNCTIONS:
            raise ValueError(
                f"unknown switching function {kind!r}; choose one of {SWITCHING_FUNCTIONS}"
            )

    # Derived from GAINS.
    @classmethod
    def default_gains(cls, dtype: Any = None) -> Any:
        """The law's default gains (:meth:`GainSpec.default`)."""
        return cls.GAINS.default(dtype)

    @classmethod
    def check_gains(cls, gains: Any) -> None:
        """``ValueError`` naming every entry of ``gains`` that breaks the declaration."""
        cls.GAINS.check(gains)

    # The law.
    def prepare(self, gains: Any, dtype: Any) -> Any:
        return gains

    def init(self, params: Any, dtype: Any) -> Any:
        return ()

    def step(self, params: Any, state: Any, e1: Array, e2: Array) -> tuple[Any, LawOutput]:
        raise NotImplementedError(f"{type(self).__name__} must implement step")


class FractionalMemory:
    """Mixin of a :class:`ControlLaw` with a fractional memory: the law's fields
    ``fractional_method`` and ``fractional_options`` (``(name, value)`` pairs) choose the
    operator (:func:`fojax.fractional.make_operator`), checked when the law is made."""

    def __post_init__(self) -> None:
        super().__post_init__()
        self.memory  # noqa: B018 (validates the method and its options before tracing)

    @functools.cached_property
    def memory(self) -> Any:
        """The law's fractional integral and its rate from one memory
        (:func:`fojax.fractional.integral_with_rate`), built once."""
        operator = fractional.make_operator(
            self.fractional_method, self.dt, self.horizon, **dict(self.fractional_options)
        )
        return fractional.integral_with_rate(operator)


def switching(kind: str, surface: Array, width: Array) -> Array:
    """The switching function ``sgn(S)`` of the reaching laws.

    ``"sign"``: exact sign; ``"sat"``: ``clip(S / width, -1, 1)`` (boundary layer);
    ``"tanh"``: ``tanh(S / width)`` (smooth; for gradient-based tuning).
    """
    if kind == "sign":
        return jnp.sign(surface)
    if kind == "sat":
        return jnp.clip(surface / width, -1.0, 1.0)
    if kind == "tanh":
        return jnp.tanh(surface / width)
    raise ValueError(f"unknown switching function {kind!r}; choose one of {SWITCHING_FUNCTIONS}")


def signed_power(value: Array, exponent: Array) -> Array:
    """``sig^r(e) = |e|^r sign(e)``, with a zero value and finite gradients at ``e = 0``.

    The paper writes ``sig^r(e)`` for the signed power in its surfaces (16)-(18),
    (37)-(39); ``|e|^r`` alone would lose the sign of the error.
    """
    magnitude = jnp.abs(value)
    nonzero = magnitude > 0
    safe = jnp.where(nonzero, magnitude, 1.0)
    return jnp.where(nonzero, jnp.sign(value) * jnp.exp(exponent * jnp.log(safe)), 0.0)


def abs_power(value: Array, exponent: Array) -> Array:
    """``|e|^r`` with a zero value and a finite gradient at ``e = 0`` (any ``r > 0``)."""
    return signed_power(jnp.abs(value), exponent)
