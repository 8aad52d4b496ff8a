"""The differentiable spring-rod engine (identified.engine) against known truth:
gradients (gradcheck), conservation laws, analytic solutions and MuJoCo itself."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from identified.engine import (
    RodState,
    SpringGraph,
    SpringRodEngine,
    SpringRodParams,
    StepContext,
    endpoint_kinematics,
    push_wrench,
    rod_accelerations,
    rod_wrench,
    semi_implicit_euler,
    spring_end_forces,
    spring_geometry,
    spring_tension,
)
from identified.rotation import matrix_apply, matrix_apply_transpose, quat_to_matrix
from identified.topology import Topology

F64 = torch.float64
ROD_LENGTH = 1.0


# ---------------------------------------------------------------------- a test system, as MJCF
def make_mjcf(
    rod_pos: np.ndarray,
    mass: np.ndarray,
    inertia: np.ndarray,
    springs: list[tuple[str, str, str, float, bool, float, float]],
    anchors: dict[str, tuple[float, float, float]] | None = None,
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81),
    dt: float = 1e-3,
    rod_quat: np.ndarray | None = None,
    rod_length: float = ROD_LENGTH,
    integrator: str = "Euler",
) -> str:
    """MJCF following the project's conventions: rods ``rod{i}`` (free joint, explicit inertial, axis =
    body z, sites ``rod{i}_end0/1`` at z = ∓L/2), springs = spatial tendons between sites
    ``(name, site0, site1, rest, pull_only, K, c)``, no contacts, Euler integrator by default."""
    def f(x) -> str:
        return " ".join(repr(float(v)) for v in np.atleast_1d(x))

    h = rod_length / 2
    world = "".join(f'<site name="{n}" pos="{f(p)}"/>' for n, p in (anchors or {}).items())
    for i in range(len(mass)):
        quat = "" if rod_quat is None else f' quat="{f(rod_quat[i])}"'
        world += (
            f'<body name="rod{i}" pos="{f(rod_pos[i])}"{quat}><freejoint/>'
            f'<inertial pos="0 0 0" mass="{f(mass[i])}" diaginertia="{f(inertia[i])}"/>'
            f'<geom type="capsule" fromto="0 0 {-h} 0 0 {h}" size="0.01" contype="0" conaffinity="0"/>'
            f'<site name="rod{i}_end0" pos="0 0 {-h}"/><site name="rod{i}_end1" pos="0 0 {h}"/></body>'
        )
    tendons = ""
    for name, a, b, rest, pull, k, c in springs:
        length = f"0 {rest!r}" if pull else repr(float(rest))
        tendons += (f'<spatial name="{name}" stiffness="{f(k)}" damping="{f(c)}" springlength="{length}">'
                    f'<site site="{a}"/><site site="{b}"/></spatial>')
    return (f'<mujoco><option timestep="{dt!r}" integrator="{integrator}" gravity="{f(gravity)}"/>'
            f"<worldbody>{world}</worldbody><tendon>{tendons}</tendon></mujoco>")


def random_rods(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Masses and rod-like diagonal inertias (Ixx ≈ Iyy >> Izz, satisfying the triangle rule)."""
    mass = rng.uniform(1.0, 5.0, n)
    inertia = np.stack([rng.uniform(0.30, 0.32, n), rng.uniform(0.30, 0.32, n), rng.uniform(0.02, 0.05, n)], 1)
    return mass, inertia


def system(rng: np.random.Generator, gravity=(0.0, 0.0, -9.81), integrator: str = "Euler"):
    """Three rods, plain springs between rods, a taut-and-slack pull-only cable, a fixed anchor."""
    mass, inertia = random_rods(rng, 3)
    k = rng.uniform(50, 150, 6)
    c = rng.uniform(1, 5, 6)
    springs = [
        ("s0", "rod0_end0", "rod1_end0", 0.8, False, k[0], c[0]),
        ("s1", "rod1_end1", "rod2_end1", 0.9, False, k[1], c[1]),
        ("s2", "rod2_end0", "rod0_end1", 0.7, False, k[2], c[2]),
        ("c0", "rod0_end1", "rod1_end1", 0.65, True, k[3], c[3]),
        ("c1", "rod1_end0", "rod2_end0", 0.75, True, k[4], c[4]),
        ("a0", "nail", "rod2_end1", 0.5, False, k[5], c[5]),
    ]
    pos = np.array([[0.0, 0.0, 1.0], [0.6, 0.2, 1.1], [0.3, 0.5, 0.9]])
    xml = make_mjcf(pos, mass, inertia, springs, anchors={"nail": (0.2, 0.1, 2.0)}, gravity=gravity,
                    integrator=integrator)
    params = SpringRodParams.from_values(k, c, mass, inertia, 1.0, gravity, n_rods=3, n_springs=6)
    rest = np.array([s[3] for s in springs])
    return xml, params, rest, pos


