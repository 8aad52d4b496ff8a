"""The identified twin: IdentifiedBackend, the batched vector env and the SB3 adapter.

The twin is checked against the plant where they must agree exactly: with parameters equal to the
plant's truth and no ground (the engine has no contact yet), a twin step is a MuJoCo Euler step to
~1e-13; spaces, reset distribution and info are the plant's. The batched vector env is checked
against a SyncVectorEnv of single twins, the SB3 adapter against SB3's DummyVecEnv.
"""

from __future__ import annotations

import os
import textwrap
import warnings
import xml.etree.ElementTree as ET

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

import tensegrity_gym  # noqa: F401  (registers the env)
from identified.mjcf import nominal_pose
from identified.model import IdentifiedModel, load_model, save_model
from identified.topology import Topology
from tensegrity_gym.backends import make_backend
from tensegrity_gym.backends.identified_backend import IdentifiedBackend, default_model_path
from tensegrity_gym.backends.mujoco_backend import default_robot_xml
from tensegrity_gym.envs.tensegrity_ico_v0 import (
    TensegrityIcoEnv,
    observation,
    reward_terms,
    termination_reason,
)
from tensegrity_gym.envs.vector import (
    TensegrityIcoVectorEnv,
    batch_observation,
    batch_reward_terms,
    batch_termination_reason,
)
from tensegrity_gym.models import preset_parameters
from tensegrity_gym.plant import RodState
from tests._data import GROUND as GROUND_FIT
from tests._render import render_in_subprocess

R, A = 6, 24
FIELDS = ("pos", "quat", "vel", "angvel")
#: the twin in identification's precision, for comparisons with the plant to ~1e-10
F64 = {"dtype": "float64"}
_INF_BOUNDS = "observation space m"  # Gymnasium always notes the deliberate infinite bounds


# ---------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    """(twin JSON, plant MJCF): the robot without its ground plane, and an identified model whose
    parameters are the plant's truth (a backend test, not an identification)."""
    d = tmp_path_factory.mktemp("truth")
    root = ET.fromstring(default_robot_xml())
    world = root.find("worldbody")
    world.remove(world.find("geom[@name='ground']"))
    xml_path = d / "robot_no_ground.xml"
    xml_path.write_text(ET.tostring(root, encoding="unicode"))
    t = preset_parameters("ico", "robot")
    model = IdentifiedModel(
        topology=Topology.from_mjcf(str(xml_path)),
        stiffness=np.array([s["stiffness"] for s in t["springs"]]),
        damping=np.array([s["damping"] for s in t["springs"]]),
        rest_length=np.array([s["rest_length"] for s in t["springs"]]),
        mass=np.array([r["mass"] for r in t["rods"]]),
        inertia=np.array([r["inertia"] for r in t["rods"]]),
        dt=t["timestep"], gravity=np.array(t["gravity"]), source_model=str(xml_path),
    )
    json_path = d / "truth.json"
    save_model(json_path, model)
    return str(json_path), str(xml_path)


def states_diff(a: RodState, b: RodState) -> float:
    return max(float(np.abs(getattr(a, f) - getattr(b, f)).max()) for f in FIELDS)


def assert_infos_equal(a: dict, b: dict, path: str = "") -> None:
    """Vector infos (dicts of arrays with masks) equal: same keys, masks, dtypes; values to 1e-12."""
    assert set(a) == set(b), f"{path}: keys differ: {set(a) ^ set(b)}"
    for k, x in a.items():
        y = b[k]
        if isinstance(x, dict):
            assert_infos_equal(x, y, f"{path}{k}.")
        elif x.dtype == object:
            for xx, yy in zip(x, y, strict=True):
                if isinstance(xx, np.ndarray):
                    np.testing.assert_array_equal(xx, yy)
                else:
                    assert xx == yy, f"{path}{k}: {x} != {y}"
        else:
            assert x.dtype == y.dtype and x.shape == y.shape, f"{path}{k}: {x.dtype} vs {y.dtype}"
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12, err_msg=f"{path}{k}")


