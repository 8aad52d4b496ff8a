"""``tensegrity fit R.csv --refine``: the output-error marker fit as a model file
(identified.fit.marker_model), against known truth: the fit's estimates and error bars land in the
model's fields exactly (a log-scale error bar times the value; a logit's times v(1 - v); none where
the fit cannot tell), from a start off the truth the clean markers bring K, c and M back, and the
command's bad input is one line."""

from __future__ import annotations

import dataclasses
import os
import re
import time

import numpy as np
import pytest
import torch

from identified.effects.pyramid_contact import START, PyramidContact
from identified.fit.bound import CramerRao
from identified.fit.marker_fit import MarkerFit, fit_markers
from identified.fit.marker_model import (
    MarkerRefineConfig,
    _checked_start,
    _contact_law,
    _model,
    refine_recording,
)
from identified.model import save_model
from identified.recording import RecordingError
from identified.recording.format import save_recording
from tensegrity_gym.cli import main
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers

from .test_record_output_error import _robot, _truth
from .test_window_contact import resting  # noqa: F401 -- a fixture, shared


@pytest.fixture(scope="module")
def robot(resting, tmp_path_factory):  # noqa: F811 -- the imported fixture
    """The robot on its ground, 0.8 s of random commands (test_window_contact's): its clean 100 Hz
    markers written as a recording."""
    path, _, _, truth, fast = resting
    d = tmp_path_factory.mktemp("mr")
    csv = str(d / "r.csv")
    save_recording(csv, fast)
    return path, fast, csv, truth, d


def _fake_fit(truth, rel: dict[str, float]) -> MarkerFit:
    """A marker fit whose estimates are the truth times 1.01 with the relative errors ``rel`` by
    name (default 2 %), transverse moments one parameter per rod (``I[rod:xy]``)."""
    topo = truth.topology
    names = ([f"K[{s}]" for s in topo.spring_names] + [f"c[{s}]" for s in topo.spring_names]
             + [f"M[{r}]" for r in topo.rod_names] + [f"I[{r}:xy]" for r in topo.rod_names]
             + ["law[beta]", "law[imp_min]", "law[mu]"])
    values = np.concatenate([truth.stiffness, truth.damping, truth.mass, truth.inertia[:, 0], [100.0, 0.9, 0.8]]) * 1.01
    values[-2] = 0.9
    se = np.array([rel.get(n, 0.02) for n in names])
    cov = CramerRao(names, values, np.diag(se ** 2), np.ones(len(names), bool))
    return MarkerFit(cov, 4, 40, 1e-3, [2.0, 1.0], 1.0, True)