def random_state(rng: np.random.Generator, pos: np.ndarray, vel_std=1.0, angvel_std=3.0) -> RodState:
    n = len(pos)
    quat = Rotation.random(n, random_state=int(rng.integers(1 << 31))).as_quat(scalar_first=True)
    return RodState(*(torch.as_tensor(x, dtype=F64) for x in (
        pos + rng.normal(0, 0.05, pos.shape), quat, rng.normal(0, vel_std, (n, 3)), rng.normal(0, angvel_std, (n, 3)))))


def mujoco_states(qpos: np.ndarray, qvel: np.ndarray, n_rods: int) -> RodState:
    """Free-joint qpos/qvel (..., 7R)/(..., 6R) -> RodState with WORLD angular velocity."""
    qp = qpos.reshape(qpos.shape[:-1] + (n_rods, 7))
    qv = qvel.reshape(qvel.shape[:-1] + (n_rods, 6))
    rot = Rotation.from_quat(qp[..., 3:].reshape(-1, 4), scalar_first=True).as_matrix()
    w = np.einsum("nab,nb->na", rot, qv[..., 3:].reshape(-1, 3)).reshape(qv[..., 3:].shape)
    return RodState(*(torch.as_tensor(np.ascontiguousarray(x), dtype=F64)
                      for x in (qp[..., :3], qp[..., 3:], qv[..., :3], w)))


def set_mujoco_state(data: mujoco.MjData, state: RodState) -> None:
    n = state.pos.shape[-2]
    for i in range(n):
        q = state.quat[i].numpy()
        rot = Rotation.from_quat(q, scalar_first=True).as_matrix()
        data.qpos[7 * i: 7 * i + 7] = np.concatenate([state.pos[i].numpy(), q])
        data.qvel[6 * i: 6 * i + 6] = np.concatenate([state.vel[i].numpy(), rot.T @ state.angvel[i].numpy()])


def energy(engine: SpringRodEngine, states: RodState, rest: torch.Tensor) -> torch.Tensor:
    """Kinetic + rotational + spring energy of (..., R, ·) states (no gravity, no dead bands)."""
    p = engine.params
    rot = quat_to_matrix(states.quat)
    w_b = matrix_apply_transpose(rot, states.angvel)
    kin = 0.5 * (p.mass * (states.vel ** 2).sum(-1)).sum(-1)
    rot_e = 0.5 * (p.inertia * w_b ** 2).sum(-1).sum(-1)
    geo = spring_geometry(endpoint_kinematics(engine.graph, *states))
    pot = 0.5 * (p.stiffness * (geo.length - rest) ** 2).sum(-1)
    return kin + rot_e + pot


# ---------------------------------------------------------------------- gradients
def small_system():
    """Two rods: a rod-rod spring, an anchored spring, a taut cable and a slack cable."""
    graph = SpringGraph.from_arrays(
        2,
        np.array([[0, 1], [-1, 0], [0, 1], [1, 0]]),
        np.array([
            [[0, 0, 0.5], [0, 0, -0.5]],
            [[0.0, 0.0, 2.0], [0, 0, -0.5]],
            [[0, 0, -0.5], [0, 0, 0.5]],
            [[0, 0, -0.5], [0, 0, 0.5]],
        ]),
        np.array([False, False, True, True]),
    )
    rest = torch.tensor([0.5, 0.8, 0.3, 5.0], dtype=F64)  # cable 2 taut, cable 3 slack
    state = RodState(
        torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.4, 1.2]], dtype=F64),
        torch.as_tensor(Rotation.random(2, random_state=3).as_quat(scalar_first=True), dtype=F64),
        torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.2, -0.1]], dtype=F64),
        torch.tensor([[1.0, -0.5, 2.0], [0.3, 0.8, -1.2]], dtype=F64),
    )
    params = SpringRodParams.from_values([80.0, 120.0, 60.0, 90.0], [2.0, 3.0, 1.5, 2.5], [2.0, 3.0],
                                         [[0.3, 0.31, 0.04], [0.29, 0.3, 0.03]], 1.3, (0.0, 0.0, -9.81))
    return graph, rest, state, params


def test_small_system_exercises_both_sides_of_the_dead_band():
    graph, rest, state, _ = small_system()
    geo = spring_geometry(endpoint_kinematics(graph, *state))
    assert geo.length[2] - rest[2] > 0.1 and geo.length[3] - rest[3] < -0.1