def _checker_warnings(record) -> list[str]:
    return [str(w.message) for w in record if _INF_BOUNDS not in str(w.message)]


#: the robot fitted with ``ground_contact`` (the shipped model's data): its twin steps ~2x faster eagerly
#: than the shipped ``pyramid_contact`` one, and nothing below depends on the contact law
GROUND = str(GROUND_FIT)


@pytest.fixture(autouse=True)
def _ground_contact_by_default(monkeypatch, request):
    """A twin built without ``model=`` loads :data:`GROUND` here; the shipped model's own test
    reads the real default."""
    if request.node.name != "test_shipped_model_is_the_default_and_resolves":
        from tensegrity_gym.backends import identified_backend

        monkeypatch.setattr(identified_backend, "default_model_path", lambda: GROUND)


# ---------------------------------------------------------------------- the single twin
def test_shipped_model_is_the_default_and_resolves():
    path = default_model_path()
    assert os.path.isfile(path), "run scripts/make_shipped_model.sh"
    m = load_model(path)
    assert m.source_model == "preset:ico/robot"  # resolvable on a fresh clone
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback warning
        env = gym.make("TensegrityIco-v0", backend="identified")
    b = env.unwrapped.backend
    assert isinstance(b, IdentifiedBackend) and b.name == "identified"
    assert b.dt == pytest.approx(0.001) and b.motor.n == A and b.n_rods == R
    assert b.model.topology.rod_names == b.rod_names


def test_twin_passes_gymnasium_and_sb3_checkers():
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        check_env(TensegrityIcoEnv(backend="identified"), skip_render_check=True)
        sb3_check_env(TensegrityIcoEnv(backend="identified"), warn=True)
    assert _checker_warnings(record) == []


def test_same_spaces_reset_distribution_and_info_as_the_plant():
    twin = gym.make("TensegrityIco-v0", backend="identified", backend_kwargs=F64)
    plant = gym.make("TensegrityIco-v0")
    assert twin.observation_space == plant.observation_space
    assert twin.action_space == plant.action_space
    assert twin.spec.max_episode_steps == plant.spec.max_episode_steps == 1000
    assert twin.unwrapped.dt == plant.unwrapped.dt
    bt, bp = twin.unwrapped.backend, plant.unwrapped.backend
    assert bt.rod_names == bp.rod_names and bt.tendon_names == bp.tendon_names
    assert bt.actuated_names == bp.actuated_names
    np.testing.assert_array_equal(bt.motor.rest_min, bp.motor.rest_min)
    np.testing.assert_array_equal(bt.nominal_rest_lengths(), bp.nominal_rest_lengths())
    assert states_diff(bt.nominal_states(), bp.nominal_states()) == 0.0
    for seed in (0, 1, 2):
        ot, it = twin.reset(seed=seed)
        op, ip = plant.reset(seed=seed)
        np.testing.assert_array_equal(ot, op)
        assert states_diff(bt.states(), bp.states()) < 1e-15
        assert set(it) == set(ip)
        for k in it:
            np.testing.assert_allclose(it[k], ip[k], rtol=0, atol=1e-15)
    _, _, _, _, it = twin.step(twin.action_space.sample())
    _, _, _, _, ip = plant.step(plant.action_space.sample())
    assert set(it) == set(ip)


def test_nominal_pose_from_xml_is_the_plants():
    xml = default_robot_xml()
    b = make_backend("mujoco", xml)
    s = nominal_pose(xml, b.rod_names)
    assert states_diff(s, b.nominal_states()) == 0.0
    # without a keyframe: the bodies' pos/quat (MuJoCo's qpos0)
    root = ET.fromstring(xml)
    root.remove(root.find("keyframe"))
    q0 = nominal_pose(ET.tostring(root, encoding="unicode"), b.rod_names)
    body = root.find("worldbody").find("body[@name='rod1']")
    np.testing.assert_allclose(q0.pos[1], [float(x) for x in body.get("pos").split()])


