"""Parameter solvers behind one interface (:class:`~identified.baselines.base.ParameterSolver`).

* :class:`ClosedForm` — ours: the first-principles linear regression of :mod:`identified.fit`
  (closed-form least squares, or the paper's Adam schedule with ``solver="adam"``);
* :class:`LBFGSB` — the paper's "LS": bounded L-BFGS-B (scipy) on the trajectory error of a
  simulator, gradients by finite differences (the simulator is a black box);
* :class:`CMAES` — the paper's "CMA-ES" (Hansen's ``cma`` package) on the same objective.

Budgets are explicit constructor arguments and are recorded in every :class:`Estimate`'s ``info``.
"""

from __future__ import annotations

import time

import numpy as np

from identified.baselines.base import Estimate, ParameterProblem

__all__ = ["CMAES", "LBFGSB", "ClosedForm", "safe_objective"]

BIG = 1e6  # objective value given to a simulation that diverged (NaN/inf): a finite "very bad"


def safe_objective(problem: ParameterProblem):
    """``problem.objective`` with non-finite values (a diverged simulation) mapped to :data:`BIG`,
    and a counter of evaluations (``f.calls``)."""
    if problem.objective is None:
        raise ValueError("this solver needs a simulator objective; the problem has none")

    def f(theta: np.ndarray) -> float:
        f.calls += 1
        v = float(problem.objective(np.asarray(theta, dtype=float)))
        return v if np.isfinite(v) else BIG

    f.calls = 0
    return f


class LBFGSB:
    """Bounded L-BFGS-B (``scipy.optimize.minimize``) on the trajectory error; finite-difference
    gradients (2-point, scipy's default step).  Stops after ``max_iter`` iterations or scipy's
    own tolerances."""

    name = "LS"

    def __init__(self, max_iter: int = 100) -> None:
        self.max_iter = int(max_iter)

    def estimate(self, problem: ParameterProblem) -> Estimate:
        from scipy.optimize import minimize

        f = safe_objective(problem)
        trace: list[np.ndarray] = []
        t0 = time.perf_counter()
        res = minimize(f, problem.x0, method="L-BFGS-B", bounds=problem.bounds,
                       callback=lambda xk: trace.append(np.array(xk, dtype=float)),
                       options={"maxiter": self.max_iter})
        sec = time.perf_counter() - t0
        x = np.asarray(res.x, dtype=float)
        return Estimate(dict(zip(problem.names, x.tolist())), int(res.nit), f.calls, sec,
                        np.array(trace).reshape(-1, x.size),
                        info={"max_iter": self.max_iter, "message": str(res.message), "objective": float(res.fun)})


class CMAES:
    """CMA-ES (``cma``) on the trajectory error inside the bounds.

    ``tolx``: the paper's "CMA tolerance ... adjusted to 1", read as cma's ``tolx`` (stop when
    every coordinate's search step is below 1, in the parameters' units); ``sigma0``: the initial
    step as a fraction of the bound range (cma's advice: about a quarter); ``max_iter``:
    generations at most; ``popsize``: cma's default ``4 + 3 ln P`` unless given.
    """

    name = "CMA-ES"

    def __init__(self, tolx: float = 1.0, sigma0: float = 0.25, max_iter: int = 100,
                 popsize: int | None = None, seed: int = 0) -> None:
        self.tolx, self.sigma0, self.max_iter, self.popsize, self.seed = tolx, sigma0, max_iter, popsize, seed

    def estimate(self, problem: ParameterProblem) -> Estimate:
        import cma

        f = safe_objective(problem)
        lo, hi = problem.bounds[:, 0], problem.bounds[:, 1]
        opts = {"bounds": [lo.tolist(), hi.tolist()], "tolx": self.tolx, "maxiter": self.max_iter,
                "seed": self.seed + 1, "verbose": -9}  # cma treats seed 0 as "random"
        if self.popsize:
            opts["popsize"] = self.popsize
        t0 = time.perf_counter()
        es = cma.CMAEvolutionStrategy(np.clip(problem.x0, lo, hi).tolist(),
                                      self.sigma0 * float(np.max(hi - lo)), opts)
        trace = []
        while not es.stop():
            xs = es.ask()
            es.tell(xs, [f(x) for x in xs])
            trace.append(np.array(es.result.xbest, dtype=float))
        sec = time.perf_counter() - t0
        x = np.array(es.result.xbest, dtype=float)
        return Estimate(dict(zip(problem.names, x.tolist())), int(es.result.iterations), f.calls, sec,
                        np.array(trace).reshape(-1, x.size),
                        info={"tolx": self.tolx, "max_iter": self.max_iter, "popsize": es.popsize,
                              "stop": {k: str(v) for k, v in es.stop().items()},
                              "objective": float(es.result.fbest)})


class ClosedForm:
    """Ours: :func:`identified.fit.identify.identify` on the recorded states (no simulator).

    One shared K, c, M (``regressors="single"``) for the parameters the problem names; a known
    mass (``problem.known["M"]``) fixes the scale, otherwise the model is normalised (mean rod mass
    1 kg) and only the ratios K/M, c/M are meaningful (paper: "any parameter combination
    satisfying K/M = 10 and c/M = 1 is a solution").  ``solver="adam"``: the paper's Adam schedule
    (30 epochs) on the same linear rows instead of the closed form.
    """

    def __init__(self, solver: str = "lstsq", regressors: str = "single") -> None:
        self.solver, self.regressors = solver, regressors
        self.name = "Ours" if solver == "lstsq" else f"Ours ({solver})"

    def estimate(self, problem: ParameterProblem) -> Estimate:
        from identified.fit.identify import ScaleSpec, identify

        if problem.dataset is None or problem.topology is None:
            raise ValueError("the closed form reads recorded states: the problem has no dataset/topology")
        rod = problem.topology.rod_names[0]
        scale = ScaleSpec(masses=((rod, float(problem.known["M"])),)) if "M" in problem.known else ScaleSpec()
        t0 = time.perf_counter()
        model = identify(problem.dataset, problem.topology, regressors=self.regressors, scale=scale,
                         solver=self.solver, weak_window=None)
        sec = time.perf_counter() - t0
        allv = {"K": float(np.mean(model.stiffness)), "c": float(np.mean(model.damping)),
                "M": float(np.mean(model.mass))}
        x = np.array([allv[n] for n in problem.names])
        iters = 30 if self.solver == "adam" else 1  # the paper's 30 Adam epochs; one solve
        return Estimate({n: allv[n] for n in problem.names}, iters, 0, sec, x[None, :],
                        info={"solver": self.solver, "regressors": self.regressors,
                              "scale": model.scale.get("anchor")})
