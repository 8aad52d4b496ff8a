"""The identified twin steps MuJoCo tendon actuators: their force on the tendons (gain times
activation plus bias) and their activation dynamics, from the model's ``actuators``.

On a plant the engine's equations describe exactly (the prism of ``examples/`` without its floor, on
MuJoCo's Euler integrator, here also with off-centre rods) a twin built from the plant's true
parameters follows the plant to rounding, and a fitted twin nearly as closely; on the prism as shipped
the twin env passes Gymnasium's and SB3's checkers.
"""

from __future__ import annotations

import os
import re
import warnings

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch

import tensegrity_gym  # noqa: F401  (registers the envs)
from identified import Topology
from identified.engine.actuators import ActuatorBank, activations
from identified.fit.identify import ScaleSpec, identify
from identified.fit.pipeline import fit_model
from identified.model import IdentifiedModel, save_model
from tensegrity_gym.backends.identified_backend import IdentifiedBackend
from tensegrity_gym.backends.mujoco_backend import MujocoBackend
from tensegrity_gym.collect import CollectConfig, collect
from tests.test_byor_inertia import _plant

PRISM = os.path.join(os.path.dirname(__file__), os.pardir, "examples", "prism3.xml")
FILTERED = ('<general name="w1" tendon="vert1" dyntype="filter" dynprm="0.03" gainprm="-7" biastype="affine" biasprm="0.5 0 0" '
            'ctrlrange="0 1"/><general name="w2" tendon="vert2" dyntype="filterexact" dynprm="0.05" gainprm="-5.5" '
            'ctrlrange="0 1"/><motor name="w3" tendon="vert3" gear="-6" ctrlrange="0 1"/>')


def _true_model(xml: str, source: str) -> IdentifiedModel:
    """The plant's own values as an identified model (the test knows the truth; no fit here)."""
    m = mujoco.MjModel.from_xml_string(xml)
    topo = Topology.from_mjcf(xml)
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, n) for n in topo.spring_names]
    bid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in topo.rod_names]
    acts = []
    for u in range(m.nu):
        dyn = {0: "none", 1: "integrator", 2: "filter", 3: "filterexact"}[int(m.actuator_dyntype[u])]
        acts.append({"name": mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, u),
                     "tendon": mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_TENDON, int(m.actuator_trnid[u, 0])),
                     "kind": "general", "dynamics": dyn, "gain": float(m.actuator_gainprm[u, 0] * m.actuator_gear[u, 0]),
                     "bias": float(m.actuator_biasprm[u, 0] * m.actuator_gear[u, 0]),
                     "time_constant": float(m.actuator_dynprm[u, 0]) if dyn != "none" else None})
    return IdentifiedModel(topology=topo, stiffness=m.tendon_stiffness[tid].copy(), damping=m.tendon_damping[tid].copy(),
                           rest_length=m.tendon_lengthspring[tid, 1].copy(), mass=m.body_mass[bid].copy(),
                           inertia=m.body_inertia[bid].copy(), com=m.body_ipos[bid].copy(),
                           inertia_frame=m.body_iquat[bid].copy(), dt=float(m.opt.timestep),
                           gravity=m.opt.gravity.copy(), actuators=acts, source_model=source)


def _floorless(actuators: str | None = None) -> str:
    xml = _plant()  # the prism without its floor, off-centre rods, sites off the axes
    if actuators is not None:
        xml = re.sub(r"<actuator>.*?</actuator>", f"<actuator>{actuators}</actuator>", xml, flags=re.DOTALL)
    return xml


def _run_both(xml: str, json_path, steps: int = 200, seed: int = 0) -> tuple[float, float]:
    """The plant and the twin from the same state under the same random commands (one physics step
    each): the largest position and activation differences."""
    plant = MujocoBackend(xml)
    twin = IdentifiedBackend(str(json_path), dtype="float64", compile=False, mjcf=xml)
    assert twin.actuator_names == plant.actuator_names
    s0 = plant.nominal_states()
    for b in (plant, twin):
        b.reset(s0, plant.nominal_rest_lengths())
    rng = np.random.default_rng(seed)
    lo, hi = plant.ctrl_bounds()
    err = act_err = 0.0
    for t in range(steps):
        if t % 10 == 0:  # the second half also outside the range: MuJoCo clamps, so does the twin
            u = rng.uniform(lo, hi) if t < steps // 2 else rng.uniform(lo - 0.2, hi + 0.2)
            plant.set_ctrl(u)
            twin.set_ctrl(u)
        for b in (plant, twin):
            b.step(np.zeros(0), 1)
        err = max(err, float(np.abs(plant.states().pos - twin.states().pos).max()))
        if t < steps // 2:  # (the plant reports the command as sent, the twin as clamped)
            act_err = max(act_err, float(np.abs(plant.actuator_state() - twin.actuator_state()).max()))
    return err, act_err