def test_twin_step_matches_the_mujoco_plant_without_contact(truth):
    twin_json, plant_xml = truth
    twin = gym.make("TensegrityIco-v0", backend="identified", model=twin_json, backend_kwargs=F64)
    plant = gym.make("TensegrityIco-v0", model=plant_xml)
    bt, bp = twin.unwrapped.backend, plant.unwrapped.backend
    ot, _ = twin.reset(seed=11)
    op, _ = plant.reset(seed=11)
    np.testing.assert_array_equal(ot, op)
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(12):  # 0.24 s of free fall with random cable commands; no rod reaches z = 0
        a = rng.uniform(-1, 1, A).astype(np.float32)
        ot, rt, tt, _, _ = twin.step(a)
        op, rp, tp, _, _ = plant.step(a)
        worst = max(worst, states_diff(bt.states(), bp.states()))
        np.testing.assert_array_equal(bt.rest_lengths(), bp.rest_lengths())
        assert rt == pytest.approx(rp, abs=1e-9) and tt == tp
        np.testing.assert_allclose(ot, op, rtol=1e-5, atol=1e-6)
    assert worst < 1e-10
    assert np.abs(bp.rest_lengths() - bp.nominal_rest_lengths()).max() > 0.03  # the motors moved

    # a push off the centre of mass, straight through the backends
    hold = bp.nominal_rest_lengths()[bp.actuated_index]
    force, point = np.zeros((R, 3)), np.zeros((R, 3))
    force[1], point[1] = [80.0, -30.0, 40.0], [0.0, 0.0, 0.6]
    for b in (bt, bp):
        b.reset(bp.nominal_states(), bp.nominal_rest_lengths())
        b.step(hold, 10, push_force=force, push_point=point)
    assert states_diff(bt.states(), bp.states()) < 1e-10
    assert np.abs(bt.states().angvel[1]).max() > 0.03  # it did turn the rod (from rest)


@pytest.mark.parametrize(("plant_integrator", "twin_integrator"), [("implicitfast", "implicit"), ("RK4", "rk4")])
def test_twin_on_the_plants_integrator_tracks_it(truth, tmp_path, plant_integrator, twin_integrator):
    """A model that records the plant's integrator makes a twin that steps like that plant."""
    twin_json, plant_xml = truth
    root = ET.parse(plant_xml).getroot()
    root.find("option").set("integrator", plant_integrator)
    xml = tmp_path / "plant.xml"
    xml.write_text(ET.tostring(root, encoding="unicode"))
    model = load_model(twin_json)
    model.integrator = twin_integrator
    save_model(tmp_path / "twin.json", model)
    twin = gym.make("TensegrityIco-v0", backend="identified", model=str(tmp_path / "twin.json"), backend_kwargs=F64)
    plant = gym.make("TensegrityIco-v0", model=str(xml))
    euler = gym.make("TensegrityIco-v0", backend="identified", model=twin_json, backend_kwargs=F64)
    for env in (twin, plant, euler):
        env.reset(seed=3)
    rng = np.random.default_rng(1)
    worst, worst_euler = 0.0, 0.0
    for _ in range(10):
        a = rng.uniform(-1, 1, A).astype(np.float32)
        for env in (twin, plant, euler):
            env.step(a)
        ref = plant.unwrapped.backend.states()
        worst = max(worst, states_diff(twin.unwrapped.backend.states(), ref))
        worst_euler = max(worst_euler, states_diff(euler.unwrapped.backend.states(), ref))
    # implicit: exact; RK4: MuJoCo 4.0's RK4 differs from its documented tableau by ~1e-8 a step
    assert worst < (1e-10 if twin_integrator == "implicit" else 1e-5)
    assert worst < 1e-3 * worst_euler