def test_estimates_and_error_bars_land_in_the_model_exactly(robot):
    path, _, _, truth, _ = robot
    law = PyramidContact.for_system(truth.topology, path)
    law.values = np.array(list(START.values()), dtype=float)
    s0 = truth.topology.spring_names[0]
    r1 = truth.topology.rod_names[1]
    fit = _fake_fit(truth, {f"c[{s0}]": 0.5, f"I[{r1}:xy]": 0.4, "law[mu]": 0.9})
    # the step left to the minimum: 1 standard error for the first K, 0.5 (backwards) for beta
    step = np.zeros(len(fit.cov.names))
    step[fit.cov.names.index(f"K[{s0}]")], step[fit.cov.names.index("law[beta]")] = 1.0, -0.5
    fit = dataclasses.replace(fit, to_minimum=step)
    held = [(i, 2) for i in range(truth.topology.n_rods)]
    m = _model(truth, fit, law, held)
    np.testing.assert_allclose(m.stiffness, truth.stiffness * 1.01, rtol=1e-15)
    # error bars widened by half the step: 1.5 x for the first K, the others as the covariance says
    np.testing.assert_allclose(m.stderr["stiffness"], truth.stiffness * 1.01 * 0.02 * np.r_[1.5, np.ones(
        truth.topology.n_springs - 1)], rtol=1e-15)
    np.testing.assert_allclose(m.mass, truth.mass * 1.01, rtol=1e-15)
    # the damping the fit cannot tell (50 %): its value kept, no error bar
    assert np.isnan(m.stderr["damping"][0]) and np.isfinite(m.stderr["damping"][1:]).all()
    np.testing.assert_allclose(m.damping[0], truth.damping[0] * 1.01, rtol=1e-15)
    # the transverse moments on x and y, the axial one the start's and never with an error bar
    np.testing.assert_allclose(m.inertia[:, :2], np.repeat(truth.inertia[:, :1] * 1.01, 2, 1), rtol=1e-15)
    np.testing.assert_array_equal(m.inertia[:, 2], truth.inertia[:, 2])
    assert np.isnan(m.stderr["inertia"][:, 2]).all() and np.isnan(m.stderr["inertia"][1, :2]).all()
    np.testing.assert_allclose(m.stderr["inertia"][0, :2], truth.inertia[0, 0] * 1.01 * 0.02, rtol=1e-15)
    # the law: beta on a log scale, imp_min on a logit scale, mu not identifiable; the others held
    e = m.effects[0]
    assert e["name"] == "pyramid_contact" and len(m.effects) == 1
    assert e["parameters"]["beta"] == pytest.approx(101.0, rel=1e-15)
    assert e["stderr"]["beta"] == pytest.approx(101.0 * 0.02 * 1.25, rel=1e-15)
    assert e["stderr"]["imp_min"] == pytest.approx(0.9 * 0.1 * 0.02, rel=1e-12)
    assert e["parameters"]["mu"] == pytest.approx(0.808) and e["stderr"]["mu"] is None
    assert e["parameters"]["kappa"] == START["kappa"] and e["stderr"]["kappa"] is None
    lines = m.metrics["not_identifiable"]
    assert sum(s0 in x for x in lines) == 1 and sum(f"I[{r1}:xy]" in x for x in lines) == 1
    assert sum("pyramid_contact.mu: not identifiable from these markers (standard error 90 %)" in x for x in lines) == 1
    assert sum("body axis z" in x for x in lines) == truth.topology.n_rods
    # written and read back: no number where there is no error bar
    assert "not identifiable" in m.summary()


def test_start_scaled_to_the_total_mass_and_checked(robot):
    _, rec, _, truth, _ = robot
    s = _checked_start(truth, rec, truth.topology, total_mass=2 * float(truth.mass.sum()))
    np.testing.assert_allclose(s.mass, 2 * truth.mass)
    np.testing.assert_allclose(s.stiffness, 2 * truth.stiffness)  # the markers see only ratios
    np.testing.assert_allclose(s.inertia, 2 * truth.inertia)
    drag = dataclasses.replace(truth, effects=[{"name": "linear_drag", "parameters": {}}])
    with pytest.raises(RecordingError, match="contact only; the start model has linear_drag"):
        _checked_start(drag, rec, truth.topology, None)
    other = dataclasses.replace(truth, topology=dataclasses.replace(truth.topology, rods=truth.topology.rods[:5]))
    with pytest.raises(RecordingError, match="not those of the MJCF"):
        _checked_start(other, rec, truth.topology, None)


def test_a_start_law_at_its_bounds_starts_those_from_the_generic_values(robot):
    """An earlier fit's law as the start (its not identifiable parameters at their bounds: an
    impedance at 1, a width of 1e-9 m, a rolling friction of 1e-65 m): those three from the generic
    start, the others exactly as given, each replacement said."""
    path, _, _, truth, _ = robot
    given = {**START, "beta": 242.5, "imp_min": 1.0, "imp_max": 0.85, "imp_width": 7.6e-9, "mu": 0.94,
             "mu_rolling": 6.5e-65}
    start = dataclasses.replace(truth, effects=[{"name": "pyramid_contact", "parameters": given}])
    law, from_start, notes = _contact_law(start, truth.topology, path)
    expected = dict(given, imp_min=START["imp_min"], imp_width=START["imp_width"], mu_rolling=START["mu_rolling"])
    np.testing.assert_array_equal(law.values, [expected[n] for n in START])
    assert from_start and [n.split()[0] for n in notes] == [
        "pyramid_contact.imp_min", "pyramid_contact.imp_width", "pyramid_contact.mu_rolling"]
    assert "at its bound (1): started from 0.8" in notes[0]
    law, from_start, notes = _contact_law(dataclasses.replace(truth, effects=[]), truth.topology, path)
    np.testing.assert_array_equal(law.values, list(START.values()))
    assert not from_start and notes == []


