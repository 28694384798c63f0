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

import csv
import dataclasses
import io
import json
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from fojax.controllers import gains_io
from fojax.optimize import lbfgs as lbfgs_lib
from fojax.optimize.problem import VALIDATION_OFFSET, ProblemSpec, TuningProblem

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
FORMAT = 2
METHODS = ("adam", "lbfgs")
HISTORY_COLUMNS = (
    "step",
    "objective",
    "mean_cost",
    "max_cost",
    "grad_norm",
    "learning_rate",
    "width_scale",
    "diverged",
    "bad_gradients",
    "draw_steps",
    "wall_time_s",
    "validation_cost",
    "best_step",
    "accepted",
)
"""Columns of ``history.csv``, one row per step. ``validation_cost``: the mean cost on
the validation draws after this step (empty where the step was not validated);
``best_step``: the step whose gains are the best validated so far (0: the start);
``accepted``: 1 when the step moved the iterate (always for Adam; L-BFGS rejects a
trial without sufficient decrease). For L-BFGS, ``objective`` is the trial point's and
``learning_rate`` the trial's step length along its direction."""


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


def fingerprint(spec: ProblemSpec, config: TunerConfig, init_label: str, init_gains) -> dict:
    """Everything a checkpoint must agree on to be resumed."""
    return {
        "format": FORMAT,
        "problem": spec.as_dict(),
        "tuner": dataclasses.asdict(config),
        "init": init_label,
        "init_gains": gains_io.gains_to_dict(
            type(init_gains)(*(np.asarray(g, np.float64) for g in init_gains))
        ),
    }


def _differences(stored: Any, current: Any, path: str = "") -> list[str]:
    if isinstance(stored, dict) and isinstance(current, dict):
        out = []
        for key in sorted(set(stored) | set(current)):
            where = f"{path}.{key}" if path else str(key)
            if key not in stored:
                out.append(f"{where}: not in the checkpoint, now {current[key]!r}")
            elif key not in current:
                out.append(f"{where}: {stored[key]!r} in the checkpoint, now absent")
            else:
                out.extend(_differences(stored[key], current[key], where))
        return out
    if isinstance(stored, list | tuple) and isinstance(current, list | tuple):
        if list(stored) == list(current):
            return []
        if len(stored) == len(current) and all(not isinstance(s, dict) for s in stored):
            if all(not isinstance(s, list) for s in stored):
                return [f"{path}: checkpoint {list(stored)!r}, now {list(current)!r}"]
        return [f"{path}: checkpoint {_short(stored)}, now {_short(current)}"]
    if stored != current:
        return [f"{path}: checkpoint {stored!r}, now {current!r}"]
    return []


def _short(value: Any) -> str:
    text = json.dumps(value)
    return text if len(text) <= 120 else text[:117] + "..."


def _canonical(document: Any) -> Any:
    """JSON round trip, so that tuples and lists compare equal."""
    return json.loads(json.dumps(document))


# ---------------------------------------------------------------------- checkpoint io


def _write_atomic_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def _save_checkpoint(path: Path, state: tuple, meta: dict) -> None:
    leaves = jax.tree.leaves(state)
    arrays = {f"leaf_{i:05d}": np.asarray(leaf) for i, leaf in enumerate(leaves)}
    arrays["meta"] = np.asarray(json.dumps(meta))
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    _write_atomic_bytes(path, buffer.getvalue())


def _read_meta(path: Path) -> dict:
    try:
        with np.load(path) as data:
            return json.loads(str(data["meta"]))
    except (OSError, KeyError, ValueError) as error:
        raise ValueError(f"{path} is not a fojax tune checkpoint ({error})") from None


def _load_state(path: Path, template: tuple) -> tuple:
    leaves, treedef = jax.tree.flatten(template)
    with np.load(path) as data:
        names = sorted(k for k in data.files if k.startswith("leaf_"))
        if len(names) != len(leaves):
            raise ValueError(
                f"{path} holds {len(names)} arrays, this run needs {len(leaves)}: it was "
                "written by another configuration"
            )
        loaded = []
        for name, leaf in zip(names, leaves, strict=True):
            value = data[name]
            if value.shape != np.shape(leaf) or value.dtype != np.asarray(leaf).dtype:
                raise ValueError(
                    f"{path}: array {name} has shape {value.shape} {value.dtype}, this run "
                    f"needs {np.shape(leaf)} {np.asarray(leaf).dtype}"
                )
            loaded.append(jnp.asarray(value))
    return jax.tree.unflatten(treedef, loaded)


