"""The fast twin: float32 against the float64 engine, the compiled substep against the eager one,
and the thread policy (scoped, overridable). No timings are asserted here (benchmarks/bench_twin.py)."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

from identified.engine import SpringRodEngine
from identified.model import IdentifiedModel
from identified.rotation import quat_to_matrix
from identified.topology import Topology
from identified.twin import engine_from_model
from tensegrity_gym.backends.identified_backend import IdentifiedBackend
from tensegrity_gym.backends.mujoco_backend import default_robot_xml
from tensegrity_gym.backends.twin_physics import (
    TwinPhysics,
    compiler_available,
    resolve_threads,
    torch_threads,
)
from tensegrity_gym.envs.tensegrity_ico_v0 import action_to_rest, perturb_start
from tensegrity_gym.models import preset_parameters
from tests._data import GROUND

N, STEPS, SUBSTEPS = 6, 100, 20  # 6 starts, 100 control steps of 20 physics steps: 2 s each


@pytest.fixture(scope="module")
def floating():
    """(model, MJCF text): the robot's true parameters without ground and without gravity, so that
    positions stay O(1) m and float32's absolute rounding stays that of the shape, not of a fall."""
    root = ET.fromstring(default_robot_xml())
    world = root.find("worldbody")
    world.remove(world.find("geom[@name='ground']"))
    xml = ET.tostring(root, encoding="unicode")
    t = preset_parameters("ico", "robot")
    model = IdentifiedModel(
        topology=Topology.from_mjcf(xml),
        stiffness=np.array([s["stiffness"] for s in t["springs"]]),
        damping=np.array([s["damping"] for s in t["springs"]]),
        rest_length=np.array([s["rest_length"] for s in t["springs"]]),
        mass=np.array([r["mass"] for r in t["rods"]]),
        inertia=np.array([r["inertia"] for r in t["rods"]]),
        dt=t["timestep"], gravity=np.zeros(3),
    )
    return model, xml


def _episode(model, xml, dtype: torch.dtype, compile: bool) -> tuple[np.ndarray, ...]:
    """N twins from perturbed nominal poses under random cable targets (new ones every 0.5 s):
    the (STEPS, N, R, ·) positions, rod axes, velocities and rest lengths, float64."""
    return _run(IdentifiedBackend(model, dtype="float64", mjcf=xml, compile=False), dtype, compile)


def _run(b: IdentifiedBackend, dtype: torch.dtype, compile: bool) -> tuple[np.ndarray, ...]:
    """The episode of :func:`_episode` on ``b``'s model and motors, in ``dtype``."""
    engine = engine_from_model(b.model, dtype=dtype)
    ph = TwinPhysics(engine, b.motor, b.actuated_index, batch=N, compile=compile)
    rng = np.random.default_rng(0)
    starts = [perturb_start(b.nominal_states(), rng, 0.05) for _ in range(N)]
    ph.reset(*(np.stack([getattr(s, f) for s in starts]) for f in ("pos", "quat", "vel", "angvel")),
             np.tile(b.nominal_rest_lengths(), (N, 1)))
    out = []
    for k in range(STEPS):
        if k % 25 == 0:
            targets = action_to_rest(rng.uniform(-1, 1, (N, b.motor.n)), b.motor.rest_min, b.motor.rest_max)
        ph.set_targets(targets)
        ph.step(SUBSTEPS)
        pos, quat, vel, _ = ph.states_numpy()
        out.append((pos, quat_to_matrix(quat)[..., 2], vel, ph.rest_numpy()))
    assert not ph.diverged.any()
    return tuple(np.stack(x) for x in zip(*out))


@pytest.fixture(scope="module")
def reference(floating):
    return _episode(*floating, torch.float64, compile=False)