@pytest.fixture(scope="module")
def floorless(tmp_path_factory):
    """The robot without its ground, falling for 0.6 s while its cables move: clean 100 Hz markers."""
    path = _robot(tmp_path_factory.mktemp("mrf"), floor=False)
    data = collect(path, CollectConfig(episodes=1, steps=600, seed=3))
    return path, record_markers(data, path, RecordConfig(rate=100, noise_pos=0.0, dropout=0.0), seed=3), _truth(path)


def test_clean_markers_bring_a_start_off_the_truth_back(floorless):
    """K 5 % and c 10 % off, the masses 5 % off at the right total: 3 windows of 10 clean 100 Hz
    frames, 1 state + 3 joint steps, Jacobians at 5 ms (measured: K 5 % -> 0.36 %, M 5 % -> 0.53 %,
    the cost per residual 20 -> 0.04 in 9 s; c, which 0.3 s of falling barely shows, 14 %)."""
    path, rec, truth = floorless
    rng = np.random.default_rng(1)
    start = dataclasses.replace(
        truth, stiffness=truth.stiffness * (1 + 0.05 * rng.choice([-1, 1], truth.stiffness.shape)),
        damping=truth.damping * (1 + 0.10 * rng.choice([-1, 1], truth.damping.shape)),
        mass=truth.mass * (1 + 0.05 * np.array([1, -1, 1, -1, 1, -1])))
    m = refine_recording(rec, path, start, total_mass=float(truth.mass.sum()),
                         config=MarkerRefineConfig(windows=3, frames=10, step=0.005, state_iterations=1, iterations=3))
    oe = m.metrics["output_error"]
    assert oe["windows"] == 3 and oe["jacobian_step_s"] == pytest.approx(0.005) and oe["contact_start"] == "no ground plane"
    assert oe["cost_per_residual"][-1] < 0.01 * oe["cost_per_residual"][0] and m.effects == []
    assert m.mass.sum() == pytest.approx(truth.mass.sum(), rel=1e-12)
    assert np.abs(m.stiffness / truth.stiffness - 1).max() < 0.01
    assert np.abs(m.mass / truth.mass - 1).max() < 0.01
    # still falling by orders at the last step (and the step left would move an estimate by more than
    # its error bar, measured: 2.05 of them): none written, and a warning that says so
    left = oe["step_left_se"]
    assert left["standard_errors"] > 1 and left["parameter"][:2] in ("K[", "c[", "M[", "I[")
    assert np.isnan(m.stderr["stiffness"]).all() and np.isnan(m.stderr["mass"]).all()
    assert "did not converge in 3 joint steps" in m.metrics["warnings"][-1]


