"""Several CMA-ES searches from several starts, the best continued: ``fojax tune``'s
default method (built by :data:`fojax.optimize.strategies.METHODS`).

Two phases, one request a generation:

1. **Search** (``stages``): one :class:`CMAES` per start, every live search's
   candidates and its mean on one common fresh sample in one call, at the coarse step
   ``coarse_dt`` (``None``: the objective's), in the tied subspace ``tie`` when given
   (coordinate ``i`` of the full parameters is coordinate ``tie[i]`` of the search's:
   the axis-shared parameters, so that a search of 66 parameters starts as one of 33).
   Each stage keeps the best of the previous stage's searches, ranked by their means'
   costs over the last ``window`` generations (common draws: a paired comparison).
2. **Convergence**: the best search goes on alone at the objective's step, lifted to
   the full parameters (its mean ``E z``, its covariance ``E C E^T`` plus ``lift`` times
   its mean variance on the diagonal, so that the axes of a group can part; with
   ``diagonal``, that covariance's diagonal and a separable CMA-ES), with
   ``popsize`` candidates on ``draws`` draws, until the budget ends (the driver ends a
   converged run: :class:`fojax.optimize.Budget`'s ``patience``).

The answer is the mean of the leading search (phase 1) or of the continued one (phase
2); the driver validates it at the objective's step and returns the best validated.
The state is arrays of fixed shapes: phase 1's searches stacked with a mask of the live
ones, phase 2's search in the full space, both kept throughout.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fojax.optimize import checks
from fojax.optimize.requests import Evaluation, Request
from fojax.optimize.strategies._population import CMAES

__all__ = ["MultiStart"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class MultiStart:
    """starts: other starting points than ``x0`` (each ``d`` floats; a start given twice
    is searched twice, with other samples). tie: ``d`` indices into the search space
    (``None``: the full space). sigma0: each search's first step. seed: the sampling
    seed. stages: the first phase, ``(generations, searches, draws)`` each: the best
    ``searches`` of the previous stage (all at first) go on for ``generations`` with
    ``draws`` draws per point. coarse_dt: the first phase's step (s; ``None``: the
    objective's). draws, popsize: the second phase's draws per point and candidates per
    generation (``None``: ``4 + floor(3 ln d)``). window: generations whose
    means rank the searches. lift: the variance added on the second phase's diagonal,
    relative to the search's mean variance. diagonal: the second phase's search is the
    separable CMA-ES (:class:`CMAES`'s ``diagonal``), whose covariance adapts in about
    ``d`` generations: a lifted search of many parameters converges within a budget
    where a full covariance (about ``d^2`` generations) would still be learning.

    The design (``stages``, ``draws``, ``window``, ``lift``, ``diagonal``) has no
    default: the default method's is declared in its entry of the method table
    (:data:`fojax.optimize.strategies.METHODS`, ``auto``), and a strategy built here
    states its own."""

    starts: tuple = ()
    tie: tuple | None = None
    sigma0: float = 0.5
    seed: int = 0
    stages: tuple
    coarse_dt: float | None = None
    draws: int
    popsize: int | None = None
    window: int
    lift: float
    diagonal: bool
    name: str = "multistart"

    def __post_init__(self) -> None:
        checks.number("sigma0", self.sigma0)
        for label in ("draws", "window"):
            checks.integer(label, getattr(self, label))
        checks.number("lift", self.lift, allow_low=True)
        if self.coarse_dt is not None:
            checks.number("coarse_dt", self.coarse_dt)
        object.__setattr__(self, "starts", tuple(tuple(map(float, s)) for s in self.starts))
        stages = tuple(tuple(int(v) for v in stage) for stage in self.stages)
        for generations, searches, draws in stages:
            checks.integer("a stage's generations", generations)
            checks.integer("a stage's searches", searches)
            checks.integer("a stage's draws", draws)
        kept = [searches for _, searches, _ in stages]
        if kept and (kept[0] > 1 + len(self.starts) or kept != sorted(kept, reverse=True)):
            raise ValueError(
                "each stage keeps at most the searches of the one before, the first at most "
                f"one per start ({1 + len(self.starts)})"
            )
        object.__setattr__(self, "stages", stages)
        if self.tie is not None:
            tie = tuple(int(i) for i in self.tie)
            if sorted(set(tie)) != list(range(max(tie) + 1)):
                raise ValueError("tie must map every search coordinate to some parameter")
            object.__setattr__(self, "tie", tie)

    @property
    def search(self) -> int:
        """Generations of the first phase."""
        return sum(generations for generations, _, _ in self.stages)

    def _stage(self, generation: int) -> tuple[int, int, int] | None:
        """``(first generation, searches, draws)`` of the stage of ``generation``
        (``None``: the second phase)."""
        first = 0
        for generations, searches, draws in self.stages:
            if generation < first + generations:
                return first, searches, draws
            first += generations
        return None

    # -- the searches -------------------------------------------------------------------
    def _search(self, k: int) -> CMAES:
        """Search ``k`` of the first phase (``k = -1``: the second phase's): its own
        sampling seed."""
        popsize, diagonal = (self.popsize, self.diagonal) if k < 0 else (None, False)
        return CMAES(sigma0=self.sigma0, seed=self.seed * 1009 + k + 1, popsize=popsize,
                     diagonal=diagonal)  # fmt: skip

    def _embed(self, d: int) -> np.ndarray:
        """``(d, k)`` 0/1 matrix: full parameters ``x = E z`` of search parameters ``z``."""
        tie = np.arange(d) if self.tie is None else np.asarray(self.tie)
        return (tie[:, None] == np.arange(tie.max() + 1)[None, :]).astype(np.float64)

    def _project(self, x: np.ndarray) -> np.ndarray:
        """The search parameters nearest ``x``: each tied group's mean."""
        E = self._embed(x.size)
        return (E.T @ x) / E.sum(0)

    def init(self, x0) -> dict:
        x0 = np.asarray(x0, np.float64)
        points = [x0] + [np.asarray(s, np.float64) for s in self.starts]
        if any(p.shape != x0.shape for p in points):
            raise ValueError(f"every start must have {x0.size} parameters")
        states = [self._search(k).init(self._project(p)) for k, p in enumerate(points)]
        return dict(
            searches={k: np.stack([s[k] for s in states]) for k in states[0]},
            alive=np.arange(len(points)) < (self.stages[0][1] if self.stages else 1),
            final=self._search(-1).init(x0),
            recent=np.full((len(points), self.window), np.nan),
            generation=np.asarray(0),
            chosen=np.asarray(0),
        )

    @staticmethod
    def _row(searches: dict, k: int) -> dict:
        return {key: value[k] for key, value in searches.items()}

    def _ranking(self, state) -> np.ndarray:
        """Mean cost of each live search's mean over the window (``inf``: none yet, or
        dropped)."""
        recent = state["recent"]
        seen = np.isfinite(recent)
        total = np.where(seen, recent, 0.0).sum(1)
        mean = np.where(seen.any(1), total / np.maximum(seen.sum(1), 1), np.inf)
        return np.where(state["alive"], mean, np.inf)

    def _best(self, state) -> int:
        ranking = self._ranking(state)
        return int(np.argmin(ranking)) if np.isfinite(ranking).any() else int(state["chosen"])

    def ask(self, state) -> Request:
        generation = int(state["generation"])
        stage = self._stage(generation)
        if stage is None:
            request = self._search(-1).ask(state["final"])
            return request._replace(sample=generation, draws=self.draws)
        E = self._embed(state["final"]["mean"].size)
        points = []
        for k in np.flatnonzero(state["alive"]):
            search = self._row(state["searches"], k)
            z = np.vstack([self._search(k).ask(search).points, search["mean"][None]])
            points.append(z @ E.T)
        return Request(np.vstack(points), False, generation, None, draws=stage[2],
                       dt=self.coarse_dt)  # fmt: skip

    def tell(self, state, request, evaluation) -> dict:
        generation = int(state["generation"]) + 1
        if self._stage(generation - 1) is None:
            final = self._search(-1).tell(state["final"], request, evaluation)
            return {**state, "final": final, "generation": np.asarray(generation)}
        values = np.asarray(evaluation.values, np.float64)
        searches = {key: value.copy() for key, value in state["searches"].items()}
        recent, E = state["recent"].copy(), self._embed(request.points.shape[1])
        live = np.flatnonzero(state["alive"])
        size = len(values) // len(live)
        for i, k in enumerate(live):
            rows = slice(i * size, (i + 1) * size - 1)
            sub = Request((request.points[rows] @ E) / E.sum(0))
            told = self._search(k).tell(
                self._row(searches, k), sub, Evaluation(values[rows], None, None, 0, 0)
            )
            for key, value in told.items():
                searches[key][k] = value
            recent[k] = np.roll(recent[k], -1)
            recent[k, -1] = values[(i + 1) * size - 1]
        state = {**state, "searches": searches, "recent": recent,
                 "generation": np.asarray(generation)}  # fmt: skip
        stage = self._stage(generation)
        if stage is not None and stage[0] == generation:  # a new stage: keep the best
            keep = np.argsort(self._ranking(state), kind="stable")[: stage[1]]
            state["alive"] = np.isin(np.arange(len(recent)), keep)
        if stage is None:  # the first phase is over: the best goes on alone
            chosen = self._best(state)
            final = self._lift(self._row(searches, chosen), E)
            state.update(final=final, chosen=np.asarray(chosen))
        return state

    def _lift(self, search: dict, E: np.ndarray) -> dict:
        """Phase 2's search from phase 1's ``search`` (module docstring)."""
        C = E @ search["C"] @ E.T
        C = C + self.lift * float(np.mean(np.diag(search["C"]))) * np.eye(len(C))
        if self.diagonal:
            C = np.diag(np.diag(C))
        return dict(
            mean=E @ search["mean"], sigma=np.asarray(float(search["sigma"])), C=C,
            ps=np.zeros(len(C)), pc=E @ search["pc"], generation=np.asarray(0),
        )  # fmt: skip

    def answer(self, state) -> np.ndarray:
        if self._stage(int(state["generation"])) is None:
            return state["final"]["mean"].copy()
        E = self._embed(state["final"]["mean"].size)
        return E @ state["searches"]["mean"][self._best(state)]

    def restart(self, state) -> dict:
        return state

    def settling(self, state) -> int | None:
        """The step from which a run is judged converged: the second phase's first, on
        its own validations (the first phase's searches are ranked, not converged; its
        validations are of other searches' means; :class:`fojax.optimize.Budget`)."""
        if self._stage(int(state["generation"])) is not None:
            return None
        return sum(generations for generations, _, _ in self.stages)

    def plan(self, steps: int, d: int) -> str:
        """What a run of ``steps`` requests on ``d`` parameters does, in words: each
        stage's searches, generations and draws, then the continued search's phase, or,
        where ``steps`` end within the first phase, that phase alone."""
        lam = CMAES().constants(int(self._embed(d).shape[1]))["lam"]
        at = "" if self.coarse_dt is None else f" at a {self.coarse_dt * 1e3:g} ms step"
        parts, first = [], 0
        for generations, searches, draws in self.stages:
            taken = min(generations, steps - first)
            if taken <= 0:
                break
            of = "" if taken == generations else f" of its {generations}"
            parts.append(f"{searches} CMA-ES searches ({lam} candidates and the mean each) for "
                         f"{taken}{of} generations on {draws} draws{at}")  # fmt: skip
            first += generations
        stages = ", then ".join(parts)
        if steps <= self.search:
            return (f"the first phase alone: {stages}; the best search is continued only with "
                    f"more than {self.search} steps")  # fmt: skip
        final = self._search(-1).constants(d)["lam"]
        kind = "separable CMA-ES" if self.diagonal else "CMA-ES"
        return (f"{stages}, then the best continued alone ({kind}, {final} candidates on "
                f"{self.draws} draws) for up to {steps - self.search} generations")  # fmt: skip

    def settings(self) -> dict:
        out = dataclasses.asdict(self)
        out["starts"] = [list(s) for s in self.starts]
        out["tie"] = None if self.tie is None else list(self.tie)
        out["stages"] = [list(stage) for stage in self.stages]
        return out

    def row(self, state) -> dict:
        """The phase of the last request, the leading (or continued) search and its
        step size, and the searches still alive."""
        generation = int(state["generation"])
        if generation <= self.search:
            k = self._best(state) if generation < self.search else int(state["chosen"])
            return {"phase": "search", "search": k, "alive": int(state["alive"].sum()),
                    "sigma": float(state["searches"]["sigma"][k])}  # fmt: skip
        return {"phase": "converge", "search": int(state["chosen"]), "alive": 1,
                "sigma": float(state["final"]["sigma"])}  # fmt: skip

    def needs(self) -> tuple:
        return (("forward", None, self.coarse_dt), ("forward", None, None))

    def lanes(self, d: int) -> int:
        """The lanes (point x draw) of the second phase's requests, for ``d`` parameters:
        the calls are cut to the phase that runs longest; a larger request of the first
        phase (an envelope's, its draws rounded up to the cases) takes more than one."""
        return (self._search(-1).constants(d)["lam"] + 1) * self.draws