def _assert_float32_close(run, reference) -> None:
    pos, axis, vel, rest = run
    pos0, axis0, vel0, rest0 = reference
    # float32 carries ~7 digits, accumulated over 2,000 stiff steps; measured (eager and compiled):
    # 1e-5 m, 1.6e-5, 1.3e-4 m/s, 2.3e-5 m: the bounds leave a factor 6-15
    assert np.abs(pos - pos0).max() < 1e-4  # m, on a 1.7 m robot
    assert np.abs(axis - axis0).max() < 1e-4  # rod directions (the axial spin is free: see below)
    assert np.abs(vel - vel0).max() < 2e-3  # m/s, of velocities ~0.5 m/s
    assert np.abs(rest - rest0).max() < 2e-4  # m: the motors integrate 0.3 mm steps
    assert np.abs(pos - pos0).max() > 0  # really two precisions


def test_float32_twin_agrees_with_float64_over_an_episode(floating, reference):
    """The default twin (float32) stays within float32 rounding of the float64 engine for 2 s of
    random cable commands. The spin of a rod about its own axis is left out: springs attach on the
    axis, so nothing but rounding drives it, and its inertia is ~1/100 of the transverse one."""
    _assert_float32_close(_episode(*floating, torch.float32, compile=False), reference)


# with the benchmarks (~33 s with inductor's cache empty, as in CI): the compiled substep equals the
# eager one (below, float64), and the eager float32 twin agrees (above)
@pytest.mark.expensive
@pytest.mark.skipif(not compiler_available(), reason="torch.compile needs a C++ compiler")
def test_compiled_float32_twin_agrees_with_float64(floating, reference):
    model, xml = floating
    _assert_float32_close(_episode(model, xml, torch.float32, compile=True), reference)


@pytest.mark.skipif(not compiler_available(), reason="torch.compile needs a C++ compiler")
def test_compiled_substep_equals_eager_in_float64(floating):
    """The compiled substep equals the eager one in float64 (cables, motors and a push; the compiled
    contact substep: test_contact_substep_traces_as_one_graph checks it is one graph, and the
    episode test with the benchmarks checks its numbers)."""
    model, xml = floating
    b = IdentifiedBackend(model, dtype="float64", mjcf=xml, compile=True)
    e = IdentifiedBackend(model, dtype="float64", mjcf=xml, compile=False)
    hold = b.nominal_rest_lengths()[b.actuated_index] * 0.9
    push = np.zeros((6, 3))
    push[2] = [20.0, 0.0, -10.0]
    for x in (b, e):
        x.reset(x.nominal_states(), x.nominal_rest_lengths())
        x.step(hold, 20)
        x.step(hold, 5, push_force=push, push_point=np.full((6, 3), 0.1))
    assert b.physics.compiled and b.physics.compile_seconds > 0
    for f in ("pos", "quat", "vel", "angvel"):
        np.testing.assert_allclose(getattr(b.states(), f), getattr(e.states(), f), rtol=0, atol=1e-12)


def test_failed_compilation_warns_and_runs_eagerly(floating, monkeypatch):
    model, xml = floating

    def broken(*args, **kwargs):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(torch, "compile", broken)
    monkeypatch.setenv("TENSEGRITY_TWIN_CACHE", "0")  # a stored entry would be loaded, not compiled
    b = IdentifiedBackend(model, dtype="float64", mjcf=xml, compile=True)
    e = IdentifiedBackend(model, dtype="float64", mjcf=xml, compile=False)
    hold = b.nominal_rest_lengths()[b.actuated_index]
    for x in (b, e):
        x.reset(x.nominal_states(), x.nominal_rest_lengths())
    with pytest.warns(UserWarning, match="runs eagerly"):
        b.step(hold, 3)
    e.step(hold, 3)
    assert not b.physics.compiled
    np.testing.assert_array_equal(b.states().pos, e.states().pos)

    # a compilation that fails later (a new shape, a push): the step is redone eagerly
    def flaky(fn, **kwargs):
        calls = []

        def compiled(*args):
            calls.append(1)
            if len(calls) > 2:
                raise RuntimeError("recompilation failed")
            return fn(*args)

        return compiled

    monkeypatch.setattr(torch, "compile", flaky)
    b = IdentifiedBackend(model, dtype="float64", mjcf=xml, compile=True)
    b.reset(e.nominal_states(), e.nominal_rest_lengths())
    e.reset(e.nominal_states(), e.nominal_rest_lengths())
    b.step(hold, 2)  # the two calls that work
    assert b.physics.compiled
    with pytest.warns(UserWarning, match="runs eagerly"):
        b.step(hold, 3)
    e.step(hold, 5)
    assert not b.physics.compiled
    np.testing.assert_array_equal(b.states().pos, e.states().pos)


