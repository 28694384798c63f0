"""Population strategies: CMA-ES and Nelder-Mead, forward evaluations only.

:class:`CMAES` is the (mu/mu_w, lambda)-CMA-ES of Hansen's tutorial (arXiv:1604.00772,
Table 1 and Algorithm: weighted recombination with active negative weights,
cumulative step-size adaptation, rank-one and rank-mu covariance updates): each request
is one generation, its ``popsize`` candidates (default ``4 + floor(3 ln d)``) on one
tuning sample in one batched call (common random numbers within a generation; a fresh
sample per generation by default), at the evaluation law unless ``width`` is given.
The candidates of generation ``g`` come from ``numpy.random.default_rng([seed, g])``,
so the state holds no generator and a resumed run asks for the same candidates. The
answer is the distribution mean (the robust choice for a noisy loss).

:class:`NelderMead` is SciPy's Nelder-Mead (``scipy.optimize.minimize(method=
"Nelder-Mead")`` with the standard coefficients, no bounds), step for step, as ask and
tell: the initial simplex ``x0 + step e_i``, then one reflection, expansion or
contraction per request (a shrink asks for ``d`` points at once), on the fixed sample
(a deterministic sample-average loss, as the simplex method needs). The answer is the
best vertex.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from fojax.optimize import checks
from fojax.optimize.requests import Request

__all__ = ["CMAES", "NelderMead"]


@dataclasses.dataclass(frozen=True)
class CMAES:
    """sigma0: initial step (in the unconstrained parameters). popsize: candidates per
    generation (``None``: ``4 + floor(3 ln d)``). seed: the sampling seed. sample:
    ``"fresh"`` (one tuning sample per generation) or ``"fixed"``. width: the tuning
    law's width scale, ``None``: the evaluation law. diagonal: the separable CMA-ES of
    Ros and Hansen (PPSN 2008): the covariance kept diagonal and learnt with the rates
    ``c1`` and ``c_mu`` times ``(d + 2) / 3``, so that it adapts in about ``d``
    generations where a full one takes about ``d^2``; what it cannot learn is
    correlation between parameters."""

    sigma0: float = 0.5
    popsize: int | None = None
    seed: int = 0
    sample: str = "fresh"
    width: float | None = None
    draws: int | tuple | None = None
    diagonal: bool = False
    name: str = "cma-es"

    def __post_init__(self) -> None:
        checks.number("sigma0", self.sigma0)
        if self.popsize is not None:
            checks.integer("popsize", self.popsize, 2)
        checks.choice("sample", self.sample, ("fresh", "fixed"))

    def constants(self, d: int) -> dict:
        """The tutorial's default constants for dimension ``d``."""
        lam = self.popsize or 4 + int(3 * math.log(d))
        mu = lam // 2
        raw = math.log((lam + 1) / 2) - np.log(np.arange(1, lam + 1))
        positive, negative = raw[:mu], raw[mu:]
        mueff = positive.sum() ** 2 / np.sum(positive**2)
        mueff_minus = negative.sum() ** 2 / np.sum(negative**2) if negative.size else 0.0
        cc = (4 + mueff / d) / (d + 4 + 2 * mueff / d)
        cs = (mueff + 2) / (d + mueff + 5)
        c1 = 2 / ((d + 1.3) ** 2 + mueff)
        cmu = min(1 - c1, 2 * (0.25 + mueff + 1 / mueff - 2) / ((d + 2) ** 2 + mueff))
        if self.diagonal:
            c1 = c1 * (d + 2) / 3
            cmu = min(1 - c1, cmu * (d + 2) / 3)
        damps = 1 + 2 * max(0.0, math.sqrt((mueff - 1) / (d + 1)) - 1) + cs
        scale_minus = min(
            1 + c1 / cmu, 1 + 2 * mueff_minus / (mueff + 2), (1 - c1 - cmu) / (d * cmu)
        )
        weights = np.where(
            raw >= 0, raw / positive.sum(), scale_minus * raw / max(-negative.sum(), 1e-300)
        )
        chi = math.sqrt(d) * (1 - 1 / (4 * d) + 1 / (21 * d * d))
        return dict(
            lam=lam, mu=mu, weights=weights, mueff=mueff, cc=cc, cs=cs, c1=c1, cmu=cmu, damps=damps,
            chi=chi,
        )  # fmt: skip

    def init(self, x0) -> dict:
        x0 = np.asarray(x0, np.float64)
        d = x0.size
        return dict(mean=x0.copy(), sigma=np.asarray(float(self.sigma0)), C=np.eye(d),
                    ps=np.zeros(d), pc=np.zeros(d), generation=np.asarray(0))  # fmt: skip

    def sample_size(self, generation: int) -> int | None:
        """Draws per candidate in ``generation``: ``draws``, or from a schedule
        ``((first generation, draws), ...)`` the last entry begun (``None``: the
        objective's)."""
        if not isinstance(self.draws, tuple):
            return self.draws
        return [n for first, n in self.draws if first <= generation][-1]

    @staticmethod
    def _eigen(C):
        values, vectors = np.linalg.eigh((C + C.T) / 2)
        return vectors, np.sqrt(np.maximum(values, 1e-300))

    def ask(self, state) -> Request:
        d, generation = state["mean"].size, int(state["generation"])
        sample = generation if self.sample == "fresh" else 0
        lam = self.constants(d)["lam"]
        z = np.random.default_rng([self.seed, generation]).standard_normal((lam, d))
        B, D = self._eigen(state["C"])
        points = state["mean"] + float(state["sigma"]) * (z * D) @ B.T
        return Request(points, False, sample, self.width, draws=self.sample_size(generation))

    def tell(self, state, request, evaluation) -> dict:
        k = self.constants(state["mean"].size)
        cs, cc, c1, cmu, mueff, chi = (k[n] for n in ("cs", "cc", "c1", "cmu", "mueff", "chi"))
        d, sigma, mean = state["mean"].size, float(state["sigma"]), state["mean"]
        values = np.where(np.isfinite(evaluation.values), evaluation.values, np.inf)
        order = np.argsort(values, kind="stable")
        y = (request.points[order] - mean) / sigma
        B, D = self._eigen(state["C"])
        inv_sqrt = (B / D) @ B.T
        step = k["weights"][: k["mu"]] @ y[: k["mu"]]
        mean = mean + sigma * step
        ps = (1 - cs) * state["ps"] + math.sqrt(cs * (2 - cs) * mueff) * (inv_sqrt @ step)
        generation = int(state["generation"]) + 1
        norm = float(np.linalg.norm(ps))
        hsig = norm / math.sqrt(1 - (1 - cs) ** (2 * generation)) < (1.4 + 2 / (d + 1)) * chi
        pc = (1 - cc) * state["pc"] + hsig * math.sqrt(cc * (2 - cc) * mueff) * step
        weights = k["weights"].copy()
        negative = weights < 0
        mahalanobis = np.sum((y @ inv_sqrt.T) ** 2, 1)
        weights[negative] *= d / np.maximum(mahalanobis[negative], 1e-300)
        delta = (1 - hsig) * cc * (2 - cc)
        C = (1 + c1 * delta - c1 - cmu * k["weights"].sum()) * state["C"]
        C = C + c1 * np.outer(pc, pc) + cmu * (y.T * weights) @ y
        C = np.diag(np.diag(C)) if self.diagonal else (C + C.T) / 2
        sigma = sigma * math.exp(min(1.0, (cs / k["damps"]) * (norm / chi - 1)))
        return dict(mean=mean, sigma=np.asarray(sigma), C=C, ps=ps, pc=pc,
                    generation=np.asarray(generation))  # fmt: skip

    def answer(self, state) -> np.ndarray:
        return state["mean"].copy()

    def restart(self, state) -> dict:
        return state

    def settings(self) -> dict:
        return dataclasses.asdict(self)

    def row(self, state) -> dict:
        return {"sigma": float(state["sigma"])}

    def needs(self) -> tuple:
        return (("forward", self.width),)