def test_command_bad_input_is_one_line(robot, tmp_path, capsys):
    path, _, csv, _, _ = robot
    out = str(tmp_path / "m.json")
    assert main(["fit", csv, "--model", path, "--out", out, "--refine", "--effects", "auto"]) != 0
    assert "--effects auto: not with --refine on a recording" in capsys.readouterr().err
    assert main(["fit", csv, "--model", path, "--out", out, "--refine", "--start", str(tmp_path / "none.json")]) != 0
    assert "none.json" in capsys.readouterr().err
    npz = str(tmp_path / "d.npz")
    assert main(["fit", npz, "--model", path, "--out", out, "--windows", "3"]) != 0
    err = capsys.readouterr().err
    assert "--windows is for a recording's marker fit" in err and len(err.strip().splitlines()) == 1
    assert main(["fit", npz, "--model", path, "--out", out, "--state-iterations", "5"]) != 0
    assert "--state-iterations is for a recording's marker fit" in capsys.readouterr().err
    assert main(["fit", npz, "--model", path, "--out", out, "--window-blocks", "2"]) != 0
    assert "--window-blocks is for a recording's marker fit" in capsys.readouterr().err
    assert main(["fit", npz, "--model", path, "--out", out, "--iterations", "8"]) != 0  # given at its default: seen
    assert "--iterations is for a recording's marker fit" in capsys.readouterr().err
    assert main(["fit", csv, "--model", path, "--out", out, "--window-blocks", "1"]) != 0  # its default, given
    assert "--window-blocks is for the marker fit: add --refine" in capsys.readouterr().err
    assert main(["fit", csv, "--model", path, "--out", out, "--refine", "--windows", "6", "--window-blocks", "4"]) != 0
    err = capsys.readouterr().err
    assert "--window-blocks 4: each block needs at least two of the --windows 6" in err and len(err.strip().splitlines()) == 1
    assert main(["fit", csv, "--model", path, "--out", out, "--refine", "--window-blocks", "33"]) != 0
    assert "--window-blocks 33: each block needs at least two of the --windows 64" in capsys.readouterr().err
    assert main(["fit", csv, "--model", path, "--out", out, "--refine", "--window-blocks", "0"]) == 2
    assert "--window-blocks" in capsys.readouterr().err
    assert main(["fit", csv, "--model", path, "--out", out, "--refine", "--state-iterations", "-1"]) == 2
    assert "--state-iterations" in capsys.readouterr().err
    assert main(["fit", csv, "--model", path, "--out", out, "--checkpoint", str(tmp_path / "c.pt")]) != 0
    assert "--checkpoint is for the marker fit: add --refine" in capsys.readouterr().err
    assert main(["fit", csv, "--model", path, "--out", out, "--refine", "--checkpoint", csv]) != 0
    assert "--checkpoint" in capsys.readouterr().err and os.path.getsize(csv) > 0
    assert not os.path.exists(out)


def test_the_marker_options_reach_the_marker_fit(robot, tmp_path, monkeypatch, capsys):
    """Each marker-fit option sets its field of ``MarkerRefineConfig`` (``--windows 0``: all windows);
    the fields not given keep the config's defaults, and the help says those defaults."""
    import identified.fit.marker_model as mm
    from tensegrity_gym.cli import build_parser

    path, _, csv, truth, _ = robot
    start = str(tmp_path / "start.json")
    save_model(start, truth)
    seen = []

    def spy(rec, mjcf, start, total_mass=None, config=None, progress=False, checkpoint=None):
        seen.append(config)
        raise RecordingError("spied")

    monkeypatch.setattr(mm, "refine_recording", spy)
    runs = [(["--state-iterations", "7"], {"state_iterations": 7}), (["--state-iterations", "0"], {"state_iterations": 0}),
            ([], {}), (["--windows", "0", "--window-blocks", "3"], {"windows": None, "blocks": 3}),
            (["--windows", "12", "--window-frames", "7", "--window-step", "0.002", "--iterations", "5"],
             {"windows": 12, "frames": 7, "step": 0.002, "iterations": 5})]
    for extra, _ in runs:
        assert main(["fit", csv, "--model", path, "--out", str(tmp_path / "m.json"), "--refine", "--start", start,
                     "--quiet", *extra]) != 0
    assert seen == [mm.MarkerRefineConfig(**fields) for _, fields in runs]
    assert seen[2] == mm.MarkerRefineConfig(windows=64, frames=10, step=0.005, state_iterations=3, iterations=8, blocks=1)
    assert capsys.readouterr().err.count("spied") == len(runs)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["fit", "--help"])
    shown = {b.split()[0]: " ".join(b.split()) for b in re.split(r"\n\s+(?=--)", capsys.readouterr().out)}
    for option, default in (("--windows", "(default 64; 0: all)"), ("--window-frames", "(default 10)"),
                            ("--window-step", "(default 0.005 s;"), ("--state-iterations", "(default 3)"),
                            ("--iterations", "(default 8)"), ("--window-blocks", "(default 1:")):
        assert default in shown[option], option


