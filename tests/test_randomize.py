"""Domain randomization of the batched twin: per-env parameters, the draws, ``auto``, files, the env.

The per-env physics is checked against single twins built with one env's parameters (float64,
eager: equal to rounding); ``auto`` against the model file's own numbers; the env's latency and
observation noise against a twin without them fed the same commands.
"""

from __future__ import annotations

import copy
import dataclasses
import json

import gymnasium as gym
import numpy as np
import pytest
import torch

import tensegrity_gym  # noqa: F401  (registers the env)
from identified.effects.ground_contact import GroundContact
from identified.model import load_model
from identified.state import RodState
from identified.twin import engine_from_model
from tensegrity_gym.backends.identified_backend import IdentifiedBackend, default_model_path
from tensegrity_gym.backends.twin_physics import TwinPhysics, compiler_available
from tensegrity_gym.cli import main
from tensegrity_gym.envs.tensegrity_ico_v0 import action_to_rest, perturb_start
from tensegrity_gym.randomize import (
    CONTACT_FACTOR,
    CONTACT_PARAMETERS,
    CONTACT_TORQUE_PARAMETERS,
    GAMMA_MAX,
    PRIOR_WIDTH,
    Randomization,
    auto_randomization,
    load_randomization,
)
from tests._data import GROUND as GROUND_FIT

#: the robot fitted with ``ground_contact`` (the shipped model's data): the law whose parameters
#: most draws below name
GROUND = str(GROUND_FIT)
N, STEPS = 3, 40  # 3 envs, 40 control steps of 20 physics steps (0.8 s, several contacts change)


@pytest.fixture(scope="module")
def backend() -> IdentifiedBackend:
    """The robot fitted with ``ground_contact`` (tests/data/robot_ground_contact.json), whose
    contact law's parameters the draws below name."""
    return IdentifiedBackend(GROUND, dtype="float64", compile=False)


