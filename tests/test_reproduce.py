"""``tensegrity reproduce`` and the baselines behind it: each piece on a case with a known answer,
every experiment's JSON schema on tiny data, and the command's one-line errors."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from identified.baselines import (
    CMAES,
    LBFGSB,
    MLP,
    Budget,
    ClosedForm,
    InteractionInt,
    KoopmanInt,
    ParameterProblem,
    make_pairs,
    monomial_pairs,
    relative_errors,
    success,
    train,
)
from identified.baselines.neural import mlp
from identified.topology import Topology
from tensegrity_gym.cli import main
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import write_model


@pytest.fixture(scope="module")
def simple(tmp_path_factory):
    """The paper's simple system: MJCF, topology, a small training and validation set."""
    d = tmp_path_factory.mktemp("simple")
    xml = str(d / "simple.xml")
    write_model(xml, "simple", preset="paper")
    tr = collect(xml, CollectConfig(episodes=6, steps=1000, seed=1))
    va = collect(xml, CollectConfig(episodes=2, steps=1000, seed=2))
    return xml, Topology.from_mjcf(xml), tr, va


# ---------------------------------------------------------------------- the pieces
def test_success_criterion_is_five_percent_of_every_parameter():
    truth = {"K/M": 10.0, "c/M": 1.0}
    assert success({"K/M": 10.4, "c/M": 0.96}, truth)
    assert not success({"K/M": 10.6, "c/M": 1.0}, truth)
    assert not success({"K/M": 10.0, "c/M": float("nan")}, truth)
    assert relative_errors({"K/M": 12.0}, {"K/M": 10.0})["K/M"] == pytest.approx(0.2)


def _convex_problem() -> tuple[ParameterProblem, np.ndarray]:
    opt = np.array([100.0, 10.0, 3.0])
    scale = np.array([100.0, 10.0, 1.0])
    f = lambda th: float(np.sum(((np.asarray(th) - opt) / scale) ** 2))
    return ParameterProblem(("K", "c", "M"), np.ones(3), np.tile([0.1, 1000.0], (3, 1)), objective=f), opt


def test_lbfgsb_finds_the_optimum_of_a_convex_case():
    problem, opt = _convex_problem()
    est = LBFGSB(max_iter=100).estimate(problem)
    x = np.array([est.values[n] for n in problem.names])
    assert np.allclose(x, opt, rtol=1e-4)
    assert est.iterations >= 1 and est.trace.shape[1] == 3


def test_cmaes_finds_the_optimum_of_a_convex_case():
    problem, opt = _convex_problem()
    est = CMAES(tolx=1e-4, max_iter=400, seed=3).estimate(problem)
    x = np.array([est.values[n] for n in problem.names])
    assert np.allclose(x, opt, rtol=1e-2)
    assert est.evaluations >= est.iterations


def test_mlp_fits_a_linear_map():
    from tensegrity_gym.reproduce.common import single_thread

    g = torch.Generator().manual_seed(0)
    A = torch.randn(3, 2, generator=g)
    x = torch.randn(512, 3, generator=g)
    y = x @ A
    torch.manual_seed(0)
    net = mlp(3, 2, hidden=30, layers=6)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    with single_thread():
        for _ in range(500):
            loss = torch.mean((net(x) - y) ** 2)
            opt.zero_grad()
            loss.backward()
            opt.step()
    assert loss.item() < 1e-3 * y.var().item()


def test_koopman_basis_holds_the_papers_terms():
    terms = monomial_pairs(15, degree=2)
    assert len(terms) == 15 + 15 * 14 // 2  # every z_a^2 and z_a z_b
    assert ((0, 2),) in terms and ((0, 1), (14, 1)) in terms
    assert len(monomial_pairs(2, degree=3)) == 7  # a², a³, b², b³, ab, a²b, ab²


