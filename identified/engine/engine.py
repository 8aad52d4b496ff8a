"""The differentiable spring-rod engine: force generation -> acceleration generation -> integration.

One step (paper, Fig. "architecture"):

1. :mod:`~identified.engine.forces` (eqs. 1-2): spring end kinematics, 1D length/rate, tension,
   end forces;
2. :mod:`~identified.engine.accelerations` (eqs. 3-4): aggregate forces and torques per rod, add
   gravity, the scaled control force ``h f_u`` and the plug-in *effects*, then ``a`` and ``α_b``;
3. :mod:`~identified.engine.integration`: semi-implicit Euler, MuJoCo's integrator for free bodies
   (``integrator="euler"``, default), optionally with the velocity update of MuJoCo's implicit
   integrators (``integrator="implicit"``: implicit spring damping and gyroscopic term), or
   MuJoCo's RK4 (``integrator="rk4"``).

Parameters are physical quantities (:class:`SpringRodParams`): stiffness ``K`` (S,), damping
``c`` (S,), mass ``M`` (R,), inertia ``(Ixx, Iyy, Izz)`` (R, 3) about the centre of mass, control
scale ``h`` (), gravity (3,); optionally each rod's centre of mass in its frame ``com`` (R, 3) and
products of inertia (R, 3) (a rod frame off the centre of mass or turned from the principal axes).  Any of them may carry leading batch dimensions that broadcast with the state's (one set of
parameters per environment), and any may ``requires_grad`` for gradient-based refinement.

Effects are forces the spring-rod model lacks (ground contact, drag, ...): callables
``effect(state, ctx) -> (force (..., R, 3) | None, torque_world (..., R, 3) | None)``, summed into
the rod wrench before the accelerations; ``ctx`` is a :class:`StepContext` with everything the step
has computed so far.

Nothing here checks finiteness: a diverging state yields NaN/inf, which the caller detects.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np
import torch

from identified.engine.accelerations import (
    push_wrench,
    push_wrench_components,
    rod_accelerations,
    rod_accelerations_components,
    rod_wrench,
    rod_wrench_components,
)
from identified.engine.forces import (
    EndpointKinematics,
    SpringGeometry,
    SpringGraph,
    end_kinematics,
    endpoint_kinematics,
    spring_end_forces,
    spring_end_forces_components,
    spring_geometry,
    spring_geometry_components,
    spring_tension,
)
from identified.engine.integration import (
    INTEGRATORS,
    RodState,
    implicit_accelerations,
    runge_kutta4,
    semi_implicit_euler,
    semi_implicit_euler_components,
)
from identified.engine.smallmat import Vec, mtv, vadd, vec
from identified.rotation import (
    matrix_apply,
    matrix_apply_transpose,
    quat_to_matrix,
    quat_to_matrix_components,
)
from identified.topology import Topology

__all__ = ["Effect", "RodState", "SpringRodEngine", "SpringRodParams", "StepContext", "StepTerms"]

_GRAVITY = (0.0, 0.0, -9.81)


@dataclass
class SpringRodParams:
    """Physical parameters of a spring-rod system, as tensors.

    ``stiffness`` (..., S) N/m, ``damping`` (..., S) N s/m, ``mass`` (..., R) kg, ``inertia``
    (..., R, 3) kg m² (rod-frame diagonal of the inertia about the centre of mass),
    ``control_scale`` (...) the control force scalar ``h``, ``gravity`` (..., 3) m/s²; optional
    (``None``: 0, the rod frame at the centre of mass along its principal axes): ``com`` (..., R, 3)
    m, the centre of mass in the rod frame, and ``inertia_products`` (..., R, 3) kg m², the inertia's
    off-diagonal entries ``(Jxy, Jxz, Jyz)`` (:mod:`identified.engine.accelerations`).  Build from
    plain numbers with :meth:`from_values`; make some or all trainable with :meth:`requires_grad_`.
    """

    stiffness: torch.Tensor
    damping: torch.Tensor
    mass: torch.Tensor
    inertia: torch.Tensor
    control_scale: torch.Tensor
    gravity: torch.Tensor
    com: torch.Tensor | None = None
    inertia_products: torch.Tensor | None = None

    NAMES = ("stiffness", "damping", "mass", "inertia", "control_scale", "gravity")
    #: per-rod parameters that may be absent (``None``)
    OPTIONAL = ("com", "inertia_products")

    @classmethod
    def from_values(
        cls,
        stiffness: Any,
        damping: Any,
        mass: Any,
        inertia: Any,
        control_scale: Any = 1.0,
        gravity: Any = _GRAVITY,
        *,
        com: Any = None,
        inertia_products: Any = None,
        n_rods: int | None = None,
        n_springs: int | None = None,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
    ) -> SpringRodParams:
        """From floats, sequences, arrays or tensors.  With ``n_rods``/``n_springs`` given, scalars
        are expanded to per-rod/per-spring tensors ((S,), (R,), (R, 3)) and shapes are checked."""

        def t(x: Any) -> torch.Tensor:
            if isinstance(x, torch.Tensor):
                return x.to(dtype=dtype, device=device)
            return torch.as_tensor(np.array(x, dtype=np.float64), dtype=dtype, device=device)

        p = cls(t(stiffness), t(damping), t(mass), t(inertia), t(control_scale), t(gravity),
                None if com is None else t(com), None if inertia_products is None else t(inertia_products))
        if n_springs is not None:
            p.stiffness = p.stiffness.expand(n_springs).clone() if p.stiffness.ndim == 0 else p.stiffness
            p.damping = p.damping.expand(n_springs).clone() if p.damping.ndim == 0 else p.damping
        if n_rods is not None:
            p.mass = p.mass.expand(n_rods).clone() if p.mass.ndim == 0 else p.mass
            if p.inertia.ndim <= 1:
                p.inertia = p.inertia.expand(n_rods, 3).clone()
        if n_rods is not None and n_springs is not None:
            p.validate(n_rods, n_springs)
        return p

    def validate(self, n_rods: int, n_springs: int) -> None:
        """Raise ValueError if a parameter's trailing shape does not fit ``n_rods``/``n_springs``."""
        want = {"stiffness": (n_springs,), "damping": (n_springs,), "mass": (n_rods,),
                "inertia": (n_rods, 3), "control_scale": (), "gravity": (3,)}
        want.update({n: (n_rods, 3) for n in self.OPTIONAL if getattr(self, n) is not None})
        for name, shape in want.items():
            got = tuple(getattr(self, name).shape)
            tail = got[len(got) - len(shape):] if shape else ()
            if len(got) < len(shape) or tail != shape:
                raise ValueError(f"parameter '{name}' has shape {got}, expected (..., {', '.join(map(str, shape))})"
                                 if shape else f"parameter '{name}' has shape {got}, expected a scalar")

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> SpringRodParams:
        """Convert every tensor (a no-op, keeping autograd leaves, where nothing changes)."""
        return replace(self, **{n: v.to(dtype=dtype, device=device) for n, v in self.as_dict().items()})

    def requires_grad_(self, requires_grad: bool = True, names: Sequence[str] | None = None) -> SpringRodParams:
        """Mark the named parameters (default: all) as trainable, in place; returns ``self``."""
        for n in names or self.as_dict():
            getattr(self, n).requires_grad_(requires_grad)
        return self

    def parameters(self) -> list[torch.Tensor]:
        """The tensors that require gradients (for a torch optimiser)."""
        return [v for v in self.as_dict().values() if v.requires_grad]

    def detach(self) -> SpringRodParams:
        return replace(self, **{n: v.detach() for n, v in self.as_dict().items()})

    def as_dict(self) -> dict[str, torch.Tensor]:
        """Every parameter that is set (the optional ones only when not ``None``)."""
        out = {n: getattr(self, n) for n in self.NAMES}
        out.update({n: getattr(self, n) for n in self.OPTIONAL if getattr(self, n) is not None})
        return out


