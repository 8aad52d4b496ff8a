"""The MuJoCo plant: physics against known truth, frames, pushes, motors, conventions, the robot."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import mujoco
import numpy as np
import pytest

from identified.rotation import quat_to_matrix
from identified.state import RodState
from tensegrity_gym.cables import ROBOT_ROLL_SEQUENCE, scripted_roll_targets
from tensegrity_gym.models import build_model, preset_parameters
from tensegrity_gym.plant import MujocoPlant


@pytest.fixture(scope="module")
def robot_xml() -> str:
    return build_model("ico", "robot")


def _simple(**overrides: float) -> tuple[MujocoPlant, dict]:
    return (MujocoPlant(build_model("simple", "paper", overrides=overrides)),
            preset_parameters("simple", "paper", overrides=overrides))


def _perpendicular_spin(s: RodState, rate: float) -> np.ndarray:
    """(R, 3) world angular velocities perpendicular to each rod axis (no axial spin)."""
    axis = quat_to_matrix(s.quat)[:, :, 2]
    w = np.cross(axis, [0.3, 0.5, 0.8])
    return rate * w / np.linalg.norm(w, axis=1, keepdims=True)


# ---------------------------------------------------------------------- frames
def test_angular_velocity_world_body_round_trip() -> None:
    plant = MujocoPlant(build_model("ico", "paper-uniform"))
    rng = np.random.default_rng(0)
    s = plant.states()
    q = rng.normal(size=(6, 4))
    s = RodState(s.pos + rng.normal(0, 0.1, (6, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                  rng.normal(size=(6, 3)), rng.normal(size=(6, 3)))
    plant.set_states(s)
    back = plant.states()
    for name in ("pos", "quat", "vel", "angvel"):
        assert np.allclose(getattr(back, name), getattr(s, name), atol=1e-12), name
    # MuJoCo's own world-frame body velocity agrees, and qvel holds the BODY-frame rate
    m, d = plant.model, plant.data
    for i, rod in enumerate(plant.rod_names):
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, rod)
        v6 = np.zeros(6)
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, b, v6, 0)
        assert np.allclose(v6[:3], s.angvel[i]) and np.allclose(v6[3:], s.vel[i])
        dof = m.jnt_dofadr[m.body_jntadr[b]]
        assert np.allclose(d.qvel[dof + 3 : dof + 6], quat_to_matrix(s.quat[i]).T @ s.angvel[i])


def test_quaternions_are_w_x_y_z() -> None:
    m = mujoco.MjModel.from_xml_string(build_model("ico", "paper-uniform"))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    plant = MujocoPlant(m)
    s = plant.states()
    assert np.allclose(quat_to_matrix(s.quat), d.xmat[1:].reshape(-1, 3, 3))


# ---------------------------------------------------------------------- physics against truth
def test_free_oscillation_conserves_energy_without_damping() -> None:
    plant, pp = _simple(damping_scale=0.0)
    s = plant.states()
    s.vel[0] = [0.3, -0.5, 0.4]
    s = s._replace(angvel=_perpendicular_spin(s, 0.9))
    plant.set_states(s)
    E0 = _simple_energy(plant, pp)
    E = []
    for _ in range(6000):
        plant.step()
        E.append(_simple_energy(plant, pp))
    E = np.array(E)
    assert E0 > 1.0
    assert np.max(np.abs(E / E0 - 1)) < 5e-3  # semi-implicit Euler: bounded oscillation, no drift
    assert abs(E[-1000:].mean() / E[:1000].mean() - 1) < 2e-3
    assert np.max(np.abs(plant.states().vel)) > 0.05  # still moving


def _simple_energy(plant: MujocoPlant, pp: dict) -> float:
    """Kinetic + spring energy of the one-rod system (no gravity)."""
    M, I = pp["rods"][0]["mass"], np.array(pp["rods"][0]["inertia"])
    K = np.array([s["stiffness"] for s in pp["springs"]])
    L0 = np.array([s["rest_length"] for s in pp["springs"]])
    s = plant.states()
    wb = quat_to_matrix(s.quat[0]).T @ s.angvel[0]
    kinetic = 0.5 * M * s.vel[0] @ s.vel[0] + 0.5 * wb @ (I * wb)
    return kinetic + 0.5 * np.sum(K * (plant.tendon_lengths() - L0) ** 2)


def test_damping_dissipates() -> None:
    """With damping the energy falls at every step.

    (It does not fall to zero quickly: at rest length the rod and its two springs form a four-bar
    linkage nail0-end0-end1-nail1, whose motion stretches the springs only at second order.)
    """
    plant, pp = _simple()
    s = plant.states()
    s.vel[0] = [0.3, -0.5, 0.0]
    plant.set_states(s)
    E = [_simple_energy(plant, pp)]
    for _ in range(8000):
        plant.step()
        E.append(_simple_energy(plant, pp))
    E = np.array(E)
    assert np.max(np.diff(E)) < 1e-9 * E[0]
    assert E[-1] < 0.8 * E[0]


def test_one_step_is_semi_implicit_euler_with_paper_forces() -> None:
    """v1 = v0 + dt F(x0, v0)/M, x1 = x0 + dt v1 (velocity first); springs f = -K(L-L0) - c dL/dt."""
    plant, pp = _simple()
    M = pp["rods"][0]["mass"]
    I11 = pp["rods"][0]["inertia"][0]
    K = np.array([s["stiffness"] for s in pp["springs"]])
    c = np.array([s["damping"] for s in pp["springs"]])
    L0 = np.array([s["rest_length"] for s in pp["springs"]])
    anchors = pp["anchors"]
    s = plant.states()
    s.pos[0] += [0.05, -0.08, 0.03]
    s.vel[0] = [0.4, 0.2, -0.3]
    s = s._replace(angvel=_perpendicular_spin(s, 0.7))  # no axial spin: the gyroscopic term vanishes
    plant.set_states(s)
    R = quat_to_matrix(s.quat[0])
    F, tau = np.zeros(3), np.zeros(3)
    for j, (site, anchor) in enumerate(s_["sites"] for s_ in pp["springs"]):
        arm = R @ np.array([0, 0, -1.0 if site.endswith("end0") else 1.0])
        end, vend = s.pos[0] + arm, s.vel[0] + np.cross(s.angvel[0], arm)
        d = np.array(anchors[anchor]) - end
        L = np.linalg.norm(d)
        u = d / L
        f = (K[j] * (L - L0[j]) + c[j] * (-vend @ u)) * u  # on the rod end, toward the nail when stretched
        F += f
        tau += np.cross(arm, f)
    v1 = s.vel[0] + plant.dt * F / M
    w1 = s.angvel[0] + plant.dt * tau / I11  # torque is perpendicular to the axis: I_world acts as I11
    plant.step()
    after = plant.states()
    assert np.allclose(after.vel[0], v1, rtol=0, atol=1e-12)
    assert np.allclose(after.angvel[0], w1, rtol=0, atol=1e-12)
    assert np.allclose(after.pos[0], s.pos[0] + plant.dt * v1, rtol=0, atol=1e-14)


# ---------------------------------------------------------------------- pushes
def test_push_at_com_gives_F_dt_over_M() -> None:
    plant, pp = _simple()
    M = pp["rods"][0]["mass"]
    F = np.array([[30.0, -12.0, 7.0]])
    plant.step(push_force=F)  # springs at rest, rod at rest: the push is the only force
    s = plant.states()
    assert np.allclose(s.vel, F * plant.dt / M, rtol=0, atol=1e-14)
    assert np.allclose(s.angvel, 0, atol=1e-14)
    assert np.all(plant.data.xfrc_applied == 0)  # cleared after the step


def test_push_off_com_gives_the_right_torque() -> None:
    plant, pp = _simple(damping_scale=0.0)
    M, I11 = pp["rods"][0]["mass"], pp["rods"][0]["inertia"][0]
    F = np.array([[0.0, 40.0, 10.0]])
    point = np.array([[0.0, 0.0, 0.7]])  # on the rod axis, 0.7 m toward end1 (world +x here)
    arm = quat_to_matrix(plant.states().quat[0]) @ point[0]
    assert np.allclose(arm, [0.7, 0, 0])
    plant.step(push_force=F, push_point=point)
    s = plant.states()
    assert np.allclose(s.vel[0], F[0] * plant.dt / M, atol=1e-14)
    assert np.allclose(s.angvel[0], np.cross(arm, F[0]) * plant.dt / I11, atol=1e-13)
    plant.step()  # the push is gone: no further kick
    assert np.allclose(plant.states().angvel[0], s.angvel[0], atol=1e-6)


def test_push_shape_errors() -> None:
    plant, _ = _simple()
    with pytest.raises(ValueError, match=r"push_force"):
        plant.step(push_force=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="push_point"):
        plant.step(push_point=np.zeros((1, 3)))


# ---------------------------------------------------------------------- motors and recording
def test_motors_rate_limited_and_recording_semantic(robot_xml: str) -> None:
    plant = MujocoPlant(robot_xml)
    assert plant.actuated_names == tuple(f"cable{j}" for j in range(24))
    lo, _ = plant.rest_bounds()
    neutral = plant.rest_lengths().copy()
    v, dt = plant.motor.speed, plant.dt
    target = neutral.copy()
    target[0], target[1] = lo[0] - 1.0, neutral[1] + 0.01  # out of range: clipped to the bound
    plant.set_targets(target)
    assert plant.targets[0] == lo[0]
    plant.step()
    r1 = plant.rest_lengths()  # the rest lengths used during that step
    assert r1[0] == pytest.approx(neutral[0] - v * dt) and r1[1] == pytest.approx(neutral[1] + v * dt)
    assert np.array_equal(r1[2:], neutral[2:])
    assert plant.model.tendon_lengthspring[0, 0] == 0  # pull-only stays a dead-band
    for _ in range(3000):
        plant.step()
    r = plant.rest_lengths()
    assert r[0] == pytest.approx(lo[0]) and r[1] == pytest.approx(neutral[1] + 0.01)
    plant.reset()
    assert np.array_equal(plant.rest_lengths(), neutral)
    with pytest.raises(ValueError, match="inside the motor bounds"):
        plant.reset(rest_lengths=np.full(24, 10.0))
    with pytest.raises(ValueError, match=r"shape \(24,\)"):
        plant.set_targets(np.zeros(3))


def test_integrator_override(robot_xml: str) -> None:
    assert MujocoPlant(robot_xml, integrator="rk4").model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert MujocoPlant(robot_xml).model.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    with pytest.raises(ValueError, match="valid integrators"):
        MujocoPlant(robot_xml, integrator="leapfrog")


# ---------------------------------------------------------------------- conventions
def test_rods_are_found_by_structure_not_by_name() -> None:
    """Rods are free bodies, whatever their sites are called; a body without a free joint is part of
    the world; a rod's centre of mass may lie anywhere in its frame; a routed cable runs."""
    xml = build_model("ico", "paper-uniform")
    renamed = xml.replace('name="rod3_end1"', 'name="rod3_tip"').replace('site="rod3_end1"', 'site="rod3_tip"')
    plant = MujocoPlant(renamed)
    assert plant.rod_names == tuple(f"rod{i}" for i in range(6))
    assert "rod3_tip" in plant.system.rods[3].attachments
    fixed = MujocoPlant(xml.replace('<freejoint name="rod2_free" />', ""))
    assert fixed.rod_names == ("rod0", "rod1", "rod3", "rod4", "rod5")
    three = xml.replace('<site site="rod0_end0" />', '<site site="rod0_end0" /><site site="rod1_end1" />', 1)
    assert MujocoPlant(three).n_rods == 6
    offset = MujocoPlant(xml.replace('<inertial pos="0 0 0"', '<inertial pos="0 0 0.1"', 1))
    assert offset.n_rods == 6


