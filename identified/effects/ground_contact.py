"""``ground_contact``: normal and friction forces between the rods' capsules and a ground plane.

Geometry (read from the MJCF, never its physics parameters): every rod's collision capsule
(radius, segment end points in the rod frame) and the ground plane (height and normal).  Each end
sphere of a capsule is a contact candidate; it is *in contact* when it penetrates the plane,
depth ``d = r - (n·c - h) > 0`` (``c`` the sphere centre), at the point ``ρ = c - r n`` (lever from
the rod's centre of mass).

Force law.  MuJoCo's contact is a soft *constraint*, not a penalty spring: the solver chooses the
force that gives the contact point a reference acceleration, ``f = (a_ref - J qacc) / R``, with
``a_ref = k d - b v`` and a regulariser ``R`` proportional to the inverse effective mass.  Written
with the acceleration ``a0`` that the contact point would have under every *other* force (springs,
gravity, pushes, other effects) this is, for one contact on a rod,

    f_n = max(0, m_n (κ d - β_n v_n - γ_n a0_n))                        (normal)
    f_a = m_a (-β_a v_a - γ_a a0_a),   f_p = m_p (-β_p v_p - γ_p a0_p)   (friction)
    |(f_a, f_p)| <= μ f_n

written here per direction for one contact: in full, the force in contact coordinates
``(n, a, p)`` is ``A⁻¹ g`` with ``g`` the bracketed reference accelerations and
``A_ab = δ_ab / M + (ρ_c×u_a)ᵀ J_w⁻¹ (ρ_c×u_b)`` the contact point's inverse effective-mass matrix
from the rod's identified mass and full inertia tensor ``J_w = R J Rᵀ`` about its centre of mass,
``ρ_c`` the point's lever from the centre of mass (a rod frame off the centre of mass, or turned
from its principal axes, as MuJoCo's ``J M⁻¹ Jᵀ``; its off-diagonal terms are why a normal force
at a tilted rod's end also moves the point sideways, which the friction must cancel to stick);
``v`` the point's velocity, ``a0 = a0_rod + α0 × ρ`` with ``ρ`` the lever from the rod frame's
origin, whose acceleration ``a0_rod`` is (no centripetal term, as MuJoCo's ``J qacc``).  ``γ ≈ 1`` cancels what would push the rod into the
ground (a hard contact), ``κ``, ``β`` are a soft spring-damper in acceleration units (1/s², 1/s),
so none of them scales with the mass.  The friction axes are per rod: ``a`` along the rod's
shadow on the ground, ``p`` across it (an end cap rolls across its rod more easily than it slides
along it; on the robot γ_p ≈ 0.7 against γ_a ≈ 0.95).  Given M, I and ``a0`` -- all from the jointly identified
spring-rod model -- the law is *linear* in ``(κ, β_n, γ_n, β_t, γ_t)``: it is fitted by least
squares on the residual wrench of the rods that touch the ground (:meth:`GroundContact.fit_residual`),
and the friction bound ``μ`` by a profile scan of the same residual.  Measured on the robot preset,
this law explains most of the contact force (``explained_variance`` in the fit's metrics).

Contact torques.  A capsule pressed on the ground also resists spinning about the contact normal
(torsional friction) and rolling (rolling resistance), as MuJoCo's ``condim 6`` contacts do; the
forces above, on the rod's axis, have no torque about the contact point.  Per rod, with ``F_n``
the sum of its contacts' normal forces and ``ω`` its world angular velocity, ``ω_n = ω·n`` its spin
about the normal and ``ω_t = ω - ω_n n`` its rolling,

    τ = -F_n [μ_t tanh(ω_n / ω_s) n + μ_r tanh(|ω_t| / ω_s) ω_t / |ω_t|]

a Coulomb torque of at most ``μ_t F_n`` (``μ_r F_n``; lengths, m) smoothed over the angular speed
``ω_s``.  Linear in ``(μ_t, μ_r)`` given ``F_n``: fitted first, by non-negative least squares on the
residual torque *about the contact point* (the residual torque less the lever times the residual
force: every force at the contact point, the force law's included, leaves none there), with the
residual force's normal component as ``F_n``, and ``ω_s`` by a profile scan
(:func:`_fit_torques`); the force law is then fitted on the residual less these torques.  A model
file written before the torques loads with none (:data:`TORQUE_DEFAULTS`).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch

from identified.effects.base import Effect, ParamBlock
from identified.engine.accelerations import inertia_matrix
from identified.engine.smallmat import (
    Mat,
    Vec,
    inverse3,
    minverse,
    mmul,
    mtranspose,
    mtv,
    mv,
    unvec,
    vadd,
    vcross,
    vdot,
    vec,
    vscale,
    vsub,
)
from identified.rotation import matrix_apply, matrix_apply_transpose

__all__ = ["CONTACT_MARGIN", "CapsuleOnPlane", "GroundContact", "capsule_geometry", "cluster_covariance", "read_contact_geometry"]

#: a rod with an end sphere this close to the ground (m) is near it: the regression's rows of it
#: hold contact forces (:meth:`CapsuleOnPlane.rows_affected`), and the marker fit's windows without a
#: contact law move it as recorded (:mod:`identified.fit.output_error`)
CONTACT_MARGIN = 0.01

#: the regulariser ε (relative, on the diagonal of the contact-space inverse mass) is identified
#: by a profile scan over these values; MuJoCo's own is (1 - d) / d ≈ 0.05 at its default impedance
EPSILONS = (0.003, 0.01, 0.02, 0.05, 0.1, 0.2)
#: the friction coefficients scanned by the fit (its profile over μ)
MU_GRID = np.geomspace(0.05, 3.0, 40)
LINEAR = ("kappa", "beta_n", "gamma_n", "beta_a", "gamma_a", "beta_p", "gamma_p")
NL = len(LINEAR)
#: indices of the contact torques' parameters: torsional and rolling friction lengths (m) and the
#: angular speed over which both saturate (rad/s)
I_TORSION, I_ROLLING, I_OMEGA = NL + 2, NL + 3, NL + 4
#: the saturation speeds scanned by the fit (its profile over ``omega_slip``); the smallest keeps the
#: explicit step stable: the torque's slope ``mu f_n / omega_slip`` stays well below ``I / dt``
OMEGA_GRID = (0.3, 1.0, 3.0, 10.0)
#: what a model file written before the contact torques holds for them: no torque
TORQUE_DEFAULTS = {"mu_torsion": 0.0, "mu_rolling": 0.0, "omega_slip": 1.0}
#: rounds of the alternating fit (the force law on the residual less the torques, the torques on
#: the residual torque about the contact point less the force law's)
TORQUE_ROUNDS = 3


class GeometryError(ValueError):
    """The MJCF lacks the geometry an effect needs."""


def read_contact_geometry(mjcf: str, rod_names: tuple[str, ...]) -> dict[str, Any]:
    """Capsule radius and segment ends per rod, and the ground plane, from an MJCF as MuJoCo compiles it
    (:func:`identified.mjcf.read_system`: geometry only, in each rod's frame).

    A rod's capsule spans its collision geoms (capsule and cylinder ends, sphere centres: a tube
    with end caps is the capsule between the caps). Returns ``{"radius": [R], "segment": [R][2][3]
    rod frame, "ground_height": h, "normal": [3]}``. Raises :class:`GeometryError` (one line) when
    there is no ground plane or a rod has no collision capsule, cylinder or sphere.
    """
    from identified.mjcf import read_system

    system = read_system(mjcf, GeometryError)
    if system.plane is None:
        raise GeometryError("ground_contact needs a ground plane (a <geom type=\"plane\">) in the MJCF; it has none")
    normal, height = system.plane
    rods = {r.name: r for r in system.rods}
    radius, segment = [], []
    for name in rod_names:
        rod = rods.get(name)
        if rod is None or rod.contact_segment is None:
            raise GeometryError(f"ground_contact needs a collision capsule on rod '{name}'; the MJCF has none")
        radius.append(float(rod.contact_radius))
        segment.append([list(map(float, e)) for e in rod.contact_segment])
    return {"radius": radius, "segment": segment, "ground_height": float(height), "normal": normal.tolist()}


def capsule_geometry(options: dict[str, Any], like: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The geometry of :func:`read_contact_geometry` as tensors in ``like``'s dtype and device:
    radius (R,), segment ends (R, 2, 3) in the rod frames, the plane's normal ``n`` and two tangents
    ``t1``, ``t2`` (3,), and its height."""
    t = lambda x: torch.as_tensor(np.asarray(x, dtype=float), dtype=like.dtype, device=like.device)
    # the plane's frame in numpy (no tensor-to-float inside a compiled step)
    n_np = np.asarray(options["normal"], dtype=float)
    a = np.array([1.0, 0, 0]) if abs(n_np[0]) < 0.9 else np.array([0, 1.0, 0])
    t1_np = np.cross(n_np, a)
    t1_np /= np.linalg.norm(t1_np)
    return (t(options["radius"]), t(options["segment"]), t(n_np), t(t1_np), t(np.cross(n_np, t1_np)),
            t(options["ground_height"]))