def test_gradcheck_force_generation():
    graph, rest, state, p = small_system()

    def forces(pos, quat, vel, angvel, rest, k, c):
        ends = endpoint_kinematics(graph, pos, quat, vel, angvel)
        geo = spring_geometry(ends)
        t = spring_tension(geo.length, geo.rate, rest, k, c, graph.pull_only)
        return spring_end_forces(geo.unit, t), ends.lever, t

    inputs = tuple(x.clone().requires_grad_() for x in (*state, rest, p.stiffness, p.damping))
    assert torch.autograd.gradcheck(forces, inputs)


def test_gradcheck_acceleration_generation():
    graph, _, state, p = small_system()
    rng = np.random.default_rng(0)
    end_forces = torch.as_tensor(rng.normal(0, 5, (4, 2, 3)))
    lever = torch.as_tensor(rng.normal(0, 0.5, (4, 2, 3)))
    fu = torch.as_tensor(rng.normal(0, 5, (2, 3)))
    ru = torch.as_tensor(rng.normal(0, 0.3, (2, 3)))

    def acc(end_forces, lever, quat, angvel, fu, ru, h, mass, inertia, gravity):
        rot = quat_to_matrix(quat)
        f, tau = rod_wrench(graph, end_forces, lever)
        pf, pt = push_wrench(rot, fu, ru, h)
        return rod_accelerations(f + pf, tau + pt, rot, matrix_apply_transpose(rot, angvel), mass, inertia, gravity)

    inputs = tuple(x.clone().requires_grad_() for x in (
        end_forces, lever, state.quat, state.angvel, fu, ru, p.control_scale, p.mass, p.inertia, p.gravity))
    assert torch.autograd.gradcheck(acc, inputs)


@pytest.mark.parametrize("angvel_scale", [1.0, 0.0])
def test_gradcheck_integration(angvel_scale):
    _, _, state, _ = small_system()
    rng = np.random.default_rng(1)
    a = torch.as_tensor(rng.normal(0, 1, (2, 3)))
    alpha = torch.as_tensor(rng.normal(0, 1, (2, 3)))
    w_b = angvel_scale * torch.as_tensor(rng.normal(0, 2, (2, 3)))

    def integrate(pos, quat, vel, w_b, a, alpha):
        return tuple(semi_implicit_euler(pos, quat, vel, w_b, a, alpha, 0.01))

    inputs = tuple(x.clone().requires_grad_() for x in (state.pos, state.quat, state.vel, w_b, a, alpha))
    if angvel_scale == 0.0:  # θ = dt (w_b + dt α) exactly 0: the small-angle branch
        inputs[5].data.zero_()
    assert torch.autograd.gradcheck(integrate, inputs)


@pytest.mark.parametrize("integrator", ["euler", "implicit", "rk4"])
def test_gradcheck_five_step_rollout_wrt_parameters_and_initial_state(integrator):
    graph, rest, state, p = small_system()
    T = 5
    rng = np.random.default_rng(2)
    rests = rest.expand(T, -1).clone()
    fu = torch.as_tensor(rng.normal(0, 3, (T, 2, 3)))
    ru = torch.as_tensor(rng.normal(0, 0.3, (T, 2, 3)))

    def roll(pos, quat, vel, angvel, k, c, m, inertia, h, g):
        params = SpringRodParams(k, c, m, inertia, h, g)
        eng = SpringRodEngine(graph, params, dt=0.01, integrator=integrator)
        return tuple(x[-1] for x in eng.rollout(RodState(pos, quat, vel, angvel), rests, fu, ru))

    inputs = tuple(x.clone().requires_grad_() for x in (*state, *p.as_dict().values()))
    assert torch.autograd.gradcheck(roll, inputs)


def test_parameters_are_trainable_tensors():
    graph, rest, state, _ = small_system()
    p = SpringRodParams.from_values(100.0, 2.0, 3.0, [0.3, 0.3, 0.03], n_rods=2, n_springs=4).requires_grad_(
        names=["stiffness", "mass"])
    assert p.stiffness.shape == (4,) and p.inertia.shape == (2, 3) and p.control_scale.shape == ()
    assert [t.shape for t in p.parameters()] == [(4,), (2,)]
    eng = SpringRodEngine(graph, p, dt=0.01)
    out = eng.rollout(state, rest.expand(3, -1))
    out.pos[-1].sum().backward()
    assert p.stiffness.grad is not None and torch.all(torch.isfinite(p.stiffness.grad))
    assert p.mass.grad is not None and p.damping.grad is None
    with pytest.raises(ValueError, match="stiffness"):
        SpringRodEngine(graph, SpringRodParams.from_values([1.0] * 3, 1.0, 1.0, [0.3, 0.3, 0.03],
                                                           n_rods=2), dt=0.01)