# Nelder-Mead's phases: the trial(s) a state is waiting for.
_INIT, _REFLECT, _EXPAND, _OUTSIDE, _INSIDE, _SHRINK = range(6)
_RHO, _CHI, _PSI, _SIGMA = 1.0, 2.0, 0.5, 0.5


@dataclasses.dataclass(frozen=True)
class NelderMead:
    """step: the initial simplex's edge. width: the tuning law's width scale, ``None``:
    the evaluation law."""

    step: float = 0.5
    width: float | None = None
    name: str = "nelder-mead"
    typical_points = 1  # a class attribute: one trial per request after the simplex

    def __post_init__(self) -> None:
        checks.number("step", self.step)

    def init(self, x0) -> dict:
        x0 = np.asarray(x0, np.float64)
        simplex = x0[None, :] + np.vstack([np.zeros(x0.size), self.step * np.eye(x0.size)])
        return self._wait(simplex, np.full(x0.size + 1, np.inf), _INIT, simplex, x0, np.inf)

    def ask(self, state) -> Request:
        return Request(state["pending"][: int(state["count"])], False, 0, self.width)

    def answer(self, state) -> np.ndarray:
        return state["simplex"][0].copy()

    def restart(self, state) -> dict:
        s = state
        return self._wait(s["simplex"], s["values"], _INIT, s["simplex"], s["reflected"],
                          s["reflected_value"])  # fmt: skip

    def settings(self) -> dict:
        return dataclasses.asdict(self)

    def row(self, state) -> dict:
        return {"best_sample_value": float(state["values"][0])}

    def needs(self) -> tuple:
        return (("forward", self.width),)

    def tell(self, state, request, evaluation) -> dict:
        sim, fsim = state["simplex"].copy(), state["values"].copy()
        phase, values = int(state["phase"]), np.asarray(evaluation.values, np.float64)
        xr, fxr = state["reflected"], float(state["reflected_value"])
        n = sim.shape[1]
        xbar = np.add.reduce(sim[:-1], 0) / n
        shrink = False
        if phase == _INIT:
            fsim = values
        elif phase == _SHRINK:
            fsim[1:] = values
        elif phase == _REFLECT:
            xr, fxr = request.points[0], float(values[0])
            if fxr < fsim[0]:
                xe = (1 + _RHO * _CHI) * xbar - _RHO * _CHI * sim[-1]
                return self._wait(sim, fsim, _EXPAND, xe, xr, fxr)
            if fxr < fsim[-2]:
                sim[-1], fsim[-1] = xr, fxr
            elif fxr < fsim[-1]:
                xc = (1 + _PSI * _RHO) * xbar - _PSI * _RHO * sim[-1]
                return self._wait(sim, fsim, _OUTSIDE, xc, xr, fxr)
            else:
                xcc = (1 - _PSI) * xbar + _PSI * sim[-1]
                return self._wait(sim, fsim, _INSIDE, xcc, xr, fxr)
        elif phase == _EXPAND:
            better = values[0] < fxr
            sim[-1], fsim[-1] = (request.points[0], values[0]) if better else (xr, fxr)
        elif phase == _OUTSIDE:
            if values[0] <= fxr:
                sim[-1], fsim[-1] = request.points[0], values[0]
            else:
                shrink = True
        else:  # _INSIDE
            if values[0] < fsim[-1]:
                sim[-1], fsim[-1] = request.points[0], values[0]
            else:
                shrink = True
        if shrink:
            sim[1:] = sim[0] + _SIGMA * (sim[1:] - sim[0])
            return self._wait(sim, fsim, _SHRINK, sim[1:], xr, fxr)
        order = np.argsort(fsim)
        sim, fsim = np.take(sim, order, 0), np.take(fsim, order, 0)
        xbar = np.add.reduce(sim[:-1], 0) / n
        return self._wait(sim, fsim, _REFLECT, (1 + _RHO) * xbar - _RHO * sim[-1], xr, fxr)

    @staticmethod
    def _wait(sim, fsim, phase, points, xr, fxr) -> dict:
        """The state waiting for ``points`` (kept in a ``(d + 1, d)`` array: fixed shapes)."""
        points = np.atleast_2d(points)
        pending = np.zeros_like(sim)
        pending[: len(points)] = points
        return dict(
            simplex=sim, values=np.asarray(fsim, np.float64), pending=pending,
            count=np.asarray(len(points)), phase=np.asarray(phase),
            reflected=np.asarray(xr, np.float64), reflected_value=np.asarray(float(fxr)),
        )  # fmt: skip