def shadow_frame(rot: Mat, n: tuple, t1: tuple) -> tuple[Vec, Vec, Vec]:
    """Each rod's contact frame in component form: the plane's normal ``n``, the unit vector along
    the rod's shadow on the plane (its axis less its normal part; ``t1`` where it stands upright)
    and ``n`` x that, from the rods' rotations ``rot`` (nine components (..., R))."""
    axis = (rot[2], rot[5], rot[8])
    an = vdot(axis, n)
    along = tuple(a - an * c for a, c in zip(axis, n))
    norm = torch.sqrt(vdot(along, along))
    inv = 1.0 / norm.clamp_min(1e-12)
    along = tuple(torch.where(norm > 1e-6, a * inv, t) for a, t in zip(along, t1))
    return n, along, vcross(n, along)


class CapsuleOnPlane(Effect):
    """What the ground-contact laws share: the rods' collision capsules on the MJCF's ground plane
    (:func:`read_contact_geometry`, geometry only), each capsule's end spheres and their depths."""

    phenomenon = "ground"

    @classmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> CapsuleOnPlane:
        if mjcf is None:
            raise GeometryError(f"{cls.name} needs the MJCF's geometry (capsules and ground plane)")
        return cls(topology.n_rods, topology.n_springs, options=read_contact_geometry(mjcf, topology.rod_names))

    # ------------------------------------------------------------------ geometry
    def _geom(self, like: torch.Tensor) -> tuple[torch.Tensor, ...]:
        key = ("geom", like.dtype, like.device)
        if key not in self._cache:
            self._cache[key] = capsule_geometry(self.options, like)
        return self._cache[key]

    def _end_spheres(self, state: Any, rot: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World centre (..., R, 2, 3) and penetration depth (..., R, 2) of every capsule end sphere."""
        radius, seg, n, _, _, height = self._geom(state.pos)
        centre = state.pos.unsqueeze(-2) + matrix_apply(rot.unsqueeze(-3), seg)
        return centre, radius.unsqueeze(-1) - ((centre * n).sum(-1) - height)

    def _geom_components(self, like: torch.Tensor) -> tuple[Any, ...]:
        """:meth:`_geom` for :meth:`wrench_components`: radius (R,), the two segment ends' rod-frame
        components, the plane's normal, first tangent (floats) and height."""
        key = ("geom_components", like.dtype, like.device)
        if key not in self._cache:
            radius, seg, n, t1, _, height = self._geom(like)
            self._cache[key] = (radius, [tuple(seg[:, e, k].contiguous() for k in range(3)) for e in range(2)],
                                tuple(float(x) for x in n), tuple(float(x) for x in t1), float(height))
        return self._cache[key]

    def rows_affected(self, state: Any, ctx: Any, margin: float = CONTACT_MARGIN) -> torch.Tensor:
        """Rods with an end sphere within ``margin`` of the ground (their equations hold contact forces)."""
        _, depth = self._end_spheres(state, ctx.rot)
        return (depth > -margin).any(-1)

    @property
    def torque_scale(self) -> float:
        """The capsules' mean half length (m): the fits divide residual torques by it to weigh them
        with the forces."""
        return float(np.mean([np.linalg.norm(np.asarray(s)[1] - np.asarray(s)[0]) for s in self.options["segment"]])) / 2


class GroundContact(CapsuleOnPlane):
    name = "ground_contact"
    description = ("rod capsules on a ground plane: constraint-like normal force, saturating friction, and "
                   "torsional and rolling friction torques")
    blocks = (
        ParamBlock("kappa", "global", mass_scaled=False, unit="1/s^2"),
        ParamBlock("beta_n", "global", mass_scaled=False, unit="1/s"),
        ParamBlock("gamma_n", "global", mass_scaled=False),
        ParamBlock("beta_a", "global", mass_scaled=False, unit="1/s"),
        ParamBlock("gamma_a", "global", mass_scaled=False),
        ParamBlock("beta_p", "global", mass_scaled=False, unit="1/s"),
        ParamBlock("gamma_p", "global", mass_scaled=False),
        ParamBlock("mu", "global", mass_scaled=False),
        ParamBlock("epsilon", "global", mass_scaled=False),
        ParamBlock("mu_torsion", "global", mass_scaled=False, unit="m"),
        ParamBlock("mu_rolling", "global", mass_scaled=False, unit="m"),
        ParamBlock("omega_slip", "global", mass_scaled=False, unit="rad/s"),
    )
    fit_strategy = "residual"
    needs_base_acceleration = True
    component_form = True
    region = "near_ground"
    profiled = ("epsilon", "omega_slip")  # profile scans (mu's is redone at every fit)
    fit_cost = 10.0  # its friction coefficient is scanned (measured ~12x a drag fit on the robot)


    def contacts(self, state: Any, ctx: Any) -> dict[str, torch.Tensor]:
        """Per end sphere (..., R, 2): depth, active, lever ρ (..., R, 2, 3); per rod the
        contact-space inverse effective-mass matrix of both ends, ``A`` (..., R, 6, 6), rows
        (end, direction) with directions (n, t1, t2), from the model's M and I."""
        _, _, n, t1, _, _ = self._geom(state.pos)
        rot = ctx.rot
        centre, depth = self._end_spheres(state, rot)
        # the force acts on the rod's axis at the end sphere's centre: with this law's independent
        # friction bound, a contact at the capsule's surface twists the rod about its own axis (the
        # small inertia M r²/2) more than the plant does; the surface point needs the friction
        # pyramid's shared normal force (``pyramid_contact``, which has both)
        lever = centre - state.pos.unsqueeze(-2)
        # friction axes per rod: along the rod's shadow on the ground (a) and across it (p); an end
        # cap rolls across its rod far more easily than it slides along it
        axis = rot[..., :, 2]
        along = axis - (axis * n).sum(-1, keepdim=True) * n
        norm = along.norm(dim=-1, keepdim=True)
        along = torch.where(norm > 1e-6, along / norm.clamp_min(1e-12), t1)
        across = torch.linalg.cross(n.expand_as(along), along)
        dirs = torch.stack((n.expand_as(along), along, across), -2).unsqueeze(-3).expand(lever.shape[:-1] + (3, 3))
        p = ctx.params
        com = getattr(p, "com", None)
        # the effective mass takes the lever from the centre of mass and the full inertia tensor
        rho = lever if com is None else lever - matrix_apply(rot.unsqueeze(-3), com.unsqueeze(-2))
        rxu = torch.linalg.cross(rho.unsqueeze(-2).expand_as(dirs), dirs)  # (..., R, 2, 3, 3)
        body = matrix_apply_transpose(rot.unsqueeze(-3).unsqueeze(-3), rxu)
        B = body.reshape(body.shape[:-3] + (6, 3))
        products = getattr(p, "inertia_products", None)
        j_inv = (torch.diag_embed(1.0 / p.inertia) if products is None else  # (..., R, 3, 3) rod frame
                 inverse3(unvec(inertia_matrix(vec(p.inertia), vec(products))).unflatten(-1, (3, 3))))
        eye = torch.eye(3, dtype=lever.dtype, device=lever.device).repeat(2, 2)
        A = eye / p.mass.unsqueeze(-1).unsqueeze(-1) + B @ j_inv @ B.transpose(-1, -2)  # J M⁻¹ Jᵀ
        return {"depth": depth, "active": depth > 0, "lever": lever, "A": A, "dirs": dirs}

    def _point_kinematics(self, state: Any, ctx: Any, c: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """Velocity and other-force acceleration of each contact point along (n, t1, t2): (..., R, 2, 3)."""
        lever = c["lever"]
        vel = state.vel.unsqueeze(-2) + torch.linalg.cross(state.angvel.unsqueeze(-2).expand_as(lever), lever)
        alpha_w = matrix_apply(ctx.rot, ctx.base_ang_acc_body)
        acc = ctx.base_lin_acc.unsqueeze(-2) + torch.linalg.cross(alpha_w.unsqueeze(-2).expand_as(lever), lever)
        dirs = c["dirs"]  # (..., R, 2, 3, 3)
        return (dirs * vel.unsqueeze(-2)).sum(-1), (dirs * acc.unsqueeze(-2)).sum(-1)

    @staticmethod
    def _inverse(A: torch.Tensor, active: torch.Tensor, eps: float | torch.Tensor) -> torch.Tensor:
        """``(A + ε diag A)⁻¹`` restricted to the active contacts of each rod (zero rows and columns
        elsewhere).  Two point contacts on one rod leave its spin about the line through them free:
        ``A`` is then singular, and the small regulariser ``ε`` (identified; as MuJoCo's own
        ``R``) picks the least-force solution.  The fit's form, on many instants at once (batched
        LAPACK); the twin's step solves the same system by 3x3 blocks (:func:`_masked_block_solve`)."""
        m = active.reshape(active.shape[:-1] + (2, 1)).expand(active.shape[:-1] + (2, 3))
        m = m.reshape(active.shape[:-1] + (6,)).to(A.dtype)  # (..., R, 6)
        mm = m.unsqueeze(-1) * m.unsqueeze(-2)
        d = torch.diagonal(A, dim1=-2, dim2=-1)
        Am = A * mm  # the inactive rows and columns the identity's, ε on the diagonal
        Am.diagonal(dim1=-2, dim2=-1).copy_((d + eps * d) * m + (1.0 - m))
        return torch.linalg.inv(Am) * mm

    def _references(self, state: Any, ctx: Any, c: dict) -> torch.Tensor:
        """Reference accelerations per unit of each linear parameter, (..., R, 2, 7, 3) contact frame."""
        v, a0 = self._point_kinematics(state, ctx, c)
        zero = torch.zeros_like(v[..., 0])
        return torch.stack([
            torch.stack((c["depth"], zero, zero), -1),
            torch.stack((-v[..., 0], zero, zero), -1),
            torch.stack((-a0[..., 0], zero, zero), -1),
            torch.stack((zero, -v[..., 1], zero), -1),
            torch.stack((zero, -a0[..., 1], zero), -1),
            torch.stack((zero, zero, -v[..., 2]), -1),
            torch.stack((zero, zero, -a0[..., 2]), -1),
        ], -2)

    @staticmethod
    def _apply(Ainv: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """``A⁻¹ g`` per rod: g (..., R, 2, [K,] 3) in (end, direction) -> forces of the same shape."""
        if g.dim() == Ainv.dim():  # (..., R, 2, 3)
            return (Ainv * g.reshape(g.shape[:-2] + (1, 6))).sum(-1).reshape(g.shape)
        K = g.shape[-2]
        flat = g.transpose(-2, -3).reshape(g.shape[:-3] + (K, 6))  # (..., R, K, 6)
        return (flat @ Ainv.transpose(-1, -2)).reshape(g.shape[:-3] + (K, 2, 3)).transpose(-2, -3)

    def _linear_terms(self, state: Any, ctx: Any, eps: float | None = None) -> tuple[dict, torch.Tensor]:
        """Force per unit of each linear parameter, per contact, in (n, t1, t2) components:
        (..., R, 2, 7, 3); zero where not in contact."""
        c = self.contacts(state, ctx)
        if eps is None:  # an unfitted law (a candidate's features): MuJoCo's default regulariser
            eps = self.theta(state.pos)[NL + 1] if self.values is not None else 0.05
        return c, self._apply(self._inverse(c["A"], c["active"], eps), self._references(state, ctx, c))

    def _to_wrench(self, c: dict, local: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Contact-frame forces, (..., R, 2, 3) or per parameter (..., R, 2, K, 3), to the rod force
        and WORLD torque about its centre of mass, (..., R, 3) or (..., R, K, 3)."""
        lever = c["lever"]
        if local.dim() == lever.dim():
            world = (local.unsqueeze(-1) * c["dirs"]).sum(-2)
        else:
            world = local @ c["dirs"]
        if local.dim() == lever.dim():
            return world.sum(-2), torch.linalg.cross(lever, world).sum(-2)
        torque = torch.linalg.cross(lever.unsqueeze(-2).expand_as(world), world)
        return world.sum(-3), torque.sum(-3)

    def features(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Force and torque per unit of the seven linear parameters (..., R, 7, 3); μ unbounded."""
        c, terms = self._linear_terms(state, ctx)
        return self._to_wrench(c, terms)

    def _unbounded(self, state: Any, ctx: Any, th: torch.Tensor) -> tuple[dict, torch.Tensor]:
        """The law before the friction bound: per contact (..., R, 2, 3), both ends of a rod solved
        together; an end whose normal force comes out pulling is released and the rod solved again."""
        c = self.contacts(state, ctx)
        g = (self._references(state, ctx, c) * th[:NL, None]).sum(-2)  # (..., R, 2, 3)
        raw = self._apply(self._inverse(c["A"], c["active"], th[NL + 1]), g)
        # solved again with the pulling ends released (always: no data-dependent branch, so the
        # twin's compiled step stays one graph)
        raw = self._apply(self._inverse(c["A"], c["active"] & (raw[..., 0] > 0), th[NL + 1]), g)
        return c, raw

    @staticmethod
    def _bound(raw: torch.Tensor, mu: torch.Tensor | float) -> torch.Tensor:
        """``f_n >= 0`` and ``|f_t| <= μ f_n`` on unbounded contact forces (..., 3)."""
        fn = raw[..., 0].clamp_min(0.0)
        ft = raw[..., 1:]
        norm = ft.norm(dim=-1).clamp_min(1e-12)
        ft = ft * torch.clamp(mu * fn / norm, max=1.0).unsqueeze(-1)
        return torch.cat((fn.unsqueeze(-1), ft), -1)

    def contact_forces(self, state: Any, ctx: Any, theta: torch.Tensor | None = None) -> tuple[dict, torch.Tensor]:
        """The law with its bounds: forces per contact in (n, t1, t2) components, (..., R, 2, 3)."""
        th = self.theta(state.pos) if theta is None else theta
        c, raw = self._unbounded(state, ctx, th)
        return c, self._bound(raw, th[NL])

    def wrench(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """The law's force and WORLD torque on each rod, (..., R, 3), for the engine's tensor form
        (the fit's rollouts, refinement, ``predict``, ``diagnose``): the fit's own formula,
        :meth:`contact_forces` then :meth:`_to_wrench` -- in eager torch on many instants its
        batched LAPACK solves cost a third of :meth:`wrench_components` (measured: a 5 x 1000-step
        robot rollout 2.0 s against 3.6 s).  The twin's compiled step calls
        :meth:`wrench_components`, the same law in component form (tests/test_twin_speed.py checks
        the two engine steps agree)."""
        c, f = self.contact_forces(state, ctx)
        force, torque = self._to_wrench(c, f)
        return force, torque + self.contact_torque(state, f, self.theta(state.pos))

    def contact_torque(self, state: Any, forces: torch.Tensor, th: torch.Tensor) -> torch.Tensor:
        """The torsional and rolling friction torques on each rod, WORLD (..., R, 3), from its
        contacts' bounded forces ``forces`` (..., R, 2, 3) (normal component first): module
        docstring, ``τ = -(Σ f_n) [μ_t tanh(ω_n / ω_s) n + μ_r tanh(|ω_t| / ω_s) ω_t / |ω_t|]``."""
        n = self._geom(state.pos)[2]
        return _friction_torque(forces[..., 0].sum(-1), state.angvel, n, th[..., I_TORSION],
                                th[..., I_ROLLING], th[..., I_OMEGA])

    def wrench_components(self, pos: Vec, vel: Vec, angvel: Vec, rot: Mat, base_lin_acc: Vec,
                          base_ang_acc_body: Vec, mass: torch.Tensor, inertia: Vec, com: Vec | None = None,
                          products: Vec | None = None) -> tuple[Vec, Vec]:
        """The law's force and WORLD torque on each rod in component form (every argument's
        components (..., R); ``mass``, ``inertia`` (the rod-frame diagonal about the centre of mass),
        ``com`` and ``products`` (``None``: 0) the identified rods'): the same law as
        :meth:`contact_forces` (then :meth:`_to_wrench`), which the fit uses, written for the
        engine's step with no per-parameter columns: the reference accelerations contracted as they
        are formed, ``J M⁻¹ Jᵀ`` as its four 3x3 blocks per rod, and the two masked 6x6 solves by
        3x3 blocks, all elementwise over rods and envs, which ``torch.compile`` fuses and
        vectorises (tests/test_twin_speed.py checks the two forms agree)."""
        # the cached tensor: a compiled step never converts ``values``; (P,), or (N, 1, P) bound
        # per environment (each env its own law, broadcast over its rods)
        th = self.theta(pos[0])
        radius, seg, n, t1, height = self._geom_components(pos[0])
        # friction axes per rod: along the rod's shadow on the ground (a) and across it (p)
        dirs = shadow_frame(rot, n, t1)  # rows n, a, p
        alpha_w = mv(rot, base_ang_acc_body)
        j_inv = None if products is None else minverse(inertia_matrix(inertia, products))
        levers, depths, bodies, scaled, refs = [], [], [], [], []
        for e in range(2):
            lever = mv(rot, seg[e])  # frame origin -> end-sphere centre
            depths.append(radius - (vdot(vadd(pos, lever), n) - height))
            # B_e (3 directions x 3 body axes) = Rᵀ (ρ_c × u), ρ_c from the centre of mass, and B_e J⁻¹
            rho = lever if com is None else mv(rot, vsub(seg[e], com))
            b = [mtv(rot, vcross(rho, d)) for d in dirs]
            bodies.append(tuple(x for row in b for x in row))
            scaled.append(tuple(x for row in b for x in (tuple(r / i for r, i in zip(row, inertia)) if j_inv is None
                                                         else mv(j_inv, row))))
            # reference accelerations g = κ d n - β v - γ a0 per direction, from the contact point's
            # velocity and its acceleration under every other force
            v = vadd(vel, vcross(angvel, lever))
            a0 = vadd(base_lin_acc, vcross(alpha_w, lever))
            refs.append(tuple(-(th[..., 1 + 2 * k] * vdot(d, v) + th[..., 2 + 2 * k] * vdot(d, a0)) for k, d in enumerate(dirs)))
            levers.append(lever)
        refs[0] = (refs[0][0] + th[..., 0] * depths[0], *refs[0][1:])
        refs[1] = (refs[1][0] + th[..., 0] * depths[1], *refs[1][1:])
        inv_m, eps = 1.0 / mass, th[..., NL + 1]

        def block(b: Mat, c: Mat, regularised: bool) -> Mat:  # E/M + B_b (J⁻¹ B_cᵀ) (ε on the diagonal)
            out = []
            for i in range(3):
                for j in range(3):
                    x = b[3 * i] * c[3 * j] + b[3 * i + 1] * c[3 * j + 1] + b[3 * i + 2] * c[3 * j + 2]
                    if i == j:
                        x = x + inv_m
                        x = x + eps * x if regularised else x
                    out.append(x)
            return tuple(out)

        P, Q, W = (block(bodies[0], scaled[0], True), block(bodies[0], scaled[1], False),
                   block(bodies[1], scaled[1], True))
        active = (depths[0] > 0, depths[1] > 0)
        raw = _masked_block_solve(P, Q, W, active, refs)
        # solved again with the pulling ends released (always: one graph)
        raw = _masked_block_solve(P, Q, W, (active[0] & (raw[0][0] > 0), active[1] & (raw[1][0] > 0)), refs)
        mu = th[..., NL]
        force: Vec = (0.0, 0.0, 0.0)
        torque: Vec = (0.0, 0.0, 0.0)
        fn_sum = 0.0
        for lever, (rn, ra, rp) in zip(levers, raw):
            # the bounds, as :meth:`_bound`: f_n >= 0, |f_t| <= μ f_n
            fn = rn.clamp_min(0.0)
            scale = torch.clamp(mu * fn / torch.sqrt(ra * ra + rp * rp).clamp_min(1e-12), max=1.0)
            world = tuple(fn * a + ra * scale * b + rp * scale * c for a, b, c in zip(*dirs))
            force, torque = vadd(force, world), vadd(torque, vcross(lever, world))
            fn_sum = fn_sum + fn
        # the torsional and rolling friction torques, as :meth:`contact_torque`
        w_n = vdot(angvel, n)
        w_t = tuple(w - w_n * c for w, c in zip(angvel, n))
        t_norm = torch.sqrt(vdot(w_t, w_t))
        inv_s = 1.0 / th[..., I_OMEGA]
        tors = -th[..., I_TORSION] * fn_sum * torch.tanh(w_n * inv_s)
        roll = -th[..., I_ROLLING] * fn_sum * torch.tanh(t_norm * inv_s) / t_norm.clamp_min(1e-12)
        torque = tuple(t + tors * c + roll * w for t, c, w in zip(torque, n, w_t))
        return force, torque

    def contact_point(self, state: Any, ctx: Any) -> torch.Tensor:
        """Each rod's contact point, the lever from its centre of mass (..., R, 3) world: the centre
        of its end sphere in contact (the mean of both when both are; 0 when none is), the point
        the law's forces act at.  The diagnosis and the torques' fit take torques about it."""
        c = self.contacts(state, ctx)
        active = c["active"].to(state.pos.dtype)  # (..., R, 2)
        return (active.unsqueeze(-1) * c["lever"]).sum(-2) / active.sum(-1).clamp_min(1.0).unsqueeze(-1)

    # ------------------------------------------------------------------ fit on the residual
    def fit_residual(self, state: Any, ctx: Any, force: torch.Tensor, torque: torch.Tensor,
                     groups: np.ndarray, rows: torch.Tensor) -> dict[str, Any]:
        """Least squares of the law on the residual wrench of the contact rows.

        ``force``/``torque`` (N, R, 3) world: the wrench the jointly fitted model leaves
        unexplained; ``rows`` (N, R) bool: the rod equations to use; ``groups`` (N,): the episode
        of each instant (cluster-robust standard errors).  Sets ``values``/``stderr`` and
        returns fit statistics.
        """
        # only the rod equations that touch: everything below runs on those, packed rod by rod
        sel = rows & (self._end_spheres(state, ctx.rot)[1] > 0).any(-1)
        law, state, ctx, force, torque, sel, groups = _pack_rows(self, state, ctx, force, torque, sel, groups)
        scale = self.torque_scale
        Yw = torch.cat((force, torque / scale), -1)[sel]  # (rows, 6)
        Y = Yw.reshape(-1).numpy()
        g = np.repeat(groups[sel.numpy()], 6)
        if Y.shape[0] < 50 * 6:
            raise ValueError("too few contact rows to identify ground_contact")
        # first the friction torques, on the residual torque about the contact point (the force
        # law's wrench has none there), then the force law on what they leave
        omegas = [float(self.options["omega_slip"])] if "omega_slip" in self.options else OMEGA_GRID
        with torch.no_grad():
            tq = _fit_torques(law, state, ctx, force, torque, sel, groups, omegas)
        spin = torch.cat((torch.zeros_like(tq["torque"]), tq["torque"] / scale), -1)  # (rows, 6)
        Yf = Yw - spin
        Y = Yf.reshape(-1).numpy()
        best = (np.inf, None, None, None, None)
        with torch.no_grad():
            grid = [float(self.options["epsilon"])] if "epsilon" in self.options else EPSILONS
            # the geometry and the reference accelerations do not depend on ε: formed once
            c = law.contacts(state, ctx)
            refs = law._references(state, ctx, c)  # (L, C, 2, 7, 3)
            for eps in grid:  # profile over the regulariser: a linear fit and a μ scan for each
                Ainv = self._inverse(c["A"], c["active"], eps)
                F, T = self._to_wrench(c, self._apply(Ainv, refs))  # (L, C, 7, 3)
                X = torch.cat((F, T / scale), -1)[sel].transpose(-1, -2).reshape(-1, NL).numpy()
                theta = np.linalg.lstsq(X, Y, rcond=None)[0]
                # the law before its bound (as :meth:`_unbounded`, with μ = 1 and this ε)
                gref = (refs * torch.as_tensor(theta, dtype=refs.dtype)[:, None]).sum(-2)
                raw = self._apply(Ainv, gref)
                raw = self._apply(self._inverse(c["A"], c["active"] & (raw[..., 0] > 0), eps), gref)
                sse, mu = _mu_scan(c, raw, sel, Yf, scale)
                if sse < best[0]:
                    best = (sse, theta, mu, eps, X)
        sse, theta, mu, eps, X = best
        cov = cluster_covariance(X, Y - X @ theta, g)
        self.values = np.concatenate([theta, [mu, eps], tq["values"]])
        # μ, ε and ω_s: profile scans, no standard error (null in the JSON)
        self.stderr = np.concatenate([np.sqrt(np.clip(np.diag(cov), 0, None)), [np.nan, np.nan], tq["stderr"], [np.nan]])
        Yall = Yw.reshape(-1).numpy()
        return {"rows": int(sel.sum()),
                "explained_variance": float(1 - sse / max(float(Yall @ Yall - len(Yall) * Yall.mean() ** 2), 1e-300)),
                "torque_explained_variance": tq["explained_variance"],
                "profile": (f"mu: scan over 0.05..3; epsilon: scan over {list(grid)}; omega_slip: scan over "
                            f"{list(omegas)} (no standard errors)")}

    def flatten(self, obj: dict[str, Any]) -> np.ndarray:
        """As :meth:`Effect.flatten`; a model file written before the contact torques (no
        ``mu_torsion``, ``mu_rolling``, ``omega_slip``) loads with none (:data:`TORQUE_DEFAULTS`)."""
        return super().flatten({**TORQUE_DEFAULTS, **obj} if "kappa" in obj else obj)


#: the context's per-rod fields (..., R, ·) that :func:`_pack_rows` gathers
_ROD_FIELDS = ("rot", "angvel_body", "push_force", "push_point", "base_lin_acc", "base_ang_acc_body",
               "recorded_lin_acc", "recorded_ang_acc_body")


def _pack_rows(eff: GroundContact, state: Any, ctx: Any, force: torch.Tensor, torque: torch.Tensor,
               sel: torch.Tensor, groups: np.ndarray
               ) -> tuple[GroundContact, Any, Any, torch.Tensor, torch.Tensor, torch.Tensor, np.ndarray]:
    """The selected rod equations ``sel`` (N, R) packed into columns of one rod each, (L, C): rod
    ``r``'s selected instants in order, cut into columns of ``L`` rows (the last padded with its
    first row), ``L`` a quarter of an even share (at most a fifth of the packed rows are padding).
    The law, elementwise over rows, then runs on the rows it is fitted to (on the robot a fifth
    of the rod equations touch the ground).  Each column is a rod of its own to the law: returns
    an effect of the columns' geometry, the packed state, the context with the columns' rod
    parameters and per-rod fields (:data:`_ROD_FIELDS`), the packed force and torque, the mask
    of the real rows (L, C) and each row's group from ``groups`` (N,), the instant's."""
    R = sel.shape[1]
    counts = [int(x) for x in sel.sum(0)]
    L = max(1, -(-sum(counts) // (4 * R)))
    rod, cols, real = [], [], []
    for r in range(R):
        t = torch.nonzero(sel[:, r]).flatten()
        for k in range(0, len(t), L):
            piece = t[k:k + L]
            real.append(torch.arange(L, device=sel.device) < len(piece))
            cols.append(torch.cat((piece, piece[:1].expand(L - len(piece)))))
            rod.append(r)
    if not rod:  # nothing selected: one empty column
        rod, cols, real = [0], [torch.zeros(L, dtype=torch.long, device=sel.device)], [torch.zeros(L, dtype=torch.bool)]
    idx, real = torch.stack(cols, -1), torch.stack(real, -1)  # (L, C)
    rods = torch.as_tensor(rod, device=sel.device)
    take = lambda x: None if x is None else x[idx, rods]
    state = type(state)(*(take(x) for x in state))
    ctx = ctx._replace(**{f: take(getattr(ctx, f)) for f in _ROD_FIELDS if getattr(ctx, f, None) is not None})
    p = ctx.params
    per_rod = {f: getattr(p, f)[..., rods] if f == "mass" else getattr(p, f)[..., rods, :]
               for f in ("mass", "inertia", "com", "inertia_products") if getattr(p, f, None) is not None}
    ctx = ctx._replace(params=replace(p, **per_rod))
    o = eff.options
    view = GroundContact(len(rod), eff.n_springs, options={
        **o, "radius": [o["radius"][r] for r in rod], "segment": [o["segment"][r] for r in rod]})
    return view, state, ctx, take(force), take(torque), real, np.asarray(groups)[idx.cpu().numpy()]


def _fit_torques(eff: GroundContact, state: Any, ctx: Any, force: torch.Tensor, torque: torch.Tensor,
                 sel: torch.Tensor, groups: np.ndarray, omegas: Any) -> dict[str, Any]:
    """The friction torques' least squares (``μ_t``, ``μ_r`` >= 0; ``ω_s`` by a profile scan) on
    the residual torque about each rod's contact point: the residual torque ``torque`` less the
    contact point's lever times the residual force ``force`` ((N, R, 3) world; the point: the
    centre of its end sphere in contact, the mean of both when both are).  Every force at the
    contact point (the force law's) leaves no torque about it: what stays is a pure torque, which
    only the friction torques explain, and the normal force they scale with is the residual force's
    normal component (the contact's, the only normal force the model lacks).  Returns the values
    ``[μ_t, μ_r, ω_s]``, the standard errors of ``μ_t``, ``μ_r`` (cluster-robust over ``groups``,
    the episode of each instant; none for a coefficient at its bound), the explained variance of
    that torque and the fitted torques on the rows ``sel`` (rows, 3)."""
    about = torque - torch.linalg.cross(eff.contact_point(state, ctx), force)
    n = eff._geom(state.pos)[2]
    y = about[sel].reshape(-1).numpy()
    fn = (force[sel] * n).sum(-1).clamp_min(0.0)
    w = state.angvel[sel]
    one = torch.ones((), dtype=w.dtype)
    best: tuple = (np.inf,)
    for om in omegas:
        X = torch.stack([_friction_torque(fn, w, n, one, 0 * one, om * one),
                         _friction_torque(fn, w, n, 0 * one, one, om * one)], -1).reshape(-1, 2).numpy()
        coef = _nonnegative_lstsq(X, y)
        sse = float(((y - X @ coef) ** 2).sum())
        if sse < best[0]:
            best = (sse, coef, om, X)
    sse, coef, om, X = best
    g = np.repeat(groups[sel.numpy()], 3)
    free = coef > 0  # a coefficient held at its bound has no standard error
    se = np.full(2, np.nan)
    if free.any():
        se[free] = np.sqrt(np.clip(np.diag(cluster_covariance(X[:, free], y - X @ coef, g)), 0, None))
    return {"values": np.array([coef[0], coef[1], om]), "stderr": se,
            "torque": torch.as_tensor((X @ coef).reshape(-1, 3)),
            "explained_variance": float(1 - sse / max(float(y @ y), 1e-300))}


def _nonnegative_lstsq(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares with every coefficient >= 0, for a few columns: the best of the unconstrained
    solutions on every subset of the columns whose coefficients come out non-negative."""
    from itertools import combinations

    k = X.shape[1]
    best, out = np.inf, np.zeros(k)
    for size in range(k + 1):
        for cols in combinations(range(k), size):
            coef = np.zeros(k)
            if cols:
                coef[list(cols)] = np.linalg.lstsq(X[:, cols], y, rcond=None)[0]
            if (coef < 0).any():
                continue
            sse = float(((y - X @ coef) ** 2).sum())
            if sse < best:
                best, out = sse, coef
    return out


def _friction_torque(fn: torch.Tensor, angvel: torch.Tensor, n: torch.Tensor, mu_t: Any, mu_r: Any,
                     omega: Any) -> torch.Tensor:
    """``-f_n [μ_t tanh(ω_n / ω_s) n + μ_r tanh(|ω_t| / ω_s) ω_t / |ω_t|]`` (..., 3), the friction
    torques of a rod with total normal force ``fn`` (...,) and world angular velocity ``angvel``
    (..., 3) on a plane of normal ``n``: ``ω_n = ω·n`` its spin about the normal, ``ω_t`` the rest
    (rolling).  The parameters broadcast against ``fn``."""
    w_n = (angvel * n).sum(-1)
    w_t = angvel - w_n.unsqueeze(-1) * n
    t_norm = w_t.norm(dim=-1)
    tors = -mu_t * fn * torch.tanh(w_n / omega)
    roll = -mu_r * fn * torch.tanh(t_norm / omega) / t_norm.clamp_min(1e-12)
    return tors.unsqueeze(-1) * n + roll.unsqueeze(-1) * w_t


def _mu_scan(c: dict, raw: torch.Tensor, sel: torch.Tensor, target: torch.Tensor, scale: float,
             mus: np.ndarray = MU_GRID) -> tuple[float, float]:
    """The friction coefficient of the grid whose bounded law (:meth:`GroundContact._bound`)
    leaves the least squared residual wrench on the rows ``sel``: (sse, μ).

    The bound scales each contact's unbounded tangential force by ``s = min(1, μ f_n / |f_t|)``,
    so each end's wrench is that of its normal force plus ``s`` times that of its tangential force:
    both are formed once and every μ costs a few elementwise operations on the selected rows."""
    lever, dirs, raw = c["lever"][sel], c["dirs"][sel], raw[sel]  # (S, 2, 3), (S, 2, 3, 3), (S, 2, 3)
    fn = raw[..., 0].clamp_min(0.0)
    tnorm = raw[..., 1:].norm(dim=-1).clamp_min(1e-12)

    def end_wrench(local: torch.Tensor) -> torch.Tensor:  # (S, 2, 3) contact frame -> (S, 2, 6)
        world = (local.unsqueeze(-1) * dirs).sum(-2)
        return torch.cat((world, torch.linalg.cross(lever, world) / scale), -1)

    zero = torch.zeros_like(fn)
    w_n = end_wrench(torch.stack((fn, zero, zero), -1))
    w_t = end_wrench(torch.cat((zero.unsqueeze(-1), raw[..., 1:]), -1))
    base = target - w_n.sum(-2)  # (S, 6)
    # the squared residual |base - s_0 w_0 - s_1 w_1|² expanded: its products formed once, each μ
    # costs a few operations on (S, 2) scalars
    bb = float((base * base).sum())
    bw = (base.unsqueeze(-2) * w_t).sum(-1)  # (S, 2)
    ww = (w_t * w_t).sum(-1)  # (S, 2)
    w01 = (w_t[:, 0] * w_t[:, 1]).sum(-1)  # (S,)
    best = (np.inf, float(mus[0]))
    for mu in mus:
        s = torch.clamp(float(mu) * fn / tnorm, max=1.0)  # (S, 2)
        sse = bb + float((s * (s * ww - 2.0 * bw)).sum() + 2.0 * (s[:, 0] * s[:, 1] * w01).sum())
        if sse < best[0]:
            best = (sse, float(mu))
    return best


def _masked_block_solve(P: Mat, Q: Mat, W: Mat, active: tuple[torch.Tensor, torch.Tensor],
                        g: list) -> tuple[Vec, Vec]:
    """``x = A⁻¹ g`` restricted to the active ends (as :meth:`GroundContact._inverse` then
    :meth:`GroundContact._apply`), for ``A = [[P, Q], [Qᵀ, W]]`` symmetric, by 3x3 blocks, in
    component form.

    ``P``, ``Q``, ``W`` nine components (..., R) each; ``active`` two (..., R) bool; ``g`` the
    two ends' reference accelerations (three components each) -> the two ends' forces, zero at
    inactive ends.  An inactive end's rows and columns are replaced by the identity's (its
    unknowns decouple and are zeroed)."""
    m0, m1 = (a.to(P[0].dtype) for a in active)
    eye = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    Pm = tuple(m0 * x + (1.0 - m0) * i for x, i in zip(P, eye))
    Qm = tuple((m0 * m1) * x for x in Q)
    Wm = tuple(m1 * x + (1.0 - m1) * i for x, i in zip(W, eye))
    g0, g1 = vscale(g[0], m0), vscale(g[1], m1)
    Pi = minverse(Pm)
    X = mmul(Pi, Qm)  # P⁻¹ Q; (Qᵀ P⁻¹) = Xᵀ, P symmetric
    Si = minverse(tuple(w - x for w, x in zip(Wm, mmul(mtranspose(Qm), X))))
    x1 = mv(Si, vsub(g1, mtv(X, g0)))
    x0 = mv(Pi, vsub(g0, mv(Qm, x1)))
    return vscale(x0, m0), vscale(x1, m1)


def cluster_covariance(X: np.ndarray, r: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Cluster-robust (sandwich) covariance of least squares, clusters = episodes."""
    XtX_inv = np.linalg.pinv(X.T @ X)
    meat = np.zeros((X.shape[1], X.shape[1]))
    for gid in np.unique(groups):
        m = groups == gid
        s = X[m].T @ r[m]
        meat += np.outer(s, s)
    G = len(np.unique(groups))
    corr = G / max(G - 1, 1)
    return corr * XtX_inv @ meat @ XtX_inv

