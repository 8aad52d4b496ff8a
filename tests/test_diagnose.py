"""Diagnosis against known truth: a clean plant leaves nothing to explain; a plant with a hidden
effect (MuJoCo's fluid viscosity: linear drag on every body) is traced to ``linear_drag``.

Small data (3 episodes x 300 steps of a paper preset): the Euler plant's equations are exact, so the
clean fit leaves a residual at rounding level.
"""

from __future__ import annotations

import json
import os
from dataclasses import replace

import numpy as np
import pytest

from identified import Topology
from identified.dataset import DatasetError
from identified.diagnose import DOFS, at_rounding_level, diagnose, improved, ljung_box, verdict, write_report
from identified.diagnose.stats import ALPHA, corr_matrix, input_correlation, whiteness
from identified.effects import EFFECTS, make_effect
from identified.fit.identify import identify
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import write_model
from tests._data import GROUND

HORIZON = 0.25  # s; the episodes hold 0.3 s


def _residual_series(model, data, rod: int, dof: int) -> np.ndarray:
    """One residual series (all episodes, flattened) of the model on the data, forward scheme."""
    import torch

    from identified.evaluate import recorded_samples, residual_wrench
    from identified.twin import engine_from_model

    ch, _, point = recorded_samples(data, "forward")
    rw = residual_wrench(engine_from_model(model), ch, point)
    return torch.cat((rw.force, rw.torque_body), -1)[:, rod, dof].numpy()
CFG = CollectConfig(episodes=3, steps=300, seed=1, push_every=100)


@pytest.fixture(scope="module")
def plants(tmp_path_factory):
    folder = tmp_path_factory.mktemp("diagnose")
    clean_xml = str(folder / "clean.xml")
    text = write_model(clean_xml, "ico", preset="paper-nonuniform", seed=3)
    visc_xml = str(folder / "viscous.xml")
    assert '<option ' in text
    with open(visc_xml, "w", encoding="utf-8") as fh:  # a plant with an effect nobody declares
        fh.write(text.replace('<option ', '<option viscosity="2" '))
    out = {}
    for name, xml in (("clean", clean_xml), ("viscous", visc_xml)):
        data = collect(xml, CFG)
        topo = Topology.from_mjcf(xml)
        model = identify(data, topo)  # no effects
        out[name] = (xml, data, topo, model)
    return out


@pytest.fixture(scope="module")
def clean_result(plants):
    _, data, _, model = plants["clean"]
    return diagnose(model, data, horizon_s=HORIZON)


@pytest.fixture(scope="module")
def viscous_result(plants):
    _, data, _, model = plants["viscous"]
    return diagnose(model, data, horizon_s=HORIZON)


def test_clean_plant_residual_at_rounding_level_and_explained(clean_result):
    r = clean_result
    json.dumps(r, allow_nan=False)  # JSON-able, no NaN
    for key in ("error_before", "error_after", "metric", "added", "explained", "candidates"):
        assert key in r
    assert r["added"] == []
    assert r["error_after"] == r["error_before"] < 1e-10  # m: the model is the plant
    assert r["one_step"]["relative"]["force"] < 1e-10
    assert r["one_step"]["relative"]["torque"] < 1e-10
    assert r["explained"] is True and "rounding" in r["explained_by"]
    assert r["k_step"]["after"]["100"]["pos"] < 1e-12
    # every library effect is scored (ground_contact needs a ground plane: this plant has none)
    names = {c["name"] for c in r["candidates"]}
    assert names == {n for n, cls in EFFECTS.items() if cls.searched} - {"ground_contact", "pyramid_contact"}
    assert {s["name"] for s in r["skipped"]} >= {"ground_contact"}
    for c in r["candidates"]:
        assert 0.0 <= c["score"] < 0.05, c
        assert c["score_alone"] < 0.05, c


