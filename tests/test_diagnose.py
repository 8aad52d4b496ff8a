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
from identified.diagnose import diagnose, ljung_box, write_report
from identified.effects import EFFECTS, make_effect
from identified.fit.identify import identify
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import write_model

HORIZON = 0.25  # s; the episodes hold 0.3 s
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
    assert names == set(EFFECTS) - {"ground_contact"}
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
    assert -1.0 <= ic["push_force"]["corr"] <= 1.0
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