def write_history(path: Path, history: list[dict]) -> None:
    """``history.csv`` (atomically): one row per step, :data:`HISTORY_COLUMNS`."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=HISTORY_COLUMNS, lineterminator="\n")
    writer.writeheader()
    for row in history:
        writer.writerow(
            {
                k: ("" if v is None else repr(v) if isinstance(v, float) else v)
                for k, v in row.items()
            }
        )
    _write_atomic_bytes(path, buffer.getvalue().encode())


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
            differences = _differences(meta.get("fingerprint"), current)
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
    spec, config = run.spec, run.config
    if problem is None:
        problem = TuningProblem(spec, run.init_gains)
    optimizer = config.optimizer()
    params = problem.params_of(run.init_gains)
    quasi_newton = config.method == "lbfgs"
    lbfgs = lbfgs_lib.LBFGS(memory=config.memory, max_step=config.max_step)
    lbfgs_state = lbfgs.start(problem.vector(params)) if quasi_newton else None
    opt_state = () if quasi_newton else optimizer.init(params)
    state = (params, opt_state, params)  # current iterate, optimiser, best validated
    history: list[dict] = []
    wall_before = 0.0
    start_step = 0
    checkpoint = run.out / CHECKPOINT if run.out is not None else None
    validating = config.validation_draws > 0
    best = {"step": 0, "cost": None, "initial": None, "final": None}
    if run.resume:
        state = _load_state(checkpoint, state)
        meta = run.checkpoint_meta
        start_step = int(meta["step"])
        history = list(meta["history"])
        wall_before = float(meta["wall_time_s"])
        best.update(meta.get("validation", {}))
        if quasi_newton:
            lbfgs_state = lbfgs_lib.state_from_json(meta["lbfgs"])
        if progress:
            print(f"resuming {checkpoint} at step {start_step}/{config.steps}", file=sys.stderr)
    if run.out is not None:
        run.out.mkdir(parents=True, exist_ok=True)
    validation_keys = problem.validation_keys(config.validation_draws) if validating else None

    last_validated: dict = {}

    def validate(params) -> float:
        from fojax.optimize.problem import evaluate

        vector = problem.vector(params)
        if "vector" in last_validated and np.array_equal(vector, last_validated["vector"]):
            return last_validated["cost"]  # the iterate has not moved (a rejected trial)
        costs = evaluate(
            spec,
            problem.gains(params),
            validation_keys,
            switching=config.validation_switching,
        )
        cost = float(np.mean(np.asarray(costs.cost, np.float64)))
        last_validated.update(vector=vector, cost=cost)
        return cost

    @jax.jit
    def update(state, gradient):
        params, opt_state, best_params = state
        updates, opt_state = optimizer.update(gradient, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, best_params

    def save(step: int) -> None:
        if checkpoint is None:
            return
        wall = history[-1]["wall_time_s"] if history else wall_before
        meta = {
            "fingerprint": run.fingerprint,
            "step": step,
            "history": history,
            "wall_time_s": wall,
            "validation": best,
        }
        if quasi_newton:
            meta["lbfgs"] = lbfgs_lib.state_to_json(lbfgs_state)
        _save_checkpoint(checkpoint, state, meta)
        write_history(run.out / "history.csv", history)

    last = config.steps if stop_after is None else min(config.steps, stop_after)
    step = start_step
    session_start = time.perf_counter()
    excluded = 0.0
    draw_steps = history[-1]["draw_steps"] if history else 0
    # The start's validation (which compiles the validation run) goes in a thread
    # beside the first step (which compiles the gradient): XLA compiles each on one
    # core, so on two cores the validation's compilation costs no wall time.
    start_validation: dict = {}
    thread = None
    if validating and best["initial"] is None:

        def validate_start(params=state[0]):
            try:
                start_validation["cost"] = validate(params)
            except BaseException as error:  # re-raised in the main thread
                start_validation["error"] = error

        thread = threading.Thread(target=validate_start, daemon=True)
        thread.start()

    def join_start() -> None:
        nonlocal thread
        if thread is None:
            return
        thread.join()
        thread = None
        if "error" in start_validation:
            raise start_validation["error"]
        best["initial"] = best["cost"] = start_validation["cost"]
        best["step"] = 0
        if progress:
            print(
                f"  start: validation cost {best['initial']:.4e} "
                f"({config.validation_draws} draws, {config.validation_switching})",
                file=sys.stderr,
                flush=True,
            )

    try:
        while step < last:
            scale = width_scale(config, step)
            if quasi_newton:
                result = problem.value_and_grad(
                    problem.unravel(lbfgs_state["trial"]), scale, problem.minibatch_keys(0)
                )
                grad_norm = optax.tree.norm(result.gradient)
                step_length = lbfgs_state["alpha"]
                lbfgs_state, accepted = lbfgs.tell(
                    lbfgs_state, float(result.objective), problem.vector(result.gradient)
                )
                new_state = (problem.unravel(lbfgs_state["x"]), (), state[2])
            else:
                keys = problem.minibatch_keys(step)
                result = problem.value_and_grad(state[0], scale, keys)
                grad_norm = optax.tree.norm(result.gradient)
                new_state = update(state, result.gradient)
                step_length, accepted = config.learning_rate_at(step), True
            jax.block_until_ready(new_state)
            draw_steps += spec.draw_steps_per_minibatch
            state, step = new_state, step + 1
            join_start()
            validation = None
            if validating and (step % config.validate_every == 0 or step == config.steps):
                validation = validate(state[0])
                if validation < best["cost"]:  # ties keep the earlier (the start's) gains
                    best["cost"], best["step"] = validation, step
                    state = (state[0], state[1], state[0])
                if step == config.steps:
                    best["final"] = validation
            wall = wall_before + time.perf_counter() - session_start - excluded
            row = _row(step - 1, result, grad_norm, config, scale, draw_steps, wall)
            row["learning_rate"] = float(step_length)
            row["validation_cost"] = validation
            row["best_step"] = best["step"] if validating else None
            row["accepted"] = int(accepted)
            history.append(row)
            if progress:
                _print_progress(row, config.steps, wall_before, wall, start_step, best)
            if callback is not None:
                t0 = time.perf_counter()
                callback(step, state[0], row)
                excluded += time.perf_counter() - t0
            if step % config.checkpoint_every == 0 or step == last:
                save(step)
    except KeyboardInterrupt:
        save(step)
        if progress:
            print(
                f"\ninterrupted after step {step}/{config.steps}; checkpoint written to "
                f"{checkpoint}; run again with --resume to continue",
                file=sys.stderr,
            )
        raise
    join_start()
    if step == start_step:
        save(step)  # nothing to do (a finished run resumed): rewrite the outputs
    final_params = state[0]
    params = state[2] if validating else final_params
    best_step = best["step"] if validating else step
    gains = problem.gains(params)
    summary = None
    if validating:
        summary = {
            "draws": config.validation_draws,
            "switching": config.validation_switching,
            "horizon_s": spec.horizon,
            "draw_indices": f"{VALIDATION_OFFSET} + [0, {config.validation_draws})",
            "initial": best["initial"],
            "best": best["cost"],
            "best_step": best["step"],
            "final": best["final"],
        }
    if run.out is not None and step == config.steps:
        metadata = {
            "tuned_by": "fojax tune",
            "problem": run.fingerprint["problem"],
            "tuner": run.fingerprint["tuner"],
            "init": run.init_label,
            "steps_done": step,
            "selected_step": best_step,
            "selected_by": "validation" if validating else "last step",
            "validation": summary,
            "final_objective": history[-1]["objective"] if history else None,
            "draw_steps": history[-1]["draw_steps"] if history else 0,
            "wall_time_s": history[-1]["wall_time_s"] if history else 0.0,
        }
        gains_io.save_gains(run.out / "gains.json", spec.controller, gains, metadata)
    return TuneResult(params, gains, history, step, problem, best_step, summary, final_params)


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