def test_hidden_viscosity_is_traced_to_linear_drag(viscous_result):
    r = viscous_result
    json.dumps(r, allow_nan=False)
    assert r["added"] == [] and r["explained"] is False and r["explained_by"] == []
    assert r["error_after"] > 1e-3  # the missing drag moves the rods by millimetres within 0.25 s
    assert r["one_step"]["relative"]["force"] > 1e-3
    assert r["whiteness"]["white"] is False and r["whiteness"]["min_p"] < 1e-6
    top, *others = r["candidates"]
    assert top["name"] == "linear_drag"
    assert top["score"] > 0.99  # it is the plant's law: nothing is left
    # clearly ahead: every other candidate leaves at least 10x more of the residual unexplained
    for c in others:
        assert c["unexplained"] > 10 * top["unexplained"] + 0.02, c
        assert c["score"] < 0.97, c
    assert r["best_feature"]["candidate"] in {c["name"] for c in r["candidates"]}


def test_added_effect_before_and_after(plants):
    _, data, topo, _ = plants["viscous"]
    model = identify(data, topo, effects=[make_effect("linear_drag", topo)])
    r = diagnose(model, data, horizon_s=HORIZON)
    assert r["added"] == ["linear_drag"]
    assert "linear_drag" not in {c["name"] for c in r["candidates"]}
    assert r["error_before"] > 1e-3  # the same parameters without the drag
    assert r["error_after"] < 1e-9 * r["error_before"]
    assert r["explained"] is True and {"rounding", "improved"} <= set(r["explained_by"])
    assert r["k_step"]["before"]["100"]["pos"] > 1e3 * r["k_step"]["after"]["100"]["pos"]
    assert max(c["score"] for c in r["candidates"]) < 0.05


def test_regions_statistics_and_inputs(viscous_result, plants):
    r = viscous_result
    reg = r["regions"]
    assert reg["near_ground"]["available"] is False  # no geometry given, none in the model
    for key in ("slack", "fast", "pushed"):
        assert reg[key]["available"] is True
        assert 0.0 < reg[key]["fraction"] < 1.0
    assert reg["fast"]["fraction"] == pytest.approx(0.1, abs=0.01)
    # pushes: 10 of every 100 steps on one rod at a time
    pushed = np.linalg.norm(plants["viscous"][1].push_force, axis=-1) > 0
    assert reg["pushed"]["fraction"] == pytest.approx(pushed.mean(), rel=1e-9)
    lb = r["whiteness"]
    assert len(lb["per_rod"]) == 6 and all(len(x["series"]) == 6 for x in lb["per_rod"])
    assert lb["median_Q_per_dof"] > 10
    ic = r["input_correlation"]
    assert ic["rest_length"]["corr"] is None  # the paper preset's rest lengths never change
    # the reported correlation is the Pearson correlation of that residual series with that push
    # component, recomputed here from the model's residual wrench
    _, data, _, model = plants["viscous"]
    pf = ic["push_force"]
    rod, dof, axis = data.rod_names.index(pf["rod"]), DOFS.index(pf["dof"]), "xyz".index(pf["input"][-1])
    series, push = _residual_series(model, data, rod, dof), data.push_force[:, :, rod, axis].reshape(-1)
    assert pf["corr"] == pytest.approx(np.corrcoef(series, push)[0, 1], rel=1e-9)
    assert abs(pf["corr"]) > 0.05  # the drag slows the pushed rods: not a chance correlation
    per = r["one_step"]["per_rod"]
    assert [p["rod"] for p in per] == list(plants["viscous"][2].rod_names)
    assert all(len(p["force_rms"]) == 3 and len(p["torque_rms"]) == 3 for p in per)
    assert len(r["free_run"]["after"]) == len(r["free_run"]["time_s"]) > 10


def test_ground_contact_candidate_needs_a_ground_plane(plants):
    xml, data, _, model = plants["clean"]
    r = diagnose(model, data.select(episodes=[0]), horizon_s=0.1, mjcf=xml)
    skipped = {s["name"]: s["reason"] for s in r["skipped"]}
    assert "ground plane" in skipped["ground_contact"]
    assert r["regions"]["near_ground"]["available"] is False


def test_bad_input_is_refused(plants):
    _, data, _, model = plants["clean"]
    with pytest.raises(ValueError, match="horizon"):
        diagnose(model, data, horizon_s=1.0)  # 0.3 s of data
    renamed = replace(data, rod_names=tuple(f"bar{i}" for i in range(6)))
    with pytest.raises(DatasetError, match="do not match"):
        diagnose(model, renamed, horizon_s=HORIZON)