def test_float32_twin_tracks_float64(truth):
    twin_json, _ = truth
    e64 = TensegrityIcoEnv(backend="identified", model=twin_json, backend_kwargs=F64)
    e32 = TensegrityIcoEnv(backend="identified", model=twin_json, backend_kwargs={"dtype": "float32"})
    assert e32.backend.engine.dtype == torch.float32
    o64, _ = e64.reset(seed=4)
    o32, _ = e32.reset(seed=4)
    np.testing.assert_allclose(o32, o64, atol=1e-6)
    a = np.full(A, -0.5, np.float32)
    for _ in range(5):
        o64, r64, *_ = e64.step(a)
        o32, r32, *_ = e32.step(a)
    assert states_diff(e32.backend.states(), e64.backend.states()) < 1e-3
    assert r32 == pytest.approx(r64, abs=1e-2)


def test_twin_seeding_is_reproducible():
    def run(env, seed):
        obs, _ = env.reset(seed=seed)
        env.action_space.seed(seed)
        out = [obs]
        for _ in range(4):
            out.append(env.step(env.action_space.sample())[0])
        return np.array(out)

    e = gym.make("TensegrityIco-v0", backend="identified")
    a, b = run(e, 3), run(e, 3)
    c = run(gym.make("TensegrityIco-v0", backend="identified"), 3)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)
    assert np.abs(run(e, 4) - a).max() > 1e-4


def test_twin_divergence_terminates_with_a_finite_observation():
    e = TensegrityIcoEnv(backend="identified", terminate_when_unhealthy=False)
    obs0, _ = e.reset(seed=0)
    b = e.backend
    s = b.states()
    s.vel[2] = 1e300  # finite, but the next step overflows
    b.reset(s, b.rest_lengths())
    obs, reward, terminated, truncated, info = e.step(np.zeros(A, np.float32))
    assert terminated and not truncated and info["termination_reason"] == "non-finite state"
    assert np.all(np.isfinite(obs)) and np.isfinite(reward) and info["reward_forward"] == 0.0
    np.testing.assert_array_equal(obs, obs0)  # the last finite observation
    assert np.all(np.isnan(b.states().pos)) and bool(b.physics.diverged)
    b.step(np.full(A, 1.0), 3)  # stays NaN, does not raise
    obs, _ = e.reset(seed=0)
    np.testing.assert_array_equal(obs, obs0)
    assert np.all(np.isfinite(b.states().pos))


def test_backend_arguments_and_source_resolution(tmp_path):
    m = load_model(default_model_path())
    m.source_model = str(tmp_path / "gone.xml")  # fitted elsewhere: falls back to the robot preset
    with pytest.warns(UserWarning, match="does not exist here"):
        b = IdentifiedBackend(m)
    assert "fallback" in b.mjcf_source
    m.source_model = None
    b = IdentifiedBackend(m, mjcf=default_robot_xml())  # an explicit MJCF wins
    assert b.mjcf_source == "mjcf text"
    other = default_robot_xml().replace('name="cable3"', 'name="cable3x"').replace(
        'cable3 ', 'cable3x ')
    with pytest.raises(ValueError, match="mjcf="):
        IdentifiedBackend(m, mjcf=other)
    with pytest.raises(ValueError, match="dtype"):
        IdentifiedBackend(m, dtype="float16")
    with pytest.raises(ValueError, match="targets"):
        b.step(np.zeros(A + 1), 1)
    with pytest.raises(ValueError, match="push_force"):
        b.step(b.nominal_rest_lengths(), 1, push_force=np.zeros((R + 1, 3)))
    with pytest.raises(ValueError, match="n_substeps"):
        b.step(b.nominal_rest_lengths(), 0)
    with pytest.raises(ValueError, match="motor bounds"):
        b.reset(b.nominal_states(), np.full(A, 5.0))


