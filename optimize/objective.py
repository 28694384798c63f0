"""The tuning objective (:class:`Objective`): a :class:`ProblemSpec` (controller,
scenario or union, cost), optionally a requirement set, the actuators and the evaluation
law, compiled once; every tuner (:mod:`fojax.optimize.strategies`) and every study calls
it. Draws: the three ranges of :mod:`fojax.optimize.spec`; a union's draw ``i`` is of
member ``i % members``, ``i`` its index in its range (a tuning sample ``k`` of ``n``
draws holds draws ``k n`` to ``k n + n - 1``: samples of fewer draws than members take
the members in turn).

Laws. A request with a width ``w`` runs the *tuning law*: the sliding-mode controllers
switch with ``tanh(S / (w b))``, ``b`` the gains' boundary layer (the field of role
``"smoothing"``); one without runs the *evaluation law* (``switching``, default ``sat``
with ``b``): the gains scored as they are used (validation and held-out draws always
run it). Both have gradients (``sat`` is piecewise linear, differentiable almost
everywhere; the paper's ``sign`` has none worth taking).

Outputs per draw (:class:`Outputs`): ``values[..., 0]`` the target ``f`` (the weighted
sum ``J`` of :mod:`fojax.optimize.cost`, or with a requirement set ``E`` or ``P + A``),
``values[..., 1:]`` the normalised violations ``v_j`` (:func:`fojax.requirements.violations`,
``<= 0`` where the draw meets requirement ``j``), the cost terms, the status flags. A loss
(:mod:`fojax.optimize.losses`) turns them into one number per point; its gradient is the
loss's cotangents on each draw's outputs through one batch-last reverse pass with one copy
of the parameters per draw (a diverged draw cannot poison the others).

Programs: a *lane* is one point on one draw; a request of ``P`` points on ``n`` draws is
``P n`` lanes, run in blocks of ``lanes`` per device and call over the mesh (the last
block padded by repeating its last lane), so a lane's numbers depend on the block size
only, never on ``P``, ``n`` or the devices. The per-draw gradient runs in blocks of
``device_batch`` draws per device (default: the whole sample), gathered to every process
and reduced there the same way, so every mesh takes the same steps.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from fojax import blocks, export_cache, observers, scenarios, sharding, simulator
from fojax import requirements as rq
from fojax.controllers import registry
from fojax.envelope import SIGN_WIDTH
from fojax.optimize import cost as cost_lib
from fojax.optimize.losses import MeanLoss
from fojax.optimize.requests import Evaluation, Outputs, Request
from fojax.optimize.spec import COMPILE_MODES, TARGETS, ProblemSpec, checkpoint_interval, draw_keys

__all__ = ["LANES", "Evaluation", "Objective", "Outputs", "Request", "stratified"]

LANES = 64
"""Default lanes (point x draw) per device and forward call."""
GRADIENT_WORK = 6
"""A draw's gradient in forward draw-steps (on a CPU: the "gradient / forward" column of
docs/performance.md's bench block)."""
SAMPLE_BLOCK = 16
"""Keys per call of the draws' program."""


def _covering(scenario: scenarios.Scenario, horizon: float) -> scenarios.Scenario:
    """The scenario with tables covering at least ``horizon`` (its own length kept when
    longer: draw ``i`` over a short horizon is the beginning of the same draw)."""
    return (
        scenario if horizon <= scenario.horizon else dataclasses.replace(scenario, horizon=horizon)
    )