def test_convention_errors_name_the_element() -> None:
    bad_act = build_model("ico", "robot").replace("cable0 cable1", "cable0 wire1")
    with pytest.raises(ValueError, match="wire1"):
        MujocoPlant(bad_act)
    with pytest.raises(ValueError, match="does not exist"):
        MujocoPlant("/nonexistent/model.xml")


def test_push_acts_at_its_point_on_a_rod_whose_centre_of_mass_is_off_its_origin() -> None:
    """A push F at a point p of the rod frame changes the velocities by dt M^-1 J(p)^T F, MuJoCo's own
    force-at-a-point (``mj_applyFT``), on a rod whose centre of mass is off its frame's origin."""
    xml = build_model("ico", "paper-uniform").replace('<inertial pos="0 0 0"', '<inertial pos="0.05 -0.02 0.1"', 1)
    pushed, still = MujocoPlant(xml), MujocoPlant(xml)
    f, p = np.zeros((6, 3)), np.zeros((6, 3))
    f[0], p[0] = [3.0, -40.0, 25.0], [0.01, 0.02, -0.4]
    m, d = pushed.model, mujoco.MjData(pushed.model)
    d.qpos[:] = pushed.data.qpos
    mujoco.mj_forward(m, d)
    b = pushed._bid[0]
    point = d.xpos[b] + d.xmat[b].reshape(3, 3) @ p[0]
    qfrc = np.zeros(m.nv)
    mujoco.mj_applyFT(m, d, f[0], np.zeros(3), point, b, qfrc)
    expect = np.zeros(m.nv)
    mujoco.mj_solveM(m, d, expect.reshape(1, -1), qfrc.reshape(1, -1))
    still.step()
    pushed.step(f, p)
    np.testing.assert_allclose(pushed.data.qvel - still.data.qvel, pushed.dt * expect, rtol=1e-9, atol=1e-12)


