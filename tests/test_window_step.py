"""The output-error windows stepped at a multiple of the reconstruction's step
(``window_problem(..., substeps=k)``, :func:`identified.fit.output_error.coarse_steps`): with
``k`` = 1 they are the windows at ``dt`` bit for bit; with ``k`` = 2 they are, to rounding, the
windows of the same states sampled every second step (a reconstruction at ``2 dt``, each coarse step
holding the rest length read at its start) -- through the contact law and through the free wrench."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from identified.dataset import Dataset
from identified.effects.pyramid_contact import PyramidContact
from identified.fit.output_error import _Problem, coarse_steps, marker_windows, window_problem
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model

from .test_pyramid_contact import TRUTH
from .test_record_output_error import _robot, _truth

HELD = [(i, 2) for i in range(6)]  # end caps on the rods' axes


def _every(data: Dataset, k: int) -> Dataset:
    """The plant's states and rest lengths at every ``k``-th step: a recording's reconstruction at
    ``k dt``."""
    return replace(data, dt=k * data.dt, pos=data.pos[:, ::k], quat=data.quat[:, ::k], vel=data.vel[:, ::k],
                   angvel=data.angvel[:, ::k], rest_length=data.rest_length[:, ::k], command=data.command[:, ::k],
                   push_force=data.push_force[:, ::k], push_point=data.push_point[:, ::k])


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """The robot on its ground, 0.4 s of random commands, clean 50 Hz markers (20 ms: 2 ms steps fit)."""
    torch.set_num_threads(1)
    path = str(tmp_path_factory.mktemp("ws") / "robot.xml")
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=1, steps=400, seed=3))
    rec = record_markers(data, path, RecordConfig(rate=50, noise_pos=0.0, dropout=0.0), seed=3)
    law = PyramidContact.for_system(_truth(path).topology, path)
    law.values = TRUTH.copy()
    return path, data, rec, _truth(path), law


def _residuals(prob: _Problem, dx: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return prob.residuals(prob.theta0, dx)


def test_coarse_steps_keep_every_frame():
    """Frames 33 and 34 ms apart (30 Hz on 1 ms): steps of at most ``k``, as equal as whole steps
    allow, every frame on one; ``k`` dividing every interval: all exactly ``k``; ``k`` = 1: every step."""
    step = np.array([0, 33, 67, 100, 133])
    g = coarse_steps(step, 5)
    assert np.isin(step, g).all() and g[0] == 0 and g[-1] == 133
    assert set(np.diff(g).tolist()) == {4, 5} and len(g) == 1 + 4 * 7
    np.testing.assert_array_equal(coarse_steps(step, 1), np.arange(134))
    np.testing.assert_array_equal(coarse_steps(np.array([0, 20, 40]), 4), np.arange(0, 41, 4))
    with pytest.raises(ValueError):
        coarse_steps(step, 0)


def test_substeps_one_is_the_windows_at_dt(robot):
    """``substeps`` 1 (the default) steps every ``dt``: the same residuals, bit for bit, as a
    problem stepped through its grid of every step by hand."""
    path, data, rec, truth, law = robot
    _, _, prob, dx, _ = window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=6, contact=law)
    _, _, one, _, _ = window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=6, contact=law, substeps=1)
    np.testing.assert_array_equal(prob.grid, np.arange(prob.win.n_steps + 1))
    assert torch.equal(_residuals(prob, dx), _residuals(one, dx))
    assert float(_residuals(prob, dx).abs().max()) * 1e-3 < 1e-8  # the plant's own states, its law: rounding


def test_two_steps_are_the_windows_of_a_reconstruction_at_2dt(robot):
    """Through the contact law: the windows at ``substeps`` 2 on the 1 ms states give exactly the
    residuals of the windows on the same states sampled at 2 ms (the rest length of each coarse step
    read at its start), and differ from the 1 ms windows (by the coarser step's error: measured
    2.8 mm at worst through the contacts of these 0.1 s windows); the free wrench's windows likewise,
    to rounding (its time is taken at the step's middle)."""
    path, data, rec, truth, law = robot
    half = _every(data, 2)
    _, _, fine, dx, _ = window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=6, contact=law)
    _, _, two, _, _ = window_problem(truth, rec, data, [0.0], path, 1e-3, HELD, frames=6, contact=law, substeps=2)
    _, _, ref, _, _ = window_problem(truth, rec, half, [0.0], path, 1e-3, HELD, frames=6, contact=law)
    assert two.grid.size == ref.grid.size == 51 and fine.grid.size == 101
    r2, rr, r1 = _residuals(two, dx), _residuals(ref, dx), _residuals(fine, dx)
    torch.testing.assert_close(r2, rr, rtol=0, atol=1e-9)
    assert 1e-4 < float((r2 - r1).abs().max()) * 1e-3 < 1e-2
    # the free wrench (rods near the ground), on the same windows and rods simulated
    win = marker_windows(rec, data, [0.0], truth.topology, path, frames=6)
    win_half = replace(marker_windows(rec, half, [0.0], truth.topology, path, frames=6), free=win.free)
    assert bool((~win.free).any())
    p2 = _Problem(truth, win, data.dt, 1e-3, HELD, 2, substeps=2)
    pr = _Problem(truth, win_half, half.dt, 1e-3, HELD, 2)
    dxw = torch.zeros(win.n_windows, 6, p2.n_x, dtype=torch.float64)
    dxw[..., 12:15] = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # 10 N up
    dxw[..., 18:21] = torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64)  # and growing sideways
    torch.testing.assert_close(_residuals(p2, dxw), _residuals(pr, dxw), rtol=0, atol=1e-9)


