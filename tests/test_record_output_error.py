"""The output-error refinement against the markers (identified.fit.output_error), against known truth."""

from __future__ import annotations

import re

import mujoco
import numpy as np
import pytest
import torch

from identified.fit.markers import states_from_recording
from identified.fit.output_error import (
    DISAGREE,
    OFF_MARKERS,
    _disagreement,
    _Problem,
    marker_windows,
    refine_markers,
)
from identified.model import IdentifiedModel
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model


def _truth(path: str) -> IdentifiedModel:
    """The plant's own values as a model (the test knows the truth; the refinement never reads it)."""
    m = mujoco.MjModel.from_xml_path(path)
    topo = Topology.from_mjcf(path)
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, n) for n in topo.spring_names]
    bid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in topo.rod_names]
    return IdentifiedModel(topology=topo, stiffness=m.tendon_stiffness[tid].copy(), damping=m.tendon_damping[tid].copy(),
                           rest_length=np.zeros(len(tid)), mass=m.body_mass[bid].copy(),
                           inertia=m.body_inertia[bid].copy(), dt=float(m.opt.timestep), gravity=m.opt.gravity.copy(),
                           scale={"anchor": "total_mass"})


def _robot(tmp_path, floor: bool) -> str:
    path = str(tmp_path / "robot.xml")
    write_model(path, "ico", preset="robot")
    if not floor:
        with open(path) as fh:
            text = re.sub(r'<geom name="ground"[^>]*/>', "", fh.read())
        with open(path, "w") as fh:
            fh.write(text)
    return path


@pytest.fixture(scope="module")
def floorless(tmp_path_factory):
    """The robot without its ground, falling for 0.6 s while its cables move: clean 100 Hz markers."""
    path = _robot(tmp_path_factory.mktemp("oe"), floor=False)
    data = collect(path, CollectConfig(episodes=1, steps=600, seed=3))
    rec = record_markers(data, path, RecordConfig(rate=100, dropout=0.02), seed=3)
    topo = Topology.from_mjcf(path)
    return path, topo, rec, states_from_recording(rec, topo, data.dt, lam=1e-12)


def test_jacobian_matches_finite_differences(floorless):
    """The forward-mode Jacobian of the marker residuals against central differences, in the
    parameters and in a window's initial state."""
    path, topo, rec, ms = floorless
    win = marker_windows(rec, ms.data, ms.starts, topo, None, frames=4).subset(np.array([0, 5]))
    prob = _Problem(_truth(path), win, ms.data.dt, 1e-3, ms.unobservable, wrench_order=0)
    theta = prob.theta0.clone()
    dx = torch.zeros(win.n_windows, topo.n_rods, prob.n_x, dtype=torch.float64)
    r, Jx, Jp = prob.jacobians(theta, dx)
    h = 1e-6
    for k in (0, 30, 49, 55):  # a stiffness, a damping, a mass, an inertia
        e = torch.zeros_like(theta)
        e[k] = h
        fd = (prob.residuals(theta + e, dx) - prob.residuals(theta - e, dx)).reshape(r.shape) / (2 * h)
        np.testing.assert_allclose(Jp[..., k].numpy(), fd.detach().numpy(), rtol=1e-5, atol=1e-5 * float(fd.abs().max()))
    for rod, comp in ((0, 0), (2, 4), (5, 7), (3, 10)):  # position, rotation, velocity, angular velocity
        e = torch.zeros_like(dx)
        e[:, rod, comp] = h
        fd = (prob.residuals(theta, dx + e) - prob.residuals(theta, dx - e)).reshape(r.shape) / (2 * h)
        col = Jx[..., rod * prob.n_x + comp]
        np.testing.assert_allclose(col.numpy(), fd.detach().numpy(), rtol=1e-5, atol=1e-5 * float(fd.abs().max()) + 1e-9)