def _starts(b: IdentifiedBackend, n: int, seed: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    rng = np.random.default_rng(seed)
    starts = [perturb_start(b.nominal_states(), rng, 0.02) for _ in range(n)]
    return ([np.stack([getattr(s, f) for s in starts]) for f in ("pos", "quat", "vel", "angvel")],
            np.tile(b.nominal_rest_lengths(), (n, 1)))


def _targets(b: IdentifiedBackend, n: int, steps: int = STEPS) -> np.ndarray:
    rng = np.random.default_rng(5)
    return action_to_rest(rng.uniform(-1, 1, (steps, n, b.motor.n)), b.motor.rest_min, b.motor.rest_max)


def _roll(ph: TwinPhysics, targets: np.ndarray) -> np.ndarray:
    out = []
    for t in targets:
        ph.set_targets(t)
        ph.step(20)
        out.append(np.concatenate(ph.states_numpy(), axis=-1))
    return np.stack(out)


def _draws(b: IdentifiedBackend, ph: TwinPhysics) -> dict:
    """Parameters 30 % away from the model's, different in every env."""
    m, rng = b.model, np.random.default_rng(1)
    f = lambda *shape: 1 + 0.3 * rng.uniform(-1, 1, shape)
    S, R = m.stiffness.size, m.mass.size
    gc = ph.effect_parameters()["ground_contact"][:, 0].numpy() * f(N, len(GroundContact.blocks))
    return {"stiffness": m.stiffness * f(N, S), "damping": m.damping * f(N, S), "mass": m.mass * f(N, R),
            "inertia": m.inertia * f(N, R, 1), "motor_speed": b.motor.speed * f(N),
            "effects": {"ground_contact": gc}}


@pytest.mark.expensive  # ~10-20 s; with the benchmarks (the suite's 10 minutes)
def test_each_env_steps_as_a_single_twin_with_its_parameters(backend):
    """Env i of the per-env batch equals an unbatched twin built from a model holding env i's
    spring, rod, contact and motor parameters, to float64 rounding."""
    b = backend
    ph = TwinPhysics(engine_from_model(b.model), b.motor, b.actuated_index, batch=N, compile=False,
                     per_env=True)
    states, rest = _starts(b, N)
    ph.reset(*states, rest)
    d = _draws(b, ph)
    ph.set_parameters(None, **d)
    targets = _targets(b, N)
    batched = _roll(ph, targets)
    assert np.ptp(batched[-1, :, :, 0].mean(-1)) > 1e-3  # the envs went different ways
    for i in range(N):
        m = copy.deepcopy(b.model)
        m.stiffness, m.damping, m.mass, m.inertia = (d[k][i] for k in ("stiffness", "damping", "mass", "inertia"))
        gc = next(e for e in m.effects if e["name"] == "ground_contact")
        gc["parameters"] = dict(zip((p.name for p in GroundContact.blocks), map(float, d["effects"]["ground_contact"][i]),
                                    strict=True))
        motor = dataclasses.replace(b.motor, speed=float(d["motor_speed"][i]))
        single = TwinPhysics(engine_from_model(m), motor, b.actuated_index, batch=None, compile=False)
        single.reset(*(x[i] for x in states), rest[i])
        alone = _roll(single, targets[:, i])
        np.testing.assert_allclose(batched[:, i], alone, rtol=0, atol=1e-12)


def test_rest_offset_is_a_shifted_rest_length(backend):
    """An offset o on every cable's rest length steps as a twin whose motors run o higher
    (commands, bounds and start shifted by o)."""
    b = backend
    off = np.random.default_rng(2).uniform(-0.01, 0.01, len(b.tendon_names))
    ph = TwinPhysics(engine_from_model(b.model), b.motor, b.actuated_index, batch=1, compile=False,
                     per_env=True)
    states, rest = _starts(b, 1)
    ph.reset(*states, rest)
    ph.set_parameters(None, rest_offset=off[None])
    targets = _targets(b, 1)
    got = _roll(ph, targets)
    a = b.actuated_index
    motor = dataclasses.replace(b.motor, rest_min=b.motor.rest_min + off[a], rest_max=b.motor.rest_max + off[a])
    shifted = TwinPhysics(engine_from_model(b.model), motor, a, batch=1, compile=False)
    shifted.reset(*states, rest + off)
    want = _roll(shifted, targets + off[a])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    assert np.abs(got - _roll(_plain(b, states, rest), targets)).max() > 1e-4  # the offset matters


def _plain(b: IdentifiedBackend, states: list, rest: np.ndarray, per_env: bool = False) -> TwinPhysics:
    ph = TwinPhysics(engine_from_model(b.model), b.motor, b.actuated_index, batch=len(rest),
                     compile=False, per_env=per_env)
    ph.reset(*states, rest)
    return ph


def test_per_env_at_the_identified_values_is_todays_twin_exactly(backend):
    states, rest = _starts(backend, N)
    targets = _targets(backend, N, 15)
    np.testing.assert_array_equal(_roll(_plain(backend, states, rest, per_env=True), targets),
                                  _roll(_plain(backend, states, rest), targets))


@pytest.mark.expensive  # a 28 s compile; with the benchmarks (the suite's 10 minutes)
@pytest.mark.skipif(not compiler_available(), reason="torch.compile needs a C++ compiler")
def test_compiled_per_env_twin_reads_new_parameters(backend):
    """The compiled substep reads the per-env parameters written after its compilation."""
    b = backend
    states, rest = _starts(b, N)
    targets = _targets(b, N, 10)
    runs = []
    for compile in (True, False):
        ph = TwinPhysics(engine_from_model(b.model), b.motor, b.actuated_index, batch=N, compile=compile,
                         per_env=True)
        ph.reset(*states, rest)
        ph.step(20)  # compiled here, at the identified values
        ph.reset(*states, rest)
        ph.set_parameters(None, **_draws(b, ph))
        runs.append(_roll(ph, targets))
    assert ph.compiled is False
    np.testing.assert_allclose(runs[0], runs[1], rtol=0, atol=1e-9)


def test_set_parameters_needs_per_env(backend):
    with pytest.raises(ValueError, match="per_env"):
        _plain(backend, *_starts(backend, 2)).set_parameters(None, mass=np.ones((2, 6)))
    with pytest.raises(ValueError, match="chunk_size"):
        TwinPhysics(backend.engine, backend.motor, backend.actuated_index, batch=4, chunk_size=2, per_env=True)


# ---------------------------------------------------------------------- the distribution
def test_draw_is_reproducible_and_within_its_widths():
    r = Randomization(stiffness=0.1, mass=0.2, rest_offset=0.003, contact={"mu": 0.3}, latency=2, motor_speed=0.1)
    a, b = (r.draw(np.random.default_rng(7), 6, 24) for _ in range(2))
    for f in dataclasses.fields(a):
        np.testing.assert_array_equal(getattr(a, f.name), getattr(b, f.name))
    c = r.draw(np.random.default_rng(8), 6, 24)
    assert not np.array_equal(a.stiffness, c.stiffness)
    many = [r.draw(np.random.default_rng(s), 6, 24) for s in range(200)]
    k = np.stack([d.stiffness for d in many])
    assert 0.9 <= k.min() < 0.92 and 1.08 < k.max() <= 1.1
    np.testing.assert_array_equal(np.stack([d.damping for d in many]), 1.0)  # width 0: untouched
    mu = np.stack([d.contact for d in many])
    assert mu.shape == (200, 16) and np.all(np.delete(mu, 7, axis=1) == 1.0)
    assert 0.7 <= mu[:, 7].min() < 0.72 and 1.28 < mu[:, 7].max() <= 1.3
    assert {d.latency for d in many} == {0, 1, 2}
    assert np.abs(np.stack([d.rest_offset for d in many])).max() <= 0.003


def test_auto_comes_from_the_fit_numbers_not_the_mjcf():
    model = load_model(GROUND)
    r = auto_randomization(model)
    ev = model.metrics["residual_stage"]["ground_contact"]["explained_variance"]
    base = CONTACT_FACTOR * np.sqrt(1 - ev)
    gc = next(e for e in model.effects if e["name"] == "ground_contact")
    stage = model.metrics["residual_stage"]["ground_contact"]
    for name in (b.name for b in GroundContact.blocks):
        if name not in gc["parameters"]:  # a model written before the contact torques: none drawn
            assert name in CONTACT_TORQUE_PARAMETERS and name not in r.contact
            continue
        se = gc["stderr"][name]
        b = base if name not in CONTACT_TORQUE_PARAMETERS else CONTACT_FACTOR * np.sqrt(1 - stage["torque_explained_variance"])
        want = max(b, 0.1, 0 if se is None else 3 * abs(se / gc["parameters"][name]))
        cap = GAMMA_MAX if name.startswith("gamma") else 0.5
        assert r.contact[name] == pytest.approx(min(want, cap), rel=1e-12)
    assert r.stiffness == PRIOR_WIDTH  # a noise-free fit: 3 se of 1e-14 is below the prior
    assert r.obs_noise["vel"] == pytest.approx(model.metrics["one_step_rms"]["vel"] * np.sqrt(20), rel=1e-12)
    free = model.metrics["free_run"]
    assert r.obs_noise["pos"] == pytest.approx(free["pos_mean"] * np.sqrt(20 / free["horizon"]), rel=1e-12)
    # a better contact fit narrows the ranges, larger standard errors widen them
    other = copy.deepcopy(model)
    other.metrics["residual_stage"]["ground_contact"]["explained_variance"] = 0.99
    other.stderr["stiffness"] = 0.04 * np.asarray(other.stiffness)
    gc_other = next(e for e in other.effects if e["name"] == "ground_contact")
    gc_other["stderr"]["beta_a"] = 0.2 * gc_other["parameters"]["beta_a"]
    w = auto_randomization(other)
    assert w.contact["kappa"] == pytest.approx(CONTACT_FACTOR * 0.1, rel=1e-12)
    assert w.contact["beta_a"] == 0.5  # 3 standard errors (0.6), capped
    assert w.stiffness == pytest.approx(0.12, rel=1e-12)
    # the MJCF is not read: another source model gives the same widths
    other = copy.deepcopy(model)
    other.source_model = "/nonexistent/robot.xml"
    assert auto_randomization(other).to_json() == r.to_json()


def test_auto_draws_the_pyramid_laws_parameters():
    """A model whose ground is ``pyramid_contact``: each of its parameters gets the width of its fit's
    unexplained variance (or 3 standard errors), the impedances at most half their way to 1, and
    a draw scales that law's parameters only."""
    from identified.effects.pyramid_contact import PyramidContact

    model = copy.deepcopy(load_model(GROUND))
    values = {"beta": 105.0, "kappa": 2770.0, "imp_min": 0.9, "imp_max": 0.95, "imp_width": 1e-3, "mu": 0.9,
              "mu_torsion": 0.02, "mu_rolling": 0.002}
    stderr = {k: 1e-12 * v for k, v in values.items()}
    stderr["mu_rolling"] = 0.1 * values["mu_rolling"]  # 3 standard errors: 0.3
    gc = next(e for e in model.effects if e["name"] == "ground_contact")
    model.effects = [{"name": "pyramid_contact", "parameters": values, "stderr": stderr, "options": gc["options"]}]
    model.metrics["residual_stage"] = {"pyramid_contact": {"explained_variance": 1 - 1e-4}}
    r = auto_randomization(model)
    base = CONTACT_FACTOR * 1e-2  # 4 sqrt(1e-4) = 0.04, below the floor
    want = {k: 0.1 for k in values} | {"mu_rolling": 0.3, "imp_min": 0.5 * 0.1 / 0.9, "imp_max": 0.5 * 0.05 / 0.95}
    assert base < 0.1 and set(r.contact) == set(values)
    for k, v in want.items():
        assert r.contact[k] == pytest.approx(v, rel=1e-12), k
    d = r.draw(np.random.default_rng(3), 6, 24)
    idx = [CONTACT_PARAMETERS.index(b.name) for b in PyramidContact.blocks]
    f = d.contact[idx]
    assert np.all(np.abs(f - 1) <= [want[b.name] for b in PyramidContact.blocks]) and np.all(f != 1)
    assert np.all(np.delete(d.contact, idx) == 1.0)  # ground_contact's own parameters: not this model's


def test_file_round_trip_and_bad_files(tmp_path):
    r = Randomization(stiffness=0.05, contact={"kappa": 0.3}, latency=1, obs_noise={"vel": 0.01}, source="x")
    p = tmp_path / "r.json"
    p.write_text(json.dumps(r.to_json()))
    back = load_randomization(p)
    assert back.to_json() | {"source": "x"} == r.to_json()
    bad = tmp_path / "bad.json"
    for text, match in (('{"stifness": 0.1}', "unknown randomization key"), ('{"mass": 1.5}', "must be < 1"),
                        ('{"contact": {"kapa": 0.1}}', "unknown key 'kapa'"), ("{", "not valid JSON"),
                        ('{"latency": 0.5}', "integer")):
        bad.write_text(text)
        with pytest.raises(ValueError, match=match):
            load_randomization(bad)


def test_cli_rejects_a_bad_randomization_file(tmp_path, capsys):
    bad = tmp_path / "r.json"
    bad.write_text('{"mass": -1}')
    code = main(["train", "--identified", default_model_path(), "--timesteps", "64", "--randomize", str(bad),
                 "--out", str(tmp_path / "P.zip"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "--randomize" in err and "'mass'" in err and "Traceback" not in err
    assert not (tmp_path / "P.zip").exists()


# ---------------------------------------------------------------------- the env
def _venv(n: int, randomize, **kw):
    return gym.make_vec("TensegrityIco-v0", num_envs=n, vectorization_mode="vector_entry_point", backend="identified",
                        model=GROUND, randomize=randomize, backend_kwargs={"dtype": "float64", "compile": False}, **kw)


def test_env_draws_per_env_and_reproducibly():
    r = Randomization(stiffness=0.2, mass=0.2, contact={"kappa": 0.3, "mu": 0.3})
    rows = []
    for _ in range(2):
        v = _venv(3, r)
        v.reset(seed=4)
        p = v.unwrapped.physics.engine.params
        rows.append((p.stiffness.numpy().copy(), p.mass.numpy().copy(),
                     v.unwrapped.physics.effect_parameters()["ground_contact"].numpy().copy()))
    for a, b in zip(*rows, strict=True):
        np.testing.assert_array_equal(a, b)
    k, m, gc = rows[0]
    assert len({tuple(x) for x in k}) == 3  # every env its own
    ratio = m / load_model(GROUND).mass
    assert np.all(np.abs(ratio - 1) <= 0.2) and np.ptp(ratio) > 0.01
    assert np.ptp(gc[:, 0, 2]) == 0  # gamma_n: width 0


def test_env_without_randomization_is_unchanged():
    acts = np.random.default_rng(0).uniform(-1, 1, (5, 2, 24))
    outs = []
    for r in (None, Randomization()):
        v = _venv(2, r)
        o, _ = v.reset(seed=1)
        seq = [o] + [v.step(a)[0] for a in acts]
        outs.append(np.stack(seq))
        assert v.unwrapped.physics.per_env is False
    np.testing.assert_array_equal(*outs)


def test_latency_delays_commands_and_noise_leaves_the_state():
    """With latency k the env is the plain env fed the actions k steps late (the first k the
    reset's rest lengths); observation noise has the width asked and does not touch the physics."""
    acts = np.random.default_rng(3).uniform(-1, 1, (8, 2, 24))
    r = Randomization(latency=2, obs_noise={"vel": 0.5})
    v = _venv(2, r)
    seed = next(s for s in range(50) if _latencies(v, s) == [2, 0])
    o_noisy, _ = v.reset(seed=seed)
    plain = _venv(2, None)
    o_clean, _ = plain.reset(seed=seed)
    nominal = np.zeros(24)  # the reset's rest lengths are the neutral command
    from tensegrity_gym.envs.tensegrity_ico_v0 import rest_to_action

    e = plain.unwrapped.env
    nominal = rest_to_action(plain.unwrapped.physics.rest_numpy()[0][e.actuated_index], e.rest_min, e.rest_max)
    diffs = []
    for k in range(len(acts)):
        late = np.stack([acts[k - 2, 0] if k >= 2 else nominal, acts[k, 1]])
        o_noisy = v.step(acts[k])[0]
        o_clean = plain.step(late)[0]
        np.testing.assert_allclose(v.unwrapped.physics.states_numpy()[0], plain.unwrapped.physics.states_numpy()[0],
                                   rtol=0, atol=1e-12)
        diffs.append(o_noisy - o_clean)
    d = np.stack(diffs)
    names = __import__("tensegrity_gym.envs.tensegrity_ico_v0", fromlist=["x"]).observation_names(
        plain.unwrapped.backend.rod_names, plain.unwrapped.backend.actuated_names)
    vel = np.array(["_vel_" in n for n in names])
    assert np.all(d[..., ~vel] == 0)
    assert 0.4 < d[..., vel].std() < 0.6


def _latencies(v, seed: int) -> list[int]:
    v.reset(seed=seed)
    return v.unwrapped._latency.tolist()


def test_pushes_move_the_robot():
    r = Randomization(push_force=200.0, push_probability=1.0)
    v, plain = _venv(2, r), _venv(2, None)
    v.reset(seed=0)
    plain.reset(seed=0)
    a = np.zeros((2, 24))
    for _ in range(3):
        v.step(a)
        plain.step(a)
    assert np.abs(v.unwrapped.physics.states_numpy()[2] - plain.unwrapped.physics.states_numpy()[2]).max() > 0.05


def test_training_records_its_randomization(tmp_path):
    from tensegrity_gym.training import TrainConfig, load_policy, train

    cfg = TrainConfig(timesteps=128, seed=0, envs=2, rollout=64, randomize="auto", identified=GROUND,
                      backend_kwargs={"compile": False})
    train(cfg, tmp_path / "P.zip", progress=False)
    meta = load_policy(tmp_path / "P.zip").meta
    want = auto_randomization(load_model(GROUND)).to_json()
    assert meta["randomization"] == json.loads(json.dumps(want))
    cfg.randomize = "none"
    train(cfg, tmp_path / "Q.zip", progress=False)
    assert load_policy(tmp_path / "Q.zip").meta["randomization"] is None
    assert torch.get_num_threads() >= 1


def test_turn_about_vertical_is_a_rigid_turn_of_the_whole_state():
    from identified.rotation import quat_to_matrix
    from tensegrity_gym.envs.tensegrity_ico_v0 import turn_about_vertical

    rng = np.random.default_rng(5)
    s = RodState(rng.normal(size=(6, 3)), rng.normal(size=(6, 4)), rng.normal(size=(6, 3)), rng.normal(size=(6, 3)))
    s.quat /= np.linalg.norm(s.quat, axis=-1, keepdims=True)
    t = turn_about_vertical(s, np.pi / 2)  # x -> y, y -> -x about the centre of mass
    com = s.pos.mean(0)
    d = s.pos - com
    np.testing.assert_allclose(t.pos - com, np.stack([-d[:, 1], d[:, 0], d[:, 2]], -1), atol=1e-12)
    np.testing.assert_allclose(t.vel, np.stack([-s.vel[:, 1], s.vel[:, 0], s.vel[:, 2]], -1), atol=1e-12)
    np.testing.assert_allclose(t.angvel, np.stack([-s.angvel[:, 1], s.angvel[:, 0], s.angvel[:, 2]], -1), atol=1e-12)
    rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(quat_to_matrix(t.quat), rz @ quat_to_matrix(s.quat), atol=1e-12)


def test_reset_yaw_turns_the_start_and_the_twin_turns_with_it():
    """A start turned about the vertical rolls as the unturned start turned: the twin's physics
    (gravity, a horizontal ground, the contact law's per-rod friction axes) has no heading, so
    the env with ``reset_yaw`` is the plain env turned by each env's own drawn angle."""
    from tensegrity_gym.envs.tensegrity_ico_v0 import turn_about_vertical

    w = 2.0
    v, plain = _venv(3, Randomization(reset_yaw=w)), _venv(3, None)
    v.reset(seed=7)
    plain.reset(seed=7)

    def yaw(a, b):  # the angle turning the rod layout b into a, about their centres of mass
        da, db = a - a.mean(0), b - b.mean(0)
        return np.arctan2((db[:, 0] * da[:, 1] - db[:, 1] * da[:, 0]).sum(), (db[:, :2] * da[:, :2]).sum())

    s0, p0 = v.unwrapped.physics.states_numpy(), plain.unwrapped.physics.states_numpy()
    angles = np.array([yaw(s0[0][i], p0[0][i]) for i in range(3)])
    assert np.all(np.abs(angles) <= w) and np.ptp(angles) > 0.1  # each env its own heading, within the width
    acts = np.random.default_rng(2).uniform(-1, 1, (15, 3, 24))
    for a in acts:
        v.step(a)
        plain.step(a)
    s, p = v.unwrapped.physics.states_numpy(), plain.unwrapped.physics.states_numpy()
    assert np.abs(s[0] - p[0]).max() > 0.1  # the turned robot is elsewhere ...
    for i in range(3):  # ... where the plain robot turned by its angle is
        t = turn_about_vertical(RodState(*(x[i] for x in p)), angles[i])
        c0, c, th = p0[0][i].mean(0), p[0][i].mean(0), angles[i]  # turned about the start's centre of mass
        rz = np.array([[np.cos(th), -np.sin(th), 0.0], [np.sin(th), np.cos(th), 0.0], [0.0, 0.0, 1.0]])
        t.pos += (c0 - c) - rz @ (c0 - c)
        for got, want in zip((s[0][i], s[2][i], s[3][i]), (t.pos, t.vel, t.angvel), strict=True):
            np.testing.assert_allclose(got, want, atol=1e-9)