class StepContext(NamedTuple):
    """What an effect may read: the quantities of the current step (shapes as in the modules).

    ``rot`` (..., R, 3, 3); ``angvel_body`` (..., R, 3); ``ends`` spring end kinematics (..., S, 2, 3);
    ``geometry`` spring length/rate (..., S) and unit (..., S, 3); ``tension`` (..., S);
    ``rest_length`` (..., S); ``push_force``/``push_point`` (..., R, 3) or None;
    ``base_lin_acc`` (..., R, 3) world / ``base_ang_acc_body`` (..., R, 3) rod frame: the
    accelerations under every force but the constraint-like effects (ground contact), given to
    those effects only (``needs_base_acceleration``); ``recorded_lin_acc`` /
    ``recorded_ang_acc_body``: in the fit only, the recorded accelerations of the step (an effect
    the integrator treats implicitly evaluates its force at the step's end velocity from them).
    """

    params: SpringRodParams
    dt: float
    graph: SpringGraph
    rot: torch.Tensor
    angvel_body: torch.Tensor
    ends: EndpointKinematics
    geometry: SpringGeometry
    tension: torch.Tensor
    rest_length: torch.Tensor
    push_force: torch.Tensor | None
    push_point: torch.Tensor | None
    base_lin_acc: torch.Tensor | None = None
    base_ang_acc_body: torch.Tensor | None = None
    recorded_lin_acc: torch.Tensor | None = None
    recorded_ang_acc_body: torch.Tensor | None = None