@pytest.mark.parametrize("actuators", [None, FILTERED], ids=["motors", "filtered-general-with-bias"])
def test_twin_from_the_true_parameters_follows_the_plant(tmp_path, actuators):
    xml = _floorless(actuators)
    path = tmp_path / "plant.xml"
    path.write_text(xml)
    json_path = tmp_path / "true.json"
    save_model(json_path, _true_model(xml, str(path)))
    err, act_err = _run_both(xml, json_path)
    assert err < 1e-9 and act_err < 1e-12


def test_actuator_bank_steps_as_the_record_does():
    """The twin's per-step law and the fit's whole-record law (:func:`activations`) agree."""
    acts = [{"name": "a", "tendon": "t1", "dynamics": "filter", "gain": -3.0, "bias": 0.2, "time_constant": 0.04},
            {"name": "b", "tendon": "t0", "dynamics": "filterexact", "gain": 2.0, "bias": 0.0, "time_constant": 0.02},
            {"name": "c", "tendon": "t1", "dynamics": "integrator", "gain": 1.5, "bias": 0.0, "time_constant": None},
            {"name": "d", "tendon": "t0", "dynamics": "none", "gain": -1.0, "bias": 0.1, "time_constant": None}]
    bank = ActuatorBank.from_json(acts, ["t0", "t1"], 1e-3)
    ctrl = np.random.default_rng(0).uniform(-1, 1, (1, 50, 4))
    act_ref, _ = activations(ctrl, 1e-3, [a["dynamics"] for a in acts], np.array([0.04, 0.02, 0.0, 0.0]))
    act = torch.zeros(4, dtype=torch.float64)
    for t in range(50):
        c = torch.as_tensor(ctrl[0, t])
        f = bank.force(c, act).numpy()
        eff = np.where([a["dynamics"] == "none" for a in acts], ctrl[0, t], act_ref[0, t])
        np.testing.assert_allclose(f, [2.0 * eff[1] - eff[3] + 0.1, -3.0 * eff[0] + 1.5 * eff[2] + 0.2], atol=1e-13)
        act = bank.step(c, act)
    with pytest.raises(ValueError, match="tendon 'nope'"):
        ActuatorBank.from_json([dict(acts[0], tendon="nope")], ["t0"], 1e-3)


def test_fitted_twin_env_on_the_prism(tmp_path):
    """A fit of the floorless prism steps as its plant (free run over 200 steps at rounding); on the
    prism as shipped, Tensegrity-v0 with backend="identified" passes Gymnasium's and SB3's checkers
    and its actions are the motors' commands."""
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    xml = _floorless()
    path = tmp_path / "plant.xml"
    path.write_text(xml)
    data = collect(str(path), CollectConfig(episodes=2, steps=300, seed=3, push_every=50))
    model = identify(data, Topology.from_mjcf(str(path)), inertia="full", scale=ScaleSpec(total_mass=0.84))
    model.source_model = str(path)
    assert {a["name"] for a in model.actuators} == {"motor1", "motor2", "motor3"}
    json_path = tmp_path / "fit.json"
    save_model(json_path, model)
    err, _ = _run_both(xml, json_path, seed=5)
    assert err < 1e-8

    shipped = collect(PRISM, CollectConfig(episodes=2, steps=300, seed=0, push_every=20, push_magnitude=10.0))
    prism = tmp_path / "prism.json"
    save_model(prism, fit_model(shipped, PRISM, jobs=1))
    env = gym.make("Tensegrity-v0", xml_file=PRISM, backend="identified", model=str(prism),
                   backend_kwargs={"compile": False})
    assert env.action_space.shape == (3,)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the unbounded observation Box
        check_env(env.unwrapped, skip_render_check=True)
        sb3_check_env(env.unwrapped, warn=False)
    env.reset(seed=0)
    env.step(np.array([1.0, -1.0, 0.0], dtype=np.float32))
    np.testing.assert_allclose(env.unwrapped.backend.physics.ctrl.numpy(), [1.0, 0.0, 0.5])
    env.close()


