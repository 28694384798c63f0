"""The per-draw metrics of :data:`fojax.requirements.METRICS`, folded over a rollout by
one observer (:class:`RequirementMetrics`), their smooth violations for gradient
tuners, and a chunked evaluation of many draws (:func:`measure`).

Every metric is one number per draw in its canonical unit (SI). Under ``grad``, the
metrics that are piecewise constant in the gains (``settling_time``,
``rotor_saturation``) carry the gradient of a smooth surrogate (straight-through:
the value is the exact metric, the derivative that of the surrogate):

* ``settling_time``: a log-sum-exp over the steps (temperature ``10 dt``) of
  ``(t_k + dt) sigmoid((|e_i| - band) / (0.1 band))``, largest over x, y, z;
* ``rotor_saturation``: the mean over the steps of ``sigmoid(d_k / 0.02)``, ``d_k`` the
  largest excess of a squared rotor speed outside ``[0, w_max^2]`` relative to
  ``w_max^2`` (to the hover squared speed without a limit).

The others are differentiable almost everywhere as they are (maxima pass the
derivative of their largest term).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fojax import observers, plant, scenarios, simulator
from fojax.blocks import EvaluatorCache, evaluate_in_blocks
from fojax.plant import rotor_speed_limit
from fojax.requirements._spec import METRICS, RequirementSet

Array = jax.Array

__all__ = [
    "DIVERGED",
    "RequirementMetrics",
    "draw_metrics",
    "measure",
    "rotor_speed_limit",
    "simulation_config",
    "smooth_share",
    "squared_hinge",
    "violations",
]

DIVERGED = observers.NONFINITE | observers.TILT_LIMIT
"""Status bits of a draw whose metrics are not used (it fails every requirement)."""

SATURATION_TEMPERATURE = 0.02
SETTLING_WIDTH = 0.1  # of the band
SETTLING_TEMPERATURE_STEPS = 10.0


def simulation_config(
    requirements: RequirementSet,
    horizon: float,
    dt: float = 1e-3,
    save_every: int | None = None,
    vehicle=None,
) -> simulator.SimulationConfig:
    """The :class:`fojax.SimulationConfig` the requirements ask for: rotor-limited
    actuators when their settings give a limit (and ``rotor_limited`` is true; a
    thrust-to-weight ratio is one of ``vehicle``, None: the paper's), else ideal ones;
    ``save_every`` defaults to a divisor of the steps near 100."""
    steps = int(round(horizon / dt))
    every = save_every or simulator.divisor_near(steps, 100.0)
    return simulator.SimulationConfig(
        dt=dt,
        horizon=horizon,
        save_every=every,
        rotor_speed_limit=requirements.settings.simulation_limit(vehicle),
    )


class RequirementState(NamedTuple):
    """Running sums of one draw (shapes without the batch; a batch adds its axes last)."""

    count: Array  # () samples seen
    squared_position: Array  # () sum |e_p|^2 dt
    squared_attitude: Array  # () sum |e_att|^2 dt
    direction: Array  # (3,) sign of the first position error above 1 mm
    overshoot: Array  # (3,)
    last_outside: Array  # (3,) last time |e_i| > band (-1: never)
    settle_max: Array  # () running max of x_k / temperature (log-sum-exp)
    settle_sum: Array  # () running sum of exp(x_k / temperature - settle_max)
    steady_error: Array  # () max |e_p| in the final window
    max_position_error: Array  # ()
    max_tilt: Array  # ()
    saturated_steps: Array  # () steps with a squared rotor speed outside [0, w_max^2]
    saturation_smooth: Array  # () sum of sigmoid(d_k / 0.02)
    peak_speed_squared: Array  # () largest commanded squared rotor speed
    thrust_variation: Array  # ()
    torque_variation: Array  # ()
    previous: Array  # (4,) last command
    squared_thrust: Array  # () sum (u_F - m g)^2 dt
    squared_torque: Array  # () sum |tau|^2 dt


def _safe_sqrt(x: Array) -> Array:
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


@dataclasses.dataclass(frozen=True)
class RequirementMetrics:
    """Observer (:mod:`fojax.observers`) of every metric of
    :data:`fojax.requirements.METRICS` for one draw or a batch (batch last).

    dt, steps: the rollout's step and number of steps. rotor_speed_limit: ``w_max``
    (rad/s) for ``rotor_saturation`` (``None``: only negative squared speeds count).
    position_band: settling band (m). steady_fraction: final share of the horizon for
    ``steady_state_error``. Feasibility and speeds come from the simulated plant's mixer
    (the draw's); the thrust effort is measured from the nominal hover thrust.
    ``finalize`` returns metric name -> ``()`` (``(draws,)`` over a batch).
    """

    dt: float
    steps: int
    rotor_speed_limit: float | None = None
    position_band: float = 0.05
    steady_fraction: float = 0.2

    @classmethod
    def for_requirements(
        cls, requirements: RequirementSet, config: simulator.SimulationConfig, vehicle=None
    ):
        """The metrics of ``requirements`` on ``config``'s steps; a thrust-to-weight ratio
        is one of ``vehicle`` (a :class:`fojax.vehicle.Vehicle`; None: the paper's)."""
        s = requirements.settings
        limit = s.speed_limit(vehicle)
        return cls(config.dt, config.steps, limit, s.position_band, s.steady_fraction)

    def init(self, dtype) -> RequirementState:
        z = jnp.zeros((), dtype)
        z3 = jnp.zeros(3, dtype)
        return RequirementState(
            count=jnp.zeros((), jnp.int32),
            squared_position=z,
            squared_attitude=z,
            direction=z3,
            overshoot=z3,
            last_outside=jnp.full(3, -1.0, dtype),
            settle_max=jnp.full((), -1e30, dtype),
            settle_sum=z,
            steady_error=z,
            max_position_error=z,
            max_tilt=z,
            saturated_steps=z,
            saturation_smooth=z,
            peak_speed_squared=jnp.full((), -jnp.inf, dtype),
            thrust_variation=z,
            torque_variation=z,
            previous=jnp.zeros(4, dtype),
            squared_thrust=z,
            squared_torque=z,
        )

    def update(self, acc: RequirementState, record) -> RequirementState:
        dt = self.dt
        dtype = acc.squared_position.dtype
        t = jnp.asarray(record.time, dtype)
        error = record.error.astype(dtype)
        inputs = record.inputs.astype(dtype)
        position, attitude = error[:3], error[3:]
        first = acc.count == 0
        squared_norm = jnp.sum(position * position, 0)
        norm = _safe_sqrt(squared_norm)

        magnitude = jnp.abs(position)
        undecided = (acc.direction == 0) & (magnitude > 1e-3)
        direction = jnp.where(undecided, jnp.sign(position), acc.direction)
        overshoot = jnp.maximum(acc.overshoot, jnp.maximum(-direction * position, 0.0))
        band = self.position_band
        last_outside = jnp.where(magnitude > band, t, acc.last_outside)
        outside = jax.nn.sigmoid((magnitude - band) / (SETTLING_WIDTH * band))
        x = jnp.max((t + dt) * outside, 0) / (SETTLING_TEMPERATURE_STEPS * dt)
        settle_max = jnp.maximum(acc.settle_max, x)
        settle_sum = acc.settle_sum * jnp.exp(acc.settle_max - settle_max) + jnp.exp(x - settle_max)

        window_start = (1.0 - self.steady_fraction) * self.steps * dt - 0.5 * dt
        steady = jnp.where(t >= window_start, jnp.maximum(acc.steady_error, norm), acc.steady_error)

        state = record.state.astype(dtype)
        phi, theta = state[3], state[4]
        cos_tilt = jnp.cos(phi) * jnp.cos(theta)
        sin_tilt_sq = jnp.sin(theta) ** 2 + (jnp.cos(theta) * jnp.sin(phi)) ** 2
        tilt = jnp.arctan2(_safe_sqrt(sin_tilt_sq), cos_tilt)

        squared = plant.rotor_speeds_squared(record.plant, inputs).astype(dtype)  # (4, ...)
        if self.rotor_speed_limit is None:
            params = record.plant
            reference = params.mass * params.gravity / (4.0 * params.thrust_factor)
            excess = jnp.max(-squared, 0) / reference.astype(dtype)
            saturated = jnp.any(squared < 0, 0)
        else:
            top = self.rotor_speed_limit**2
            excess = jnp.max(jnp.maximum(-squared, squared - top), 0) / top
            saturated = jnp.any((squared < 0) | (squared > top), 0)
        smooth = jax.nn.sigmoid(excess / SATURATION_TEMPERATURE)

        jump = jnp.abs(inputs - acc.previous)
        model = record.model
        thrust_deviation = inputs[0] - model.mass * model.gravity
        return RequirementState(
            count=acc.count + 1,
            squared_position=acc.squared_position + dt * squared_norm,
            squared_attitude=acc.squared_attitude + dt * jnp.sum(attitude * attitude, 0),
            direction=direction,
            overshoot=overshoot,
            last_outside=last_outside,
            settle_max=settle_max,
            settle_sum=settle_sum,
            steady_error=steady,
            max_position_error=jnp.maximum(acc.max_position_error, norm),
            max_tilt=jnp.maximum(acc.max_tilt, tilt),
            saturated_steps=acc.saturated_steps + saturated.astype(dtype),
            saturation_smooth=acc.saturation_smooth + smooth,
            peak_speed_squared=jnp.maximum(acc.peak_speed_squared, jnp.max(squared, 0)),
            thrust_variation=acc.thrust_variation + jnp.where(first, 0.0, jump[0]),
            torque_variation=acc.torque_variation + jnp.where(first, 0.0, jnp.sum(jump[1:], 0)),
            previous=inputs,
            squared_thrust=acc.squared_thrust + dt * thrust_deviation**2,
            squared_torque=acc.squared_torque + dt * jnp.sum(inputs[1:] ** 2, 0),
        )

    def finalize(self, acc: RequirementState) -> dict[str, Array]:
        dt = self.dt
        dtype = acc.squared_position.dtype
        count = acc.count.astype(dtype)
        horizon = count * dt
        per_second = 1.0 / horizon
        settled = jnp.where(acc.last_outside < 0, 0.0, jnp.minimum(acc.last_outside + dt, horizon))
        settling = jnp.max(settled, 0)
        settling_smooth = (
            SETTLING_TEMPERATURE_STEPS * dt * (acc.settle_max + jnp.log(acc.settle_sum))
        )
        share = acc.saturated_steps / count
        share_smooth = acc.saturation_smooth / count

        def straight_through(exact, smooth):
            return exact + (smooth - jax.lax.stop_gradient(smooth))

        out = {
            "position_overshoot": jnp.max(acc.overshoot, 0),
            "settling_time": straight_through(settling, settling_smooth),
            "steady_state_error": acc.steady_error,
            "max_position_error": acc.max_position_error,
            "position_rmse": _safe_sqrt(acc.squared_position * per_second),
            "attitude_rmse": _safe_sqrt(acc.squared_attitude * per_second),
            "max_tilt": acc.max_tilt,
            "rotor_saturation": straight_through(share, share_smooth),
            "peak_rotor_speed": _safe_sqrt(acc.peak_speed_squared),
            "thrust_chattering": acc.thrust_variation * per_second,
            "torque_chattering": acc.torque_variation * per_second,
            "thrust_effort": _safe_sqrt(acc.squared_thrust * per_second),
            "torque_effort": _safe_sqrt(acc.squared_torque * per_second),
        }
        assert set(out) == set(METRICS), "the observer and the catalogue disagree"
        return out


def draw_metrics(outputs: dict, status: Any = None) -> dict[str, np.ndarray]:
    """Host copies of :class:`RequirementMetrics`' outputs (name -> ``(draws,)`` float64),
    NaN for draws whose ``status`` has a :data:`DIVERGED` bit."""
    out = {name: np.asarray(value, np.float64) for name, value in outputs.items()}
    if status is not None:
        bad = (np.asarray(status) & DIVERGED) != 0
        out = {name: np.where(bad, np.nan, value) for name, value in out.items()}
    return out


def violations(requirements: RequirementSet, metrics: dict) -> Array:
    """``(requirements, draws)`` normalised signed violations (JAX, differentiable):
    ``(m - b) / s`` for an upper bound ``b``, ``(b - m) / s`` for a lower one, ``s`` the
    requirement's :attr:`~fojax.requirements.Requirement.scale`; a draw meets the
    requirement exactly when its violation is ``<= 0``."""
    rows = []
    for r in requirements:
        m = jnp.asarray(metrics[r.metric])
        b = r.canonical_value
        rows.append((m - b) / r.scale if r.bound == "upper" else (b - m) / r.scale)
    return jnp.stack(rows)


def squared_hinge(v: Array, margin: float = 0.0) -> Array:
    """``max(v + margin, 0)^2``: zero (with zero gradient) where the draw meets the
    requirement by at least ``margin``."""
    return jnp.square(jnp.maximum(v + margin, 0.0))


def smooth_share(v: Array, temperature: float = 0.1, margin: float = 0.0) -> Array:
    """``sigmoid((v + margin) / temperature)``: a smooth indicator of a violation, whose
    mean over draws is a smooth share of draws violating (the chance-constraint
    surrogate)."""
    return jax.nn.sigmoid((v + margin) / temperature)


_EVALUATORS = EvaluatorCache(16)
"""The compiled evaluations of :func:`measure`, by their settings (at most 16 kept)."""


def _evaluator(controller, scenario, config, observer, dtype, model):
    def build():
        def run(gains, keys):
            result = simulator.rollout_from_keys(
                controller, gains, model, scenario, keys, config, observer, dtype
            )
            return result.outputs, result.status

        return jax.jit(run)

    return _EVALUATORS.get((controller, scenario, config, observer, str(dtype)), build)


def measure(
    controller,
    gains,
    scenario: scenarios.Scenario,
    requirements: RequirementSet,
    keys,
    config: simulator.SimulationConfig,
    chunk: int = 64,
    dtype=None,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Per-draw metrics (name -> ``(draws,)``, canonical units, NaN for diverged draws)
    and status ``(draws,)`` of ``gains`` on the draws ``keys`` (``(draws, 2)``,
    :func:`fojax.scenarios.draw_keys`), in blocks of ``chunk`` draws (at most the draw
    count; :func:`fojax.blocks.evaluate_in_blocks`), one compilation per setting
    (cached). ``config``: e.g. :func:`simulation_config`; its ``rotor_speed_limit``
    decides the actuators. Forward only."""
    dtype = jnp.dtype(jnp.result_type(float)) if dtype is None else jnp.dtype(dtype)
    if scenario.horizon < config.horizon:
        scenario = dataclasses.replace(scenario, horizon=config.horizon)
    observer = RequirementMetrics.for_requirements(requirements, config, scenario.vehicle)
    model = scenario.plant_params(dtype)
    run = _evaluator(controller, scenario, config, observer, dtype, model)
    gains = type(gains)(*(jnp.asarray(g, dtype) for g in gains))
    keys = np.asarray(keys)
    block = max(1, min(chunk, keys.shape[0]))
    outputs, status = evaluate_in_blocks(run, gains, keys, block=block)
    return draw_metrics(outputs, status), status
