"""The diagnosis on a recording: the candidates scored as the fit reads markers (the weak form,
contact rows left out) and on data they were not fitted on; an undeclared drag found from 100 Hz
markers, nothing found on the same robot without it.

Cheap parts first (the held-out algebra, the dataset's spans, the weak form on exact equations),
then one recording of the robot with and without a hidden viscosity, diagnosed against the robot's
ground-contact fit (tests/data/robot_ground_contact.json: K, c, M the robot's, no drag).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from identified import Topology
from identified.diagnose import SUPPORTED_GAIN, diagnose, held_out_share, missing_effects, supported
from identified.diagnose.residual import held_out_score
from identified.diagnose.stats import explained_sum_of_squares, least_squares
from identified.fit.identify import identify
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model
from tests._data import GROUND
from tests._recordings import drag_recordings


# ---------------------------------------------------------------------- the algebra
def test_held_out_score_by_brute_force():
    """``held_out_score`` from normal equations equals, with numpy's least squares on the rows: the
    model's columns ``B`` regressed out of ``X`` and ``y`` over all rows, the candidate's
    coefficients fitted on one set of rows, the share of the other rows' sum of squares they
    remove; columns unrelated to ``y`` remove about nothing."""
    rng = np.random.default_rng(0)
    n = 400
    B = rng.normal(size=(n, 3)) * [1.0, 50.0, 0.02]
    X = 0.5 * B[:, :1] + rng.normal(size=(n, 2)) * [1.0, 1e3]  # a candidate column partly along B
    y = B @ [0.3, -0.01, 4.0] + X @ [1.0, -2e-3] + rng.normal(size=n)
    a, b = np.arange(0, n, 2), np.arange(1, n, 2)

    def sums(rows, y):
        Br, Xr, yr = B[rows], X[rows], y[rows]
        return (Br.T @ Br, Br.T @ yr, Br.T @ Xr, Xr.T @ Xr, Xr.T @ yr, float(yr @ yr))

    def brute(y):
        lst = lambda A, z: np.linalg.lstsq(A, z, rcond=None)[0]
        Xt, yt = X - B @ lst(B, X), y - B @ lst(B, y)
        theta = lst(Xt[a], yt[a])
        return 1.0 - float(np.sum((yt[b] - Xt[b] @ theta) ** 2)) / float(yt[b] @ yt[b])

    whole = lambda y: (B.T @ B, B.T @ y, B.T @ X)
    want = brute(y)
    assert held_out_score(sums(a, y), sums(b, y), whole(y)) == pytest.approx(want, rel=1e-9)
    assert 0.5 < want < 1.0
    noise = B @ [1.0, 0.1, -3.0] + rng.normal(size=n)  # B explains it, X's columns do not
    got = held_out_score(sums(a, noise), sums(b, noise), whole(noise))
    assert got == pytest.approx(brute(noise), rel=1e-9) and abs(got) < 0.05
    np.testing.assert_allclose(least_squares(X.T @ X, X.T @ y), np.linalg.lstsq(X, y, rcond=None)[0], rtol=1e-8)
    np.testing.assert_allclose(least_squares(B.T @ B, B.T @ X), np.linalg.lstsq(B, X, rcond=None)[0], rtol=1e-8)
    assert explained_sum_of_squares(X.T @ X, X.T @ y) == pytest.approx(
        float(y @ y - np.sum((y - X @ np.linalg.lstsq(X, y, rcond=None)[0]) ** 2)), rel=1e-9)


def test_a_column_that_is_all_zero_gets_no_coefficient():
    rng = np.random.default_rng(1)
    X = np.column_stack([rng.normal(size=50), np.zeros(50), rng.normal(size=50)])
    y = X @ [2.0, 0.0, -1.0]
    np.testing.assert_allclose(least_squares(X.T @ X, X.T @ y), [2.0, 0.0, -1.0], atol=1e-12)


def test_the_share_beyond_the_null():
    """With a null, a candidate is supported by its held-out share beyond the null's (a negative
    null counts as 0); without one, by its held-out share itself."""
    assert held_out_share({"score_held_out": 0.5}) == 0.5
    assert held_out_share({"score_held_out": 0.9, "score_held_out_null": 0.8}) == pytest.approx(0.1)
    assert held_out_share({"score_held_out": 0.3, "score_held_out_null": -1.2}) == 0.3
    assert held_out_share({"score_held_out": 0.3, "score_held_out_null": None}) is None
    assert held_out_share({"score_held_out": None, "score_held_out_null": 0.1}) is None
    cands = [{"name": "constant_force", "score_held_out": 0.95, "score_held_out_null": 0.85},
             {"name": "linear_drag", "score_held_out": 0.31, "score_held_out_null": -1.2}]
    assert supported(cands) == [{"name": "linear_drag", "score_held_out": 0.31, "score_held_out_null": -1.2}]


def test_a_residual_at_rounding_level_leaves_nothing_missing():
    """Held-out shares of rounding noise mean nothing: at rounding level no candidate is missing."""
    cands = [{"name": "cable_friction", "score_held_out": 0.9}]
    assert missing_effects(cands, rounding=True) == []
    assert missing_effects(cands, rounding=False) == [{"name": "cable_friction", "score_held_out": 0.9}]


def test_supported_at_its_threshold():
    cands = [{"name": "a", "score_held_out": SUPPORTED_GAIN}, {"name": "b", "score_held_out": SUPPORTED_GAIN - 1e-4},
             {"name": "c", "score_held_out": None}, {"name": "d", "score_held_out": 0.5}]
    assert supported(cands) == [{"name": "d", "score_held_out": 0.5}, {"name": "a", "score_held_out": SUPPORTED_GAIN}]
    assert supported([]) == []


# ---------------------------------------------------------------------- spans and windows
def _with_weights(data, seed: int = 0):
    rng = np.random.default_rng(seed)
    E, T, R = data.n_episodes, data.n_steps, data.n_rods
    return replace(data, weight=rng.uniform(0.0, 1.0, size=(E, T, R)))


@pytest.fixture(scope="module")
def viscous(tmp_path_factory):
    """A paper preset with a viscosity nobody declares (Euler plant: its equations are exact), its
    fit without effects."""
    folder = tmp_path_factory.mktemp("diagrec")
    xml = str(folder / "viscous.xml")
    text = write_model(xml, "ico", preset="paper-nonuniform", seed=3)
    with open(xml, "w", encoding="utf-8") as fh:
        fh.write(text.replace("<option ", '<option viscosity="2" '))
    data = collect(xml, CollectConfig(episodes=4, steps=400, seed=1, push_every=100))
    return xml, data, identify(data, Topology.from_mjcf(xml))


def test_span_cuts_every_per_step_array(viscous):
    _, data, _ = viscous
    d = _with_weights(data)
    d = replace(d, replicas=(d,))
    s = d.span([1, 3], 50, 120)
    assert s.n_episodes == 2 and s.n_steps == 70
    np.testing.assert_array_equal(s.pos, d.pos[[1, 3], 50:121])
    np.testing.assert_array_equal(s.angvel, d.angvel[[1, 3], 50:121])
    np.testing.assert_array_equal(s.rest_length, d.rest_length[[1, 3], 50:120])
    np.testing.assert_array_equal(s.push_point, d.push_point[[1, 3], 50:120])
    np.testing.assert_array_equal(s.weight, d.weight[[1, 3], 50:120])
    np.testing.assert_array_equal(s.replicas[0].weight, d.weight[[1, 3], 50:120])
    np.testing.assert_array_equal(d.select(slice(0, 2), 30).weight, d.weight[:2, :30])
    with pytest.raises(ValueError, match="span"):
        d.span([0], 100, 100)


def test_scores_do_not_depend_on_how_the_data_are_cut(viscous):
    """The one-step pass cuts long episodes into windows; each window's rows keep their own
    weights (a dataset reconstructed from markers weighs out steps): the candidates' scores are
    the same whatever the cut."""
    _, data, model = viscous
    d = _with_weights(data)
    whole = diagnose(model, d, horizon_s=0.1, chunk_steps=10**6)
    cut = diagnose(model, d, horizon_s=0.1, chunk_steps=150)
    for a, b in zip(whole["candidates"], cut["candidates"]):
        assert a["name"] == b["name"]
        assert a["score"] == pytest.approx(b["score"], rel=1e-9, abs=1e-12)
        assert a["score_held_out"] == pytest.approx(b["score_held_out"], rel=1e-9, abs=1e-12)


def test_the_weak_form_keeps_exact_equations_exact(viscous):
    """On an Euler plant's exact states the equations summed over windows are still exact: the
    hidden drag explains the whole residual, also on the halves it was not fitted on."""
    _, data, model = viscous
    r = diagnose(model, data, horizon_s=0.1, weak_window=31)
    top = r["candidates"][0]
    assert top["name"] == "linear_drag"
    assert top["score"] > 1 - 1e-9 and top["score_held_out"] > 1 - 1e-9
    assert r["explained"] is False and r["unexplained_by"][0]["name"] == "linear_drag"
    assert "summed over 0.031 s windows" in r["score_rule"]
    with pytest.raises(ValueError, match="shorter than one 0.5 s window of the weak form"):
        diagnose(model, data, horizon_s=0.1, weak_window=500)  # the episodes hold 0.4 s
    # a window of one step is the rows as they are
    one = diagnose(model, data, horizon_s=0.1, weak_window=1)
    plain = diagnose(model, data, horizon_s=0.1)
    for a, b in zip(one["candidates"], plain["candidates"]):
        assert a["score"] == pytest.approx(b["score"], rel=1e-12, abs=1e-15)


# ---------------------------------------------------------------------- a recording
@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """tests/_recordings.py: the robot in still and viscous air, 6 takes of 2 s at 100 Hz, 1 mm."""
    return drag_recordings(tmp_path_factory.mktemp("drag"))


def _diagnose_recording(rec, xml: str) -> dict:
    from identified.fit.markers import diagnosis_options, recording_dataset
    from identified.model import load_model

    model = load_model(str(GROUND))
    data = recording_dataset(rec, model)
    return diagnose(model, data, horizon_s=1.0, mjcf=xml, **diagnosis_options(rec, model.dt))


def test_an_undeclared_drag_is_found_from_markers(recordings):
    r = _diagnose_recording(recordings["viscous"], recordings["xml"])
    assert r["candidates"][0]["name"] == "linear_drag"
    assert r["explained"] is False and r["unexplained_by"][0]["name"] == "linear_drag"
    assert r["candidates"][0]["score_held_out"] > 3 * SUPPORTED_GAIN
    assert "left out" in r["score_rule"] and "0.301 s windows" in r["score_rule"]


def test_nothing_is_found_where_nothing_is_hidden(recordings):
    r = _diagnose_recording(recordings["still"], recordings["xml"])
    assert r["unexplained_by"] == []
    assert r["explained"] is not False
    assert max(c["score_held_out"] for c in r["candidates"] if c["score_held_out"] is not None) < SUPPORTED_GAIN


def test_the_command_scores_a_recording_as_the_fit_reads_it(recordings, tmp_path, capsys):
    """``tensegrity diagnose R.csv``: the drag named, with its held-out share (scored on one-step
    rows of every rod instead, the splines' second derivatives and the impacts put a constant force
    first and call the residual explained)."""
    from identified.recording import save_recording
    from tensegrity_gym.cli import main

    path = str(tmp_path / "viscous.csv")
    save_recording(path, recordings["viscous"])
    assert main(["diagnose", path, "--identified", str(GROUND), "--model", recordings["xml"]]) == 0
    out = capsys.readouterr().out
    assert "residual explained: False (linear_drag removes" in out
    assert f"next: refit with it, `tensegrity fit {path} --effects ground_contact,linear_drag ...`" in out
    assert out.index("candidate linear_drag") < out.index("candidate constant_force")
    assert "on the model's own motion recorded alike)" in out and "(null " in out


@pytest.mark.expensive  # 40-60 s; its cheap siblings: test_the_share_beyond_the_null, the command's test above
def test_the_null_takes_out_what_coarse_markers_make_up(tmp_path, capsys):
    """The robot in still air recorded at 30 Hz with 1 cm of noise: scored alone, a constant force
    per rod explains most of the residual on held-out halves (the reconstruction's own error); the
    model's own motion recorded alike explains as much, so nothing is called missing."""
    from identified.fit.markers import diagnosis_options, recording_dataset
    from identified.model import load_model
    from identified.recording import save_recording
    from tensegrity_gym.cli import main

    xml = str(tmp_path / "robot.xml")
    write_model(xml, "ico", preset="robot")
    data = collect(xml, CollectConfig(episodes=6, steps=3000, seed=31))
    rec = record_markers(data, xml, RecordConfig(rate=30, noise_pos=0.01, dropout=0.02), seed=31)
    model = load_model(str(GROUND))
    alone = diagnose(model, recording_dataset(rec, model), horizon_s=1.0, mjcf=xml, **diagnosis_options(rec, model.dt))
    assert alone["unexplained_by"][0]["name"] == "constant_force" and alone["explained"] is False
    path = str(tmp_path / "still.csv")
    save_recording(path, rec)
    assert main(["diagnose", path, "--identified", str(GROUND), "--model", xml, "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["unexplained_by"] == [] and r["explained"] is not False
    top = next(c for c in r["candidates"] if c["name"] == "constant_force")
    assert top["score_held_out"] > SUPPORTED_GAIN and top["score_held_out_null"] > top["score_held_out"] - SUPPORTED_GAIN