def test_an_interrupted_fit_resumes_to_the_same_result(floorless, tmp_path, capsys):
    """1 state + 2 joint steps at once, against 1 + 1 with a checkpoint and then 1 + 2 from it: the
    same history and estimates bit for bit (the resumed fit does only the last step, and counts the
    seconds before the interruption); a checkpoint
    of another fit (other noise) or a truncated one is said and not used."""
    from identified.fit.markers import states_from_recording

    _, rec, truth = floorless
    ms = states_from_recording(rec, truth.topology, truth.dt)
    start = dataclasses.replace(truth, stiffness=truth.stiffness * 1.03)

    def run(joint: int, checkpoint: str | None = None, sigma: float = 1e-3):
        return fit_markers(start, rec, ms.data, ms.starts, None, sigma, ms.unobservable, frames=6, max_windows=1,
                           state_iters=1, joint_iters=joint, substeps=5, checkpoint=checkpoint, progress=True)

    whole = run(2)
    ck = str(tmp_path / "fit.pt")
    part = run(1, ck)
    assert part.history == whole.history[:3] and os.path.exists(ck)
    capsys.readouterr()
    saved = torch.load(ck, weights_only=True)
    assert 0 < saved["seconds"] < part.seconds
    saved["seconds"] = 1000.0  # an interrupted fit of 1000 s: the resumed one counts them
    torch.save(saved, ck)
    t = time.perf_counter()
    resumed = run(2, ck)
    assert 1000.0 < resumed.seconds < 1000.0 + time.perf_counter() - t
    steps = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("marker fit:")]
    assert steps[0].startswith(f"marker fit: resumed from '{ck}' after 1 state + 1 joint steps") and len(steps) == 2
    assert steps[1].startswith("marker fit: joint step 2, ")  # the last only, numbered among the joint steps
    assert resumed.history == whole.history
    np.testing.assert_array_equal(resumed.cov.values, whole.cov.values)
    np.testing.assert_array_equal(resumed.cov.cov, whole.cov.cov)
    np.testing.assert_array_equal(resumed.to_minimum, whole.to_minimum)
    with pytest.warns(UserWarning, match="not of this fit"):
        other = run(1, ck, sigma=2e-3)
    assert len(other.history) == 3  # from the start, not from the checkpoint's step
    with open(ck, "wb") as fh:
        fh.write(b"trunc")
    with pytest.warns(UserWarning, match="not of this fit"):
        again = run(1, ck)
    assert again.history == part.history


def test_a_model_with_some_error_bars_withheld_reads_back_with_the_others(robot, tmp_path):
    """One damping not identifiable (null in the file): the others keep their error bars on reading."""
    from identified.model import load_model, save_model

    truth = robot[3]
    se = truth.damping * 0.02
    se[3] = np.nan
    path = str(tmp_path / "m.json")
    save_model(path, dataclasses.replace(truth, stderr={"damping": se}))
    back = load_model(path).stderr["damping"]
    assert np.isnan(back[3]) and np.array_equal(np.delete(back, 3), np.delete(se, 3))
    assert "not estimable" in load_model(path).summary().splitlines()[truth.topology.n_rods + 3]