# ---------------------------------------------------------------------- the robot stands and rolls
def _ground_ends(plant: MujocoPlant) -> set[str]:
    e = plant.end_points()
    return {f"rod{i}_end{k}" for i in range(e.shape[0]) for k in (0, 1) if e[i, k, 2] < 0.06}


def test_robot_stands_for_5_seconds(robot_xml: str) -> None:
    plant = MujocoPlant(robot_xml)
    nominal = math.sqrt(6) / 4 * 1.7
    L_key = plant.tendon_lengths()
    com0 = plant.states().pos.mean(axis=0)
    feet = _ground_ends(plant)
    for _ in range(5000):
        plant.step()
    L = plant.tendon_lengths()
    assert np.all(np.abs(L / nominal - 1) < 0.05)
    assert np.all(np.abs(L / L_key - 1) < 0.01)
    com = plant.states().pos.mean(axis=0)
    assert abs(com[2] - com0[2]) < 0.01 and np.linalg.norm(com[:2] - com0[:2]) < 0.01
    assert com0[2] > 0.6
    assert _ground_ends(plant) == feet and len(feet) == 3


@pytest.mark.parametrize("perturb", [0, 1, 2])
def test_robot_rolls_with_scripted_cables(robot_xml: str, perturb: int) -> None:
    plant = MujocoPlant(robot_xml)
    if perturb:  # a small random perturbation of the initial state
        rng = np.random.default_rng(perturb)
        s = plant.states()
        s.pos[...] += rng.normal(0, 0.01, s.pos.shape)
        s.vel[...] += rng.normal(0, 0.05, s.vel.shape)
        s.angvel[...] += rng.normal(0, 0.1, s.angvel.shape)
        plant.set_states(s)
    com0 = plant.states().pos.mean(axis=0)
    feet0 = _ground_ends(plant)
    targets = scripted_roll_targets(plant.motor, plant.rest_lengths(), plant.dt, rolls=1)
    assert targets.shape == (4500, 24)
    for u in targets:
        plant.set_targets(u)
        plant.step()
    com = plant.states().pos.mean(axis=0)
    feet = _ground_ends(plant)
    assert com[0] - com0[0] > 0.3  # rolled along +x
    assert np.linalg.norm(com[:2] - com0[:2]) > 0.3
    assert len(feet) == 3 and feet != feet0  # on a neighbouring face
    names = plant.tendon_names
    sites = {n: tuple(s["sites"]) for n, s in zip(names, preset_parameters("ico", "robot")["springs"])}
    edges = {frozenset(v) for v in sites.values()}
    f = sorted(feet)
    assert {frozenset((f[0], f[1])), frozenset((f[1], f[2])), frozenset((f[0], f[2]))} <= edges  # closed face
    L = plant.tendon_lengths()
    assert np.all(np.abs(L / (math.sqrt(6) / 4 * 1.7) - 1) < 0.05)  # back in its nominal shape
    assert np.max(np.abs(plant.states().vel)) < 0.1  # and (nearly) at rest


