"""Bad input never produces silent nonsense, a destroyed file or a dishonest error bar.

Targeted tests of each guard (residual degrees of freedom, physical constraints, the model
loader, outputs that are inputs, limits checked before work, one clear line), the tests that kill
the mutants the suite used to let live, and a property-based fuzz suite over the command line and
the env API.  Every command runs in-process (:func:`tests._fuzz.run_cli`): an exception escaping
``main`` fails the test as a traceback would.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import tensegrity_gym  # noqa: F401  (registers the env)
from identified import Topology
from identified.dataset import DatasetError, load_dataset, save_dataset
from identified.fit.checks import (
    InsufficientDataError,
    constrain_inertias,
    overlap_factor,
    physical_warnings,
    residual_dof,
)
from identified.fit.identify import identify
from identified.fit.regression import BlockFactors
from identified.fit.uncertainty import LinearSolve, covariance
from identified.jsonsafe import json_safe
from identified.model import ModelFileError, load_model, save_model
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.limits import MemoryLimitError, check_memory, collect_bytes
from tensegrity_gym.models import preset_parameters, write_model
from tests._fuzz import (
    BAD_FLAGS,
    BAD_FLOATS,
    DATASET_KEYS,
    DATASET_KINDS,
    FILE_KINDS,
    MODEL_FIELDS,
    MODEL_KINDS,
    check_outcome,
    corrupt_dataset,
    corrupt_file,
    corrupt_model,
    digest,
    finite,
    finite_json,
    flag_argv,
    run_cli,
)

FUZZ = settings(max_examples=int(os.environ.get("TENSEGRITY_FUZZ_EXAMPLES", "12")), deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, str]:
    """A valid ico model, a small clean dataset with pushes, and its fit."""
    d = tmp_path_factory.mktemp("valid")
    f = {"ico": str(d / "ico.xml"), "data": str(d / "data.npz"), "fit": str(d / "fit.json")}
    write_model(f["ico"], "ico", preset="paper-nonuniform", seed=3)
    data = collect(f["ico"], CollectConfig(episodes=2, steps=60, seed=1, push_every=20))
    save_dataset(f["data"], data)
    save_model(f["fit"], identify(data, Topology.from_mjcf(f["ico"])))
    return f


@pytest.fixture
def work(tmp_path, monkeypatch) -> Path:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("TENSEGRITY_DEBUG", raising=False)
    return tmp_path


def one_error(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tensegrity: error: "), err
    return lines[0]


# ---------------------------------------------------------------------- 1. honest estimates
def test_no_residual_dof_is_refused_with_how_much_more_data(files, work):
    """1 x 400 noisy steps, weak form: 72 equations for 96 free parameters (24 preloads included)."""
    noisy = collect(files["ico"], CollectConfig(episodes=1, steps=400, seed=1, push_every=50, noise_pos=1e-3,
                                                noise_vel=1e-2, noise_quat=1e-3, noise_angvel=1e-2))
    save_dataset("noisy.npz", noisy)
    before = digest(work)
    rc, _out, err = run_cli(["fit", "noisy.npz", "--model", files["ico"], "--out", "F.json", "--quiet"])
    line = one_error(err)
    assert rc == 2 and "free parameters" in line and "more steps" in line, line
    assert digest(work) == before  # no F.json
    with pytest.raises(InsufficientDataError):
        identify(noisy, Topology.from_mjcf(files["ico"]))


def test_few_dof_marks_error_bars_not_estimable(files, work):
    # 4 instants: 144 equations for 95 free parameters (24 preloads included): solvable, 49 residual
    # degrees of freedom, too few for error bars (3 instants leave K and K l0 of some springs apart)
    tiny = collect(files["ico"], CollectConfig(episodes=4, steps=1, seed=1))
    save_dataset("tiny.npz", tiny)
    rc, out, err = run_cli(["fit", "tiny.npz", "--model", files["ico"], "--out", "F.json"])
    assert rc == 0, err
    assert "not estimable" in out and "warning: standard errors not estimable" in err
    obj = json.loads(Path("F.json").read_text())
    assert obj["springs"][0]["stiffness_stderr"] is None and obj["rods"][0]["mass_stderr"] is None
    assert obj["metrics"]["data"]["residual_dof"] < obj["metrics"]["data"]["free_parameters"]
    assert any("not estimable" in w for w in obj["metrics"]["warnings"])
    # the Adam solver gives no error bars at all: the same data are refused
    rc, _, err = run_cli(["fit", "tiny.npz", "--model", files["ico"], "--solver", "adam", "--out", "G.json",
                          "--quiet"])
    assert rc == 2 and "more steps" in one_error(err) and not Path("G.json").exists()


def test_adam_that_did_not_converge_says_so(files):
    data = collect(files["ico"], CollectConfig(episodes=3, steps=5, seed=2))
    model = identify(data, Topology.from_mjcf(files["ico"]), solver="adam")
    assert any("Adam did not converge" in w for w in model.metrics["warnings"])


def test_residual_dof_discounts_overlapping_windows():
    assert residual_dof(100, 10) == 90
    assert overlap_factor(0) == 1.0 and overlap_factor(301) == pytest.approx(2.684, abs=1e-3)
    assert residual_dof(100, 10, weak_window=301) == pytest.approx(100 / 2.6844 - 10, abs=1e-2)


def test_few_run_error_bars_equal_the_textbook_covariance():
    """The iid fallback (< 10 episodes) is sigma^2 (B^T B)^-1 with sigma^2 = RSS / (n - p): the
    residual-variance factor and the degrees of freedom both matter."""
    rng = np.random.default_rng(0)
    n, p = 40, 3
    B = rng.normal(size=(n, p)) * [1.0, 10.0, 0.1]
    y = B @ [1.0, 2.0, 3.0] + rng.normal(0, 0.5, n)
    theta = np.linalg.lstsq(B, y, rcond=None)[0]
    rss = float(np.sum((B @ theta - y) ** 2))
    _U, s, Vt = np.linalg.svd(B, full_matrices=False)
    lin = LinearSolve(M=Vt.T / s, IK=None, singular_values=s, residual=rss)
    factors = BlockFactors(R=[], rows=[n], blocks=[], columns=[], cluster_R=[[], []])
    cov, how = covariance(factors, np.eye(p), np.eye(p), theta, np.ones(1), None, lin)
    np.testing.assert_allclose(cov, rss / (n - p) * np.linalg.inv(B.T @ B), rtol=1e-10)
    assert "iid" in how


def test_noisy_fit_error_bars_cover_the_truth(files):
    """3 episodes (iid fallback) of 1 mm noise: every K, c, M within 4 standard errors of the truth."""
    data = collect(files["ico"], CollectConfig(episodes=3, steps=1500, seed=4, push_every=100, noise_pos=1e-3,
                                               noise_vel=1e-2, noise_quat=1e-3, noise_angvel=1e-2))
    model = identify(data, Topology.from_mjcf(files["ico"]))
    p = preset_parameters("ico", "paper-nonuniform", 3)
    for key, true in (("stiffness", [s["stiffness"] for s in p["springs"]]),
                      ("damping", [s["damping"] for s in p["springs"]]),
                      ("mass", [r["mass"] for r in p["rods"]])):
        z = (getattr(model, key) - np.array(true)) / model.stderr[key]
        assert np.all(np.isfinite(z)) and np.max(np.abs(z)) < 4.5, (key, np.max(np.abs(z)))


def test_physical_warnings_name_each_violation():
    w = physical_warnings(["r0", "r1"], ["s0"], np.array([1.0, -2.0]),
                          np.array([[1.0, 1.0, 0.01], [0.5, 2.0, 0.1]]), np.array([-5.0]), np.array([-1.0]))
    text = "\n".join(w)
    assert "r1: mass -2 kg is not positive" in text
    assert "r1: inertia about y 2 kg m^2 exceeds the sum of the other two" in text
    assert "s0: stiffness -5 N/m is not positive" in text and "s0: damping -1 N s/m is negative" in text
    assert not any(x.startswith("r0") for x in w)
    # within two standard errors a thin rod's triangle inequality is no evidence of anything
    assert physical_warnings(["r"], [], np.array([1.0]), np.array([[1.02, 1.0, 0.01]]), np.array([]),
                             np.array([]), np.array([[0.02, 0.02, 0.001]])) == []


def test_non_positive_inertia_is_held_by_a_constrained_fit():
    """A 2-parameter toy: the first solve gives I < 0, the constrained one pins it at the floor."""
    from identified.fit.regression import Solution

    def sol(theta):
        return Solution(theta=np.array(theta, dtype=float), cov=np.eye(3), residual_rms=[], condition=1.0,
                        rows=10, free=3)

    calls = []

    def resolve(fixed):
        calls.append(dict(fixed))
        return sol([2.0, 1.5, fixed[2]])

    out, notes, held = constrain_inertias(sol([2.0, 1.5, -0.5]), resolve, lambda i, a: a, 1, ["rod0"], {})
    assert held == [(0, 2)] and out.theta[2] > 0 and calls == [{2: 2e-3}]
    assert "constrained fit" in notes[0] and "rod0" in notes[0]


def test_robot_fit_warns_and_writes_a_loadable_model(work):
    """Robot-on-ground data (contact the model lacks): non-physical values are warned about on
    stderr and in the JSON, never silently kept; every inertia the loader needs is positive."""
    write_model("robot.xml", "ico", preset="robot")
    save_dataset("rob.npz", collect("robot.xml", CollectConfig(episodes=2, steps=400, seed=0, push_every=50)))
    rc, _out, err = run_cli(["fit", "rob.npz", "--model", "robot.xml", "--out", "R.json", "--quiet"])
    assert rc == 0, err
    warned = [ln for ln in err.splitlines() if ln.startswith("tensegrity: warning: ")]
    obj = json.loads(Path("R.json").read_text())
    assert warned and len(warned) == len(obj["metrics"]["warnings"])
    m = load_model("R.json")
    assert np.all(m.inertia > 0) and np.all(m.mass > 0)


# ---------------------------------------------------------------------- the model loader
@pytest.mark.parametrize("field,value,fragment", [
    ("dt", 0.0, "'dt'"), ("dt", -0.02, "'dt'"), ("gravity", float("inf"), "'gravity'"),
    ("mass", -1.0, "mass"), ("inertia_axial", -4e-5, "inertia about z"), ("inertia", 0.0, "inertia"),
    ("effects", None, "unknown effect 'ground'"), ("control_scale", float("nan"), "control_scale"),
])
def test_loader_refuses_bad_fields(files, work, field, value, fragment):
    corrupt_model(Path(files["fit"]), work / "bad.json", field, "value", value if value is not None else 0.0, 1)
    with pytest.raises(ModelFileError, match=fragment.replace("(", r"\(")):
        load_model(work / "bad.json")
    rc, _, err = run_cli(["predict", files["data"], "--identified", "bad.json"])
    assert rc == 2 and "bad.json" in one_error(err)
    with pytest.raises(ValueError, match="bad.json"):
        gym.make("TensegrityIco-v0", backend="identified", model=str(work / "bad.json"))


# ---------------------------------------------------------------------- 2. inputs never destroyed
@pytest.mark.parametrize("case", ["collect out=model", "fit out=data", "fit out=mjcf", "predict plot=data",
                                  "predict plot=model", "fit out=symlink to data", "fit out=hard link to mjcf",
                                  "fit out=./../dir/data"])
def test_output_that_is_an_input_is_refused(files, work, case):
    for k in ("ico", "data", "fit"):
        (work / Path(files[k]).name).write_bytes(Path(files[k]).read_bytes())
    os.mkdir("dir")
    os.symlink("data.npz", "link.npz")
    os.link("ico.xml", "hard.xml")
    argv = {
        "collect out=model": ["collect", "--model", "ico.xml", "--episodes", "1", "--steps", "5", "--out", "ico.xml"],
        "fit out=data": ["fit", "data.npz", "--model", "ico.xml", "--out", "data.npz"],
        "fit out=mjcf": ["fit", "data.npz", "--model", "ico.xml", "--out", "ico.xml"],
        "predict plot=data": ["predict", "data.npz", "--identified", "fit.json", "--plot", "data.npz"],
        "predict plot=model": ["predict", "data.npz", "--identified", "fit.json", "--plot", "fit.json"],
        "fit out=symlink to data": ["fit", "data.npz", "--model", "ico.xml", "--out", "link.npz"],
        "fit out=hard link to mjcf": ["fit", "data.npz", "--model", "ico.xml", "--out", "hard.xml"],
        "fit out=./../dir/data": ["fit", "data.npz", "--model", "ico.xml", "--out", "./dir/../data.npz"],
    }[case]
    before = digest(work)
    rc, _, err = run_cli(argv + ["--quiet"] if argv[0] != "predict" else argv)
    line = one_error(err)
    assert rc == 2 and "same file" in line and "refusing to overwrite" in line, line
    assert argv[argv.index("--out" if "--out" in argv else "--plot") + 1] in line  # the user's path
    assert digest(work) == before


def test_output_in_missing_folder_names_the_users_path(files, work):
    rc, _, err = run_cli(["fit", files["data"], "--model", files["ico"], "--out", "no/such/F.json"])
    line = one_error(err)
    assert rc == 2 and "'no/such/F.json'" in line and "'no/such'" in line and "does not exist" in line


# ---------------------------------------------------------------------- 3. limits before work
def test_collect_too_large_for_memory_is_refused_with_the_figure(files, work):
    rc, _, err = run_cli(["collect", "--model", files["ico"], "--episodes", "1000000", "--steps", "1000000",
                          "--out", "D.npz", "--quiet"])
    line = one_error(err)
    assert rc == 2 and "PiB" in line and "--episodes 1000000" in line and not Path("D.npz").exists()
    assert collect_bytes(2, 10, 6, 24, 24) == 2 * 8 * (2 * 11 * 6 * 13 + 2 * 10 * (24 + 24 + 36))
    with pytest.raises(MemoryLimitError, match="1 KiB"):
        check_memory(900, "x", available=1024 + 1)  # more than 80 % of what is available
    check_memory(800, "x", available=1024)


def test_unstable_plant_is_an_error_naming_the_episode(files, work):
    rc, out, err = run_cli(["collect", "--model", files["ico"], "--episodes", "2", "--steps", "300",
                            "--push-every", "50", "--push-magnitude", "1e6", "--out", "D.npz", "--quiet"])
    line = one_error(err)
    assert rc == 2 and "unstable in episode 0" in line and "push-magnitude" in line, line
    assert not Path("D.npz").exists() and not Path("MUJOCO_LOG.TXT").exists() and "WARNING" not in out


def test_model_without_tendons_is_refused_by_collect(work):
    Path("empty.xml").write_text(
        '<mujoco><worldbody><body name="rod0"><freejoint/><inertial pos="0 0 0" mass="1" diaginertia="1 1 0.01"/>'
        '<geom type="capsule" fromto="0 0 -0.5 0 0 0.5" size="0.02"/>'
        '<site name="rod0_end0" pos="0 0 -0.5"/><site name="rod0_end1" pos="0 0 0.5"/></body></worldbody></mujoco>')
    rc, _, err = run_cli(["collect", "--model", "empty.xml", "--episodes", "1", "--steps", "5", "--out", "D.npz"])
    assert rc == 2 and "empty.xml" in one_error(err) and not Path("D.npz").exists()


def test_mujoco_detail_and_the_users_path_in_xml_errors(files, work):
    Path("bad.xml").write_text(Path(files["ico"]).read_text().replace("<geom ", '<geom foo="1" ', 1))
    rc, _, err = run_cli(["collect", "--model", "bad.xml", "--episodes", "1", "--steps", "5", "--out", "D.npz"])
    line = one_error(err)
    assert rc == 2 and "'bad.xml'" in line and "line " in line and "foo" in line, line


# ---------------------------------------------------------------------- 4. one clear line
@pytest.mark.parametrize("cmd,opt,value", BAD_FLAGS)
def test_bad_flag_is_refused_with_the_options_name(files, work, cmd, opt, value):
    before = digest(work)
    rc, _, err = run_cli(flag_argv(cmd, opt, value, files))
    line = one_error(err)
    assert rc == 2
    assert opt in line or value in line, line
    assert digest(work) == before


def test_text_file_as_dataset_gives_no_pickle_advice(work):
    Path("notes.npz").write_text("just text\n")
    rc, _, err = run_cli(["summary", "notes.npz"])
    line = one_error(err)
    assert rc == 2 and "notes.npz" in line and "pickle" not in line


def test_json_outputs_are_strict_json(files, work):
    rc, out, _ = run_cli(["summary", files["data"], "--json"])
    assert rc == 0 and finite_json(out)
    rc, out, _ = run_cli(["predict", files["data"], "--identified", files["fit"], "--json"])
    assert rc == 0 and finite_json(out)
    assert json_safe({"a": [np.float64("nan"), 1.0, np.inf], "b": np.array([np.nan])}) == {"a": [None, 1.0, None],
                                                                                          "b": [None]}


def test_unwritable_output_names_the_users_path_not_a_temp_file(files, work):
    rc, _, err = run_cli(["model", "ico", "--out", "/proc/x.xml"])
    line = one_error(err)
    assert rc == 2 and "/proc/x.xml" in line and ".tmp-" not in line


# ---------------------------------------------------------------------- env API
@pytest.mark.parametrize("kwargs,fragment", [
    ({"ctrl_cost_weight": float("nan")}, "ctrl_cost_weight"),
    ({"forward_reward_weight": float("inf")}, "forward_reward_weight"),
    ({"healthy_z_range": (float("nan"), 2.0)}, "healthy_z_range"),
    ({"backend": "identified", "backend_kwargs": {"effects": ["ground"]}}, "unknown name"),
    ({"backend": "identified", "backend_kwargs": {"effects": ["ground_contact"]}}, "effect object"),
    ({"backend": "identified", "backend_kwargs": {"effects": [3]}}, "not an effect"),
])
def test_env_refuses_bad_arguments_at_construction(kwargs, fragment):
    with pytest.raises(ValueError, match=fragment):
        gym.make("TensegrityIco-v0", **kwargs)


# ---------------------------------------------------------------------- mutants that used to live
def test_quaternion_with_norm_below_one_is_refused(files, work):
    with np.load(files["data"]) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["quat"][1, 3, 2] *= 0.99
    np.savez("short.npz", **arrays)
    with pytest.raises(DatasetError, match=r"'quat' is not a unit quaternion at index \(1, 3, 2\)"):
        load_dataset("short.npz")


def test_vector_env_keeps_an_unhealthy_sub_env_running_when_told(files):
    from tensegrity_gym.envs.vector import TensegrityIcoVectorEnv

    A = 24
    ended = {}
    for flag in (False, True):
        v = TensegrityIcoVectorEnv(2, None, terminate_when_unhealthy=flag)
        v.reset(seed=0)
        pos, quat, vel, angvel = v.physics.states_numpy()
        pos[1, :, 2] -= 5.0  # sub-env 1 far below the healthy height range
        v.physics.reset(pos[1:2], quat[1:2], vel[1:2], angvel[1:2], v.physics.rest_numpy()[1:2], index=[1])
        obs, rew, term, _trunc, _info = v.step(np.zeros((2, A), np.float32))
        assert np.all(np.isfinite(obs)) and np.all(np.isfinite(rew))
        ended[flag] = bool(term[1])
    assert ended == {False: False, True: True}


# ---------------------------------------------------------------------- 6. fuzz
def fresh(work: Path) -> Path:
    return Path(tempfile.mkdtemp(dir=work))


@FUZZ
@given(key=st.sampled_from(DATASET_KEYS), kind=st.sampled_from(DATASET_KINDS), value=st.sampled_from(BAD_FLOATS),
       index=st.integers(0, 10**6), command=st.sampled_from(["summary", "fit"]))
def test_fuzz_corrupted_dataset(files, work, key, kind, value, index, command):
    d = fresh(work)
    corrupt_dataset(Path(files["data"]), d / "d.npz", key, kind, value, index)
    os.chdir(d)
    before = digest(d)
    argv = ["summary", "d.npz", "--json"] if command == "summary" else [
        "fit", "d.npz", "--model", files["ico"], "--out", "f.json", "--quiet"]
    rc, out, err = run_cli(argv)
    assert check_outcome(rc, out, err, before, d) == []
    if rc == 0 and command == "summary":
        assert finite_json(out)
    if rc == 0 and command == "fit":
        m = load_model(d / "f.json")
        assert finite(m.stiffness) and finite(m.mass) and finite(m.inertia)


def test_a_fit_that_is_not_physical_writes_nothing(files, work):
    """Found by the fuzz test above: a dataset whose declared gravity is -1 instead of -9.81 makes
    the fit give a rod a non-positive mass or inertia; the fit used to write that model, which
    ``load_model`` then refused.  Now: one line, exit 2, no file."""
    d = fresh(work)
    corrupt_dataset(Path(files["data"]), d / "d.npz", "gravity", "value", -1.0, 24386)
    os.chdir(d)
    before = digest(d)
    rc, out, err = run_cli(["fit", "d.npz", "--model", files["ico"], "--out", "f.json", "--quiet"])
    assert check_outcome(rc, out, err, before, d) == []
    assert rc == 2 and "f.json' not written" in one_error(err) and "positive" in one_error(err)
    assert not (d / "f.json").exists()


def test_a_model_with_an_unknown_effect_is_not_written(files, work):
    """``save_model`` validates before writing: an effect name no loader knows (a model built in
    code) is refused naming it, and an existing file at the path is left as it was."""
    model = load_model(files["fit"])
    model.effects = [{"name": "ground", "parameters": [], "stderr": [], "options": {}}]
    (work / "m.json").write_text("keep")
    with pytest.raises(ModelFileError, match=r"m.json' not written: .*unknown effect 'ground' \(known: "):
        save_model(work / "m.json", model)
    assert (work / "m.json").read_text() == "keep"


@FUZZ
@given(kind=st.sampled_from(FILE_KINDS), index=st.integers(0, 10**6),
       command=st.sampled_from(["summary", "fit", "predict-model", "predict-data"]))
def test_fuzz_foreign_files(files, work, kind, index, command):
    d = fresh(work)
    src = files["fit"] if command == "predict-model" else files["data"]
    corrupt_file(Path(src), d / "x.bin", kind, index)
    os.chdir(d)
    before = digest(d)
    argv = {"summary": ["summary", "x.bin"],
            "fit": ["fit", "x.bin", "--model", files["ico"], "--out", "f.json"],
            "predict-model": ["predict", files["data"], "--identified", "x.bin"],
            "predict-data": ["predict", "x.bin", "--identified", files["fit"]]}[command]
    rc, out, err = run_cli(argv)
    assert rc == 2 and check_outcome(rc, out, err, before, d) == [] and "x.bin" in err


@FUZZ
@given(field=st.sampled_from(MODEL_FIELDS), kind=st.sampled_from(MODEL_KINDS), value=st.sampled_from(BAD_FLOATS),
       index=st.integers(0, 10**6))
def test_fuzz_corrupted_model(files, work, field, kind, value, index):
    d = fresh(work)
    corrupt_model(Path(files["fit"]), d / "m.json", field, kind, value, index)
    os.chdir(d)
    before = digest(d)
    rc, out, err = run_cli(["predict", files["data"], "--identified", "m.json", "--horizon", "20", "--json"])
    assert check_outcome(rc, out, err, before, d) == []
    if rc == 0:
        assert finite_json(out)


@FUZZ
@given(flag=st.sampled_from(BAD_FLAGS))
def test_fuzz_bad_flags(files, work, flag):
    d = fresh(work)
    os.chdir(d)
    before = digest(d)
    rc, out, err = run_cli(flag_argv(*flag, files))
    assert rc == 2 and check_outcome(rc, out, err, before, d) == []


@FUZZ
@given(ctrl=st.sampled_from([0.0, 0.01, 1e6, *BAD_FLOATS]), noise=st.sampled_from([0.0, 0.01, 0.5, *BAD_FLOATS]),
       lo=st.sampled_from([0.4, -1.0, float("nan"), 3.0]), seed=st.integers(0, 2**31))
@example(ctrl=0.01, noise=0.01, lo=0.4, seed=0)  # valid: must go through
@example(ctrl=0.01, noise=0.01, lo=3.0, seed=0)  # an empty healthy range: refused
@example(ctrl=0.01, noise=2.0, lo=0.4, seed=0)  # reset noise beyond 1: refused
def test_fuzz_env_arguments(ctrl, noise, lo, seed):
    """Refused up front exactly when a value is out of range (a weight not finite, the reset noise
    outside [0, 1], an empty healthy range); otherwise the env runs with finite observations and
    rewards."""
    valid = bool(np.isfinite(ctrl) and np.isfinite(noise) and 0.0 <= noise <= 1.0 and np.isfinite(lo) and lo < 2.0)
    try:
        env = gym.make("TensegrityIco-v0", ctrl_cost_weight=ctrl, reset_noise_scale=noise, healthy_z_range=(lo, 2.0))
    except ValueError as err:
        assert not valid, f"a valid input was refused: {err}"
        return
    assert valid, f"accepted ctrl_cost_weight={ctrl}, reset_noise_scale={noise}, healthy_z_range=({lo}, 2.0)"
    obs, _ = env.reset(seed=seed)
    assert finite(obs)
    for _ in range(3):
        obs, reward, terminated, _truncated, _info = env.step(env.action_space.sample())
        assert finite(obs) and np.isfinite(reward)
        if terminated:
            break
    env.close()