# ---------------------------------------------------------------------- conservation
def free_system(rng):
    """Three rods held together by eight plain springs between rods only: no anchors, no cables."""
    mass, inertia = random_rods(rng, 3)
    pairs = [(0, 0, 1, 0), (0, 1, 1, 1), (1, 0, 2, 0), (1, 1, 2, 1), (2, 0, 0, 1), (2, 1, 0, 0), (0, 0, 2, 1),
             (1, 1, 0, 1)]
    k = rng.uniform(50, 150, len(pairs))
    pos = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.1], [0.25, 0.45, -0.1]])
    xml_springs = [(f"s{n}", f"rod{a}_end{ea}", f"rod{b}_end{eb}", 0.6, False, k[n], 0.0)
                   for n, (a, ea, b, eb) in enumerate(pairs)]
    topo = Topology.from_mjcf(make_mjcf(pos, mass, inertia, xml_springs, gravity=(0, 0, 0)))
    params = SpringRodParams.from_values(k, 0.0, mass, inertia, 1.0, (0.0, 0.0, 0.0), n_rods=3,
                                         n_springs=len(pairs))
    return topo, params, pos


def test_free_system_conserves_momentum_and_energy():
    rng = np.random.default_rng(10)
    topo, params, pos = free_system(rng)
    T = 2000  # 2 s at dt = 1e-3
    err_e, err_l = {}, {}
    for dt in (2e-3, 1e-3):
        eng = SpringRodEngine(topo, params, dt=dt)
        state = random_state(np.random.default_rng(11), pos, vel_std=0.5, angvel_std=2.0)
        n = round(T * 1e-3 / dt)
        rest = torch.full((n, topo.n_springs), 0.6, dtype=F64)
        traj = eng.rollout(state, rest)
        e = energy(eng, traj, rest[0])
        err_e[dt] = float((e - e[0]).abs().max() / e[0])

        # linear momentum: internal forces cancel pairwise -> exact up to rounding
        mom = (params.mass[:, None] * traj.vel).sum(-2)
        assert (mom - mom[0]).abs().max() < 1e-12
        # angular momentum about the origin (orbital + spin R I w_b): the spring torques cancel
        # exactly, the explicit gyroscopic term and the rotation update leave an O(dt) error
        rot = quat_to_matrix(traj.quat)
        spin = matrix_apply(rot, params.inertia * matrix_apply_transpose(rot, traj.angvel))
        ang = (torch.cross(traj.pos, params.mass[:, None] * traj.vel, dim=-1) + spin).sum(-2)
        err_l[dt] = float((ang - ang[0]).norm(dim=-1).max() / ang[0].norm())
        # the system really moved: springs exchanged a large part of the energy
        geo = spring_geometry(endpoint_kinematics(eng.graph, *traj))
        assert (0.5 * params.stiffness * (geo.length - 0.6) ** 2).sum(-1).max() > 0.05 * e[0]
    # energy and angular momentum errors are small, bounded and first order in dt (no O(1) drift)
    assert err_e[1e-3] < 1e-2 and err_l[1e-3] < 1e-2
    assert 1.5 < err_e[2e-3] / err_e[1e-3] < 3.0
    assert 1.4 < err_l[2e-3] / err_l[1e-3] < 3.0


# ---------------------------------------------------------------------- analytic
def axial_oscillator(k=100.0, c=1.0, m=10.0, dt=1e-3, gap=0.5):
    """One rod along world x (body z rotated onto x) between two anchors on its axis."""
    q = np.array([math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0])  # z -> x
    h = ROD_LENGTH / 2
    anchors = {"left": (-(h + gap), 0.0, 0.0), "right": (h + gap, 0.0, 0.0)}
    springs = [("l", "left", "rod0_end0", gap, False, k, c), ("r", "rod0_end1", "right", gap, False, k, c)]
    xml = make_mjcf(np.zeros((1, 3)), np.array([m]), np.array([[0.4, 0.4, 0.05]]), springs, anchors=anchors,
                    gravity=(0, 0, 0), rod_quat=q[None])
    params = SpringRodParams.from_values(k, c, m, [0.4, 0.4, 0.05], 0.7, (0, 0, 0), n_rods=1, n_springs=2)
    return SpringRodEngine(Topology.from_mjcf(xml), params, dt), q