def test_roll_sequence_validation(robot_xml: str) -> None:
    plant = MujocoPlant(robot_xml)
    with pytest.raises(ValueError, match="rolls"):
        scripted_roll_targets(plant.motor, plant.rest_lengths(), plant.dt, rolls=len(ROBOT_ROLL_SEQUENCE) + 1)


# ---------------------------------------------------------------------- rendering
def test_render_rgb_in_a_fresh_process(tmp_path) -> None:
    """Rendering from a clean process, as a user would (MUJOCO_GL is chosen when mujoco is imported)."""
    code = (
        "import numpy as np\n"
        "from tensegrity_gym.plant import MujocoPlant\n"
        "from tensegrity_gym.models import build_model\n"
        "p = MujocoPlant(build_model('ico', 'robot'))\n"
        "try:\n"
        "    img = p.render(width=96, height=64)\n"
        "except RuntimeError as e:\n"
        "    print('NOGL', e); raise SystemExit(0)\n"
        "np.save(r'%s', img)\n" % (tmp_path / "img.npy")
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120,
                         check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    if out.stdout.startswith("NOGL"):
        pytest.skip(f"no offscreen GL on this machine: {out.stdout.strip()}")
    img = np.load(tmp_path / "img.npy")
    assert img.shape == (64, 96, 3) and img.dtype == np.uint8 and img.std() > 1