@pytest.mark.parametrize(("history", "converged", "off", "kept", "warned", "dof", "stated"), [
    ([2.0, 1.0], True, 1.1, True, False, 0, True),  # converged: its error bars
    ([1.0, 0.995], False, 1.1, True, True, 0, True),  # stopped while falling 0.5 % a step: kept, said
    ([1.0, 0.98], False, 1.1, False, True, 0, True),  # falling 2 % a step: withheld, said
    ([2.0, 1.0], True, 1.3, False, True, 0, True),  # converged, but the markers 1.3 times their noise off: withheld
    # the stated noise's variance times 1.049 over 20000 degrees of freedom: 4.9 chi-square standard
    # deviations (sqrt(2 / dof) = 0.01) above it, kept; 1.051: 5.1, withheld
    ([2.0, 1.0], True, 1.049 ** 0.5, True, False, 20000, True),
    ([2.0, 1.0], True, 1.051 ** 0.5, False, True, 20000, True),
    ([2.0, 1.0], True, 1.051 ** 0.5, True, False, 20000, False),  # the noise not stated (measured): kept
    ([2.0, 1.0], True, 1.043, False, True, 84000, True),  # the all-window 30 Hz fit's: 18 standard deviations
])
def test_error_bars_only_where_the_fit_stopped_on_the_markers(robot, history, converged, off, kept, warned, dof,
                                                              stated):
    from identified.fit.marker_model import _judge_fit, _still_moving

    _, _, _, truth, _ = robot
    law = PyramidContact.for_system(truth.topology, robot[0])
    law.values = np.array(list(START.values()), dtype=float)
    fit = dataclasses.replace(_fake_fit(truth, {}), history=history, converged=converged, residual_rms=off * 0.01,
                              to_minimum=np.zeros(len(_fake_fit(truth, {}).cov.names)), dof=dof)
    m = _model(truth, fit, law, [], withheld=_still_moving(fit))
    _judge_fit(m, fit, 5, 0.01, stated=stated)
    if dof and not kept:
        assert "stated noise" in m.metrics["warnings"][-1] and f"over {dof} degrees of freedom" in m.metrics["warnings"][-1]
    assert np.isfinite(m.stderr["stiffness"]).all() == kept and np.isnan(m.stderr["mass"]).all() != kept
    assert (m.effects[0]["stderr"]["beta"] is not None) == kept
    assert bool(m.metrics.get("warnings")) == warned and "withheld" not in m.metrics
    assert m.metrics.get("stderr", "").startswith("withheld") != kept


