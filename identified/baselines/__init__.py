"""The paper's comparison methods, each a row of ``tensegrity reproduce``.

* parameter solvers behind one interface (:mod:`~identified.baselines.base`): the closed form of
  :mod:`identified.fit` ("Ours"), bounded L-BFGS-B ("LS") and CMA-ES on a simulator's trajectory
  error (:mod:`~identified.baselines.solvers`); MuJoCo's own ``mujoco.sysid`` adapter lives in
  ``tensegrity_gym.reproduce.sysid`` (it steps MuJoCo, which this package never does);
* learned one-step models (:mod:`~identified.baselines.neural`): MLP, MLP+Int, Interaction,
  Interaction+Int; and Koopman+Int (:mod:`~identified.baselines.koopman`);
* one evaluation path for all of them (:mod:`~identified.baselines.rollout`).
"""

from identified.baselines.base import Estimate, ParameterProblem, ParameterSolver, relative_errors, success
from identified.baselines.koopman import KoopmanInt, monomial_pairs
from identified.baselines.neural import MLP, Budget, Interaction, InteractionInt, MLPInt, make_pairs, train
from identified.baselines.rollout import rollout, rollout_errors
from identified.baselines.solvers import CMAES, LBFGSB, ClosedForm

__all__ = [
    "CMAES",
    "LBFGSB",
    "MLP",
    "Budget",
    "ClosedForm",
    "Estimate",
    "Interaction",
    "InteractionInt",
    "KoopmanInt",
    "MLPInt",
    "ParameterProblem",
    "ParameterSolver",
    "make_pairs",
    "monomial_pairs",
    "relative_errors",
    "rollout",
    "rollout_errors",
    "success",
    "train",
]