def test_effects_reach_the_engine(truth):
    twin_json, _ = truth
    m = load_model(twin_json)
    calls = []

    def lift(state, ctx):  # cancels gravity on every rod
        calls.append(1)
        return -ctx.params.mass.unsqueeze(-1) * ctx.params.gravity, None

    free = IdentifiedBackend(m, dtype="float64")
    lifted = IdentifiedBackend(m, effects=[lift], dtype="float64")
    hold = free.nominal_rest_lengths()[free.actuated_index]
    for b in (free, lifted):
        b.reset(b.nominal_states(), b.nominal_rest_lengths())
        b.step(hold, 1)
    assert len(calls) == 1
    np.testing.assert_allclose(lifted.states().vel - free.states().vel, np.tile([0, 0, 9.81e-3], (R, 1)),
                               atol=1e-12)
    m.effects = [{"name": "ground", "parameters": {}}]
    with pytest.raises(ValueError, match="unknown effect 'ground'"):
        IdentifiedBackend(m)


# ---------------------------------------------------------------------- rendering
_RENDER_SCRIPT = textwrap.dedent(
    """
    import json, numpy as np, gymnasium as gym, tensegrity_gym
    try:
        env = gym.make("TensegrityIco-v0", backend="identified", render_mode="rgb_array", width=96, height=64)
        env.reset(seed=0)
        img = env.render()
    except RuntimeError as exc:
        if "offscreen rendering is not available" in str(exc):
            print(json.dumps({"unavailable": str(exc)})); raise SystemExit(0)
        raise
    plant = gym.make("TensegrityIco-v0", render_mode="rgb_array", width=96, height=64)
    plant.reset(seed=0)
    ref = plant.render()
    for _ in range(5):
        env.step(env.action_space.sample())
    img2 = env.render()
    venv = gym.make_vec("TensegrityIco-v0", num_envs=2, backend="identified", render_mode="rgb_array",
                        width=96, height=64)
    venv.reset(seed=0)
    frames = venv.render()
    print(json.dumps({"shape": list(img.shape), "dtype": str(img.dtype), "std": float(img.std()),
                      "same_as_plant": float(np.abs(img.astype(int) - ref).mean()),
                      "moved": float(np.abs(img2.astype(int) - img).mean()),
                      "frames": len(frames), "frame_shape": list(frames[0].shape),
                      "frame0_is_env": float(np.abs(frames[0].astype(int) - img).mean())}))
    """
)


def test_render_rgb_array():
    r = render_in_subprocess(_RENDER_SCRIPT)
    assert r["shape"] == [64, 96, 3] and r["dtype"] == "uint8" and r["std"] > 5.0
    assert r["same_as_plant"] < 1.0  # same reset state, drawn by the same MJCF
    assert r["moved"] > 0.0
    assert r["frames"] == 2 and r["frame_shape"] == [64, 96, 3] and r["frame0_is_env"] < 1.0


# ---------------------------------------------------------------------- batched pure functions
def test_batched_pure_functions_equal_the_single_env_functions():
    rng = np.random.default_rng(0)
    b = IdentifiedBackend()
    N = 5
    pos = rng.normal(0, 1, (N, R, 3)) + [0, 0, 0.7]
    quat = rng.normal(0, 1, (N, R, 4))
    quat /= np.linalg.norm(quat, axis=-1, keepdims=True)
    vel, angvel = rng.normal(0, 1, (N, R, 3)), rng.normal(0, 1, (N, R, 3))
    rest = rng.uniform(0.6, 1.1, (N, A))
    pos[1, :, 2] -= 0.6  # collapsed
    pos[2, :, 2] += 2.0  # thrown
    angvel[3, 4, 1] = np.nan
    lo, hi, idx = b.motor.rest_min, b.motor.rest_max, b.actuated_index
    for exclude in (True, False):
        obs = batch_observation(pos, quat, vel, angvel, rest, idx, lo, hi, exclude)
        for i in range(N):
            s = RodState(pos[i], quat[i], vel[i], angvel[i])
            np.testing.assert_array_equal(obs[i], observation(s, rest[i], idx, lo, hi, exclude))
    for z in ((0.4, 2.0), None):
        reasons = batch_termination_reason(pos, quat, vel, angvel, rest, z)
        for i in range(N):
            assert reasons[i] == termination_reason(RodState(pos[i], quat[i], vel[i], angvel[i]), rest[i], z)
    assert list(batch_termination_reason(pos, quat, vel, angvel, rest, (0.4, 2.0))[:4]) == [
        None, "collapsed", "left the ground", "non-finite state"]
    before, after = rng.normal(size=(N, 3)), rng.normal(size=(N, 3))
    a = rng.uniform(-1, 1, (N, A))
    terms = batch_reward_terms(before, after, a, 0.02, 1.5, 0.01)
    for i in range(N):
        single = reward_terms(before[i], after[i], a[i], 0.02, 1.5, 0.01)
        for k, v in single.items():
            assert terms[k][i] == pytest.approx(v, rel=1e-14, abs=1e-15)


