"""A tuning problem: one controller, one scenario, the cost, the draws, compiled.

:class:`ProblemSpec` is the static description (a frozen dataclass, validated in
Python before anything is traced); :class:`TuningProblem` binds it to compiled
functions of the unconstrained parameters that the gradient tuner
(:mod:`fojax.optimize.tuner`) and the derivative-free tuners
(:mod:`fojax.optimize.derivative_free`) share, so every tuner sees the same cost and the
same draws.

Draws (``scenarios.draw_keys(seed, i)``): minibatch ``b`` of the tuning stream holds
draw indices ``b n ... (b + 1) n - 1`` (``n`` = ``draws``), fresh draws every step;
held-out evaluation draws are indices ``HELDOUT_OFFSET + j``, a disjoint index range
of the same seed (a run would need over 2^31 tuning draws to reach it); validation
draws, which the tuners use to choose among their own iterates, are indices
``VALIDATION_OFFSET + j`` (``2^30 <= VALIDATION_OFFSET + j < HELDOUT_OFFSET``): disjoint
from the tuning stream and from the held-out draws.

During tuning the sliding-mode controllers switch with ``tanh(S / (scale w))``, ``w``
the gains' smoothing width (the field declared with role ``"smoothing"``,
``boundary_layer``): ``scale`` is annealed by the tuner from
``anneal_start`` down to ``anneal_end`` (1: the evaluation width of ``sat``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fojax import export_cache, scenarios, sharding, simulator
from fojax.controllers import registry
from fojax.optimize import cost as cost_lib
from fojax.optimize import params as params_lib

Array = jax.Array

__all__ = [
    "HELDOUT_OFFSET",
    "VALIDATION_OFFSET",
    "ProblemSpec",
    "Step",
    "TuningProblem",
    "checkpoint_interval",
    "evaluate",
]

HELDOUT_OFFSET = 2**31
"""Held-out draws are indices ``HELDOUT_OFFSET + j`` of the tuning seed."""

VALIDATION_OFFSET = 2**30
"""Validation draws are indices ``VALIDATION_OFFSET + j`` of the tuning seed (below the
held-out range, above any tuning minibatch a run reaches)."""

DTYPES = ("float32", "float64")
COMPILE_MODES = {"optimized": None, "fast": {"xla_backend_optimization_level": 0}}
"""``ProblemSpec.compile`` -> XLA compiler options of the tuning functions. ``"fast"``:
measured on 2 shared cores (load about 5), the gradient of 16 draws x 10 s compiled in
23 s instead of 66 s and ran in 8-12 s instead of 5 s."""


def checkpoint_interval(steps: int, target: float | None = None) -> int:
    """Steps per checkpointed block of the rollout: the divisor of ``steps`` nearest
    to ``target`` (default ``0.75 sqrt(steps)``; :func:`fojax.simulator.divisor_near`).

    Reverse mode keeps one carry per block and rematerialises one block at a time,
    so memory goes as ``(steps / L) c + L r`` for blocks of ``L`` steps, ``c`` the
    carry and ``r`` the residuals of one step; ``L = sqrt(steps c / r)`` minimises it
    and makes it grow like the square root of the horizon. For the AFONFTSMC,
    ``c / r`` is about 0.55 (1.8 kB and 3.1 kB per draw in float32, measured with
    ``experiments/tune_memory.py``), hence ``0.75 sqrt(steps)``.
    """
    target = 0.75 * math.sqrt(steps) if target is None else target
    return simulator.divisor_near(steps, target)


@dataclasses.dataclass(frozen=True)
class ProblemSpec:
    """Everything that fixes a tuning cost (validated on construction).

    controller: registry name. scenario: 1, 2 or 3. horizon: tuning horizon (s).
    dt: step (s). draws: draws per minibatch. seed: the draws' seed.
    cost: :class:`fojax.optimize.cost.CostConfig`. fields: tuned gain fields (``None``: the
    default, :func:`fojax.optimize.params.default_fields`). share: axis sharing
    (:data:`fojax.optimize.params.SHARING`). fractional: fractional method of a controller
    with fractional operators (the AFONFTSMC, the FOBSMC); a controller without them
    takes only the default ``"soe"`` (another value is a ``ValueError``). dtype:
    ``"float32"`` or ``"float64"``. save_every: steps per checkpointed block
    (``None``: :func:`checkpoint_interval`). compile: ``"optimized"`` (XLA's
    default) or ``"fast"``: the tuning functions compiled
    without LLVM's optimisation passes (:data:`COMPILE_MODES`; several times faster to
    compile, slower to run, rounding may differ); evaluations (:func:`evaluate`) are
    always compiled optimised.
    """

    controller: str = "afonftsmc"
    scenario: int = 2
    horizon: float = 10.0
    dt: float = 1e-3
    draws: int = 16
    seed: int = 0
    cost: cost_lib.CostConfig = cost_lib.CostConfig()
    fields: tuple[str, ...] | None = None
    share: str = "paper"
    fractional: str = "soe"
    dtype: str = "float32"
    save_every: int | None = None
    compile: str = "optimized"

    def __post_init__(self) -> None:
        registry.get_controller_class(self.controller)
        if self.compile not in COMPILE_MODES:
            raise ValueError(
                f"compile must be one of {', '.join(COMPILE_MODES)}, got {self.compile!r}"
            )
        scenarios.get_scenario(self.scenario)
        for label in ("horizon", "dt"):
            value = getattr(self, label)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        steps = self.horizon / self.dt
        if abs(steps - round(steps)) > 1e-6 * steps or round(steps) < 1:
            raise ValueError(
                f"the horizon ({self.horizon} s) must be a whole, positive number of steps "
                f"of {self.dt} s"
            )
        if not isinstance(self.draws, int) or self.draws < 1:
            raise ValueError(f"draws must be a positive integer, got {self.draws!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        if self.dtype not in DTYPES:
            raise ValueError(f"dtype must be one of {DTYPES}, got {self.dtype!r}")
        if self.save_every is not None and (
            not isinstance(self.save_every, int)
            or self.save_every < 1
            or self.steps % self.save_every
        ):
            raise ValueError(
                f"save_every must be a positive divisor of the {self.steps} steps, got "
                f"{self.save_every!r}"
            )
        if self.fields is not None:
            object.__setattr__(self, "fields", tuple(self.fields))
        params_lib.make_parameter_map(self.controller, self.fields, self.share)  # validates
        takes = registry.controller_options(self.controller)
        if "fractional_method" not in takes and self.fractional != "soe":
            raise ValueError(
                f"fractional={self.fractional!r} does not apply to {self.controller}, which "
                "has no fractional operator; leave fractional at its default 'soe'"
            )
        self.make_controller("tanh", self.horizon)  # validates fractional method etc.

    @property
    def steps(self) -> int:
        """Simulated steps per draw."""
        return int(round(self.horizon / self.dt))

    @property
    def block(self) -> int:
        return self.save_every or checkpoint_interval(self.steps)

    @property
    def draw_steps_per_minibatch(self) -> int:
        return self.draws * self.steps

    @property
    def jnp_dtype(self):
        return jnp.dtype(self.dtype)

    def make_controller(self, switching: str, horizon: float):
        """The controller over ``horizon`` with ``switching`` and the spec's fractional
        method, each where the controller has one (the FL has neither)."""
        options = dict(dt=self.dt, horizon=horizon, fractional_method=self.fractional)
        options["switching"] = switching
        return registry.make_controller(
            self.controller, **registry.options_for(self.controller, options)
        )

    def as_dict(self) -> dict:
        """JSON-ready description (the tuning fingerprint)."""
        out = dataclasses.asdict(self)
        out["fields"] = list(
            params_lib.make_parameter_map(self.controller, self.fields, self.share).names
        )
        out["save_every"] = self.block
        return out


class Step(NamedTuple):
    """One evaluation of the objective on a minibatch.

    objective: ``()``. costs: :class:`fojax.optimize.cost.DrawCosts`.
    gradient: parameters dict (``None`` for value-only evaluations).
    bad_gradients: ``()`` int, draws whose gradient was not finite (left out).
    """

    objective: Array
    costs: cost_lib.DrawCosts
    gradient: Any
    bad_gradients: Array


def _scenario_for(scenario: scenarios.Scenario, horizon: float) -> scenarios.Scenario:
    """The scenario with random tables covering at least ``horizon``.

    The tables keep the scenario's own length when it is longer, so draw ``i`` over a
    short tuning horizon is the beginning of the same draw over the full horizon.
    """
    if horizon <= scenario.horizon:
        return scenario
    return dataclasses.replace(scenario, horizon=horizon)


def _scale_width(gains, base, widths, width_scale):
    """``gains`` with the smoothing widths ``widths`` (field names) of ``base`` scaled."""
    return gains._replace(**{name: getattr(base, name) * width_scale for name in widths})


def _per_draw_gradients(batch_cost, gains_of):
    """``(params, width_scale, keys) -> ((j, (terms, status)), per-draw gradients)``."""

    def per_draw_grads(params, width_scale, keys):
        # One copy of the parameters per draw (the draws last), mapped onto gains per
        # draw, one batch-last rollout: the gradient with respect to the copies is
        # the stack of the per-draw gradients (fojax.optimize.cost.per_draw_gradients).
        n = keys.shape[0]

        def per_draw_gains(copies):
            to_gains = jax.vmap(gains_of, in_axes=(-1, None), out_axes=-1)
            return to_gains(copies, width_scale)

        def total(copies):
            j, terms, status = batch_cost(per_draw_gains(copies), keys)
            return jnp.sum(j), (j, (terms, status))

        copies = jax.tree.map(lambda p: jnp.broadcast_to(p[..., None], p.shape + (n,)), params)
        grads, out = jax.grad(total, has_aux=True)(copies)
        return out, jax.tree.map(lambda g: jnp.moveaxis(g, -1, 0), grads)

    return per_draw_grads


def _reduce_draws(cost_config, per_draw):
    """The :class:`Step` of per-draw costs and gradients: objective, gradient weighted
    over the usable draws (finite gradient, not diverged), count of the unusable."""
    (j, (terms, status)), grads = per_draw
    effective, diverged = cost_lib.guard(cost_config, j, status)
    objective, weights = cost_lib.combine(cost_config, effective)
    finite = jnp.all(
        jnp.stack(
            [
                jnp.all(jnp.isfinite(g.reshape(g.shape[0], -1)), axis=1)
                for g in jax.tree.leaves(grads)
            ]
        ),
        axis=0,
    )
    usable = finite & ~diverged
    weights = jnp.where(usable, weights, 0.0)
    gradient = jax.tree.map(
        lambda g: jnp.tensordot(
            weights, jnp.where(usable.reshape((-1,) + (1,) * (g.ndim - 1)), g, 0.0), axes=1
        ),
        grads,
    )
    bad = jnp.sum(~finite & ~diverged).astype(jnp.int32)
    costs = cost_lib.DrawCosts(effective, terms, status, diverged)
    return Step(objective, costs, gradient, bad)


class TuningProblem:
    """:class:`ProblemSpec` + base gains, compiled (one compilation per shape).

    base_gains: the gains the tuned fields start from and the untuned fields keep
    (validated by the controller's ``check_gains``). mesh: a
    :func:`fojax.sharding.draw_mesh` (e.g. over every process's devices): the per-draw
    gradients of :meth:`value_and_grad` are computed over its devices in blocks of
    ``device_batch`` draws (default: the whole minibatch), gathered to every process
    and reduced there by one program, so that every mesh gives the same numbers for a
    given ``device_batch`` (:func:`_over_mesh`); ``device_batch`` without a mesh is a
    ``ValueError`` (it would change nothing).

    Attributes: ``spec``, ``param_map``, ``base_gains``, ``sim_config``,
    ``controller`` (``tanh`` switching when the controller has a switching function).
    """

    def __init__(self, spec: ProblemSpec, base_gains: Any, mesh=None, device_batch=None):
        if mesh is None and device_batch is not None:
            raise ValueError(
                f"device_batch={device_batch!r} applies to draws split over a mesh; pass "
                "mesh= (e.g. fojax.sharding.draw_mesh()) or leave device_batch out"
            )
        self.spec = spec
        dtype = spec.jnp_dtype
        cls = registry.get_controller_class(spec.controller)
        base_gains = type(base_gains)(*(jnp.asarray(g, dtype) for g in base_gains))
        cls.check_gains(base_gains)
        self.base_gains = base_gains
        self.param_map = params_lib.make_parameter_map(spec.controller, spec.fields, spec.share)
        self.scenario = _scenario_for(scenarios.get_scenario(spec.scenario), spec.horizon)
        self.sim_config = simulator.SimulationConfig(
            dt=spec.dt, horizon=spec.horizon, save_every=spec.block
        )
        self.controller = spec.make_controller("tanh", spec.horizon)
        batch_cost = cost_lib.make_batch_cost(
            self.controller, self.scenario, self.sim_config, spec.cost, dtype
        )
        cost_config = spec.cost
        param_map = self.param_map
        widths = cls.GAINS.with_role("smoothing")

        def gains_of(params, width_scale):
            gains = param_map.to_gains(params, base_gains)
            return _scale_width(gains, base_gains, widths, width_scale)

        def value(params, width_scale, keys):
            j, terms, status = batch_cost(gains_of(params, width_scale), keys)
            effective, diverged = cost_lib.guard(cost_config, j, status)
            objective, _ = cost_lib.combine(cost_config, effective)
            costs = cost_lib.DrawCosts(effective, terms, status, diverged)
            return Step(objective, costs, None, jnp.zeros((), jnp.int32))

        per_draw_grads = _per_draw_gradients(batch_cost, gains_of)
        reduce_draws = functools.partial(_reduce_draws, cost_config)

        options = COMPILE_MODES[spec.compile]
        self._value = jax.jit(value, compiler_options=options)
        self._gains_of = gains_of
        # The gradient always runs as a mesh's per-device program (one device when no
        # mesh is given): every mesh then gives the same numbers (fojax.sharding).
        self.mesh = mesh
        self._value_and_grad = _over_mesh(
            per_draw_grads,
            jax.jit(reduce_draws),
            mesh or sharding.one_device_mesh(),
            device_batch,
            options,
            key={"spec": spec.as_dict(), "base_gains": _gains_key(base_gains)},
        )
        template = {f.name: jnp.zeros(f.param_shape, dtype) for f in param_map.fields}
        _, self._unravel = param_map.ravel(template)

        def batch_value(vectors, width_scale, keys):
            def candidate(vector):
                step = value(self._unravel(vector), width_scale, keys)
                return step.objective, step.costs

            return jax.vmap(candidate)(vectors)

        self._batch_value = jax.jit(batch_value, compiler_options=options)

    # -- draws ------------------------------------------------------------------------
    def minibatch_keys(self, index: int, draws: int | None = None) -> Array:
        """Keys ``(n, 2)`` of minibatch ``index`` of the tuning stream."""
        n = self.spec.draws if draws is None else draws
        return scenarios.draw_keys(self.spec.seed, np.arange(index * n, (index + 1) * n))

    def heldout_keys(self, draws: int) -> Array:
        """Keys ``(draws, 2)`` of the held-out draws (disjoint from every minibatch)."""
        return scenarios.draw_keys(self.spec.seed, HELDOUT_OFFSET + np.arange(draws))

    def validation_keys(self, draws: int) -> Array:
        """Keys ``(draws, 2)`` of the validation draws (disjoint from every minibatch and
        from the held-out draws)."""
        return scenarios.draw_keys(self.spec.seed, VALIDATION_OFFSET + np.arange(draws))

    # -- parameters -------------------------------------------------------------------
    def initial_params(self) -> dict:
        return self.param_map.to_params(self.base_gains, self.spec.jnp_dtype)

    def gains(self, params) -> Any:
        """Evaluation gains of ``params`` (the base boundary layer, not the annealed one)."""
        return self.param_map.to_gains(params, self.base_gains)

    def params_of(self, gains: Any) -> dict:
        """Unconstrained parameters of ``gains``, a start other than the base gains.

        Raises ``ValueError`` when a field the problem does not tune differs from the
        base gains (that field would silently take the base value)."""
        tuned = set(self.param_map.names)
        different = [
            name
            for name in self.base_gains._fields
            if name not in tuned
            and not np.array_equal(
                np.asarray(getattr(gains, name), np.float64),
                np.asarray(getattr(self.base_gains, name), np.float64),
            )
        ]
        if different:
            raise ValueError(
                f"untuned fields differ from the problem's base gains: {', '.join(different)}"
            )
        return self.param_map.to_params(gains, self.spec.jnp_dtype)

    def vector(self, params) -> np.ndarray:
        """``params`` as one float64 vector ``(param_map.size,)`` (the ``ravel`` order)."""
        return np.asarray(self.param_map.ravel(params)[0], np.float64)

    def unravel(self, vector) -> dict:
        """The inverse of :meth:`vector`."""
        return self._unravel(jnp.asarray(vector, self.spec.jnp_dtype))

    # -- evaluations ------------------------------------------------------------------
    def value(self, params, width_scale: float, keys: Array) -> Step:
        return self._value(params, jnp.asarray(width_scale, self.spec.jnp_dtype), keys)

    def value_and_grad(self, params, width_scale: float, keys: Array) -> Step:
        return self._value_and_grad(params, jnp.asarray(width_scale, self.spec.jnp_dtype), keys)

    def lower_gradient(self, params, width_scale: float, keys: Array):
        """The gradient's per-device program lowered (``jax.jit``'s ``Lowered``) for
        ``keys`` as one block per device of the problem's mesh: ``.compile()`` then
        ``memory_analysis()`` or ``cost_analysis()``."""
        scale = jnp.asarray(width_scale, self.spec.jnp_dtype)
        return self._value_and_grad.lower(params, scale, keys)

    def batch_value(self, vectors, width_scale: float, keys: Array):
        """Objectives ``(P,)`` and :class:`fojax.optimize.cost.DrawCosts` with ``(P, n, ...)``
        leaves of ``P`` candidates (rows of ``vectors``, :meth:`vector` order), each on
        the same ``n`` draws ``keys`` (common random numbers): one compiled, batched call
        (a ``vmap`` over candidates of :meth:`value`), compiled once per ``(P, n)``."""
        vectors = jnp.asarray(vectors, self.spec.jnp_dtype)
        if vectors.ndim != 2 or vectors.shape[1] != self.param_map.size:
            raise ValueError(
                f"candidates must be an array (P, {self.param_map.size}), got shape "
                f"{tuple(vectors.shape)}"
            )
        return self._batch_value(vectors, jnp.asarray(width_scale, self.spec.jnp_dtype), keys)


def _gains_key(gains) -> dict:
    """Gains as a JSON-ready description (a program key of :mod:`fojax.export_cache`)."""
    return {name: np.asarray(value).tolist() for name, value in gains._asdict().items()}


def _over_mesh(per_draw, reduce, mesh, device_batch=None, compiler_options=None, key=None):
    """``value_and_grad`` with the draws over ``mesh``: the minibatch's keys in blocks of
    ``device_batch`` (default: the whole minibatch, one block), one block per device
    and call (the last block completed by repeating the last key, a short last call by
    repeating its last block), ``per_draw`` (vmapped over the keys) compiled for one
    block per device, the per-draw values gathered to every process
    (``jax.distributed``), the padding dropped, then ``reduce`` (jitted) on this
    process's default device.

    Each draw is computed by the same per-device program at the same place in its
    block whatever the mesh, so every mesh, one device or the devices of several
    processes, gives the same per-draw values and hence the same objective and
    gradient, bit for bit, for a given ``device_batch`` (XLA rounds a draw according to
    its batch: :mod:`fojax.study`). key: what ``per_draw`` closes over; given, its
    program is kept across processes (:func:`fojax.export_cache.reusable`)."""
    devices = int(mesh.devices.size)
    program = sharding.sharded_batch(
        per_draw, mesh, batched=(False, False, True), compiler_options=compiler_options
    )
    run = program
    if key is not None:
        run = export_cache.reusable(program, "gradient", key, compiler_options)
    several = any(d.process_index != jax.process_index() for d in mesh.devices.flat)

    def value_and_grad(params, width_scale, keys):
        keys = np.asarray(keys)
        n = keys.shape[0]
        batch = int(device_batch or n)
        blocks = -(-n // batch)
        params = sharding.replicate(params, mesh)
        width_scale = sharding.replicate(width_scale, mesh)
        parts = []
        for first_block in range(0, blocks, devices):
            chosen = [min(b, blocks - 1) for b in range(first_block, first_block + devices)]
            index = np.concatenate([np.arange(b * batch, (b + 1) * batch) for b in chosen])
            out = run(
                params, width_scale, sharding.shard_draws(keys[np.minimum(index, n - 1)], mesh)
            )
            if several:
                from jax.experimental import multihost_utils

                sharding.barrier("gradients")  # compilations may end far apart
                out = multihost_utils.process_allgather(out, tiled=True)
            real = min(devices, blocks - first_block) * batch
            parts.append(jax.tree.map(lambda x, real=real: np.asarray(x)[:real], out))
        out = jax.tree.map(lambda *xs: jnp.asarray(np.concatenate(xs)[:n]), *parts)
        return reduce(out)

    def lower(params, width_scale, keys):
        """The per-device program lowered for ``keys`` as one block per device."""
        return program.lower(
            sharding.replicate(params, mesh),
            sharding.replicate(width_scale, mesh),
            sharding.shard_draws(np.asarray(keys), mesh),
        )

    value_and_grad.lower = lower
    return value_and_grad


@functools.lru_cache(maxsize=16)
def _evaluator(
    spec: ProblemSpec,
    scenario: scenarios.Scenario,
    horizon: float,
    switching: str,
    registered: bool = False,
):
    """The compiled per-draw evaluation; ``registered``: ``scenario`` is the spec's own
    (its program is then kept across processes, :mod:`fojax.export_cache`)."""
    dtype = spec.jnp_dtype
    steps = int(round(horizon / spec.dt))
    sim_config = simulator.SimulationConfig(
        dt=spec.dt, horizon=horizon, save_every=checkpoint_interval(steps, 100.0)
    )
    scenario = _scenario_for(scenario, horizon)
    controller = spec.make_controller(switching, horizon)
    batch_cost = cost_lib.make_batch_cost(controller, scenario, sim_config, spec.cost, dtype)

    def run(gains, keys):
        j, terms, status = batch_cost(gains, keys)
        effective, diverged = cost_lib.guard(spec.cost, j, status)
        return cost_lib.DrawCosts(effective, terms, status, diverged)

    if not registered:  # a modified scenario: its functions have no stable description
        return jax.jit(run)
    key = {"spec": spec.as_dict(), "horizon": horizon, "switching": switching}
    return export_cache.reusable(jax.jit(run), "evaluation", key)


def evaluate(
    spec: ProblemSpec,
    gains: Any,
    keys: Array,
    horizon: float | None = None,
    switching: str = "sat",
    scenario: scenarios.Scenario | None = None,
    chunk: int = 64,
) -> cost_lib.DrawCosts:
    """Per-draw costs (NumPy) of ``gains`` under ``spec.cost`` on ``keys``, with the
    evaluation ``switching`` (default ``sat``; for a controller with a switching
    function, which the FL has not: it runs as it is), at ``horizon`` (default the
    spec's) on ``scenario`` (default the spec's; pass a modified one for an unseen
    reference).

    Runs in chunks of ``chunk`` draws (one compilation per setting). Forward only.
    """
    horizon = spec.horizon if horizon is None else float(horizon)
    registered = scenario is None
    scenario = scenarios.get_scenario(spec.scenario) if scenario is None else scenario
    # The seed and the minibatch size do not enter the compiled evaluation.
    key = dataclasses.replace(spec, seed=0, draws=1, compile="optimized")
    run = _evaluator(key, scenario, horizon, switching, registered)
    dtype = spec.jnp_dtype
    gains = type(gains)(*(jnp.asarray(g, dtype) for g in gains))
    keys = np.asarray(keys)
    n = keys.shape[0]
    chunk = min(chunk, n)
    parts = []
    for first in range(0, n, chunk):
        index = np.minimum(np.arange(first, first + chunk), n - 1)
        out = run(gains, jnp.asarray(keys[index]))
        size = min(chunk, n - first)
        parts.append([np.asarray(x)[:size] for x in out])
    return cost_lib.DrawCosts(*(np.concatenate(leaves) for leaves in zip(*parts, strict=True)))
