"""Error bars of the regression over independent runs: the cluster jackknife, exactly."""

from __future__ import annotations

import numpy as np

from identified.fit.uncertainty import BlockFactors, LinearSolve, covariance


def _problem(rng: np.random.Generator, sizes: list[int], p: int = 3):
    """Runs of rows ``[B, -y]`` (one equation block), ``theta = [beta, 1]`` with the last entry the
    anchor: the least-squares fit, its factors and the explicit leave-one-run-out refits."""
    beta = np.arange(1.0, p + 1)
    Bs = [rng.normal(size=(n, p)) * np.geomspace(1, 10, p) for n in sizes]
    ys = [B @ beta + rng.normal(0, 0.3, len(B)) * (1 + np.abs(B[:, 0])) for B in Bs]  # heteroscedastic
    fit = lambda keep: np.linalg.lstsq(np.vstack([Bs[g] for g in keep]), np.concatenate([ys[g] for g in keep]),
                                       rcond=None)[0]
    est = fit(range(len(sizes)))
    loo = np.array([fit([h for h in range(len(sizes)) if h != g]) for g in range(len(sizes))])
    rows = [np.column_stack([B, -y]) for B, y in zip(Bs, ys)]
    whole = np.vstack([b for b in Bs])
    _U, s, Vt = np.linalg.svd(whole, full_matrices=False)
    factors = BlockFactors(R=[np.linalg.qr(np.vstack(rows), mode="r")], rows=[len(whole)], blocks=[(0, 0)],
                           columns=[np.arange(p + 1)], cluster_R=[[np.linalg.qr(r, mode="r")] for r in rows])
    lin = LinearSolve(M=Vt.T / s, IK=None, singular_values=s, residual=0.0)
    G, Nul = np.eye(p + 1), np.eye(p + 1)[:, :p]
    return factors, G, Nul, np.append(est, 1.0), lin, est, loo


def test_error_bars_are_the_jackknife_of_the_runs():
    """The covariance is (G-1)/G times the spread of the estimates refitted without each run: for
    least squares the Newton step from the full fit is the refit, to rounding."""
    rng = np.random.default_rng(0)
    factors, G, Nul, phi, lin, _est, loo = _problem(rng, [30, 12, 25, 40, 8, 20, 33, 15, 27, 19, 22, 60])
    cov, how = covariance(factors, G, Nul, phi, np.ones(1), None, lin)
    d = loo - loo.mean(axis=0)
    want = (len(loo) - 1) / len(loo) * d.T @ d
    np.testing.assert_allclose(cov[:3, :3], want, rtol=1e-9, atol=1e-14 * np.abs(want).max())
    assert np.all(cov[3] == 0) and how.startswith("cluster-robust jackknife over 12")
    # wider than the first-order sandwich A^-1 (sum psi psiᵀ) A^-1 with a run of large leverage
    Ainv = lin.M @ lin.M.T
    psi = np.array([Nul.T @ (R[0].T @ (R[0] @ phi)) for R in factors.cluster_R])
    sandwich = Ainv @ (psi.T @ psi) @ Ainv * len(psi) / (len(psi) - 1)
    assert np.all(np.diag(cov)[:3] > np.diag(sandwich))


def test_a_run_holding_a_direction_alone_falls_back_to_the_sandwich_for_it():
    """When the other runs cannot determine the parameters without a run (its rows alone excite a
    column), that run's shift is the sandwich's ``A^-1 psi_g``: finite error bars, no exception."""
    rng = np.random.default_rng(1)
    factors, G, Nul, _phi, _lin, _est, _loo = _problem(rng, [20] * 10)
    for Rg in factors.cluster_R[1:]:
        Rg[0][:, 2] = 0.0  # the third column is excited by run 0 alone
    rows = np.vstack([Rg[0] for Rg in factors.cluster_R])
    B = rows[:, :3]
    _U, s, Vt = np.linalg.svd(B, full_matrices=False)
    lin = LinearSolve(M=Vt.T / s, IK=None, singular_values=s, residual=0.0)
    phi = np.append(np.linalg.lstsq(B, -rows[:, 3], rcond=None)[0], 1.0)
    cov, _ = covariance(factors, G, Nul, phi, np.ones(1), None, lin)
    assert np.all(np.isfinite(cov)) and np.all(np.diag(cov)[:3] > 0)


def test_the_equation_of_an_unseen_spin_is_left_out(tmp_path, monkeypatch):
    """A held moment's rotation equation (the rod's spin about that axis, which its markers do not
    show) enters no factor: its block is exactly zero, in the merged factors and every run's, while
    the other rotation equations of the same rod and the same equation of the other rods keep
    their rows.  Without the hold every block has rows."""
    import identified.fit.identify as ident
    from identified.fit.identify import identify
    from identified.topology import Topology
    from tensegrity_gym.collect import CollectConfig, collect
    from tensegrity_gym.models import write_model

    path = str(tmp_path / "robot.xml")
    write_model(path, "ico", preset="robot")
    data = collect(path, CollectConfig(episodes=2, steps=300, seed=1))
    topo = Topology.from_mjcf(path)
    seen = []
    solve = ident.solve
    monkeypatch.setattr(ident, "solve", lambda f, *a, **k: seen.append(f) or solve(f, *a, **k))
    held = [(0, 2), (3, 1)]
    identify(data, topo, weak_window=None, hold_inertia=held)
    f = seen[-1]
    for b, (i, k) in enumerate(f.blocks):
        energy = [np.abs(f.R[b]).max()] + [np.abs(Rg[b]).max() for Rg in f.cluster_R]
        if (i, k - 3) in held:
            assert max(energy) == 0.0, (i, k)
        else:
            assert min(energy) > 0.0, (i, k)
    # a classified effect's passes add its columns to rows kept between passes: left out there too
    from identified.effects import make_effect

    seen.clear()
    identify(data, topo, weak_window=None, hold_inertia=held, effects=[make_effect("cable_friction", topo, path)])
    assert len(seen) > 1
    for f in seen:
        assert all(np.abs(f.R[b]).max() == 0.0 for b, (i, k) in enumerate(f.blocks) if (i, k - 3) in held)
    seen.clear()
    identify(data, topo, weak_window=None)
    assert all(np.abs(r).max() > 0 for r in seen[-1].R)


def test_a_moment_without_error_bar_is_printed_as_not_identifiable():
    """The summary prints a moment of inertia the data cannot see (no standard error: its spin
    unobservable) as not identifiable, never its placeholder value; the others as numbers."""
    from identified.model import load_model
    from tests._data import GROUND

    model = load_model(GROUND)
    model.stderr["inertia"] = np.full((model.topology.n_rods, 3), 1e-3)
    model.stderr["inertia"][1, 2] = np.nan
    model.inertia[1, 2] = 0.000765
    lines = model.summary().splitlines()
    rod1 = next(x for x in lines if x.startswith(model.topology.rods[1].name + ":"))
    assert "not identifiable" in rod1 and "0.000765" not in rod1 and f"{model.inertia[1, 0]:.4g}" in rod1
    rods = [x for x in lines if x.split(":")[0] in {r.name for r in model.topology.rods}]
    assert sum("not identifiable" in x for x in rods) == 1