# ---------------------------------------------------------------------- the batched twin
def _vec_pair(truth_json: str, n: int, mode: AutoresetMode, **kw):
    v = gym.make_vec("TensegrityIco-v0", num_envs=n, vectorization_mode="vector_entry_point",
                     backend="identified", model=truth_json, autoreset_mode=mode, **kw)
    s = gym.make_vec("TensegrityIco-v0", num_envs=n, vectorization_mode="sync",
                     vector_kwargs={"autoreset_mode": mode}, backend="identified", model=truth_json, **kw)
    return v, s


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_vector_env_matches_single_envs_step_for_step(truth, mode):
    """The batched twin against a SyncVectorEnv of gym.make'd single twins: the same seeds and actions
    give the same observations (bit for bit), rewards, flags and infos, through terminations (the
    truth robot without ground collapses after ~12 steps), truncations (time limit 9) and resets."""
    n = 3
    v, s = _vec_pair(truth[0], n, mode, max_episode_steps=9)
    assert isinstance(v, TensegrityIcoVectorEnv) and isinstance(s, gym.vector.SyncVectorEnv)
    assert v.metadata["autoreset_mode"] == mode
    assert v.single_observation_space == s.single_observation_space
    assert v.observation_space == s.observation_space and v.action_space == s.action_space
    ov, iv = v.reset(seed=5)
    os_, is_ = s.reset(seed=5)
    np.testing.assert_array_equal(ov, os_)
    assert_infos_equal(iv, is_)
    rng = np.random.default_rng(1)
    done_any, finals = 0, 0
    for t in range(24):
        if t == 4:  # put sub-env 1 out of phase with the others
            mask = np.array([False, True, False])
            ov, iv = v.reset(options={"reset_mask": mask.copy()})
            os_, is_ = s.reset(options={"reset_mask": mask.copy()})
            np.testing.assert_array_equal(ov, os_)
            assert_infos_equal(iv, is_)
        a = rng.uniform(-1, 1, (n, A)).astype(np.float32)
        rv, rs = v.step(a), s.step(a)
        np.testing.assert_array_equal(rv[0], rs[0])
        np.testing.assert_allclose(rv[1], rs[1], rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(rv[2], rs[2])
        np.testing.assert_array_equal(rv[3], rs[3])
        assert_infos_equal(rv[4], rs[4])
        done_any += int((rv[2] | rv[3]).any())
        finals += int("final_obs" in rv[4])
        assert rv[0].dtype == np.float32 and rv[1].dtype == np.float64 and rv[2].dtype == bool
    assert done_any >= 3
    assert (finals > 0) == (mode == AutoresetMode.SAME_STEP)


def test_vector_autoreset_next_step_and_disabled(truth):
    v = TensegrityIcoVectorEnv(2, truth[0], max_episode_steps=3, terminate_when_unhealthy=False)
    with pytest.raises(gym.error.ResetNeeded):
        v.step(np.zeros((2, A), np.float32))
    v.reset(seed=0)
    for _ in range(3):
        obs, rew, term, trunc, info = v.step(np.zeros((2, A), np.float32))
    assert trunc.all() and not term.any()
    # next step: the action is ignored, the sub-envs restart (reward 0, no reward terms in info)
    obs, rew, term, trunc, info = v.step(np.ones((2, A), np.float32))
    assert not (term | trunc).any() and np.all(rew == 0.0)
    assert "reward_forward" not in info and info["_x_position"].all()
    np.testing.assert_allclose(obs[:, -A:], 0.5, atol=1e-6)  # neutral rest lengths: a fresh episode
    assert np.all(info["x_velocity"] == 0.0)

    d = TensegrityIcoVectorEnv(2, truth[0], max_episode_steps=2, autoreset_mode="Disabled",
                               terminate_when_unhealthy=False)
    d.reset(seed=0)
    d.step(np.zeros((2, A), np.float32))
    *_, trunc, _ = d.step(np.zeros((2, A), np.float32))
    assert trunc.all()
    with pytest.raises(RuntimeError, match="reset_mask"):
        d.step(np.zeros((2, A), np.float32))
    d.reset(options={"reset_mask": np.array([True, True])})
    d.step(np.zeros((2, A), np.float32))
    with pytest.raises(ValueError, match="shape"):
        d.step(np.zeros((3, A), np.float32))
    with pytest.raises(ValueError, match="num_envs"):
        d.reset(seed=[1, 2, 3])


def test_vector_non_finite_sub_env_terminates_alone(truth):
    kw = {"terminate_when_unhealthy": False}
    v = TensegrityIcoVectorEnv(3, truth[0], **kw)
    ref = TensegrityIcoVectorEnv(3, truth[0], **kw)
    o0, _ = v.reset(seed=2)
    ref.reset(seed=2)
    pos, quat, vel, angvel = v.physics.states_numpy()
    vel[1, 0] = 1e300  # sub-env 1 will overflow
    v.physics.reset(pos[1:2], quat[1:2], vel[1:2], angvel[1:2], v.physics.rest_numpy()[1:2], index=[1])
    a = np.zeros((3, A), np.float32)
    obs, rew, term, trunc, info = v.step(a)
    obs_ref, rew_ref, *_ = ref.step(a)
    assert list(term) == [False, True, False] and not trunc.any()
    assert info["termination_reason"][1] == "non-finite state" and list(info["_termination_reason"]) == [
        False, True, False]
    assert np.all(np.isfinite(obs)) and np.all(np.isfinite(rew))
    np.testing.assert_array_equal(obs[1], o0[1])  # its last finite observation
    assert info["reward_forward"][1] == 0.0
    np.testing.assert_array_equal(obs[[0, 2]], obs_ref[[0, 2]])  # the others are untouched
    np.testing.assert_array_equal(rew[[0, 2]], rew_ref[[0, 2]])
    obs, rew, term, *_ = v.step(a)  # next step: sub-env 1 restarts with a finite state
    assert not term.any() and np.all(np.isfinite(v.physics.states_numpy()[0]))


def test_chunked_batch_equals_one_batched_call(truth):
    whole = TensegrityIcoVectorEnv(5, truth[0], backend_kwargs=F64)
    chunked = TensegrityIcoVectorEnv(5, truth[0], chunk_size=2, backend_kwargs=F64)
    whole.reset(seed=1)
    chunked.reset(seed=1)
    a = np.random.default_rng(0).uniform(-1, 1, (5, A)).astype(np.float32)
    for _ in range(3):
        whole.step(a)
        chunked.step(a)
    for x, y in zip(whole.physics.states_numpy(), chunked.physics.states_numpy(), strict=True):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12)