@pytest.mark.expensive
def test_refinement_recovers_the_truth_from_clean_markers(floorless):
    """From K, c, M and inertia 4-10 % off (the total mass kept), clean markers of the floorless
    robot bring every parameter back to the plant's values."""
    path, _, rec, ms = floorless
    truth = _truth(path)
    rng = np.random.default_rng(0)
    start = IdentifiedModel(**truth.__dict__)
    start.stiffness = truth.stiffness * (1 + 0.04 * rng.choice([-1, 1], truth.stiffness.shape))
    start.damping = truth.damping * (1 + 0.10 * rng.choice([-1, 1], truth.damping.shape))
    start.mass = truth.mass * (1 + 0.05 * rng.choice([-1, 1], truth.mass.shape))
    start.mass *= truth.mass.sum() / start.mass.sum()
    start.inertia = truth.inertia * 1.05
    out = refine_markers(start, rec, ms.data, ms.starts, None, ms.unobservable, frames=10, jacobians=2,
                         chord_steps=4, sigma=1e-3)
    # what is left is the encoders': rest lengths read at 100 Hz, interpolated between frames
    # (measured: K 3e-4, c 4e-3, M 3e-4, I 2e-3, 11 um of marker residual)
    assert np.abs(out.stiffness / truth.stiffness - 1).max() < 1e-3
    assert np.abs(out.damping / truth.damping - 1).max() < 1e-2
    assert np.abs(out.mass / truth.mass - 1).max() < 1e-3
    assert np.abs(out.inertia[:, :2] / truth.inertia[:, :2] - 1).max() < 5e-3
    assert out.metrics["output_error"]["residual_rms_m"] < 3e-5
    assert out.metrics["output_error"]["cost_after"] < 1e-4 * out.metrics["output_error"]["cost_before"]


def test_bound_scales_with_the_marker_noise(floorless):
    """With the true parameters held and the noise known, the standard errors are the Cramer-Rao
    bound of the windows' markers: proportional to the noise, and the parameters left at the truth."""
    path, _, rec, ms = floorless
    truth = _truth(path)
    se = []
    for sigma in (1e-3, 4e-3):
        out = refine_markers(truth, rec, ms.data, ms.starts, None, ms.unobservable, frames=10, max_windows=1,
                             jacobians=1, chord_steps=1, sigma=sigma, fit_params=False, known_noise=True)
        np.testing.assert_allclose(out.stiffness, truth.stiffness, rtol=1e-12)
        np.testing.assert_allclose(out.mass, truth.mass, rtol=1e-12)
        se.append(np.concatenate([out.stderr[k] for k in ("stiffness", "damping", "mass")]))
    assert np.all(se[0] > 0)
    np.testing.assert_allclose(se[1], 4 * se[0], rtol=1e-6)


def test_windows_that_do_not_follow_the_markers_keep_the_regression(floorless):
    """Stiffnesses 10x the truth: the windows leave the clean markers centimetres off, far beyond their
    noise, and the refinement keeps the model it was given (saying why) instead of error bars taken
    at such a residual; at the truth it is kept open (the residual is the noise's)."""
    path, _, rec, ms = floorless
    truth = _truth(path)
    truth.stderr = {k: 0.01 * getattr(truth, k) for k in ("stiffness", "damping", "mass")}
    wrong = IdentifiedModel(**truth.__dict__)
    wrong.stiffness = 10.0 * truth.stiffness
    kw = {"frames": 10, "max_windows": 2, "jacobians": 1, "chord_steps": 1, "sigma": 1e-3}
    out = refine_markers(wrong, rec, ms.data, ms.starts, None, ms.unobservable, **kw)
    oe = out.metrics["output_error"]
    assert oe["residual_rms_m"] > OFF_MARKERS * 1e-3 and "do not follow" in oe["kept_regression"]
    np.testing.assert_array_equal(out.stiffness, wrong.stiffness)
    assert out.stderr is not None and np.array_equal(out.stderr["stiffness"], truth.stderr["stiffness"])
    near = refine_markers(truth, rec, ms.data, ms.starts, None, ms.unobservable, **kw).metrics["output_error"]
    assert near["residual_rms_m"] < 1e-3 and "kept_regression" not in near