def test_write_report(viscous_result, tmp_path):
    out = tmp_path / "report"
    paths = write_report(viscous_result, str(out))
    names = sorted(os.path.basename(p) for p in paths)
    assert names == ["free_run_error.png", "report.md", "residual_feature.png", "residual_time.png"]
    for p in paths:
        assert os.path.getsize(p) > 500
    assert sorted(os.listdir(out)) == names  # atomic writes leave no temporary files
    with open(out / "report.md", encoding="utf-8") as fh:
        text = fh.read()
    assert "NOT explained" in text and "**linear_drag**" in text
    held = viscous_result["candidates"][0]["score_held_out"]
    assert f"**Verdict: the residual is NOT explained**: linear_drag removes {held:.1%}" in text
    assert f"| linear_drag | {held:.4f} |" in text
    for png in names:
        if png != "report.md":
            assert f"]({png})" in text  # the report shows every figure


def test_ljung_box_tells_white_from_correlated():
    from scipy.stats import chi2

    rng = np.random.default_rng(0)
    white = rng.standard_normal((4, 2000))
    q, dof = ljung_box(white, 20)
    assert dof == 80 and chi2.sf(q, dof) > 0.01
    ar = np.zeros((4, 2000))
    for t in range(1, 2000):
        ar[:, t] = 0.8 * ar[:, t - 1] + white[:, t]
    q, dof = ljung_box(ar, 20)
    assert chi2.sf(q, dof) < 1e-12
    # the statistic itself, by its definition, on one short series
    x = rng.standard_normal(50)
    xc = x - x.mean()
    rho = [np.sum(xc[:-k] * xc[k:]) / np.sum(xc * xc) for k in range(1, 4)]
    want = 50 * 52 * sum(r * r / (50 - k) for k, r in zip(range(1, 4), rho))
    assert ljung_box(x, 3) == (pytest.approx(want, rel=1e-12), 3)