@pytest.mark.parametrize(("steps", "withheld"), [
    ({"M[rod2]": 1.95}, {}),  # the step left moves an estimate 1.95 se: kept (widened)
    ({"M[rod2]": -2.05}, {"M[rod2]": 2.05}),  # 2.05 se: that one withheld, the others kept
    ({"I[rod1:xy]": 9.0}, {}),  # 9 se, but of one with no error bar (40 %): nothing to withhold
    ({"law[beta]": 5.4, "I[rod0:xy]": -2.4, "K[" + "{s0}]": 0.6, "c[" + "{s1}]": 2.2},  # the 128-window fit's kind
     {"pyramid_contact.beta": 5.4, "I[rod0:xy]": 2.4, "c[" + "{s1}]": 2.2}),
])
def test_only_the_estimates_the_fit_would_still_move_lose_their_error_bars(robot, steps, withheld):
    """A converged fit on the markers whose step left would move some estimates by more than
    ``STILL_MOVING_SE`` (2) of their standard errors: exactly those have none (null), named with
    their steps in ``metrics.withheld`` and a warning; every other keeps its widened bar exactly."""
    from identified.fit.marker_model import _judge_fit, _still_moving

    _, _, _, truth, _ = robot
    topo = truth.topology
    fmt = {"s0": topo.spring_names[0], "s1": topo.spring_names[1]}
    steps = {k.format(**fmt): v for k, v in steps.items()}
    withheld = {k.format(**fmt): v for k, v in withheld.items()}
    law = PyramidContact.for_system(topo, robot[0])
    law.values = np.array(list(START.values()), dtype=float)
    fit = _fake_fit(truth, {"I[rod1:xy]": 0.4})
    to_minimum = np.zeros(len(fit.cov.names))
    for n, v in steps.items():
        to_minimum[fit.cov.names.index(n)] = v
    fit = dataclasses.replace(fit, to_minimum=to_minimum)
    m = _model(truth, fit, law, [], withheld=_still_moving(fit))
    _judge_fit(m, fit, 5, 0.01)
    assert m.metrics.get("withheld", {}) == withheld and "stderr" not in m.metrics
    assert bool(m.metrics.get("warnings")) == bool(withheld)
    if withheld:
        assert f"would move {max(withheld, key=withheld.get)} by {max(withheld.values()):.3g}" \
               in m.metrics["warnings"][0]
    # every other error bar: the value times its relative error widened by half its step, exactly
    rel = {n: 0.02 * (1 + 0.5 * abs(s)) for n, s in zip(fit.cov.names, to_minimum)}
    for field, kind, names in (("stiffness", "K", topo.spring_names), ("damping", "c", topo.spring_names),
                               ("mass", "M", topo.rod_names)):
        for j, n in enumerate(names):
            key = f"{kind}[{n}]"
            want = np.nan if key in withheld else getattr(m, field)[j] * rel[key]
            np.testing.assert_equal(m.stderr[field][j], want)
    for i, r in enumerate(topo.rod_names):
        key = f"I[{r}:xy]"
        want = np.nan if key in withheld or r == "rod1" else m.inertia[i, 0] * rel[key]
        np.testing.assert_equal(m.stderr["inertia"][i, :2], [want, want])
    assert (m.effects[0]["stderr"]["beta"] is None) == ("pyramid_contact.beta" in withheld)
    assert m.effects[0]["stderr"]["mu"] == pytest.approx(0.8 * 1.01 * 0.02, rel=1e-12)


def test_a_model_whose_error_bars_were_withheld_says_so_in_words(robot, tmp_path):
    """Withheld error bars are "± withheld" in the summary, in the fit and read back from its file
    (where the groups are all null), the transverse moments printed, the unseen axial ones not."""
    from identified.fit.marker_model import _judge_fit, _still_moving
    from identified.model import load_model, save_model

    _, _, _, truth, _ = robot
    law = PyramidContact.for_system(truth.topology, robot[0])
    law.values = np.array(list(START.values()), dtype=float)
    fit = dataclasses.replace(_fake_fit(truth, {}), history=[1.0, 0.9], converged=False, residual_rms=0.011)
    m = _model(truth, fit, law, [(i, 2) for i in range(truth.topology.n_rods)], withheld=_still_moving(fit))
    _judge_fit(m, fit, 5, 0.01)
    path = str(tmp_path / "w.json")
    save_model(path, m)
    for text in (m.summary(), load_model(path).summary()):
        rod0, cable0 = text.splitlines()[0], text.splitlines()[truth.topology.n_rods]
        assert rod0 == f"rod0: M = {m.mass[0]:.6g} kg ± withheld; I = ({m.inertia[0, 0]:.4g}, {m.inertia[0, 1]:.4g}, " \
                       "not identifiable) kg m^2"
        assert cable0.count("± withheld") == 2 and "not estimable" not in text
        assert "beta = [101.] ± withheld 1/s" in text