@runtime_checkable
class Effect(Protocol):
    """A force term the spring-rod model lacks (contact, drag, ...), added to the rod wrench.

    Called once per step with the current state and the :class:`StepContext`; returns a force
    (..., R, 3) and a torque about each rod's COM (..., R, 3), both WORLD frame (either may be
    ``None`` for zero).  Must be differentiable torch code if gradients are wanted.

    A plug-in may declare, as class attributes, ``needs_base_acceleration`` (added after every
    other force, with the accelerations they cause in the context) and ``component_form`` (has
    ``wrench_components``, for :meth:`SpringRodEngine.step_components`); the library's effects
    (:class:`identified.effects.base.Effect`) declare both, a plain callable neither.
    """

    def __call__(self, state: RodState, ctx: StepContext) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        ...


class StepTerms(NamedTuple):
    """Every intermediate of one step's dynamics (for diagnosis and effects).

    ``force``/``torque`` (..., R, 3): total world wrench without gravity; ``lin_acc`` (..., R, 3)
    world; ``ang_acc_body`` (..., R, 3) rod frame.
    """

    ctx: StepContext
    force: torch.Tensor
    torque: torch.Tensor
    lin_acc: torch.Tensor
    ang_acc_body: torch.Tensor


class SpringRodEngine:
    """The identified spring-rod engine: ``step`` and ``rollout`` batched over leading dimensions.

    ``topology``: the system graph (:class:`~identified.topology.Topology` or a prepared
    :class:`SpringGraph`); ``params``: :class:`SpringRodParams` (or a mapping of its fields);
    ``dt``: time step, s; ``effects``: extra force terms (:class:`Effect`); ``integrator``:
    ``"euler"`` (MuJoCo's default), ``"implicit"`` (MuJoCo's implicit/implicitfast) or ``"rk4"``
    (MuJoCo's RK4), see :mod:`~identified.engine.integration`.  States and inputs may be arrays or tensors; they are
    converted to ``dtype``/``device`` (a no-op when they match).
    """

    def __init__(
        self,
        topology: Topology | SpringGraph,
        params: SpringRodParams | Mapping[str, Any],
        dt: float,
        effects: Sequence[Effect] = (),
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
        integrator: str = "euler",
    ) -> None:
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {', '.join(INTEGRATORS)}, got '{integrator}'")
        self.integrator = integrator
        self.dtype = dtype
        self.device = torch.device(device)
        if isinstance(topology, SpringGraph):
            self.graph = topology.to(dtype, self.device)
        else:
            self.graph = SpringGraph.from_topology(topology, dtype=dtype, device=self.device)
        if not isinstance(params, SpringRodParams):
            params = SpringRodParams.from_values(**dict(params), n_rods=self.graph.n_rods,
                                                 n_springs=self.graph.n_springs, dtype=dtype, device=self.device)
        params.validate(self.graph.n_rods, self.graph.n_springs)
        if integrator == "implicit" and any(getattr(params, n) is not None for n in params.OPTIONAL):
            raise ValueError("the implicit integrator takes rods with their centre of mass at the frame's origin "
                             "and a diagonal inertia (no 'com', no 'inertia_products'); use 'euler' or 'rk4'")
        self.params = params.to(dtype, self.device)
        self.dt = float(dt)
        self.effects = list(effects)

    @property
    def n_rods(self) -> int:
        return self.graph.n_rods

    @property
    def n_springs(self) -> int:
        return self.graph.n_springs

    def _t(self, x: Any) -> torch.Tensor:
        """A tensor in the engine's dtype and device (a no-op, autograd kept, if it already is)."""
        if isinstance(x, torch.Tensor):
            return x.to(dtype=self.dtype, device=self.device)
        return torch.as_tensor(np.array(x, dtype=np.float64), dtype=self.dtype, device=self.device)

    def state(self, pos: Any, quat: Any, vel: Any, angvel: Any) -> RodState:
        """A :class:`RodState` from arrays or tensors (world-frame angular velocity)."""
        return RodState(self._t(pos), self._t(quat), self._t(vel), self._t(angvel))

    # ------------------------------------------------------------------ one step
    def dynamics(
        self,
        state: RodState,
        rest_length: Any,
        push_force: Any | None = None,
        push_point: Any | None = None,
        tendon_force: Any | None = None,
    ) -> StepTerms:
        """Force and acceleration generation for ``state`` (no integration).

        ``rest_length`` (..., S) m; ``push_force`` (..., R, 3) world, N; ``push_point`` (..., R, 3)
        rod frame (``None`` = COM); ``tendon_force`` (..., S) N: the actuators' force along each
        tendon (positive lengthens it, MuJoCo's sign: :mod:`identified.engine.actuators`), which
        lowers its tension by as much; ``None``: no actuators.
        """
        p = self.params
        state = RodState(*(self._t(x) for x in state))
        pos, quat, vel, angvel = state
        rest = self._t(rest_length)
        rot = quat_to_matrix(quat)
        w_b = matrix_apply_transpose(rot, angvel)
        ends = endpoint_kinematics(self.graph, pos, quat, vel, angvel, rot=rot)
        geom = spring_geometry(ends)
        tension = spring_tension(geom.length, geom.rate, rest, p.stiffness, p.damping, self.graph.pull_only)
        if tendon_force is not None:
            tension = tension - self._t(tendon_force)
        force, torque = rod_wrench(self.graph, spring_end_forces(geom.unit, tension), ends.lever)
        fu = ru = None
        if push_force is not None:
            fu = self._t(push_force)
            ru = None if push_point is None else self._t(push_point)
            pf, pt = push_wrench(rot, fu, ru, p.control_scale)
            force, torque = force + pf, torque + pt
        ctx = StepContext(p, self.dt, self.graph, rot, w_b, ends, geom, tension, rest, fu, ru)
        late = []
        for effect in self.effects:
            if _declares(effect, "needs_base_acceleration"):
                late.append(effect)
                continue
            ef, et = effect(state, ctx)
            if ef is not None:
                force = force + ef
            if et is not None:
                torque = torque + et
        lin_acc, ang_acc_b = self._implicit_damping(
            *rod_accelerations(force, torque, rot, w_b, p.mass, p.inertia, p.gravity, p.com, p.inertia_products))
        if late:  # constraint-like effects see the accelerations under every other force
            ctx = ctx._replace(base_lin_acc=lin_acc, base_ang_acc_body=ang_acc_b)
            for effect in late:
                ef, et = effect(state, ctx)
                force, torque = force + ef, torque + et
            lin_acc, ang_acc_b = self._implicit_damping(
                *rod_accelerations(force, torque, rot, w_b, p.mass, p.inertia, p.gravity, p.com, p.inertia_products))
        if self.integrator == "implicit":
            lin_acc, ang_acc_b = implicit_accelerations(self.graph, geom.unit, ends.lever, rot, w_b, lin_acc,
                                                        ang_acc_b, p.mass, p.inertia, p.damping, self.dt)
        return StepTerms(ctx, force, torque, lin_acc, ang_acc_b)

    def _implicit_damping(self, lin_acc: torch.Tensor, ang_acc_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Damping effects the integrator takes implicitly (MuJoCo's Euler does so for joint damping):
        ``(M + dt b) a = F - b v`` and ``(I + dt b_rot) α_b = ...``, i.e. the explicit accelerations
        scaled by ``M / (M + dt b)`` and ``I / (I + dt b_rot)`` (each effect's velocity derivative)."""
        for effect in self.effects:
            d = self._damping_of(effect, lin_acc)
            if d is None:
                continue
            b_lin, b_rot = d
            m, inertia = self.params.mass, self.params.inertia
            lin_acc = lin_acc * (m / (m + self.dt * b_lin)).unsqueeze(-1)
            ang_acc_b = ang_acc_b * inertia / (inertia + self.dt * b_rot.unsqueeze(-1))
        return lin_acc, ang_acc_b

    def _damping_of(self, effect: Effect, like: torch.Tensor | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """An effect's implicit damping ``(b_lin, b_rot)`` (its optional ``implicit_damping``), or
        None: explicit."""
        damping = getattr(effect, "implicit_damping", None)
        return None if damping is None else damping(self.params.mass if like is None else like)

    def step(
        self,
        state: RodState,
        rest_length: Any,
        push_force: Any | None = None,
        push_point: Any | None = None,
        tendon_force: Any | None = None,
    ) -> RodState:
        """Advance every rod by ``dt``: ``state`` (..., R, ·), ``rest_length`` (..., S),
        ``push_force`` (..., R, 3) world or None, ``push_point`` (..., R, 3) rod frame or None (COM),
        ``tendon_force`` (..., S) the actuators' force on each tendon, held over the step, or None.
        Returns the next :class:`RodState`."""
        state = RodState(*(self._t(x) for x in state))
        if self.integrator == "rk4":
            rest = self._t(rest_length)
            fu = None if push_force is None else self._t(push_force)
            ru = None if push_point is None else self._t(push_point)

            rot0 = quat_to_matrix(state.quat)
            lever = None if ru is None else matrix_apply(rot0, ru)

            def acc(s: RodState, _w_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                # the push is held for the step as a WORLD force and torque (as MuJoCo's
                # xfrc_applied): its point moves with the stage's rotation so the lever stays put
                point = None if lever is None else matrix_apply_transpose(quat_to_matrix(s.quat), lever)
                terms = self.dynamics(s, rest, fu, point, tendon_force)
                return terms.lin_acc, terms.ang_acc_body

            return runge_kutta4(acc, state, matrix_apply_transpose(rot0, state.angvel), self.dt)
        terms = self.dynamics(state, rest_length, push_force, push_point, tendon_force)
        return semi_implicit_euler(state.pos, state.quat, state.vel, terms.ctx.angvel_body,
                                   terms.lin_acc, terms.ang_acc_body, self.dt)

    # ------------------------------------------------------------------ the fused step
    @property
    def fused(self) -> bool:
        """True when :meth:`step_components` steps this engine: the Euler integrator and every
        effect a constraint-like one that declares a component-form wrench (``component_form``:
        ground contact) and no implicit damping. Otherwise the twin steps through :meth:`step`."""
        return self.integrator == "euler" and all(
            _declares(e, "needs_base_acceleration") and _declares(e, "component_form")
            and self._damping_of(e) is None for e in self.effects)

    def step_components(self, pos: Vec, quat: tuple, vel: Vec, angvel: Vec, rest_length: torch.Tensor,
                        push_force: torch.Tensor | None = None, push_point: torch.Tensor | None = None,
                        tendon_force: torch.Tensor | None = None) -> tuple[Vec, tuple, Vec, Vec]:
        """:meth:`step` in component form, for an engine that is :attr:`fused`: the state as the
        components of ``pos``, ``quat`` (four), ``vel``, ``angvel`` (WORLD), each (..., R) in the
        engine's dtype; ``rest_length`` (..., S); ``push_force``/``push_point`` (..., R, 3) or None.
        Returns the new state's components.

        The same formulas as :meth:`dynamics` then :func:`semi_implicit_euler` (the tensor-form
        functions are these component functions, stacked), with nothing stacked in between: under
        ``torch.compile`` a whole step is a few loops over rods and envs, vectorised (the twin's
        substep, :mod:`tensegrity_gym.backends.twin_physics`)."""
        p, g = self.params, self.graph
        rot = quat_to_matrix_components(quat)
        w_b = mtv(rot, angvel)
        point, velocity, lever = end_kinematics(g, pos, vel, angvel, rot)
        S = g.n_springs
        length, rate, unit = spring_geometry_components(
            tuple(x[..., :S] for x in point), tuple(x[..., S:] for x in point),
            tuple(x[..., :S] for x in velocity), tuple(x[..., S:] for x in velocity))
        tension = spring_tension(length, rate, rest_length, p.stiffness, p.damping, g.pull_only)
        if tendon_force is not None:
            tension = tension - tendon_force
        force, torque = rod_wrench_components(g, spring_end_forces_components(unit, tension), lever)
        if push_force is not None:
            pf, pt = push_wrench_components(rot, vec(push_force), None if push_point is None else vec(push_point),
                                            p.control_scale.unsqueeze(-1))
            force = vadd(force, pf)
            torque = torque if pt is None else vadd(torque, pt)
        inertia, gravity = vec(p.inertia), tuple(p.gravity.unsqueeze(-2).unbind(-1))
        com = None if p.com is None else vec(p.com)
        products = None if p.inertia_products is None else vec(p.inertia_products)
        lin_acc, ang_acc_b = rod_accelerations_components(force, torque, rot, w_b, p.mass, inertia, gravity, com,
                                                          products)
        if self.effects:  # constraint-like effects see the accelerations under every other force
            for effect in self.effects:
                ef, et = effect.wrench_components(pos, vel, angvel, rot, lin_acc, ang_acc_b, p.mass, inertia,
                                                   com, products)
                force, torque = vadd(force, ef), vadd(torque, et)
            lin_acc, ang_acc_b = rod_accelerations_components(force, torque, rot, w_b, p.mass, inertia, gravity,
                                                              com, products)
        return semi_implicit_euler_components(pos, quat, vel, w_b, lin_acc, ang_acc_b, self.dt)

    # ------------------------------------------------------------------ many steps
    def rollout(
        self,
        state0: RodState,
        rest_lengths: Any,
        push_force: Any | None = None,
        push_point: Any | None = None,
        tendon_forces: Any | None = None,
    ) -> RodState:
        """Roll ``T`` steps from ``state0`` (..., R, ·).

        ``rest_lengths`` (..., T, S); ``push_force`` (..., T, R, 3) or None; ``push_point``
        (..., T, R, 3) or None; ``tendon_forces`` (..., T, S) the actuators' force on each tendon
        or None.  Returns the states at the ``T + 1`` instants stacked on a time axis:
        (..., T + 1, R, ·), the first being ``state0``.
        """
        rest = self._t(rest_lengths)
        fu = None if push_force is None else self._t(push_force)
        ru = None if push_point is None else self._t(push_point)
        ft = None if tendon_forces is None else self._t(tendon_forces)
        state = RodState(*(self._t(x) for x in state0))
        out = [state]
        for t in range(rest.shape[-2]):
            state = self.step(
                state,
                rest[..., t, :],
                None if fu is None else fu[..., t, :, :],
                None if ru is None else ru[..., t, :, :],
                None if ft is None else ft[..., t, :],
            )
            out.append(state)
        return RodState(*(torch.stack(xs, dim=-3) for xs in zip(*out)))


def _declares(effect: Effect, flag: str) -> bool:
    """Whether a plug-in declares ``flag`` (:class:`Effect`'s optional class attributes
    ``needs_base_acceleration``, ``component_form``); a plain callable declares none."""
    return bool(getattr(effect, flag, False))