def _gauss_newton_step(jac: _Problem, r: torch.Tensor, dx: torch.Tensor, acts: torch.Tensor) -> torch.Tensor:
    """The parameters' Gauss-Newton step (total mass held) from ``jac``'s Jacobian and residuals ``r``,
    the windows' states eliminated."""
    import scipy.linalg as sla

    from identified.fit.window_solve import window_schur

    _, Jx, Jp = jac.jacobians(jac.theta0, dx)
    Jx = Jx * acts.unsqueeze(1)
    U = torch.as_tensor(sla.null_space(jac.total_mass_row(jac.base.mass.numpy())[None]))
    Ju = Jp @ U
    A = Jx.transpose(1, 2) @ Jx
    A = A + torch.diag_embed(1 - acts + 1e-9 * torch.diagonal(A, dim1=-2, dim2=-1).amax(-1, keepdim=True))
    sc = window_schur(A, Jx.transpose(1, 2) @ Ju, (Ju.transpose(1, 2) @ Ju).sum(0))
    _, gs = sc.reduce(Jx.transpose(1, 2) @ r.unsqueeze(-1), (Ju.transpose(1, 2) @ r.unsqueeze(-1)).sum(0))
    return (U @ -torch.linalg.solve(sc.S, gs)).squeeze(-1)


def test_coarse_jacobian_with_the_cost_at_dt_leaves_the_truth(tmp_path):
    """What ``fit_markers(substeps=k)`` does: the Jacobian from the windows at ``k dt``, the residuals
    at ``dt``.  From the truth on clean markers (the robot without its ground, falling) its step
    stays at the truth (the residuals at ``dt`` are rounding), where the coarse windows' own
    residuals move K, c, M (by their step's error)."""
    torch.set_num_threads(1)
    path = _robot(tmp_path, floor=False)
    data = collect(path, CollectConfig(episodes=1, steps=200, seed=3))
    rec = record_markers(data, path, RecordConfig(rate=50, noise_pos=0.0, dropout=0.0), seed=3)
    _, _, prob, dx, acts = window_problem(_truth(path), rec, data, [0.0], None, 1e-3, HELD, frames=3, max_windows=2,
                                          order=0)
    jac = prob.at_step(2)
    W = dx.shape[0]
    fine = _gauss_newton_step(jac, _residuals(prob, dx).reshape(W, -1), dx, acts)
    coarse = _gauss_newton_step(jac, _residuals(jac, dx).reshape(W, -1), dx, acts)
    n = jac.n_spring_rod
    assert float(fine[:n].abs().max()) < 1e-6
    assert float(coarse[:n].abs().max()) > 1e-3