def test_a_model_with_some_error_bars_withheld_names_them_in_its_summary(robot, tmp_path):
    """The fit withheld rod2's mass, cable0's damping, rod0's transverse moments and the law's beta
    (their steps left over 2 se): those say "± withheld" (the moments printed), in the fit and read
    back from its file; every other keeps its error bar, and a moment the markers cannot see stays
    "not identifiable"."""
    from identified.fit.marker_model import _judge_fit, _still_moving
    from identified.model import load_model, save_model

    _, _, _, truth, _ = robot
    topo = truth.topology
    s0 = topo.spring_names[0]
    law = PyramidContact.for_system(topo, robot[0])
    law.values = np.array(list(START.values()), dtype=float)
    fit = _fake_fit(truth, {"I[rod1:xy]": 0.4})
    to_minimum = np.zeros(len(fit.cov.names))
    for n, v in (("M[rod2]", 3.0), (f"c[{s0}]", -2.5), ("I[rod0:xy]", 2.2), ("law[beta]", 5.0)):
        to_minimum[fit.cov.names.index(n)] = v
    fit = dataclasses.replace(fit, to_minimum=to_minimum)
    m = _model(truth, fit, law, [(i, 2) for i in range(topo.n_rods)], withheld=_still_moving(fit))
    _judge_fit(m, fit, 5, 0.01)
    path = str(tmp_path / "some.json")
    save_model(path, m)
    R = topo.n_rods
    for text in (m.summary(), load_model(path).summary()):
        lines = text.splitlines()
        assert lines[0] == (f"rod0: M = {m.mass[0]:.6g} kg ± {m.stderr['mass'][0]:.2g}; I = ({m.inertia[0, 0]:.4g}, "
                            f"{m.inertia[0, 1]:.4g}, not identifiable) kg m^2")
        assert lines[1].endswith("I = (not identifiable, not identifiable, not identifiable) kg m^2")  # 40 %
        assert lines[2].startswith(f"rod2: M = {m.mass[2]:.6g} kg ± withheld; I = ({m.inertia[2, 0]:.4g}, ")
        assert lines[R].startswith(f"{s0} (cable): K = {m.stiffness[0]:.6g} N/m ± {m.stderr['stiffness'][0]:.2g}; "
                                   f"c = {m.damping[0]:.6g} N s/m ± withheld;")
        assert text.count("± withheld") == 3 and "beta = [101.] ± withheld 1/s" in text
        assert "not estimable" not in text and "mu = [0.808] ± " in text


def test_a_stalled_coarse_jacobian_hands_over_to_the_exact_one(floorless, monkeypatch, capsys):
    """The coarse Jacobians replaced by ones whose parameter columns point the wrong way (a planted
    stall: no joint step of theirs lowers the cost): the fit switches to the exact step's Jacobians,
    says so, and goes on towards the truth from the clean markers (measured, one window of 6 frames: K 3 % -> 0.66 % off)."""
    from identified.fit import output_error
    from identified.fit.markers import states_from_recording

    _, rec, truth = floorless
    ms = states_from_recording(rec, truth.topology, truth.dt)
    start = dataclasses.replace(truth, stiffness=truth.stiffness * 1.03)

    def run(substeps: int, joint: int):
        return fit_markers(start, rec, ms.data, ms.starts, None, 1e-3, ms.unobservable, frames=6, max_windows=1,
                           state_iters=1, joint_iters=joint, substeps=substeps, progress=True)

    real = output_error._Problem.at_step

    class Wrong:
        def __init__(self, prob):
            self.prob = prob

        def jacobians(self, theta, dx, params=True):
            r, Jx, Jp = self.prob.jacobians(theta, dx, params=params)
            return r, Jx, (None if Jp is None else -Jp)

    monkeypatch.setattr(output_error._Problem, "at_step", lambda self, k: self if k == 1 else Wrong(real(self, k)))
    capsys.readouterr()
    switched = run(2, 4)
    out = capsys.readouterr().out
    assert "the 2-step Jacobians stalled; the exact step's from joint step 2" in out
    h = switched.history  # the wrong Jacobians' joint step takes nothing (the states' step after it
    # lowers the cost a little); the exact ones bring it down by orders
    assert f"joint step 1, cost per residual {h[2]:.4f} ({h[1]:.4f} before the states' step)" in out
    assert h[2] < h[1] and h[-1] < 1e-3 * h[1]
    assert np.abs(switched.group("K")[0] / truth.stiffness - 1).max() < 0.01  # from 3 % off; stalled: 3 %
