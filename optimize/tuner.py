"""Gradient-based gain tuning on optax, with checkpoints and exact resume.

Each step ``k = 0 ... steps - 1``:

1. draws: minibatch ``k`` of the tuning stream (:meth:`TuningProblem.minibatch_keys`:
   fresh draws every step, disjoint from the held-out ones);
2. switching: ``tanh(S / (scale_k w))`` with ``scale_k`` geometric from
   ``anneal_start`` to ``anneal_end`` (the evaluation width of ``sat`` at 1);
3. the objective (mean or CVaR, :mod:`fojax.optimize.cost`) and its gradient by reverse
   mode through the whole horizon (the rollout rematerialises each block of
   ``save_every`` steps);
4. ``method="adam"``: ``clip_by_global_norm(clip_norm)`` then Adam with a
   cosine-decayed learning rate (from ``learning_rate`` to ``final_learning_rate``
   times it), on the unconstrained parameters of :mod:`fojax.optimize.params` (so every
   iterate is feasible).

``method="lbfgs"``: a quasi-Newton method on one fixed sample of ``draws`` draws
(minibatch 0 of the tuning stream: a deterministic sample-average objective, as the
derivative-free Nelder-Mead gets) at the final switching width (``anneal_end``):
every step evaluates the objective and its gradient at one trial point of
:class:`fojax.optimize.lbfgs.LBFGS` (accepted on sufficient decrease, else the step is
halved), steps capped at ``max_step`` per coordinate. The current iterate is the last
accepted point.

Validation, so that a run never hands back gains worse than its start: the start
(step 0), every ``validate_every`` steps and the last step are scored on
``validation_draws`` validation draws (:meth:`TuningProblem.validation_keys`: disjoint
from the tuning stream and from the held-out draws) with the evaluation switching
``validation_switching`` (``sat``: the width the gains are used with) at the tuning
horizon, the same draws every time. The run returns the best validated iterate and
says which step it came from (``best_step``; 0: the start, which wins ties); with
``validation_draws = 0`` it returns the last iterate. Validation time is part of the
run's wall time.

Every ``checkpoint_every`` steps (and at the end, and on Ctrl-C) the parameters,
the optimiser state, the step, the history and the counters are written to
``DIR/checkpoint.npz`` atomically (a temporary file, then ``os.replace``). A resumed
run reloads them and continues with the same minibatches and schedules, so it
reproduces the uninterrupted run exactly (same compiled functions, same inputs).
A checkpoint records the run's fingerprint (problem, tuner settings, initial gains);
resuming with any difference is refused with the list of differences. Nothing is
written before every input has been checked.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import optax

from fojax.controllers import gains_io
from fojax.optimize import lbfgs as lbfgs_lib
from fojax.optimize.checkpoint import (
    HISTORY_COLUMNS,
    _canonical,
    _load_state,
    _read_meta,
    _save_checkpoint,
    fingerprint,
    write_history,
)
from fojax.optimize.problem import VALIDATION_OFFSET, ProblemSpec, TuningProblem
from fojax.study import describe_differences, fingerprint_differences

__all__ = [
    "CHECKPOINT",
    "HISTORY_COLUMNS",
    "TuneResult",
    "TunerConfig",
    "fingerprint",
    "prepare",
    "tune",
    "width_scale",
]

CHECKPOINT = "checkpoint.npz"
METHODS = ("adam", "lbfgs")


@dataclasses.dataclass(frozen=True)
class TunerConfig:
    """Settings of the gradient tuner (validated on construction).

    steps: optimisation steps (>= 1): evaluations of the objective and its gradient.
    method: ``"adam"`` or ``"lbfgs"`` (see the module docstring).
    learning_rate: Adam's initial step (> 0), in the unconstrained parameters (about a
    relative change for log-mapped gains). final_learning_rate: fraction of it reached
    at the last step (cosine decay, in ``[0, 1]``). clip_norm: Adam's global
    gradient-norm clip (> 0). anneal_start, anneal_end: boundary-layer scale of the
    first and last step (> 0; L-BFGS uses ``anneal_end`` throughout; a controller
    without a smoothing gain, the FL, has none to scale). checkpoint_every: steps between
    checkpoints (>= 1). validation_draws: validation draws (>= 0; 0: no validation,
    the last iterate is returned). validate_every: steps between validations (>= 1;
    the start and the last step are always validated). validation_switching: the
    switching function of the validation runs (``sat``, ``tanh`` or ``sign``; the FL
    has none). ``learning_rate``, ``final_learning_rate`` and ``clip_norm`` are Adam's,
    ``max_step`` and ``memory`` L-BFGS's: the other method does not read them (``fojax
    tune`` refuses them there).
    max_step: L-BFGS's largest change of any parameter per step (> 0). memory:
    L-BFGS's number of stored pairs (>= 1).
    """

    steps: int = 100
    method: str = "lbfgs"
    learning_rate: float = 0.05
    final_learning_rate: float = 0.1
    clip_norm: float = 1.0
    anneal_start: float = 4.0
    anneal_end: float = 1.0
    checkpoint_every: int = 10
    validation_draws: int = 32
    validate_every: int = 5
    validation_switching: str = "sat"
    max_step: float = 1.0
    memory: int = 10

    def __post_init__(self) -> None:
        from fojax.controllers import SWITCHING_FUNCTIONS

        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        for label in ("steps", "checkpoint_every", "validate_every", "memory"):
            value = getattr(self, label)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{label} must be a positive integer, got {value!r}")
        value = self.validation_draws
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise ValueError(f"validation_draws must be an integer >= 0, got {value!r}")
        if self.validation_switching not in SWITCHING_FUNCTIONS:
            raise ValueError(
                f"validation_switching must be one of {SWITCHING_FUNCTIONS}, got "
                f"{self.validation_switching!r}"
            )
        for label in ("learning_rate", "clip_norm", "anneal_start", "anneal_end", "max_step"):
            value = getattr(self, label)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        if not (0 <= self.final_learning_rate <= 1):
            raise ValueError(
                f"final_learning_rate must be in [0, 1], got {self.final_learning_rate!r}"
            )

    def optimizer(self) -> optax.GradientTransformation:
        schedule = optax.cosine_decay_schedule(
            self.learning_rate, max(self.steps - 1, 1), alpha=self.final_learning_rate
        )
        return optax.chain(optax.clip_by_global_norm(self.clip_norm), optax.adam(schedule))

    def learning_rate_at(self, step: int) -> float:
        fraction = min(step, max(self.steps - 1, 1)) / max(self.steps - 1, 1)
        cosine = 0.5 * (1 + math.cos(math.pi * fraction))
        return self.learning_rate * (
            (1 - self.final_learning_rate) * cosine + self.final_learning_rate
        )


def width_scale(config: TunerConfig, step: int) -> float:
    """Boundary-layer scale of step ``step`` (geometric from start to end; L-BFGS:
    ``anneal_end`` throughout, its objective must not change)."""
    if config.steps == 1 or config.method == "lbfgs":
        return float(config.anneal_end)
    fraction = step / (config.steps - 1)
    return float(config.anneal_start * (config.anneal_end / config.anneal_start) ** fraction)


class TuneResult(NamedTuple):
    """params: the returned unconstrained parameters (the best validated iterate; the
    last one without validation). gains: their evaluation gains. history: one dict per
    step (:data:`HISTORY_COLUMNS`). completed: steps done. problem: the
    :class:`TuningProblem`. best_step: the step ``params`` come from (0: the start).
    validation: ``{"draws", "switching", "horizon_s", "initial", "best", "best_step",
    "final"}`` (mean validation costs; ``None`` without validation).
    final_params: the last iterate."""

    params: dict
    gains: Any
    history: list
    completed: int
    problem: TuningProblem
    best_step: int = 0
    validation: dict | None = None
    final_params: dict | None = None


# ------------------------------------------------------------------------------- run


@dataclasses.dataclass
class PreparedRun:
    """A validated run, nothing written yet (:func:`prepare`)."""

    spec: ProblemSpec
    config: TunerConfig
    init_label: str
    init_gains: Any
    out: Path | None
    resume: bool
    fingerprint: dict
    checkpoint_meta: dict | None


def prepare(
    spec: ProblemSpec,
    config: TunerConfig,
    init_gains: Any,
    init_label: str,
    out: str | os.PathLike | None,
    resume: bool = False,
) -> PreparedRun:
    """Validate a run before anything is compiled or written.

    Raises ``ValueError`` when the initial gains are infeasible or cannot be mapped,
    when ``out`` holds a checkpoint and ``resume`` is false (it is never
    overwritten), when ``resume`` is true and there is no checkpoint, or when the
    checkpoint belongs to another configuration (the message lists what differs).
    """
    from fojax.controllers import registry
    from fojax.optimize import params as params_lib

    cls = registry.get_controller_class(spec.controller)
    cls.check_gains(init_gains)
    params_lib.make_parameter_map(spec.controller, spec.fields, spec.share).to_params(init_gains)
    current = _canonical(fingerprint(spec, config, init_label, init_gains))
    meta = None
    if out is not None:
        out = Path(out)
        if out.exists() and not out.is_dir():
            raise ValueError(f"--out {out} exists and is not a directory")
        checkpoint = out / CHECKPOINT
        if resume:
            if not checkpoint.exists():
                raise ValueError(f"nothing to resume: {checkpoint} does not exist")
            meta = _read_meta(checkpoint)
            differences = describe_differences(
                fingerprint_differences(meta.get("fingerprint") or {}, current),
                earlier="checkpoint",
            )
            if differences:
                raise ValueError(
                    f"{checkpoint} was written by another configuration; it differs in:\n  "
                    + "\n  ".join(differences)
                    + "\nrerun with the original options, or choose another --out"
                )
        elif checkpoint.exists():
            raise ValueError(
                f"{out} holds the checkpoint of an earlier run ({checkpoint}); pass --resume to "
                "continue it, or choose another --out"
            )
    elif resume:
        raise ValueError("resume needs an output directory")
    return PreparedRun(spec, config, init_label, init_gains, out, resume, current, meta)


def _row(step, result, grad_norm, config, scale, draw_steps, wall) -> dict:
    cost = np.asarray(result.costs.cost, np.float64)
    return {
        "step": step + 1,
        "objective": float(result.objective),
        "mean_cost": float(np.mean(cost)),
        "max_cost": float(np.max(cost)),
        "grad_norm": float(grad_norm),
        "learning_rate": config.learning_rate_at(step),
        "width_scale": scale,
        "diverged": int(np.sum(np.asarray(result.costs.diverged))),
        "bad_gradients": int(result.bad_gradients),
        "draw_steps": int(draw_steps),
        "wall_time_s": round(float(wall), 3),
    }


def tune(
    run: PreparedRun,
    progress: bool = True,
    stop_after: int | None = None,
    callback: Callable[[int, dict, dict], None] | None = None,
    problem: TuningProblem | None = None,
) -> TuneResult:
    """Run (or continue) a prepared tuning run.

    stop_after: stop once this many steps are done in total (an interruption, for
    tests; the checkpoint is written). callback: ``callback(step, params, row)`` after
    each step (its time is not counted in ``wall_time_s``). problem: a
    :class:`TuningProblem` of the same spec and initial gains, to share compiled
    functions.

    With ``run.out``, writes ``checkpoint.npz``, ``history.csv`` and, when all steps
    are done, ``gains.json`` (:func:`fojax.controllers.gains_io.save_gains`).
    """
    if problem is None:
        problem = TuningProblem(run.spec, run.init_gains)
    loop = _Loop(run, problem, progress)
    last = run.config.steps if stop_after is None else min(run.config.steps, stop_after)
    try:
        while loop.step < last:
            row = loop.advance()
            if callback is not None:
                t0 = time.perf_counter()
                callback(loop.step, loop.state[0], row)
                loop.excluded += time.perf_counter() - t0
            if loop.step % run.config.checkpoint_every == 0 or loop.step == last:
                loop.save()
    except KeyboardInterrupt:
        loop.save()
        if progress:
            print(
                f"\ninterrupted after step {loop.step}/{run.config.steps}; checkpoint written "
                f"to {loop.checkpoint}; run again with --resume to continue",
                file=sys.stderr,
            )
        raise
    loop._start_validation()  # a run resumed with no step left: its start is validated
    loop.join_start()
    if loop.step == loop.start_step:
        loop.save()  # nothing to do (a finished run resumed): rewrite the outputs
    return loop.finish()


class _Loop:
    """The state of one tuning run between steps: the iterate, the optimiser's state,
    the best validated iterate, the history and the counters (what a checkpoint holds),
    restored from ``run``'s checkpoint when it resumes."""

    def __init__(self, run: PreparedRun, problem: TuningProblem, progress: bool):
        self.run, self.spec, self.config = run, run.spec, run.config
        self.problem, self.progress = problem, progress
        config = self.config
        self.optimizer = config.optimizer()
        params = problem.params_of(run.init_gains)
        self.quasi_newton = config.method == "lbfgs"
        self.lbfgs = lbfgs_lib.LBFGS(memory=config.memory, max_step=config.max_step)
        self.lbfgs_state = self.lbfgs.start(problem.vector(params)) if self.quasi_newton else None
        opt_state = () if self.quasi_newton else self.optimizer.init(params)
        self.state = (params, opt_state, params)  # current iterate, optimiser, best validated
        self.history: list[dict] = []
        self.wall_before = 0.0
        self.start_step = 0
        self.checkpoint = run.out / CHECKPOINT if run.out is not None else None
        self.validating = config.validation_draws > 0
        self.best = {"step": 0, "cost": None, "initial": None, "final": None}
        if run.resume:
            self._restore()
        if run.out is not None:
            run.out.mkdir(parents=True, exist_ok=True)
        self.validation_keys = (
            problem.validation_keys(config.validation_draws) if self.validating else None
        )
        self._last_validated: dict = {}
        self._update = jax.jit(self._optax_update)
        self.step = self.start_step
        self.session_start = time.perf_counter()
        self.excluded = 0.0
        self.draw_steps = self.history[-1]["draw_steps"] if self.history else 0
        self._start_params, self._start_result, self._thread = self.state[0], {}, None
        self._start_pending = self.validating and self.best["initial"] is None

    def _restore(self) -> None:
        self.state = _load_state(self.checkpoint, self.state)
        meta = self.run.checkpoint_meta
        self.start_step = int(meta["step"])
        self.history = list(meta["history"])
        self.wall_before = float(meta["wall_time_s"])
        self.best.update(meta.get("validation", {}))
        if self.quasi_newton:
            self.lbfgs_state = lbfgs_lib.state_from_json(meta["lbfgs"])
        if self.progress:
            print(
                f"resuming {self.checkpoint} at step {self.start_step}/{self.config.steps}",
                file=sys.stderr,
            )

    def _optax_update(self, state, gradient):
        params, opt_state, best_params = state
        updates, opt_state = self.optimizer.update(gradient, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, best_params

    def validate(self, params) -> float:
        """Mean cost of ``params``' gains on the validation draws."""
        from fojax.optimize.problem import evaluate

        problem, last = self.problem, self._last_validated
        vector = problem.vector(params)
        if "vector" in last and np.array_equal(vector, last["vector"]):
            return last["cost"]  # the iterate has not moved (a rejected trial)
        costs = evaluate(
            self.spec,
            problem.gains(params),
            self.validation_keys,
            switching=self.config.validation_switching,
        )
        cost = float(np.mean(np.asarray(costs.cost, np.float64)))
        last.update(vector=vector, cost=cost)
        return cost

    def _start_validation(self) -> None:
        """The start's validation (which compiles the validation run), once, in a thread
        launched when the first step's gradient is done: XLA compiles a program on more
        than one core (the gradient: 20 s of CPU in 12 s), so compiling the two side by
        side delays the first step; beside the next steps' runs it costs little. Joined
        when a validation is due (:meth:`join_start`)."""
        if not self._start_pending:
            return
        self._start_pending = False

        def validate_start(params=self._start_params):
            try:
                self._start_result["cost"] = self.validate(params)
            except BaseException as error:  # re-raised in the main thread
                self._start_result["error"] = error

        self._thread = threading.Thread(target=validate_start, daemon=True)
        self._thread.start()

    def join_start(self) -> None:
        """Wait for the start's validation, once; it is the best so far."""
        if self._thread is None:
            return
        self._thread.join()
        self._thread = None
        if "error" in self._start_result:
            raise self._start_result["error"]
        best = self.best
        best["initial"] = best["cost"] = self._start_result["cost"]
        best["step"] = 0
        if self.progress:
            print(
                f"  start: validation cost {best['initial']:.4e} "
                f"({self.config.validation_draws} draws, {self.config.validation_switching})",
                file=sys.stderr,
                flush=True,
            )

    def _gradient_step(self, scale: float):
        """One optimiser step from the current iterate: ``(result, grad_norm, new state,
        step length, accepted)``."""
        problem, state = self.problem, self.state
        if self.quasi_newton:
            result = problem.value_and_grad(
                problem.unravel(self.lbfgs_state["trial"]), scale, problem.minibatch_keys(0)
            )
            grad_norm = optax.tree.norm(result.gradient)
            step_length = self.lbfgs_state["alpha"]
            self.lbfgs_state, accepted = self.lbfgs.tell(
                self.lbfgs_state, float(result.objective), problem.vector(result.gradient)
            )
            new_state = (problem.unravel(self.lbfgs_state["x"]), (), state[2])
        else:
            result = problem.value_and_grad(state[0], scale, problem.minibatch_keys(self.step))
            grad_norm = optax.tree.norm(result.gradient)
            new_state = self._update(state, result.gradient)
            step_length, accepted = self.config.learning_rate_at(self.step), True
        return result, grad_norm, new_state, step_length, accepted

    def _validate_step(self) -> float | None:
        """Validate the new iterate when it is due; keep it when it is the best."""
        config, best = self.config, self.best
        if not (
            self.validating
            and (self.step % config.validate_every == 0 or self.step == config.steps)
        ):
            return None
        self.join_start()
        validation = self.validate(self.state[0])
        if validation < best["cost"]:  # ties keep the earlier (the start's) gains
            best["cost"], best["step"] = validation, self.step
            self.state = (self.state[0], self.state[1], self.state[0])
        if self.step == config.steps:
            best["final"] = validation
        return validation

    def advance(self) -> dict:
        """One step: gradient, update, validation when due; returns its history row."""
        scale = width_scale(self.config, self.step)
        result, grad_norm, new_state, step_length, accepted = self._gradient_step(scale)
        jax.block_until_ready(new_state)
        self.draw_steps += self.spec.draw_steps_per_minibatch
        self.state, self.step = new_state, self.step + 1
        self._start_validation()
        validation = self._validate_step()
        wall = self.wall_before + time.perf_counter() - self.session_start - self.excluded
        row = _row(self.step - 1, result, grad_norm, self.config, scale, self.draw_steps, wall)
        row["learning_rate"] = float(step_length)
        row["validation_cost"] = validation
        row["best_step"] = self.best["step"] if self.validating else None
        row["accepted"] = int(accepted)
        self.history.append(row)
        if self.progress:
            _print_progress(
                row, self.config.steps, self.wall_before, wall, self.start_step, self.best
            )
        return row

    def save(self) -> None:
        """Checkpoint and ``history.csv`` (nothing without an output folder)."""
        if self.checkpoint is None:
            return
        history = self.history
        meta = {
            "fingerprint": self.run.fingerprint,
            "step": self.step,
            "history": history,
            "wall_time_s": history[-1]["wall_time_s"] if history else self.wall_before,
            "validation": self.best,
        }
        if self.quasi_newton:
            meta["lbfgs"] = lbfgs_lib.state_to_json(self.lbfgs_state)
        _save_checkpoint(self.checkpoint, self.state, meta)
        write_history(self.run.out / "history.csv", history)

    def finish(self) -> TuneResult:
        """The result: the best validated (or the last) gains; ``gains.json`` when every
        step is done."""
        run, config, best, step = self.run, self.config, self.best, self.step
        final_params = self.state[0]
        params = self.state[2] if self.validating else final_params
        best_step = best["step"] if self.validating else step
        gains = self.problem.gains(params)
        summary = None
        if self.validating:
            summary = {
                "draws": config.validation_draws,
                "switching": config.validation_switching,
                "horizon_s": self.spec.horizon,
                "draw_indices": f"{VALIDATION_OFFSET} + [0, {config.validation_draws})",
                "initial": best["initial"],
                "best": best["cost"],
                "best_step": best["step"],
                "final": best["final"],
            }
        if run.out is not None and step == config.steps:
            self._save_gains(gains, best_step, summary)
        return TuneResult(
            params, gains, self.history, step, self.problem, best_step, summary, final_params
        )

    def _save_gains(self, gains, best_step: int, summary: dict | None) -> None:
        run, history = self.run, self.history
        metadata = {
            "tuned_by": "fojax tune",
            "problem": run.fingerprint["problem"],
            "tuner": run.fingerprint["tuner"],
            "init": run.init_label,
            "steps_done": self.step,
            "selected_step": best_step,
            "selected_by": "validation" if self.validating else "last step",
            "validation": summary,
            "final_objective": history[-1]["objective"] if history else None,
            "draw_steps": history[-1]["draw_steps"] if history else 0,
            "wall_time_s": history[-1]["wall_time_s"] if history else 0.0,
        }
        gains_io.save_gains(run.out / "gains.json", self.spec.controller, gains, metadata)


def _print_progress(
    row: dict, total: int, wall_before: float, wall: float, start: int, best: dict
) -> None:
    done = row["step"]
    per_step = (wall - wall_before) / max(done - start, 1)
    left = per_step * (total - done)
    validation = ""
    if row.get("validation_cost") is not None:
        validation = (
            f"  validation {row['validation_cost']:.4e} (best {best['cost']:.4e}, "
            f"step {best['step']})"
        )
    print(
        f"  step {done}/{total}  objective {row['objective']:.4e}  |grad| "
        f"{row['grad_norm']:.3e}  lr {row['learning_rate']:.3g}  width x{row['width_scale']:.3g}"
        f"  diverged {row['diverged']}{validation}  {wall:.0f} s (about {left:.0f} s left)",
        file=sys.stderr,
        flush=True,
    )