def test_axial_oscillator_matches_analytic_damped_oscillator():
    k, c, m, dt, x0 = 400.0, 1.0, 10.0, 1e-3, 0.1
    eng, q = axial_oscillator(k, c, m, dt)
    state = eng.state([[x0, 0, 0]], [q], [[0, 0, 0]], [[0, 0, 0]])
    T = 3000
    traj = eng.rollout(state, torch.full((T, 2), 0.5, dtype=F64))
    x = traj.pos[:, 0, 0].numpy()
    t = np.arange(T + 1) * dt
    # m x'' = -2k x - 2c x'  ->  w0² = 2k/m, decay rate g = c/m
    w0, g = math.sqrt(2 * k / m), c / m
    wd = math.sqrt(w0 ** 2 - g ** 2)
    exact = np.exp(-g * t) * (x0 * np.cos(wd * t) + g * x0 / wd * np.sin(wd * t))
    assert np.abs(x - exact).max() < 5e-3 * x0  # semi-implicit Euler: O(dt) phase lag only
    # frequency from the zero crossings (linear interpolation)
    i = np.flatnonzero(np.sign(x[:-1]) != np.sign(x[1:]))
    tz = t[i] - x[i] * dt / (x[i + 1] - x[i])
    assert len(tz) >= 8
    w_measured = math.pi / np.mean(np.diff(tz))
    assert abs(w_measured / wd - 1) < 1e-4
    # the motion stays on the axis: no transverse motion, no rotation
    assert traj.pos[:, 0, 1:].abs().max() < 1e-12 and traj.angvel.abs().max() < 1e-12