def test_batched_twin_steps_the_actuators_as_the_single_twin(tmp_path):
    """``gym.make_vec("Tensegrity-v0", backend="identified")`` on a model with MuJoCo actuators (the
    floorless prism with a filtered general actuator with bias, a filterexact one and a motor):
    the batched twin against a SyncVectorEnv of single twins under the same seeds and random
    actions, observations (activations included) and rewards equal step by step; the actions move
    the activations."""
    from tensegrity_gym.envs.vector import TensegrityIcoVectorEnv

    xml = _floorless(FILTERED)
    path = tmp_path / "plant.xml"
    path.write_text(xml)
    json_path = tmp_path / "true.json"
    save_model(json_path, _true_model(xml, str(path)))
    kw = {"xml_file": str(path), "backend": "identified", "model": str(json_path), "frame_skip": 5,
          "backend_kwargs": {"dtype": "float64", "compile": False}}
    n = 3
    v = gym.make_vec("Tensegrity-v0", num_envs=n, vectorization_mode="vector_entry_point", **kw)
    s = gym.make_vec("Tensegrity-v0", num_envs=n, vectorization_mode="sync", **kw)
    assert isinstance(v, TensegrityIcoVectorEnv)
    assert v.single_action_space.shape == (3,) and v.action_space == s.action_space
    assert v.single_observation_space == s.single_observation_space
    ov, _ = v.reset(seed=7)
    os_, _ = s.reset(seed=7)
    np.testing.assert_array_equal(ov, os_)
    rng = np.random.default_rng(2)
    for _ in range(12):
        a = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        ov, rv, tv, trv, _ = v.step(a)
        os_, rs, ts, trs, _ = s.step(a)
        np.testing.assert_allclose(ov, os_, rtol=1e-6, atol=1e-6)  # float32 observations
        np.testing.assert_allclose(rv, rs, rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(tv, ts)
        np.testing.assert_array_equal(trv, trs)
    act_v = v.physics.actuator_state_numpy()
    act_s = np.stack([e.unwrapped.backend.actuator_state() for e in s.envs])
    np.testing.assert_allclose(act_v, act_s, rtol=0, atol=1e-13)
    assert np.all(np.abs(act_v[:, :2]) > 1e-3)  # the filters follow the commands
    pos_v = v.physics.states_numpy()[0]
    pos_s = np.stack([e.unwrapped.backend.states().pos for e in s.envs])
    np.testing.assert_allclose(pos_v, pos_s, rtol=0, atol=1e-12)
    v.close()
    s.close()


@pytest.mark.expensive
@pytest.mark.parametrize("name", ["six_bar_composite", "six_bar_nested"])
def test_twin_env_of_the_six_bars_passes_the_checkers(tmp_path, name):
    """Tensegrity-v0 with backend="identified" on the composite and nested 6-bars of ``examples/``
    (fitted from a short collection, ground contact included): Gymnasium's and SB3's checkers pass,
    its actions are the model's controls (the nested bar's filtered actuators, the composite's
    rest-length motors) as on the plant, and an episode starts where the plant's does."""
    from gymnasium.utils.env_checker import check_env
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    xml = os.path.join(os.path.dirname(PRISM), f"{name}.xml")
    data = collect(xml, CollectConfig(episodes=3, steps=1000, seed=1, push_every=50, push_magnitude=5.0))
    path = tmp_path / "fit.json"
    save_model(path, fit_model(data, xml, effects="ground_contact", jobs=1))
    twin = gym.make("Tensegrity-v0", xml_file=xml, backend="identified", model=str(path),
                    backend_kwargs={"compile": False})
    plant = gym.make("Tensegrity-v0", xml_file=xml)
    assert twin.action_space == plant.action_space and twin.observation_space.shape == plant.observation_space.shape
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the unbounded observation Box
        check_env(twin.unwrapped, skip_render_check=True)
        sb3_check_env(twin.unwrapped, warn=False)
    o_twin, _ = twin.reset(seed=4)
    o_plant, _ = plant.reset(seed=4)
    np.testing.assert_allclose(o_twin, o_plant, rtol=0, atol=1e-5)
    twin.close()
    plant.close()