def test_thread_policy_is_scoped_and_overridable(floating):
    """The twin steps under its own thread count and gives the caller's back afterwards."""
    model, xml = floating
    seen: list[int] = []

    def spy(state, ctx):  # an effect that only records the thread count during the step
        seen.append(torch.get_num_threads())
        return None, None

    before = torch.get_num_threads()
    for threads, expected in (("auto", 1), (None, before), (3, 3)):
        b = IdentifiedBackend(model, mjcf=xml, effects=[spy], compile=False, num_threads=threads)
        b.step(b.nominal_rest_lengths()[b.actuated_index], 1)
        assert seen[-1] == expected
        assert torch.get_num_threads() == before  # the user's setting is untouched
    with torch_threads(2):
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == before
    assert resolve_threads("auto", torch.device("cuda")) is None  # nothing to set for a GPU
    for bad in (0, -1, "many", 1.5, True):
        with pytest.raises(ValueError, match="num_threads"):
            resolve_threads(bad, torch.device("cpu"))
    with pytest.raises(ValueError, match="compile"):
        IdentifiedBackend(model, mjcf=xml, compile="sometimes")


# ---------------------------------------------------------------------- with ground contact
@pytest.fixture(scope="module")
def contact_backend():
    """The robot fitted with ground contact (tests/data/robot_ground_contact.json: the shipped
    model's data fitted with ``ground_contact``), float64, as the reference's source."""
    b = IdentifiedBackend(str(GROUND), dtype="float64",
                          compile=False)
    assert [e.name for e in b.engine.effects] == ["ground_contact"]
    return b


def _contact_episode(b: IdentifiedBackend, dtype: torch.dtype, compile: bool) -> tuple[np.ndarray, ...]:
    """As :func:`_episode`, on the shipped model: the robot falls onto, stands and rolls on the
    ground (its end caps touch down and lift off), 2 s of random cable commands."""
    return _run(b, dtype, compile)


# both with the benchmarks (the compiled one ~61 s with inductor's cache empty, as in CI; compiling
# the contact substep takes 50-85 s there): the compiled substep equals the eager one in float64
# without contact (test_compiled_substep_equals_eager_in_float64) and the contact substep is one
# graph for the compiler (test_contact_substep_traces_as_one_graph)
@pytest.mark.expensive
@pytest.mark.parametrize("compile", [False, pytest.param(True, marks=pytest.mark.skipif(
    not compiler_available(), reason="torch.compile needs a C++ compiler"))])
def test_float32_contact_twin_agrees_with_float64_over_an_episode(contact_backend, compile):
    """The default twin (float32, compiled or not) with ground contact against the float64 engine
    over 2 s (2,000 steps) of random commands, the end caps touching down and lifting off.

    The contact force is a difference of large terms (it cancels the acceleration that the springs
    and gravity give the contact point, ~100 m/s², to leave the soft-constraint remainder), so
    float32 rounding accumulates faster than without contact. Measured, eager and compiled alike,
    and the same before the contact law was rewritten for speed (so the rewrite adds nothing):
    positions 0.7-1.0 mm (rising ~linearly: 7e-5 m at 0.5 s), rod axes 1.6e-3, velocities 0.035 m/s,
    rest lengths 2.3e-5 m. The float64 engine started from the float32-rounded state stays within
    1e-7 m: the error is float32's arithmetic, not the dynamics amplifying the start."""
    b = contact_backend
    ref = _contact_episode(b, torch.float64, compile=False)
    pos, axis, vel, rest = _contact_episode(b, torch.float32, compile=compile)
    pos0, axis0, vel0, rest0 = ref
    assert np.abs(pos0[..., 2]).min() < 0.3 and np.ptp(pos0[..., 0]) > 0.2  # it lies and rolls on the ground
    assert np.abs(pos - pos0).max() < 4e-3  # m, on a 1.7 m robot moving ~1 m
    assert np.abs(pos - pos0)[:25].max() < 4e-4  # the first 0.5 s
    assert np.abs(axis - axis0).max() < 6e-3
    assert np.abs(vel - vel0).max() < 0.12  # m/s
    assert np.abs(rest - rest0).max() < 2e-4  # m
    assert np.abs(pos - pos0).max() > 0  # really two precisions