def test_push_at_com_gives_h_f_dt_over_m():
    eng, q = axial_oscillator()
    state = eng.state([[0.0, 0, 0]], [q], [[0, 0, 0]], [[0, 0, 0]])
    f = torch.tensor([[3.0, -4.0, 5.0]], dtype=F64)
    h, m, dt = 0.7, 10.0, eng.dt
    for point in (None, torch.zeros(1, 3, dtype=F64)):
        nxt = eng.step(state, torch.full((2,), 0.5, dtype=F64), f, point)
        np.testing.assert_allclose(nxt.vel.numpy(), (h * f * dt / m).numpy(), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(nxt.pos.numpy(), (h * f * dt * dt / m).numpy(), rtol=1e-12, atol=1e-14)
        assert nxt.angvel.abs().max() < 1e-14


def test_push_off_com_gives_torque():
    eng, q = axial_oscillator()
    state = eng.state([[0.0, 0, 0]], [q], [[0, 0, 0]], [[0, 0, 0]])
    f = torch.tensor([[0.0, 2.0, 0.0]], dtype=F64)  # sideways
    r = torch.tensor([[0.0, 0.0, 0.5]], dtype=F64)  # at the rod's end 1 (world +x)
    nxt = eng.step(state, torch.full((2,), 0.5, dtype=F64), f, r)
    h, dt, izz_world = 0.7, eng.dt, 0.4  # rotation about world z = a transverse rod axis
    np.testing.assert_allclose(nxt.vel.numpy(), (h * f * dt / 10.0).numpy(), rtol=1e-12, atol=1e-15)
    # torque = (0.5 x̂) × (2 ŷ) h = h ẑ ; Δw = dt h / I
    np.testing.assert_allclose(nxt.angvel.numpy(), [[0.0, 0.0, dt * h / izz_world]], atol=1e-14)


# ---------------------------------------------------------------------- MuJoCo
def run_mujoco(xml: str, state0: RodState, steps: int, rng: np.random.Generator | None, rest_fn=None):
    """Step MuJoCo (on the model's integrator) from ``state0``.

    ``rest_fn(t, tendon_length) -> (S,)``, if given, sets every tendon's rest length before step ``t``
    (written to ``tendon_lengthspring``, as an actuated cable's motor does).  With ``rng``: random
    pushes at random rod points via xfrc_applied (force at the COM plus torque (R r) × f).
    Returns qpos, qvel (T+1, ·), rest lengths (T, S), pushes f, r (T, R, 3).
    """
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    pull_only = m.tendon_lengthspring[:, 0] < m.tendon_lengthspring[:, 1]
    set_mujoco_state(d, state0)
    n = state0.pos.shape[-2]
    qpos, qvel = np.zeros((steps + 1, m.nq)), np.zeros((steps + 1, m.nv))
    rests = np.zeros((steps, m.ntendon))
    fu, ru = np.zeros((steps, n, 3)), np.zeros((steps, n, 3))
    for t in range(steps):
        qpos[t], qvel[t] = d.qpos, d.qvel
        if rest_fn is not None:
            mujoco.mj_fwdPosition(m, d)
            m.tendon_lengthspring[:, 1] = rest_fn(t, d.ten_length.copy())
            m.tendon_lengthspring[:, 0] = np.where(pull_only, 0.0, m.tendon_lengthspring[:, 1])
        rests[t] = m.tendon_lengthspring[:, 1]
        if rng is not None:
            fu[t] = rng.normal(0, 20, (n, 3))
            ru[t] = rng.normal(0, 0.3, (n, 3))
            for i in range(n):
                rot = Rotation.from_quat(d.qpos[7 * i + 3: 7 * i + 7], scalar_first=True).as_matrix()
                body = m.body(f"rod{i}").id
                d.xfrc_applied[body, :3] = fu[t, i]
                d.xfrc_applied[body, 3:] = np.cross(rot @ ru[t, i], fu[t, i])
        mujoco.mj_step(m, d)
    qpos[steps], qvel[steps] = d.qpos, d.qvel
    return qpos, qvel, rests, fu, ru


def cable_motor(rest: np.ndarray, dt: float):
    """Rest lengths as motors would drive them: the springs (0-2, 5) fixed; the two cables (3, 4)
    follow their current length -/+ 2 %, alternating every 50 ms, so they go taut and slack."""
    def fn(t: int, length: np.ndarray) -> np.ndarray:
        out = rest.copy()
        sign = 1.0 if (t * dt) % 0.1 < 0.05 else -1.0
        out[3:5] = length[3:5] * (1.0 - sign * np.array([0.02, -0.02]))
        return out
    return fn


@pytest.mark.parametrize(("pushes", "plant", "integrator"), [
    (False, "Euler", "euler"), (True, "Euler", "euler"),
    (True, "implicitfast", "implicit"), (True, "implicit", "implicit"),
], ids=["free", "pushed", "implicitfast-pushed", "implicit-pushed"])
def test_one_step_matches_mujoco_exactly(pushes, plant, integrator):
    """One step from every recorded MuJoCo state lands on MuJoCo's next state, for the Euler plant
    with the Euler engine and for MuJoCo's implicit integrators with the implicit engine."""
    rng = np.random.default_rng(20 + pushes)
    xml, params, rest, pos = system(rng, integrator=plant)
    eng = SpringRodEngine(Topology.from_mjcf(xml), params, dt=1e-3, integrator=integrator)
    T = 400
    qpos, qvel, rests, fu, ru = run_mujoco(xml, random_state(rng, pos), T, rng if pushes else None,
                                           cable_motor(rest, 1e-3))
    rests = torch.as_tensor(rests)
    rec = mujoco_states(qpos, qvel, 3)
    # both sides of each cable's dead band are visited
    geo = spring_geometry(endpoint_kinematics(eng.graph, *rec))
    for j in (3, 4):
        slack = (geo.length[:-1, j] < rests[:, j]).double().mean()
        assert 0.05 < slack < 0.95, f"cable {j} slack fraction {slack:.2f}"
    now = RodState(*(x[:-1] for x in rec))
    nxt = eng.step(now, rests, torch.as_tensor(fu) if pushes else None, torch.as_tensor(ru) if pushes else None)
    for name, ours, ref in zip(RodState._fields, nxt, rec):
        scale = max(1.0, float(ref.abs().max()))
        err = float((ours - ref[1:]).abs().max())
        assert err < 1e-12 * scale, f"{name}: max error {err:.3g}"
    # the body-frame angular velocity (MuJoCo's qvel) too
    w_b = matrix_apply_transpose(quat_to_matrix(nxt.quat), nxt.angvel).numpy()
    assert np.abs(w_b - qvel[1:].reshape(T, 3, 6)[..., 3:]).max() < 1e-12 * max(1.0, np.abs(w_b).max())


def test_rk4_engine_steps_like_mujoco_rk4():
    """The RK4 engine follows MuJoCo's RK4 tableau (mj_RungeKutta).  MuJoCo 4.0 differs from that
    documented algorithm by ~1e-8 per step in orientation without pushes (a re-implementation
    with mj_forward and mj_integratePos shows the same; with the large random pushes here up to
    ~6e-6 rad/s in angular velocity), 3+ orders below the error of stepping an RK4 plant with
    the Euler engine."""
    rng = np.random.default_rng(22)
    xml, params, rest, pos = system(rng, integrator="RK4")
    T = 200
    qpos, qvel, rests, fu, ru = run_mujoco(xml, random_state(rng, pos), T, rng, cable_motor(rest, 1e-3))
    rec = mujoco_states(qpos, qvel, 3)
    now = RodState(*(x[:-1] for x in rec))
    err = {}
    for integrator in ("rk4", "euler"):
        eng = SpringRodEngine(Topology.from_mjcf(xml), params, dt=1e-3, integrator=integrator)
        nxt = eng.step(now, torch.as_tensor(rests), torch.as_tensor(fu), torch.as_tensor(ru))
        err[integrator] = [float((ours - ref[1:]).abs().max()) for ours, ref in zip(nxt, rec)]
    assert max(err["rk4"]) < 2e-5
    for e_rk4, e_euler in zip(err["rk4"], err["euler"]):
        assert e_rk4 < 1e-3 * e_euler


def test_rollout_tracks_mujoco():
    rng = np.random.default_rng(30)
    xml, params, rest, pos = system(rng)
    eng = SpringRodEngine(Topology.from_mjcf(xml), params, dt=1e-3)
    T = 300
    qpos, qvel, rests, fu, ru = run_mujoco(xml, random_state(rng, pos), T, rng, cable_motor(rest, 1e-3))
    rec = mujoco_states(qpos, qvel, 3)
    traj = eng.rollout(RodState(*(x[0] for x in rec)), torch.as_tensor(rests), torch.as_tensor(fu),
                       torch.as_tensor(ru))
    for ours, ref in zip(traj, rec):
        assert ours.shape == ref.shape
        assert float((ours - ref).abs().max()) < 1e-11


def test_pushed_mujoco_plant_with_control_scale():
    """h scales the push: h = 2 with half the push gives MuJoCo's trajectory (h = 1)."""
    rng = np.random.default_rng(40)
    xml, params, _, pos = system(rng, gravity=(0.0, 0.0, 0.0))
    params.control_scale = torch.tensor(2.0, dtype=F64)
    eng = SpringRodEngine(Topology.from_mjcf(xml), params, dt=1e-3)
    T = 50
    qpos, qvel, rests, fu, ru = run_mujoco(xml, random_state(rng, pos), T, rng)
    rec = mujoco_states(qpos, qvel, 3)
    nxt = eng.step(RodState(*(x[:-1] for x in rec)), torch.as_tensor(rests), torch.as_tensor(fu) / 2,
                   torch.as_tensor(ru))
    for ours, ref in zip(nxt, rec):
        assert float((ours - ref[1:]).abs().max()) < 1e-11


# ---------------------------------------------------------------------- API behaviour
@pytest.mark.parametrize("integrator", ["euler", "implicit", "rk4"])
def test_batched_leading_dims_equal_individual_steps(integrator):
    rng = np.random.default_rng(50)
    xml, params, rest, pos = system(rng)
    eng = SpringRodEngine(Topology.from_mjcf(xml), params, dt=1e-3, integrator=integrator)
    states = [random_state(rng, pos) for _ in range(6)]
    batch = RodState(*(torch.stack([s[k] for s in states]).reshape(2, 3, 3, -1) for k in range(4)))
    rests = torch.as_tensor(rest).expand(2, 3, 6) + torch.as_tensor(rng.normal(0, 0.01, (2, 3, 6)))
    fu = torch.as_tensor(rng.normal(0, 5, (2, 3, 3, 3)))
    out = eng.step(batch, rests, fu)
    for b in range(6):
        single = eng.step(states[b], rests.reshape(6, 6)[b], fu.reshape(6, 3, 3)[b])
        for x, y in zip(out, single):
            torch.testing.assert_close(x.reshape(6, 3, -1)[b], y, rtol=0, atol=1e-15)
    # rollout: (E, T+1, R, ·)
    traj = eng.rollout(batch[0] if False else RodState(*(x[0] for x in batch)), rests[0][:, None].expand(3, 7, 6))
    assert traj.pos.shape == (3, 8, 3, 3) and traj.quat.shape == (3, 8, 3, 4)


def test_per_environment_parameters_broadcast():
    rng = np.random.default_rng(51)
    xml, params, rest, pos = system(rng)
    topo = Topology.from_mjcf(xml)
    s = random_state(rng, pos)
    batch = RodState(*(x.expand(2, *x.shape) for x in s))
    scaled = SpringRodParams(params.stiffness * torch.tensor([[1.0], [2.0]], dtype=F64), params.damping,
                             params.mass.expand(2, 3), params.inertia, params.control_scale.expand(2),
                             params.gravity.expand(2, 3))
    out = SpringRodEngine(topo, scaled, dt=1e-3).step(batch, torch.as_tensor(rest), torch.ones(2, 3, 3, dtype=F64))
    for b, factor in enumerate((1.0, 2.0)):
        p = SpringRodParams(params.stiffness * factor, params.damping, params.mass, params.inertia,
                            params.control_scale, params.gravity)
        ref = SpringRodEngine(topo, p, dt=1e-3).step(s, torch.as_tensor(rest), torch.ones(3, 3, dtype=F64))
        for x, y in zip(out, ref):
            torch.testing.assert_close(x[b], y, rtol=0, atol=1e-15)


def test_effects_are_added_to_the_wrench():
    rng = np.random.default_rng(52)
    xml, params, rest, pos = system(rng)
    topo = Topology.from_mjcf(xml)
    s = random_state(rng, pos)
    fu = torch.as_tensor(rng.normal(0, 5, (3, 3)))
    ru = torch.as_tensor(rng.normal(0, 0.3, (3, 3)))
    seen = {}

    def push_like(state: RodState, ctx: StepContext):
        seen["ctx"] = ctx
        return push_wrench(ctx.rot, fu, ru, 1.0)

    def nothing(state, ctx):
        return None, None

    with_effect = SpringRodEngine(topo, params, 1e-3, effects=[push_like, nothing]).step(s, torch.as_tensor(rest))
    with_push = SpringRodEngine(topo, params, 1e-3).step(s, torch.as_tensor(rest), fu, ru)
    for x, y in zip(with_effect, with_push):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-15)
    ctx = seen["ctx"]
    assert ctx.tension.shape == (6,) and ctx.ends.lever.shape == (6, 2, 3) and ctx.rot.shape == (3, 3, 3)