def test_koopman_recovers_the_linear_acceleration_exactly(simple):
    """a = -(K/M)(Δp̂1 + Δp̂2) - (c/M)(Δv̂1 + Δv̂2) is linear in the basis (appendix B)."""
    _, topo, tr, va = simple
    k = KoopmanInt(topo, tr.dt, degree=2, aggregate=True).fit(tr, va)
    assert k.n_features == 1 + 15 + 120
    for data, tol in ((tr, 1e-18), (va, 1e-6)):  # exact on the fitting rows, near exact on unseen ones
        for phi, y in k._pairs(data):
            err = ((k._apply(k.coef_, phi) - y)[..., :3] ** 2).mean() / (y[..., :3] ** 2).mean()
            assert float(err) < tol
    assert max(k.validation_mse_[3:]) > 1e-6  # α is not: the basis has no gyroscopic term


def test_koopman_streamed_fit_does_not_depend_on_the_block_size(simple):
    """Paper scale streams the rows through the QR and the validation pass in blocks: the ridges
    and coefficients must be those of one block."""
    _, topo, tr, va = simple
    whole = KoopmanInt(topo, tr.dt, degree=2, aggregate=True)
    whole.chunk = 10 ** 7
    whole.fit(tr, va)
    streamed = KoopmanInt(topo, tr.dt, degree=2, aggregate=True)
    streamed.chunk = 300  # several blocks per trajectory
    streamed.fit(tr, va)
    assert streamed.ridge_ == whole.ridge_
    for phi, _ in whole._pairs(va):  # the same predictions (the basis is rank deficient: the
        a, b = streamed._apply(streamed.coef_, phi), whole._apply(whole.coef_, phi)  # coefficients may not be)
        assert float((a - b).norm() / b.norm()) < 1e-6
    for lam, mse in whole.validation_.items():
        assert np.allclose(streamed.validation_[lam], mse, rtol=1e-4, atol=1e-10)  # rounding-level a errors


def test_paper_scale_neural_budget_picks_the_rate_on_a_subset(simple, monkeypatch):
    """Paper scale: the grid on the first trajectories, then one run at the chosen rate on all."""
    from tensegrity_gym.reproduce import simple as sim
    from tensegrity_gym.reproduce.common import Context

    assert sim.lr_selection(True) is None and sim.lr_selection(False)["train"] < sim.physics_sizes(False)["train"]
    _, topo, tr, va = simple
    P, V = make_pairs(tr), make_pairs(va)
    assert len(sim._head(P, tr.n_steps)) == tr.n_steps
    ctx = Context(quick=False, seed=0, out=None, workdir=".", progress=False)
    sel = {"train": 1, "val": 1, "max_epochs": 2, "patience": 1}
    res, chosen, curve = sim._train_neural(ctx, "MLP", lambda: MLP(topo, tr.dt), P, V,
                                           Budget(lrs=(3e-3, 3e-4), max_epochs=2, patience=1, batch=256), sel,
                                           tr.n_steps)
    assert res.lr == chosen.lr and set(chosen.per_lr) == {3e-3, 3e-4} and list(res.per_lr) == [chosen.lr]
    assert len(curve) == res.per_lr[res.lr]["epochs"] and res.seconds >= chosen.seconds


def test_bound_heap_applies_on_glibc():
    import sys

    from tensegrity_gym.reproduce.common import bound_heap

    assert bound_heap() is sys.platform.startswith("linux")


def test_closed_form_solver_recovers_the_ratios(simple):
    _, topo, tr, _ = simple
    ref = tr.select(episodes=slice(0, 1))
    p = ParameterProblem(("K", "c", "M"), np.ones(3), np.tile([0.1, 1000.0], (3, 1)), dataset=ref, topology=topo)
    est = ClosedForm().estimate(p)
    assert est.values["K"] / est.values["M"] == pytest.approx(10.0, rel=1e-10)
    assert est.values["c"] / est.values["M"] == pytest.approx(1.0, rel=1e-10)
    known = ParameterProblem(("K", "c"), np.ones(2), np.tile([0.1, 1000.0], (2, 1)), dataset=ref, topology=topo,
                             known={"M": 10.0})
    est = ClosedForm().estimate(known)
    assert est.values["K"] == pytest.approx(100.0, rel=1e-10) and est.values["c"] == pytest.approx(10.0, rel=1e-10)