def _states_in_the_ground(b, rng: np.random.Generator, n: int):
    """``n`` perturbed nominal states of the contact backend's engine, lowered by up to 0.3 m (end
    caps in the ground) and moving."""
    st = [perturb_start(b.nominal_states(), rng, 0.3) for _ in range(n)]
    s = b.engine.state(*(np.stack([getattr(x, f) for x in st]) for f in ("pos", "quat", "vel", "angvel")))
    s.pos[..., 2] -= torch.as_tensor(rng.uniform(0, 0.3, (n, 1)))
    s.vel += torch.as_tensor(rng.normal(0, 0.5, s.vel.shape))
    s.angvel += torch.as_tensor(rng.normal(0, 1.0, s.angvel.shape))
    return s


def test_fast_contact_wrench_equals_the_fitted_law(contact_backend):
    """The twin's form of the contact law (:meth:`GroundContact.wrench_components`: component form,
    no per-parameter columns, 3x3 blocks) equals the form the fit and the eager engine use
    (``contact_forces`` then ``_to_wrench``) in float64, on states that put end caps into the
    ground, moving."""
    from identified.engine.smallmat import mat, unvec, vec

    b = contact_backend
    e = b.engine
    gc = e.effects[0]
    rng = np.random.default_rng(1)
    n = 64
    s = _states_in_the_ground(b, rng, n)
    bare = SpringRodEngine(e.graph, e.params, e.dt, dtype=torch.float64)
    t = bare.dynamics(s, np.tile(b.nominal_rest_lengths(), (n, 1)))
    ctx = t.ctx._replace(base_lin_acc=t.lin_acc, base_ang_acc_body=t.ang_acc_body)
    c, f = gc.contact_forces(s, ctx)
    force0, torque0 = gc._to_wrench(c, f)
    torque0 = torque0 + gc.contact_torque(s, f, gc.theta(s.pos))  # torsional and rolling friction
    force, torque = (unvec(x) for x in gc.wrench_components(
        vec(s.pos), vec(s.vel), vec(s.angvel), mat(ctx.rot), vec(ctx.base_lin_acc), vec(ctx.base_ang_acc_body),
        ctx.params.mass, vec(ctx.params.inertia)))
    active = c["active"]
    assert 50 < int(active.sum()) < active.numel()  # contacts and free ends, both
    assert ((f[..., 0] == 0) & active).any()  # and ends released as pulling
    scale = float(force0.abs().max())
    torch.testing.assert_close(force, force0, rtol=0, atol=1e-12 * scale)
    torch.testing.assert_close(torque, torque0, rtol=0, atol=1e-12 * scale)


def test_fused_step_equals_the_engine_step(contact_backend):
    """The twin's step in component form (``SpringRodEngine.step_components``, what the compiled
    substep runs) equals the identification engine's ``step`` (``dynamics`` then
    ``semi_implicit_euler``, the tensor form) in float64, with ground contact and a push at a point,
    on states with end caps in the ground."""
    from identified.engine.smallmat import unvec, vec

    b = contact_backend
    e = b.engine
    assert e.fused
    rng = np.random.default_rng(2)
    n = 32
    s = _states_in_the_ground(b, rng, n)
    rest = torch.as_tensor(np.tile(b.nominal_rest_lengths(), (n, 1)))
    push, point = torch.as_tensor(rng.normal(0, 5, (n, 6, 3))), torch.as_tensor(rng.normal(0, 0.2, (n, 6, 3)))
    for pf, pp in ((None, None), (push, None), (push, point)):
        want = e.step(s, rest, pf, pp)
        got = e.step_components(vec(s.pos), tuple(s.quat.unbind(-1)), vec(s.vel), vec(s.angvel), rest, pf, pp)
        for a, w in zip(got, want):
            torch.testing.assert_close(unvec(a), w, rtol=1e-12, atol=1e-12 * float(w.abs().max()))