def test_make_vec_without_identified_backend_stays_a_sync_vector_env():
    v = gym.make_vec("TensegrityIco-v0", num_envs=2)
    assert isinstance(v, gym.vector.SyncVectorEnv)
    v.reset(seed=0)
    v.step(v.action_space.sample())
    v.close()


def test_vector_env_default_model_and_seeding():
    v = gym.make_vec("TensegrityIco-v0", num_envs=4, backend="identified")
    assert isinstance(v, TensegrityIcoVectorEnv) and v.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    o1, _ = v.reset(seed=7)
    single, _ = gym.make("TensegrityIco-v0", backend="identified").reset(seed=9)
    np.testing.assert_array_equal(o1[2], single)  # sub-env i gets seed + i
    o2, _ = v.reset(seed=7)
    np.testing.assert_array_equal(o1, o2)
    assert v.np_random_seed == (7, 8, 9, 10)
    o3, _ = v.reset(seed=[7, None, 9, 10])
    np.testing.assert_array_equal(o3[[0, 2, 3]], o1[[0, 2, 3]])
    assert v.get_attr("frame_skip") == (20,) * 4
    v.close()


# ---------------------------------------------------------------------- SB3
def test_sb3_adapter_matches_dummy_vec_env(truth):
    from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecMonitor
    from stable_baselines3.common.vec_env.util import obs_space_info

    from tensegrity_gym.envs.sb3 import SB3VecEnvAdapter

    n, limit = 3, 7
    for mode in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
        venv = SB3VecEnvAdapter(gym.make_vec("TensegrityIco-v0", num_envs=n, backend="identified",
                                             model=truth[0], max_episode_steps=limit, autoreset_mode=mode))
        dummy = DummyVecEnv([lambda: gym.make("TensegrityIco-v0", backend="identified", model=truth[0],
                                              max_episode_steps=limit)] * n)
        assert isinstance(venv, VecEnv) and venv.num_envs == n
        assert venv.observation_space == dummy.observation_space and venv.action_space == dummy.action_space
        _, shapes, dtypes = obs_space_info(venv.observation_space)
        assert venv.get_attr("render_mode") == [None] * n and venv.env_is_wrapped(gym.Wrapper) == [False] * n
        assert venv.get_attr("frame_skip", indices=[1]) == [20]
        venv.seed(3)
        dummy.seed(3)
        ov, od = venv.reset(), dummy.reset()
        assert isinstance(ov, np.ndarray) and ov.shape == (n,) + shapes[None] and ov.dtype == dtypes[None]
        np.testing.assert_array_equal(ov, od)
        assert set(venv.reset_infos[0]) == set(dummy.reset_infos[0])
        rng = np.random.default_rng(0)
        ends = 0
        for _ in range(16):
            a = rng.uniform(-1, 1, (n, A)).astype(np.float32)
            ov, rv, dv, iv = venv.step(a)
            od, rd, dd, id_ = dummy.step(a)
            np.testing.assert_array_equal(ov, od)  # after a done: the next episode's first observation
            np.testing.assert_allclose(rv, rd, rtol=1e-6)
            assert rv.dtype == np.float32 and dv.dtype == bool and isinstance(iv, list) and len(iv) == n
            np.testing.assert_array_equal(dv, dd)
            for i in range(n):
                assert set(iv[i]) == set(id_[i]), (set(iv[i]) ^ set(id_[i]))
                assert iv[i]["TimeLimit.truncated"] == id_[i]["TimeLimit.truncated"]
                if dv[i]:
                    np.testing.assert_array_equal(iv[i]["terminal_observation"],
                                                  id_[i]["terminal_observation"])
                    ends += 1
        assert ends >= n
        monitored = VecMonitor(venv)  # SB3 wrappers accept it
        monitored.reset()
        monitored.step(np.zeros((n, A), np.float32))
        venv.close()


def test_ppo_learns_256_steps_on_the_batched_twin():
    from stable_baselines3 import PPO

    from tensegrity_gym.envs.sb3 import SB3VecEnvAdapter

    venv = SB3VecEnvAdapter(gym.make_vec("TensegrityIco-v0", num_envs=4, backend="identified"))
    model = PPO("MlpPolicy", venv, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=256)
    assert model.num_timesteps >= 256
    venv.close()