def test_training_loop_early_stops_on_validation_and_keeps_the_best(simple):
    _, topo, tr, va = simple
    from tensegrity_gym.reproduce.common import single_thread

    P, V = make_pairs(tr), make_pairs(va)
    with single_thread():
        res = train(lambda: InteractionInt(topo, tr.dt), P, V,
                    Budget(lrs=(3e-3, 1e-3), max_epochs=6, patience=3, batch=128))
    assert res.lr in (3e-3, 1e-3)
    assert res.val_loss == min(v["val_loss"] for v in res.per_lr.values())
    from identified.baselines.neural import _val_loss

    assert _val_loss(res.model, V) == pytest.approx(res.val_loss, rel=1e-5)  # the best weights are kept
    assert res.val_loss < 1.0  # better than predicting the mean of the standardised targets


def test_trajectory_simulator_reproduces_the_plant_at_the_truth(simple):
    from tensegrity_gym.reproduce.blackbox import TrajectorySimulator

    xml, _, tr, _ = simple
    sim = TrajectorySimulator(xml, tr.select(episodes=slice(0, 1)), ("K", "c", "M"), {})
    assert sim.objective(np.array([100.0, 10.0, 10.0])) < 1e-20
    assert sim.objective(np.array([1.0, 1.0, 1.0])) > 1e-4


# ---------------------------------------------------------------------- every experiment, tiny
@pytest.fixture
def tiny(monkeypatch):
    """Every experiment's sizes and budgets shrunk to seconds."""
    from identified.baselines import Budget as B
    from tensegrity_gym.reproduce import ico
    from tensegrity_gym.reproduce import simple as sim

    monkeypatch.setattr(sim, "blackbox_sizes", lambda quick: (1, 300, 15))
    monkeypatch.setattr(sim, "physics_sizes",
                        lambda quick: {"train": 2, "val": 1, "test": 1, "steps": 200, "test_steps": 100})
    monkeypatch.setattr(sim, "neural_budget", lambda quick, seed: B(lrs=(1e-3,), max_epochs=1, patience=1))
    small = {"train": 2, "val": 1, "test": 1, "steps": 200, "test_steps": 200}
    monkeypatch.setattr(ico, "sizes", lambda quick: dict(small))
    monkeypatch.setattr(ico, "efficiency_sizes", lambda quick: dict(small, train=1))
    monkeypatch.setattr(ico, "FRACTIONS", (0.1,))
    monkeypatch.setattr(ico, "generalization_sizes", lambda quick: ((1, 400), (1, 300), (1, 300)))


def _run(tmp_path, name: str) -> dict:
    out, js = tmp_path / "fig", tmp_path / f"{name}.json"
    assert main(["reproduce", name, "--quick", "--quiet", "--json", str(js), "--out", str(out)]) == 0
    data = json.loads(js.read_text())
    assert data["experiment"] == name
    assert data["rows"] and all(isinstance(r["method"], str) for r in data["rows"])
    assert data["figures"] and all(os.path.isfile(f) for f in data["figures"])
    return data


def _row(data: dict, method: str, **match) -> dict:
    rows = [r for r in data["rows"] if r["method"] == method and all(r.get(k) == v for k, v in match.items())]
    assert rows, f"no row {method} {match}"
    return rows[0]