def test_endpoint_lever_is_the_world_arm_from_the_rod_com():
    """The regression's contract: ends.lever[..., j, e] = point - pos[rod], zero at anchors."""
    rng = np.random.default_rng(53)
    xml, _, _, pos = system(rng)
    topo = Topology.from_mjcf(xml)
    s = random_state(rng, pos)
    batch = RodState(*(x.expand(4, *x.shape) for x in s))
    ends = endpoint_kinematics(topo, *batch)  # a Topology is accepted directly
    assert ends.point.shape == ends.lever.shape == ends.velocity.shape == (4, 6, 2, 3)
    rods = topo.endpoint_rods
    for j in range(6):
        for e in range(2):
            if rods[j, e] < 0:
                np.testing.assert_array_equal(ends.lever[:, j, e].numpy(), 0.0)
                np.testing.assert_allclose(ends.point[:, j, e].numpy(), np.broadcast_to(topo.endpoint_offsets[j, e], (4, 3)))
            else:
                np.testing.assert_allclose((ends.point[:, j, e] - batch.pos[:, rods[j, e]]).numpy(),
                                           ends.lever[:, j, e].numpy(), atol=1e-15)
    # the tension of a spring is consistent with MuJoCo's tendon length and velocity
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    set_mujoco_state(d, s)
    mujoco.mj_forward(m, d)
    geo = spring_geometry(endpoint_kinematics(topo, *s))
    np.testing.assert_allclose(geo.length.numpy(), d.ten_length, atol=1e-14)
    np.testing.assert_allclose(geo.rate.numpy(), d.ten_velocity, atol=1e-13)