class Objective:
    """:class:`ProblemSpec` + base gains (+ a requirement set), compiled.

    base_gains: the gains the tuned fields start from and the untuned fields keep
    (checked by the controller). requirements: a :class:`fojax.requirements.RequirementSet`
    (violations join the outputs; the loss must then be a constrained one). target: what
    ``f`` is (:data:`TARGETS`; ``"cost"`` without requirements). scenario: a
    :class:`fojax.scenarios.Scenario` simulated instead of the spec's (e.g. a nominal
    run). rotor_speed_limit: ``w_max`` (rad/s) for rotor-limited actuators, ``None``:
    ideal. switching: the evaluation law. mesh: a :func:`fojax.sharding.draw_mesh`
    (default one device). device_batch: draws per device and call of the gradient
    (default: the sample; with a mesh only). lanes: lanes per device and forward call.
    """

    def __init__(
        self,
        spec: ProblemSpec,
        base_gains: Any,
        requirements: rq.RequirementSet | None = None,
        target: str = "cost",
        scenario: scenarios.Scenario | None = None,
        rotor_speed_limit: float | None = None,
        switching: str = "sat",
        mesh=None,
        device_batch: int | None = None,
        lanes: int = LANES,
    ):
        if target not in TARGETS or (requirements is None and target != "cost"):
            raise ValueError(
                f"target must be one of {TARGETS} ('cost' without requirements), got {target!r}"
            )
        if mesh is None and device_batch is not None:
            raise ValueError(
                f"device_batch={device_batch!r} applies to draws split over a mesh; pass "
                "mesh= (e.g. fojax.sharding.draw_mesh()) or leave device_batch out"
            )
        self.spec, self.requirements, self.target = spec, requirements, target
        self.switching, self.rotor_speed_limit = switching, rotor_speed_limit
        self.dtype = jnp.dtype(spec.dtype)
        cls = registry.get_controller_class(spec.controller)
        base_gains = type(base_gains)(*(jnp.asarray(g, self.dtype) for g in base_gains))
        cls.check_gains(base_gains)
        self.base_gains, self._widths = base_gains, cls.GAINS.with_role("smoothing")
        self.param_map = spec.parameter_map()
        template = self.param_map.to_params(base_gains, self.dtype)
        x0, self._unravel = self.param_map.ravel(template)
        self.size, self.x0 = int(x0.size), np.asarray(x0, np.float64)
        self.registered = scenario is None
        self.scenario = spec.scenario_object() if scenario is None else scenario
        self.members = len(self.scenario.members) if self.scenario.members else 0
        self.mesh, self._mesh = mesh, mesh or sharding.one_device_mesh()
        self.device_batch, self.lanes, self.loss = device_batch, int(lanes), MeanLoss(spec.cost)
        self._programs: dict = {}
        self._ahead: dict = {}  # (kind, law, dt) -> set once compiled ahead (:meth:`expect`)
        self._lock = threading.Lock()

    # -- description, parameters, draws -------------------------------------------
    @property
    def count(self) -> int:
        """Outputs per draw: the target and one violation per requirement."""
        return 1 + (len(self.requirements) if self.requirements is not None else 0)

    def describe(self) -> dict:
        """JSON-ready: what the objective's numbers depend on (a run's fingerprint)."""
        reqs = self.requirements
        return {
            "problem": self.spec.as_dict(),
            "target": self.target,
            "requirements": None if reqs is None else reqs.to_dict(),
            "rotor_speed_limit": self.rotor_speed_limit,
            "evaluation_switching": self.switching,
            "scenario": "spec" if self.registered else repr(self.scenario)[:200],
            "lanes": self.lanes,
            "device_batch": self.device_batch,
        }

    def vector(self, gains: Any) -> np.ndarray:
        """``(d,)`` float64 parameters of ``gains``; ``ValueError`` when a field the
        objective does not tune differs from the base gains (it would be lost)."""
        tuned, base = set(self.param_map.names), self.base_gains
        different = [
            n
            for n in base._fields
            if n not in tuned
            and not np.array_equal(*(np.asarray(getattr(g, n), np.float64) for g in (gains, base)))
        ]
        if different:
            raise ValueError(
                f"untuned fields differ from the objective's base gains: {', '.join(different)}"
            )
        params = self.param_map.to_params(gains, self.dtype)
        return np.asarray(self.param_map.ravel(params)[0], np.float64)

    def gains(self, x) -> Any:
        """The evaluation gains of ``x`` ``(d,)`` (the base boundary layer)."""
        return self.param_map.to_gains(self._unravel(jnp.asarray(x, self.dtype)), self.base_gains)

    def keys(self, kind: str, count: int | None = None, first: int = 0) -> np.ndarray:
        """``(count, 2)`` keys of range ``kind`` of the spec's seed (:func:`draw_keys`)."""
        return draw_keys(self.spec.seed, kind, self.spec.draws if count is None else count, first)

    def sample(self, index: int, draws: int | None = None) -> np.ndarray:
        """Tuning sample ``index`` of ``draws`` (default the spec's) draws."""
        n = self.spec.draws if draws is None else draws
        return self.keys("tuning", n, index * n)

    # -- the compiled rollouts ------------------------------------------------------
    def _gains_of(self, x, width):
        gains = self.param_map.to_gains(self._unravel(x), self.base_gains)
        return gains._replace(**{w: getattr(self.base_gains, w) * width for w in self._widths})

    def _observer(self, config):
        chain = {"cost": cost_lib.CostObserver(self.spec.cost, config.dt)}
        if self.spec.envelope is not None and self.requirements is None:
            chain["torques"] = cost_lib.TorqueVariation()
        if self.requirements is not None:
            chain["requirements"] = rq.RequirementMetrics.for_requirements(
                self.requirements, config, self.scenario.vehicle
            )
        return observers.Chain(**chain)

    def _rollout(self, law: str, horizon: float, scenario, save_every: int, dt: float):
        """``run(x (d, L), width, draws) -> (values (K, L), terms (4, L), metrics,
        status (L,))``: one batch-last rollout of ``draws`` (batch first, as
        :meth:`draws` makes them, at the step ``dt``), one copy of the gains per lane."""
        spec, dtype = self.spec, self.dtype
        config = simulator.SimulationConfig(
            dt=dt,
            horizon=horizon,
            save_every=save_every,
            rotor_speed_limit=self.rotor_speed_limit,
        )
        controller, observer = spec.make_controller(law, horizon, dt), self._observer(config)
        scenario = _covering(scenario, horizon)
        weights = jnp.asarray(spec.cost.weights, dtype)
        model = scenario.plant_params(dtype)
        scales = None if spec.case_scales is None else jnp.asarray(spec.case_scales, dtype)
        bounds = (None if spec.case_chattering is None
                  else jnp.asarray(spec.case_chattering, dtype))  # fmt: skip
        tracking = (None if spec.case_tracking is None
                    else jnp.asarray(spec.case_tracking, dtype))  # fmt: skip
        laws = spec.envelope.laws() if spec.envelope is not None else ()
        narrow = (jnp.asarray([SIGN_WIDTH if law == "sign" else 1.0 for law in laws], dtype)
                  if "sign" in laws and self._widths else None)  # fmt: skip

        def run(xs, width, draws):
            gains = jax.vmap(self._gains_of, in_axes=(-1, None), out_axes=-1)(xs, width)
            draws = scenarios.batch_last(draws)
            if narrow is not None:  # the envelope's sign cases: the boundary layer closed
                share = narrow[draws.member]
                gains = gains._replace(**{w: getattr(gains, w) * share for w in self._widths})
            out = simulator.rollout(controller, gains, model, scenario, draws, config, observer)
            terms = out.outputs["cost"]
            cost = jnp.sum(weights[:, None] * terms, 0)
            if scales is not None:  # each draw's cost in units of its case's scale
                cost = cost / scales[draws.member]
            if bounds is not None:  # chattering beyond its case's bound
                variation = out.outputs["torques"]
                excess = jnp.maximum(variation / bounds[draws.member] - 1.0, 0.0)
                cost = cost + spec.bound_excess * excess
            if tracking is not None:  # position RMSE beyond its case's bound
                ratio = jnp.sqrt(jnp.maximum(terms[0], 0.0) / tracking[draws.member])
                cost = cost + spec.bound_excess * jnp.maximum(ratio - 1.0, 0.0)
            f = {"cost": cost, "effort": terms[2]}
            f["tracking"] = terms[0] + terms[1]
            metrics = out.outputs.get("requirements")
            rows = [f[self.target][None]]
            if metrics is not None:
                rows.append(rq.violations(self.requirements, metrics))
            elif "torques" in out.outputs:  # an envelope's: the torques' total variation
                metrics = {"torque_variation": out.outputs["torques"]}
            return jnp.concatenate(rows), terms, metrics, out.status

        return run

    def stratified(self, draws: int) -> int:
        """:func:`stratified` for this objective's union (``draws`` itself without one)."""
        return stratified(draws, self.members)

    def _members(self, count: int, first: int = 0) -> np.ndarray:
        if not self.members:
            return np.zeros(count, np.int64)
        return (first + np.arange(count)) % self.members

    def _cached(self, key, make):
        """The program under ``key``, made by ``make()`` the first time (under a lock)."""
        with self._lock:
            if key not in self._programs:
                self._programs[key] = make()
        return self._programs[key]

    def _sampler(self, scenario, registered: bool, dt: float | None = None):
        """The draws of a block of :data:`SAMPLE_BLOCK` keys at the step ``dt`` (default
        the spec's; a program of its own, shared by every rollout program: compiled once,
        beside them)."""
        dt, dtype = self.spec.dt if dt is None else dt, self.dtype

        def sample(keys, member):
            return scenarios.batch_first(scenarios.sample_draws(scenario, keys, dt, dtype, member))

        # Without LLVM's optimisation passes: a tenth of the compile time (its calls take
        # milliseconds); the draws agree with an optimised program's to an ulp or two.
        fast = COMPILE_MODES["fast"]
        key = ("sampler", None if registered else id(scenario), dt)
        return self._cached(key, lambda: _FirstCall(jax.jit(sample, compiler_options=fast)))

    def draws(self, keys, scenario=None, horizon: float | None = None, dt: float | None = None,
              first: int = 0):  # fmt: skip
        """The draws of ``keys`` ``(n, 2)`` (a union's draw ``i`` of member ``(first + i)
        % members``: ``first`` the index of the first key in its range) at the step ``dt``
        (default the spec's), batch first, on the host: sampled in blocks of
        :data:`SAMPLE_BLOCK`."""
        registered = scenario is None and self.registered
        scenario = _covering(self.scenario if scenario is None else scenario,
                             self.spec.horizon if horizon is None else horizon)  # fmt: skip
        keys = np.asarray(keys)
        member = self._members(len(keys), first).astype(np.int32)
        program = self._sampler(scenario, registered, self._step(dt))
        return blocks.evaluate_in_blocks(
            lambda shared, batch: program(*batch), None, (keys, member), None, SAMPLE_BLOCK
        )

    def _step(self, dt: float | None) -> float | None:
        """``dt`` checked (a coarser step of the spec's), ``None`` for the spec's own."""
        if dt is None or dt == self.spec.dt:
            return None
        self.spec.check_step(dt)
        return float(dt)

    def _forward(self, law: str, horizon: float, scenario, registered: bool, dt=None):
        """The lanes program of ``law`` at ``horizon`` and step ``dt`` (``None``: the
        spec's; lanes first in and out) over the mesh, compiled once."""

        def make():
            step = self.spec.dt if dt is None else dt
            steps = int(round(horizon / step))
            run = self._rollout(law, horizon, scenario, checkpoint_interval(steps, 100.0), step)

            def lanes(width, batch):
                xs, draws = batch
                values, terms, metrics, status = run(xs.T, width, draws)
                return values.T, terms.T, metrics, status

            key = dict(law=law, horizon=horizon, kind="lanes") if registered else None
            if key is not None and dt is not None:
                key["dt"] = dt
            return self._program(lanes, key, None)

        key = ("forward", law, horizon, None if registered else id(scenario), dt)
        return self._cached(key, make)

    def _program(self, fn, kind: dict | None, options):
        """``fn(shared, batch)`` compiled for one block per device of the mesh (kept
        across processes under what it closes over and ``kind``,
        :mod:`fojax.export_cache`); its first call holds a lock, so that two threads never
        compile it twice."""
        program = sharding.sharded_batch(fn, self._mesh, (False, True), options)
        if kind is not None:
            gains = {k: np.asarray(v).tolist() for k, v in self.base_gains._asdict().items()}
            key = {**self.describe(), "base_gains": gains, **kind}
            program = export_cache.reusable(program, key["kind"], key, options)
        return _FirstCall(program)

    def forward(
        self,
        points,
        keys,
        width: float | None = None,
        horizon: float | None = None,
        scenario: scenarios.Scenario | None = None,
        dt: float | None = None,
        first: int = 0,
    ) -> Outputs:
        """Outputs ``(P, n, ...)`` of ``points`` ``(P, d)`` on the draws ``keys`` ``(n, 2)``
        (common to the points), at the tuning law with ``width`` or the evaluation law
        (``None``), at ``horizon`` (default the spec's) on ``scenario`` (default the
        objective's), at the step ``dt`` (default the spec's; a whole multiple of it);
        ``first``: the index of the first key in its range (:meth:`draws`)."""
        points = np.atleast_2d(np.asarray(points, np.float64))
        if points.shape[1] != self.size:
            raise ValueError(f"points must be (P, {self.size}), got {points.shape}")
        keys = np.asarray(keys)
        horizon = self.spec.horizon if horizon is None else float(horizon)
        registered = scenario is None and self.registered
        scenario = self.scenario if scenario is None else scenario
        law = self.switching if width is None else "tanh"
        dt = self._step(dt)
        program = self._forward(law, horizon, scenario, registered, dt)
        count, n = points.shape[0], keys.shape[0]
        draws = self.draws(keys, None if registered else scenario, horizon, dt, first)
        xs = np.repeat(points, n, axis=0).astype(self.dtype)
        batch = (xs, jax.tree.map(lambda a: np.tile(a, (count,) + (1,) * (a.ndim - 1)), draws))
        width = jnp.asarray(1.0 if width is None else width, self.dtype)
        out = blocks.evaluate_in_blocks(program, width, batch, self._mesh, self.lanes)
        values, terms, metrics, status = jax.tree.map(_float64, out)
        shape = (count, n)
        metrics = None if metrics is None else {k: v.reshape(shape) for k, v in metrics.items()}
        return Outputs(
            values.reshape(shape + (-1,)),
            terms.reshape(shape + (4,)),
            status.reshape(shape),
            metrics,
        )

    def _gradient(self, law: str = "tanh"):
        """The per-draw gradient program of ``law``, compiled once."""
        kind = dict(kind="gradient", law=law) if self.registered else None
        options = COMPILE_MODES[self.spec.compile]
        return self._cached(
            ("gradient", law), lambda: self._program(self._per_draw_function(law), kind, options)
        )

    def _per_draw_function(self, law: str):
        """``per_draw((x, width), (keys, member, cotangent)) -> (values, terms, status,
        gradients)`` of one block of draws (the gradient program before the mesh)."""
        spec = self.spec
        run = self._rollout(law, spec.horizon, self.scenario, spec.block, spec.dt)

        def per_draw(shared, batch):
            (x, width), (draws, cotangent) = shared, batch
            copies = jnp.broadcast_to(x[:, None], x.shape + (cotangent.shape[0],))

            def outputs(c):
                values, terms, _, status = run(c, width, draws)
                return values.T, (terms.T, status)

            values, pullback, (terms, status) = jax.vjp(outputs, copies, has_aux=True)
            (grads,) = pullback(cotangent.astype(values.dtype))
            return values, terms, status, grads.T

        return per_draw

    def _per_draw(self, law, x, width, draws, cotangent):
        """``(values (n, K), terms (n, 4), status (n,), gradients (n, d))``: the outputs
        of ``x`` on ``draws`` and the per-draw gradients of ``cotangent . outputs``, in
        blocks of ``device_batch`` draws per device (default: the whole sample) over the
        mesh; every mesh gives the same per-draw values, bit for bit, for a given
        ``device_batch`` (:func:`fojax.blocks.evaluate_in_blocks`)."""
        shared = (jnp.asarray(x, self.dtype), jnp.asarray(width, self.dtype))
        batch = (draws, np.asarray(cotangent, self.dtype))
        block = self.device_batch or len(cotangent)
        out = blocks.evaluate_in_blocks(self._gradient(law), shared, batch, self._mesh, block)
        return jax.tree.map(_float64, out)

    def work(self, lanes: int, block: int | None = None, dt: float | None = None) -> int:
        """The cost of ``lanes`` lanes in lane-steps of whole calls (at the step ``dt``,
        default the spec's): rounded up to the calls of ``block`` (default the
        objective's lanes) per device over the mesh."""
        per_call = (block or self.lanes) * int(self._mesh.devices.size)
        return -(-lanes // per_call) * per_call * self.spec.steps_at(dt)

    def compile(self, kind: str, width: float | None = None, dt: float | None = None) -> None:
        """Compile a program ahead of its first call (in a thread beside another's
        compilation or a phase that does not need it yet), from the shapes of its
        arguments, running nothing: ``kind`` ``"sampler"`` (the draws' at the step
        ``dt``), ``"forward"`` (the lanes program of the law of ``width``, ``None`` the
        evaluation law, at the step ``dt``, default the spec's) or ``"gradient"`` (the
        per-draw gradient of that law). :meth:`ready` waits for it."""
        event = self.expect(kind, width, dt)
        dt, law = self._step(dt), "tanh" if width is not None else self.switching
        try:
            self._compile(kind, law, dt)
        finally:
            event.set()

    def expect(self, kind: str, width: float | None = None, dt: float | None = None):
        """The event set once the program of :meth:`compile`'s arguments is compiled
        ahead; registered before the compiling thread starts, so that :meth:`ready`
        waits for a compilation that has not begun yet."""
        dt, law = self._step(dt), "tanh" if width is not None else self.switching
        key = (kind, "sampler" if kind == "sampler" else law, dt)
        with self._lock:
            return self._ahead.setdefault(key, threading.Event())

    def _compile(self, kind: str, law: str, dt: float | None) -> None:
        blank = [
            jax.ShapeDtypeStruct((SAMPLE_BLOCK,) + s, t)
            for s, t in (((2,), "uint32"), ((), "int32"))
        ]
        sampler = self._sampler(self.scenario, self.registered, dt)
        if kind == "sampler":
            sampler.ahead(*blank)
            return
        block = self.lanes if kind == "forward" else self.device_batch or self.spec.draws
        count = block * int(self._mesh.devices.size)
        structure = jax.eval_shape(sampler.program, *blank)
        draws = jax.tree.map(lambda a: jax.ShapeDtypeStruct((count,) + a.shape[1:], a.dtype),
                             structure)  # fmt: skip
        if kind == "gradient":
            shared = (jax.ShapeDtypeStruct((self.size,), self.dtype),
                      jax.ShapeDtypeStruct((), self.dtype))  # fmt: skip
            batch = (draws, jax.ShapeDtypeStruct((count, self.count), self.dtype))
            program = self._gradient(law)
        else:
            shared = jax.ShapeDtypeStruct((), self.dtype)
            batch = (jax.ShapeDtypeStruct((count, self.size), self.dtype), draws)
            program = self._forward(law, self.spec.horizon, self.scenario, self.registered, dt)
        program.ahead(*blocks.abstract(shared, batch, self._mesh))

    def ready(self, request: Request, timeout: float) -> bool:
        """Whether the programs ``request`` needs (its draws' and its own) are compiled,
        waiting at most ``timeout`` seconds in all for their compilations ahead
        (:meth:`compile`); ``True`` for a program not compiled ahead (its first call
        compiles it)."""
        kind = "gradient" if request.gradient else "forward"
        law = "tanh" if request.width is not None else self.switching
        dt = self._step(request.dt)
        with self._lock:
            events = [self._ahead.get(key) for key in (("sampler", "sampler", dt), (kind, law, dt))]
        end = time.perf_counter() + timeout
        return all(e is None or e.wait(max(end - time.perf_counter(), 0.0)) for e in events)

    def lower_gradient(self, x=None, law: str = "tanh"):
        """``(lowered, args)``: the per-draw gradient of the fixed sample in one block on
        one device, lowered at ``x`` (default the start); ``lowered.compile()`` is the
        program (its ``memory_analysis()`` the working set: ``experiments/tune_memory.py``),
        called with ``*args``."""
        x = self.x0 if x is None else np.asarray(x, np.float64)
        keys = self.sample(0)
        shared = (jnp.asarray(x, self.dtype), jnp.asarray(1.0, self.dtype))
        batch = (self.draws(keys), np.ones((len(keys), self.count), self.dtype))
        program = jax.jit(
            self._per_draw_function(law), compiler_options=COMPILE_MODES[self.spec.compile]
        )
        return program.lower(shared, batch), (shared, batch)

    # -- what strategies and the driver call -------------------------------------------
    def __call__(self, request: Request) -> Evaluation:
        """Evaluate a strategy's request on its tuning sample."""
        loss = self.loss if request.loss is None else request.loss
        keys = self.sample(request.sample, request.draws)
        # a union's cases by the draws' index in the tuning range: a sample of fewer
        # draws than cases flies the next cases in the next sample
        first = request.sample * keys.shape[0]
        points = np.atleast_2d(np.asarray(request.points, np.float64))
        draw_steps = points.shape[0] * keys.shape[0] * self.spec.steps_at(request.dt)
        if not request.gradient:
            outputs = self.forward(points, keys, request.width, dt=request.dt, first=first)
            work = self.work(points.shape[0] * keys.shape[0], dt=request.dt)
            return Evaluation(np.asarray(loss.values(outputs)), None, outputs, 0, draw_steps, work)
        if request.dt is not None and request.dt != self.spec.dt:
            raise ValueError("a gradient is taken at the spec's step dt")
        if points.shape[0] != 1:
            raise ValueError("a gradient is taken at one point")
        if self.requirements is not None and isinstance(loss, MeanLoss):
            raise ValueError(
                "a requirement set is tuned with a constrained loss (an augmented Lagrangian)"
            )
        n = keys.shape[0]
        work = GRADIENT_WORK * self.work(n, self.device_batch or n)
        if isinstance(loss, MeanLoss):
            cotangent = np.ones((n, 1))
        else:  # the cotangents need the outputs at the point first
            cotangent = loss.cotangents(
                _first(self.forward(points, keys, request.width, first=first))
            )
            draw_steps, work = 2 * draw_steps, work + self.work(n)
        law = "tanh" if request.width is not None else self.switching
        width = 1.0 if request.width is None else request.width
        values, terms, status, grads = self._per_draw(
            law, points[0], width, self.draws(keys, first=first), cotangent
        )
        outputs = Outputs(values, terms, status)
        finite = np.all(np.isfinite(grads), -1)
        usable = finite & outputs.valid
        weights = loss.weights(outputs)[1] if isinstance(loss, MeanLoss) else np.ones(n)
        gradient = np.sum(np.where(usable[:, None], grads, 0.0) * weights[:, None], 0)
        bad = int(np.sum(~finite & outputs.valid))
        outputs = Outputs(values[None], terms[None], status[None])
        return Evaluation(
            np.asarray(loss.values(outputs)), gradient, outputs, bad, draw_steps, work
        )

    def score(self, outputs: Outputs) -> tuple[tuple, dict]:
        """``(key, summary)`` of one point's outputs ``(n, ...)`` at the evaluation law:
        a smaller key is better. Weighted sum: the mean cost. Requirements: more draws
        passing every requirement, then fewer failed (draw, requirement) pairs, then the
        lower mean target over the valid draws. Every summary holds ``kind`` (``"cost"``
        or ``"yield"``) and ``score`` (the mean cost, lower is better, or the yield,
        higher is better), then the kind's details."""
        valid = outputs.valid
        if self.requirements is None:
            cost = np.where(valid, outputs.values[:, 0], self.spec.cost.divergence_cost)
            mean = float(self.loss.values(outputs))
            terms = dict(zip(("P", "A", "E", "C"), np.mean(outputs.terms, 0).tolist(), strict=True))
            spread = float(np.std(cost, ddof=1)) if len(cost) > 1 else None
            summary = {"kind": "cost", "score": mean, "cost": mean, "std": spread, "terms": terms,
                       "diverged": int(np.sum(~valid))}  # fmt: skip
            return (mean,), summary
        metrics = rq.draw_metrics(outputs.metrics, outputs.status)
        result = rq.evaluate(self.requirements, metrics, valid=valid)
        f = outputs.values[..., 0]
        mean = float(np.mean(f[valid])) if np.any(valid) else math.inf
        failures = {n: int(k) for n, k in zip(result.names, result.failures, strict=True)}
        summary = {
            "kind": "yield",
            "score": float(result.yield_),
            "passed": int(result.passed),
            "draws": int(result.draws),
            "yield": float(result.yield_),
            "interval": [float(v) for v in result.interval],
            "most_failed": result.most_failed,
            "failures": failures,
            "objective": mean,
        }
        return (-result.passed, sum(failures.values()), mean), summary

    def evaluate(self, x, keys, horizon=None, scenario=None) -> tuple[tuple, dict, Outputs]:
        """:meth:`score` of the point ``x`` ``(d,)`` on ``keys`` at the evaluation law
        (``horizon``, ``scenario``: as :meth:`forward`), and its outputs ``(n, ...)``."""
        outputs = _first(self.forward(np.asarray(x)[None], keys, None, horizon, scenario))
        key, summary = self.score(outputs)
        return key, summary, outputs


def _float64(array: np.ndarray) -> np.ndarray:
    return array.astype(np.float64) if array.dtype.kind == "f" else array


class _FirstCall:
    """A program whose first call holds a lock (two threads never compile it twice),
    which :meth:`ahead` compiles from its arguments' shapes without running it."""

    def __init__(self, program):
        self.program, self.lock, self.ready = program, threading.Lock(), False

    def ahead(self, *abstract) -> None:
        """Compile for arguments of these shapes (``jax.ShapeDtypeStruct`` trees), as
        the first call would, running nothing."""
        with self.lock:
            if not self.ready:
                lower = getattr(self.program, "lower", None)
                if lower is None:  # fojax.export_cache: it lowers and compiles itself
                    self.program.ahead(*abstract)
                else:
                    lower(*abstract).compile()

    def __call__(self, *args):
        if not self.ready:
            with self.lock:
                out = self.program(*args)
                self.ready = True
                return out
        return self.program(*args)


def stratified(draws: int, members: int) -> int:
    """The fewest draws, at least ``draws``, that hold each of a union's ``members``
    (an envelope's cases) equally often: a multiple of ``members`` (``draws`` itself for
    ``members`` 0 or 1). A sample of them weighs every case alike."""
    m = max(int(members), 1)
    return -(-int(draws) // m) * m


def _first(outputs: Outputs) -> Outputs:
    """The outputs of the first point of ``(P, n, ...)`` outputs."""
    return jax.tree.map(lambda a: a[0], outputs)