def test_disagreement_in_combined_standard_errors(tmp_path):
    """How far apart two estimates are, in their combined standard errors (the refinement's guard)."""
    truth = _truth(_robot(tmp_path, floor=True))
    a = IdentifiedModel(**truth.__dict__)
    b = IdentifiedModel(**truth.__dict__)
    a.stderr = {k: 0.03 * getattr(truth, k) for k in ("stiffness", "damping", "mass")}
    b.stderr = {k: 0.04 * getattr(truth, k) for k in ("stiffness", "damping", "mass")}
    b.damping = truth.damping.copy()
    b.damping[3] *= 1.10  # 0.1 c apart, combined standard error 0.05 c: 2
    assert _disagreement(a, b) == pytest.approx(2.0)
    b.mass = truth.mass * 1.3  # 0.3 M apart: 6, beyond the guard
    assert _disagreement(a, b) == pytest.approx(6.0) and _disagreement(a, b) > DISAGREE
    b.stderr = {}
    assert _disagreement(a, b) == 0.0  # no error bars to judge by


def test_recording_bound_agrees_with_the_refinement_and_flags_the_axial_spin(floorless):
    """The bound of identified.fit.marker_bound at the truth: K, c, M equal the Gauss-Newton
    standard errors of the refinement with the noise known (two implementations, one quantity:
    the constrained bound, and the refinement's gauge projection with its delta-method rescaling),
    the bound's information scaled to every window of the recording and by the noise; the axial
    moments of rods whose markers lie on their axes have no bound (not identifiable)."""
    from identified.fit.marker_bound import recording_bound

    path, _, rec, ms = floorless
    truth = _truth(path)
    ref = refine_markers(truth, rec, ms.data, ms.starts, None, ms.unobservable, frames=5, max_windows=1,
                         jacobians=1, chord_steps=1, sigma=1e-3, fit_params=False, known_noise=True)
    rb = recording_bound(truth, rec, ms.data, ms.starts, None, 4e-3, ms.unobservable, frames=5, max_windows=1,
                         state_steps=0)
    assert rb.windows == 1 and rb.available > 5
    for key, name in (("K", "stiffness"), ("c", "damping"), ("M", "mass")):
        want = 4 * ref.stderr[name] / getattr(truth, name) / np.sqrt(rb.available)
        # within 4e-4 (measured): the refinement regularises its windows by a ridge of 1e-10, and the
        # axial moments are parameters here only
        np.testing.assert_allclose(rb.group(key), want, rtol=2e-3)
    axial = [i for i, n in enumerate(rb.bound.names) if n.startswith("I[") and n.endswith(":z]")]
    assert len(axial) == len(ms.unobservable) == truth.topology.n_rods
    assert not rb.bound.identifiable()[axial].any()
    assert all("not identifiable" in rb.bound.describe(i) for i in axial)


@pytest.mark.expensive
def test_marker_fit_from_a_start_off_the_truth(floorless):
    """The staged output-error fit (identified.fit.marker_fit) from K 5 % and c 10 % off (the total
    mass known) on clean markers: back to the truth, states first, then jointly, the cost falling
    by orders; the held axial moments are not among its parameters (48 s at a load of 3)."""
    from identified.fit.marker_fit import fit_markers

    path, _, rec, ms = floorless
    truth = _truth(path)
    start = IdentifiedModel(**truth.__dict__)
    rng = np.random.default_rng(1)
    start.stiffness = truth.stiffness * (1 + 0.05 * rng.choice([-1, 1], truth.stiffness.shape))
    start.damping = truth.damping * (1 + 0.10 * rng.choice([-1, 1], truth.damping.shape))
    fit = fit_markers(start, rec, ms.data, ms.starts, None, 1e-3, ms.unobservable, frames=10, max_windows=3,
                      state_iters=1, joint_iters=3)
    K, se = fit.group("K")
    assert np.abs(K / truth.stiffness - 1).max() < 2e-3
    assert np.abs(fit.group("M")[0] / truth.mass - 1).max() < 2e-3
    assert np.isfinite(se).all() and fit.history[-1] < 1e-3 * fit.history[0]
    assert not any(n.endswith(":z]") for n in fit.cov.names)