def test_simple_blackbox_schema_and_ours_recovers_the_truth(tiny, tmp_path):
    data = _run(tmp_path, "simple-blackbox")
    methods = {r["method"] for r in data["rows"]}
    assert {"LS", "CMA-ES", "mujoco.sysid", "Ours", "Ours (adam)"} <= methods
    ours = _row(data, "Ours", variant="M unknown")
    assert ours["success"] == 1.0
    assert ours["K/M"] == pytest.approx(10.0, rel=1e-9) and ours["c/M"] == pytest.approx(1.0, rel=1e-9)
    known = _row(data, "Ours", variant="M known")
    assert known["K"] == pytest.approx(100.0, rel=1e-9) and known["c"] == pytest.approx(10.0, rel=1e-9)
    for r in data["rows"]:
        if "success" in r:
            assert 0.0 <= r["success"] <= 1.0 and r["sec_per_iter"] > 0


def test_simple_physics_schema(tiny, tmp_path):
    data = _run(tmp_path, "simple-physics")
    assert [r["method"] for r in data["rows"]] == ["MLP", "MLP+Int", "Interaction", "Interaction+Int",
                                                   "Koopman+Int", "Ours"]
    assert _row(data, "Ours")["pos_mean"] < 1e-10


def test_ico_uniform_and_nonuniform_schema(tiny, tmp_path):
    uni = _run(tmp_path, "ico-uniform")
    assert {r["method"] for r in uni["rows"]} == {"Koopman+Int", "Ours"}
    assert _row(uni, "Ours")["param_max_rel_error"] < 1e-9
    non = _run(tmp_path, "ico-nonuniform")
    single, multiple = _row(non, "Single"), _row(non, "Multiple")
    assert multiple["param_max_rel_error"] < 1e-9 and multiple["pos_mean"] < 1e-10
    assert single["param_max_rel_error"] > 0.01  # one K, c, M cannot fit 54 different ones


def test_data_efficiency_schema(tiny, tmp_path):
    data = _run(tmp_path, "data-efficiency")
    full = _row(data, "Ours", fraction=1.0)
    assert full["param_max_rel_error"] < 1e-9
    assert any(r["method"] == "Koopman+Int" for r in data["rows"])
    smallest = _row(data, "Ours (smallest)")
    assert smallest["steps"] is not None and smallest["steps"] <= 200
    assert smallest["param_max_rel_error"] <= 1e-4


def test_generalization_recovers_the_control_scale(tiny, tmp_path):
    data = _run(tmp_path, "generalization")
    fitted = [r for r in data["rows"] if r["h"]]
    assert fitted and all(r["h_rel_error"] < 1e-6 for r in fitted)
    ignored = [r for r in data["rows"] if not r["h"]]
    assert all(r["pos_mean"] > f["pos_mean"] for r, f in zip(ignored, fitted))


# ---------------------------------------------------------------------- bad input
@pytest.mark.parametrize("argv, expect", [
    (["reproduce", "no-such-experiment"], "invalid choice"),
    (["reproduce", "ico-uniform", "--seed", "-3", "--quick"], "--seed must be >= 0"),
    (["reproduce", "ico-uniform", "--quick", "--out", "/proc/no/such/folder"], "cannot write"),
])
def test_bad_input_is_one_line_and_exit_2(argv, expect, capsys):
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse's own errors exit from the parser
        rc = exc.code
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.startswith("tensegrity: error:") and expect in err and "\n" not in err


def test_out_that_is_a_file_is_refused(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["reproduce", "ico-uniform", "--quick", "--out", str(f)]) == 2
    assert "not a folder" in capsys.readouterr().err


@pytest.mark.expensive
def test_simple_blackbox_quick_ranks_ours_first(tmp_path):
    """The real --quick run: ours succeeds on every trajectory and is the fastest per iteration."""
    data = _run(tmp_path, "simple-blackbox")
    for variant in ("M unknown", "M known"):
        ours = _row(data, "Ours", variant=variant)
        assert ours["success"] == 1.0
        others = [r for r in data["rows"] if r.get("variant") == variant and r["method"] in ("LS", "CMA-ES")]
        assert all(ours["sec_per_iter"] < r["sec_per_iter"] for r in others)
