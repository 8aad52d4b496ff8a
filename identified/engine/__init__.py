"""The paper's differentiable spring-rod engine, in torch.

Modules (one per block of the paper's Fig. "architecture"):

* :mod:`identified.engine.forces` — force generation (eqs. 1-2): ``endpoint_kinematics``,
  ``spring_geometry``, ``spring_stretch``, ``spring_tension``, ``spring_end_forces``;
* :mod:`identified.engine.accelerations` — acceleration generation (eqs. 3-4): ``rod_wrench``,
  ``push_wrench``, ``rod_accelerations``;
* :mod:`identified.engine.integration` — semi-implicit Euler as MuJoCo's ``mj_Euler``:
  ``semi_implicit_euler``, ``RodState``;
* :mod:`identified.engine.engine` — ``SpringRodEngine`` (``step``, ``rollout``, ``dynamics``,
  ``step_components``), ``SpringRodParams``, the ``Effect`` plug-in protocol and its ``StepContext``;
* :mod:`identified.engine.smallmat` — small matrices as elementwise work, and the component form
  (a 3-vector as a tuple of three tensors) in which the Euler step's formulas are written once:
  each tensor-form function above unbinds into components and stacks back, and the twin's
  compiled substep (``step_components``) runs the components directly.

Conventions: quaternions w-x-y-z, angular velocity in the WORLD frame in every state, rod-frame
(body) quantities named ``*_body``; batched over any leading dimensions.
"""

from identified.engine.accelerations import push_wrench, rod_accelerations, rod_wrench
from identified.engine.engine import Effect, SpringRodEngine, SpringRodParams, StepContext, StepTerms
from identified.engine.forces import (
    EndpointKinematics,
    SpringGeometry,
    SpringGraph,
    endpoint_kinematics,
    spring_end_forces,
    spring_geometry,
    spring_stretch,
    spring_tension,
)
from identified.engine.integration import RodState, semi_implicit_euler

__all__ = [
    "Effect",
    "EndpointKinematics",
    "RodState",
    "SpringGeometry",
    "SpringGraph",
    "SpringRodEngine",
    "SpringRodParams",
    "StepContext",
    "StepTerms",
    "endpoint_kinematics",
    "push_wrench",
    "rod_accelerations",
    "rod_wrench",
    "semi_implicit_euler",
    "spring_end_forces",
    "spring_geometry",
    "spring_stretch",
    "spring_tension",
]