def test_diagnose_out_never_overwrites_an_input(tmp_path, capsys):
    from tensegrity_gym.cli import main

    data, model = tmp_path / "D.npz", tmp_path / "F.json"
    data.write_bytes(b"not touched")
    model.write_text("{}")
    for out in (data, model):
        assert main(["diagnose", str(data), "--identified", str(model), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("tensegrity: error: --out") and err.count("\n") == 1
    assert data.read_bytes() == b"not touched" and model.read_text() == "{}"


def test_free_run_error_is_the_mean_over_steps_one_to_h(viscous_result, plants):
    """error_after: the rods' centre-of-mass distance, mean over episodes, rods and steps 1..H (the
    recorded start, where the error is 0 by construction, is not averaged in)."""
    from identified.twin import engine_from_model

    _, data, _, model = plants["viscous"]
    H = viscous_result["horizon_steps"]
    eng = engine_from_model(model)
    s0 = eng.state(data.pos[:, 0], data.quat[:, 0], data.vel[:, 0], data.angvel[:, 0])
    st = eng.rollout(s0, data.rest_length[:, :H], data.push_force[:, :H], data.push_point[:, :H])
    err = np.linalg.norm(st.pos.numpy() - data.pos[:, : H + 1], axis=-1).mean(axis=(0, 2))
    assert err[0] == 0.0 and H == round(HORIZON / data.dt)
    assert viscous_result["error_after"] == pytest.approx(err[1:].mean(), rel=1e-12)
    assert viscous_result["free_run"]["after"][-1] == pytest.approx(err[-1], rel=1e-12)


def test_corr_matrix_gives_known_correlations_exactly():
    rng = np.random.default_rng(3)
    x = rng.standard_normal((500, 2))
    y = np.column_stack((3.0 * x[:, 0] + 1.0, -2.0 * x[:, 1], 5.0 * np.ones(500)))
    c = corr_matrix(y, x)
    assert c[0, 0] == pytest.approx(1.0, abs=1e-12) and c[1, 1] == pytest.approx(-1.0, abs=1e-12)
    assert c[0, 1] == pytest.approx(np.corrcoef(x[:, 0], x[:, 1])[0, 1], abs=1e-12)
    assert np.all(c[2] == 0.0)  # a constant series correlates with nothing
    assert corr_matrix(y, np.ones((500, 2))) is None


def test_input_correlation_finds_the_push_a_residual_follows(plants):
    _, data, _, _ = plants["viscous"]
    E, T, R = data.n_episodes, data.n_steps, data.n_rods
    res = np.random.default_rng(0).standard_normal((E, T, R, 6)) * 1e-3
    res[:, :, 4, 1] -= 0.5 * data.push_force[:, :T, 4, 2]  # rod 4's fy against its push's z
    out = input_correlation(res, np.arange(T), data)
    pf = out["push_force"]
    assert (pf["rod"], pf["dof"], pf["input"]) == (data.rod_names[4], "fy", "push_force.z")
    want = np.corrcoef(res[:, :, 4, 1].reshape(-1), data.push_force[:, :T, 4, 2].reshape(-1))[0, 1]
    assert pf["corr"] == pytest.approx(want, rel=1e-12) and pf["corr"] < -0.99
    assert out["rest_length"]["corr"] is None  # the preset's rest lengths never change


def _rows(inside, outside, per_in=None, per_out=None):
    entry = {"effect": "ground_contact", "region": "near_ground",
             "inside": {"force": inside, "torque": inside / 2}, "outside": {"force": outside, "torque": outside}}
    entry["inside_per_episode"] = [{"force": v, "torque": v / 2} for v in (per_in or [inside])]
    entry["outside_per_episode"] = [{"force": v, "torque": v} for v in (per_out or [outside])]
    return [entry]


def test_verdict_true_partial_false():
    # a clear signature on the effect's rows: partial, naming the effect and the part
    ex, why, partial = verdict(False, False, True, _rows(0.21, 1e-13, [0.2, 0.22], [1e-13, 2e-13]))
    assert ex == "partial" and why == ["improved"]
    assert [(p["effect"], p["part"]) for p in partial] == [("ground_contact", "force"), ("ground_contact", "torque")]
    # at the thresholds exactly (1 % and 10x): still partial; just below either: explained
    assert verdict(True, False, False, _rows(0.01, 0.001))[0] == "partial"
    assert verdict(True, False, False, _rows(0.0099, 1e-9))[0] is True
    assert verdict(True, False, False, _rows(0.05, 0.0051))[0] is True
    # every episode past 10x but not the whole: not clear
    assert verdict(True, False, False, _rows(0.2, 0.05, [0.2, 0.2], [0.001, 0.001]))[0] is True
    # one episode without the signature: not clear
    assert verdict(True, False, False, _rows(0.2, 1e-6, [0.3, 0.1], [1e-6, 0.02]))[0] is True
    # no rule explains it: false whatever the rows say; no effect with a region: true
    assert verdict(False, False, False, _rows(0.2, 1e-13)) == (False, [], [])
    assert verdict(False, True, False, []) == (True, ["white"], [])


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """The robot fitted with ``ground_contact`` (tests/data/robot_ground_contact.json: the same data
    as the shipped model, scripts/make_shipped_model.sh, fitted with that law) on fresh robot data."""
    from identified.model import load_model

    xml = str(tmp_path_factory.mktemp("robot") / "robot.xml")
    write_model(xml, "ico", preset="robot")
    data = collect(xml, CollectConfig(episodes=2, steps=400, seed=5, push_every=50))
    path = str(GROUND)
    return xml, data, load_model(path)


def test_contact_rods_reported_apart_and_explained_partial(robot):
    """Ground contact's law leaves tens of percent of the contact wrench on the rods it acts on and
    nothing elsewhere: diagnose says so (effect_rows) and calls the residual partly explained."""
    import torch

    from identified.effects import read_contact_geometry
    from identified.rotation import quat_to_matrix

    xml, data, model = robot
    r = diagnose(model, data, horizon_s=0.2, mjcf=xml)
    json.dumps(r, allow_nan=False)
    rows = r["one_step"]["effect_rows"]
    assert [e["effect"] for e in rows] == ["ground_contact"]
    e = rows[0]
    assert e["inside"]["force"] > 0.05 and e["inside"]["torque"] > 0.05
    assert e["outside"]["force"] < 1e-6 and e["outside"]["torque"] < 1e-6  # the free rods are exact
    assert r["explained"] == "partial" and "improved" in r["explained_by"]
    assert {p["effect"] for p in r["partial_by"]} == {"ground_contact"}
    # the near-ground rods: an end sphere of the capsule within 1 cm of the plane, by hand
    geo = read_contact_geometry(xml, model.topology.rod_names)
    rot = quat_to_matrix(torch.as_tensor(data.quat[:, :-1])).numpy()  # the analysed instants (forward)
    ends = data.pos[:, :-1, :, None] + np.einsum("etrij,rkj->etrki", rot, np.asarray(geo["segment"]))
    depth = geo["ground_height"] + np.asarray(geo["radius"])[:, None] - ends @ np.asarray(geo["normal"])
    near = (depth > -0.01).any(-1)
    assert r["regions"]["near_ground"]["fraction"] == pytest.approx(near.mean(), abs=1e-12)
    assert e["fraction"] == pytest.approx(near.mean(), abs=1e-12)
    # the residual relative to the recorded force (torque) on those rods, by hand
    from identified.evaluate import recorded_samples, residual_wrench
    from identified.twin import engine_from_model

    ch, _, point = recorded_samples(data, "forward")
    rw = residual_wrench(engine_from_model(model), ch, point)
    m = torch.as_tensor(near.reshape(-1, near.shape[-1]))
    for part, res, ref in (("force", rw.force, rw.inertial_force), ("torque", rw.torque_body, rw.inertial_torque_body)):
        want = (res[m].square().mean().sqrt() / ref[m].square().mean().sqrt()).item()
        assert e["inside"][part] == pytest.approx(want, rel=1e-9), part
    # the torque about the contact point (the centre of the end sphere in contact), by hand: the
    # residual torque less the residual force's moment about it
    from identified.rotation import matrix_apply

    geo_pts = np.einsum("etrij,rkj->etrki", rot, np.asarray(geo["segment"]))  # COM -> end centres
    inside = (depth > 0).reshape(-1, near.shape[-1], 2)
    lever = torch.as_tensor((geo_pts.reshape(inside.shape + (3,)) * inside[..., None]).sum(-2)
                            / np.maximum(inside.sum(-1), 1)[..., None])
    tq = matrix_apply(torch.as_tensor(rot.reshape(-1, near.shape[-1], 3, 3)), rw.torque_body)
    about = tq - torch.linalg.cross(lever, rw.force)
    want = (about[m].square().mean().sqrt() / rw.inertial_torque_body[m].square().mean().sqrt()).item()
    assert e["inside"]["torque_about_contact_point"] == pytest.approx(want, rel=1e-9)
    assert want < 0.5 * e["inside"]["torque"]  # most of the torque residual is a missed force's moment


def test_whiteness_corrects_for_the_number_of_series():
    """36 white series (6 rods x 6 dofs): the smallest p-value of this draw is 0.0073, below 1 % but
    above 1 % / 36, so the Bonferroni-corrected test calls the residual white; an AR(1) series among
    them makes it not white."""
    from scipy.stats import chi2

    res = np.random.default_rng(0).standard_normal((2, 400, 6, 6))
    rods = tuple(f"rod{i}" for i in range(6))
    w = whiteness(res, rods)
    assert ALPHA / 36 < w["min_p"] < ALPHA and w["white"] is True
    assert w["fraction_rejected"] == pytest.approx(1 / 36)
    cell = w["per_rod"][2]["series"][4]
    q, dof = ljung_box(res[:, :, 2, 4], w["lags"])
    assert (cell["Q"], cell["df"]) == (pytest.approx(q, rel=1e-12), dof) and cell["p"] == pytest.approx(chi2.sf(q, dof))
    for t in range(1, 400):
        res[:, t, 3, 0] = 0.5 * res[:, t - 1, 3, 0] + res[:, t, 3, 0]
    assert whiteness(res, rods)["white"] is False


def test_the_rules_behind_the_verdict():
    assert at_rounding_level({"force": 9.9e-7, "torque": 1e-12})
    assert not at_rounding_level({"force": 1e-12, "torque": 1e-6})  # both must be
    assert not at_rounding_level({"force": 1e-12, "torque": None})
    assert improved(["linear_drag"], 1.0, 0.2) and not improved(["linear_drag"], 1.0, 0.21)  # 5x
    assert not improved([], 1.0, 0.0)  # nothing added: nothing improved
    assert improved(["ground_contact"], None, 3.0) and not improved(["ground_contact"], 1.0, None)
    assert not improved(["linear_drag"], 0.0, 0.0)


def test_one_step_summary_by_hand(viscous_result, plants):
    """The one-step RMS per axis, per rod and relative to the recorded wrench, from the residual
    wrench recomputed here; the fast region is the top 10 % of rod speeds."""
    import torch

    from identified.evaluate import recorded_samples, residual_wrench
    from identified.twin import engine_from_model

    _, data, _, model = plants["viscous"]
    ch, _, point = recorded_samples(data, "forward")
    rw = residual_wrench(engine_from_model(model), ch, point)
    f, t = rw.force.numpy(), rw.torque_body.numpy()  # (N, R, 3)
    rf, rt = rw.inertial_force.numpy(), rw.inertial_torque_body.numpy()
    os_ = viscous_result["one_step"]
    assert os_["force_rms"] == pytest.approx(np.sqrt((f ** 2).mean((0, 1))), rel=1e-9)
    assert os_["torque_rms"] == pytest.approx(np.sqrt((t ** 2).mean((0, 1))), rel=1e-9)
    assert os_["relative"]["force"] == pytest.approx(np.sqrt((f ** 2).mean() / (rf ** 2).mean()), rel=1e-9)
    assert os_["relative"]["torque"] == pytest.approx(np.sqrt((t ** 2).mean() / (rt ** 2).mean()), rel=1e-9)
    per = os_["per_rod"][3]
    assert per["force_rms"] == pytest.approx(np.sqrt((f[:, 3] ** 2).mean(0)), rel=1e-9)
    speed = torch.as_tensor(data.vel[:, :-1]).norm(dim=-1).numpy()
    fast = speed >= np.quantile(speed, 0.9)
    fn = np.linalg.norm(f, axis=-1).reshape(fast.shape)
    reg = viscous_result["regions"]["fast"]
    assert reg["fraction"] == pytest.approx(fast.mean(), abs=1e-12)
    assert reg["force_rms_in"] == pytest.approx(np.sqrt((fn[fast] ** 2).mean()), rel=1e-9)
    assert reg["force_rms_out"] == pytest.approx(np.sqrt((fn[~fast] ** 2).mean()), rel=1e-9)


def test_candidate_scores_hold_the_total_mass():
    """The parameter changes a candidate's score may use keep the total mass (else the model's own
    parameters, scaled, would explain any residual): every direction adds nothing to the sum of
    the masses, the rest move freely, and only the scale direction is lost (rank n - 1)."""
    from identified.diagnose.residual import _mass_total_held

    m_idx = np.array([2, 4, 5])
    Z = _mass_total_held(7, m_idx)
    assert Z.shape == (7, 6) and np.linalg.matrix_rank(Z) == 6
    np.testing.assert_array_equal(Z[m_idx].sum(axis=0), np.zeros(6))
    np.testing.assert_array_equal(Z[[0, 1, 3, 6]], np.eye(6)[[0, 1, 3, 5]])
    np.testing.assert_array_equal(Z[:, 2], [0, 0, 1, 0, 0, -1, 0])



def test_the_command_names_no_next_step_where_nothing_is_missing(plants, tmp_path, capsys):
    """``tensegrity diagnose`` on the clean plant: explained, no refit proposed (the viscous case,
    where it names ``--effects ground_contact,linear_drag``, is tests/test_diagnose_recording.py's)."""
    from identified.dataset import save_dataset
    from identified.model import save_model
    from tensegrity_gym.cli import main

    xml, data, _, model = plants["clean"]
    d, f = str(tmp_path / "D.npz"), str(tmp_path / "F.json")
    save_dataset(d, data)
    save_model(f, model)
    assert main(["diagnose", d, "--identified", f, "--model", xml, "--horizon", str(HORIZON)]) == 0
    out = capsys.readouterr().out
    assert "residual explained: True (the one-step residual is at rounding level" in out and "next:" not in out