def test_block_inverses_equal_lapack():
    from identified.effects.ground_contact import _masked_block_solve
    from identified.engine.smallmat import inverse3, mat, mmul, unvec, vec

    g = torch.Generator().manual_seed(0)
    a = torch.randn(50, 6, 6, generator=g, dtype=torch.float64)
    spd = a @ a.transpose(-1, -2) + 0.5 * torch.eye(6, dtype=torch.float64)
    rhs = torch.randn(50, 6, generator=g, dtype=torch.float64)
    blocks = [mat(spd[:, i:i + 3, j:j + 3].contiguous()) for i, j in ((0, 0), (0, 3), (3, 3))]
    on = torch.ones(50, dtype=torch.bool)
    x0, x1 = _masked_block_solve(*blocks, (on, on), [vec(rhs[:, :3]), vec(rhs[:, 3:])])
    torch.testing.assert_close(torch.cat((unvec(x0), unvec(x1)), -1), torch.linalg.solve(spd, rhs),
                               rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(inverse3(spd[:, :3, :3]), torch.linalg.inv(spd[:, :3, :3]), rtol=1e-9, atol=1e-9)
    prod = torch.stack(mmul(mat(a[:, :3, :3]), mat(a[:, 3:, 3:])), -1).unflatten(-1, (3, 3))
    torch.testing.assert_close(prod, a[:, :3, :3] @ a[:, 3:, 3:])


def test_contact_substep_traces_as_one_graph(contact_backend):
    """The twin's substep with ground contact is ONE graph for torch.compile (no graph break), as
    the physics compiles it: after one eager substep has filled the effects' caches."""
    b = IdentifiedBackend(compile=False)  # the twin as shipped: float32, contact on
    ph = b.physics
    assert ph._fused  # the component-form step (SpringRodEngine.step_components)
    from tensegrity_gym.backends.twin_physics import _split

    args = (_split(ph.state), ph.rest, ph.rest_act, ph.target, None, None)
    with torch.no_grad():
        ph._eager_substep(*args)
        explained = torch._dynamo.explain(ph._eager_substep)(*args)
    assert explained.graph_count == 1 and explained.graph_break_count == 0, explained.break_reasons


def test_auto_compile_without_a_compiler_warns_once_and_runs_eagerly(monkeypatch):
    """``compile="auto"`` on a CPU without a C++ compiler runs the twin eagerly and says so once a
    process (the exact contact law is many times slower eagerly); ``TENSEGRITY_TWIN_COMPILE=0``
    asks for eager: no warning; with a compiler the twin compiles."""
    import warnings

    from tensegrity_gym.backends import twin_physics as tp

    cpu = torch.device("cpu")
    monkeypatch.delenv(tp.COMPILE_ENV, raising=False)
    monkeypatch.setattr(tp, "compiler_available", lambda: False)
    monkeypatch.setattr(tp, "_warned_eager", False)
    with pytest.warns(RuntimeWarning, match=r"no C\+\+ compiler on the PATH"):
        assert tp._wants_compile("auto", cpu) is False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert tp._wants_compile("auto", cpu) is False  # said once
        monkeypatch.setattr(tp, "_warned_eager", False)
        monkeypatch.setenv(tp.COMPILE_ENV, "0")
        assert tp._wants_compile("auto", cpu) is False  # eager asked for: nothing to say
        monkeypatch.delenv(tp.COMPILE_ENV)
        monkeypatch.setattr(tp, "compiler_available", lambda: True)
        assert tp._wants_compile("auto", cpu) is True
        assert tp._wants_compile(False, cpu) is False
