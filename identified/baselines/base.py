"""One interface for the parameter estimators the paper compares (closed form, LS, CMA-ES, ...).

A :class:`ParameterProblem` names the parameters to estimate (``("K", "c", "M")`` or, with the
mass known, ``("K", "c")``; paper, Sec. "Simple Spring-Rod System Identification" and appendix A),
their initial guess and bounds, and gives two ways to reach the data: ``objective(theta)``, the
trajectory error of a simulator run with ``theta`` against the reference (what the black-box
methods see: "they resample a new trajectory from the simulator after each optimization
iteration"), and ``dataset``/``topology``, the recorded rod states (what the first-principles
regression sees).  A :class:`ParameterSolver` turns a problem into an :class:`Estimate`, so a row
of a results table is a solver, not a script.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from identified.dataset import Dataset
    from identified.topology import Topology

__all__ = ["Estimate", "ParameterProblem", "ParameterSolver", "relative_errors", "success"]


@dataclass
class ParameterProblem:
    """Estimate ``names`` from one reference trajectory.

    ``x0`` (P,) initial guess; ``bounds`` (P, 2) box for the searching solvers; ``objective``
    maps theta (P,) to the trajectory error of a simulator run with it (None: not available), and
    ``residual`` to the vector whose squared sum it is (for least-squares solvers);
    ``dataset``/``topology`` the recorded data for solvers that read states; ``known`` parameters
    that are given, not estimated (e.g. ``{"M": 10.0}``, appendix A).
    """

    names: tuple[str, ...]
    x0: np.ndarray
    bounds: np.ndarray
    objective: Callable[[np.ndarray], float] | None = None
    residual: Callable[[np.ndarray], np.ndarray] | None = None
    dataset: Dataset | None = None
    topology: Topology | None = None
    known: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.x0 = np.asarray(self.x0, dtype=float).reshape(-1)
        self.bounds = np.asarray(self.bounds, dtype=float).reshape(-1, 2)
        if not (len(self.names) == self.x0.size == self.bounds.shape[0]):
            raise ValueError(f"names {self.names}, x0 {self.x0.shape} and bounds {self.bounds.shape} disagree")
        if np.any(self.bounds[:, 0] >= self.bounds[:, 1]):
            raise ValueError(f"every bound needs low < high, got {self.bounds.tolist()}")


@dataclass
class Estimate:
    """What a solver returns: ``values`` by name, its ``iterations`` and objective ``evaluations``,
    wall ``seconds``, and ``trace`` (iterations, P) the estimate after every iteration."""

    values: dict[str, float]
    iterations: int
    evaluations: int
    seconds: float
    trace: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def seconds_per_iteration(self) -> float:
        return self.seconds / max(self.iterations, 1)


@runtime_checkable
class ParameterSolver(Protocol):
    """Anything with a ``name`` and ``estimate(problem) -> Estimate``."""

    name: str

    def estimate(self, problem: ParameterProblem) -> Estimate:
        ...


def relative_errors(values: Mapping[str, float], truth: Mapping[str, float]) -> dict[str, float]:
    """``|value / truth - 1|`` for every name in ``truth`` (inf where a value is missing or not finite)."""
    out = {}
    for k, t in truth.items():
        v = values.get(k, np.nan)
        out[k] = float(abs(v / t - 1.0)) if np.isfinite(v) else float("inf")
    return out


def success(values: Mapping[str, float], truth: Mapping[str, float], tol: float = 0.05,
            keys: Sequence[str] | None = None) -> bool:
    """The paper's criterion: every parameter within ``tol`` (5 %) of the ground truth (relative)."""
    errs = relative_errors(values, {k: truth[k] for k in (keys or truth)})
    return all(e <= tol for e in errs.values())