def test_float32_runs_and_agrees():
    rng = np.random.default_rng(54)
    xml, params, rest, pos = system(rng)
    topo = Topology.from_mjcf(xml)
    s = random_state(rng, pos)
    rests = torch.as_tensor(rest).expand(20, 6)
    ref = SpringRodEngine(topo, params, 1e-3).rollout(s, rests)
    eng32 = SpringRodEngine(topo, params, 1e-3, dtype=torch.float32)
    out = eng32.rollout(RodState(*(x.float() for x in s)), rests.float())
    assert out.pos.dtype == torch.float32
    for x, y in zip(out, ref):
        assert float((x.double() - y).abs().max()) < 1e-4


def test_non_finite_states_do_not_raise():
    graph, rest, state, p = small_system()
    eng = SpringRodEngine(graph, p, dt=0.01)
    bad = RodState(state.pos.clone(), state.quat, state.vel, state.angvel)
    bad.pos[0, 0] = float("nan")
    out = eng.step(bad, rest)
    assert not torch.isfinite(out.pos).all()
    huge = RodState(state.pos, state.quat, state.vel * 1e300, state.angvel * 1e300)
    eng.step(huge, rest)  # inf/NaN, no exception
    # a zero-length spring (both ends on one point) gives NaN, not an exception
    z = RodState(torch.zeros(2, 3, dtype=F64), torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64),
                 torch.zeros(2, 3, dtype=F64), torch.zeros(2, 3, dtype=F64))
    coincident = SpringGraph.from_arrays(2, [[0, 1]], [[[0, 0, 0.5], [0, 0, 0.5]]], [False])
    SpringRodEngine(coincident, SpringRodParams.from_values(1.0, 1.0, 1.0, [0.3, 0.3, 0.03], n_rods=2,
                                                            n_springs=1), 0.01).step(z, torch.ones(1, dtype=F64))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    rng = np.random.default_rng(55)
    xml, params, rest, pos = system(rng)
    topo = Topology.from_mjcf(xml)
    s = random_state(rng, pos)
    rests = torch.as_tensor(rest).expand(10, 6)
    ref = SpringRodEngine(topo, params, 1e-3).rollout(s, rests)
    gpu = SpringRodEngine(topo, params, 1e-3, device="cuda")
    out = gpu.rollout(RodState(*(x.cuda() for x in s)), rests.cuda())
    assert out.pos.device.type == "cuda"
    for x, y in zip(out, ref):
        torch.testing.assert_close(x.cpu(), y, rtol=0, atol=1e-12)
