"""The ``tensegrity`` command end to end: the happy path, ``--help``, and every bad input.

Commands run in-process through :func:`tensegrity_gym.cli.main` (stdout/stderr captured by
``capsys``); one test runs the real console script in a subprocess to prove that what the user
sees on a failure is one line and no traceback.  The contract (docs/ARCHITECTURE.md, "Contracts"): on bad
input exit status 2, exactly one line ``tensegrity: error: ...`` on stderr, no traceback, and no
output file (nor a temporary ``.tmp-*`` file) left behind.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from identified import Topology
from identified.dataset import save_dataset
from identified.fit.identify import identify
from identified.model import save_model
from tensegrity_gym.cli import main
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import preset_parameters, write_model

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SUBCOMMANDS = {
    "model": ["--preset", "--seed", "--integrator", "--out"],
    "collect": ["--model", "--episodes", "--steps", "--seed", "--push-every", "--push-magnitude",
                "--push-duration", "--noise-pos", "--noise-vel", "--noise-quat", "--noise-angvel", "--out",
                "--quiet"],
    "summary": ["--json"],
    "fit": ["--model", "--out", "--regressors", "--solver", "--mass", "--total-mass", "--pushes-unscaled",
            "--integrator", "--scheme", "--refine", "--effects", "--quiet"],
    "predict": ["--identified", "--horizon", "--plot", "--json"],
}


def mjcf_names(path: Path) -> tuple[list[str], list[str]]:
    """Rod bodies (bodies with a free joint) and spatial tendons, in file order."""
    root = ET.parse(path).getroot()
    rods = [b.get("name") for b in root.iter("body") if b.find("freejoint") is not None
            or any(j.get("type") == "free" for j in b.findall("joint"))]
    tendons = [s.get("name") for s in root.iter("spatial")]
    return rods, tendons


def rel(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, dtype=float) / np.asarray(b, dtype=float) - 1.0)))


# ---------------------------------------------------------------------- shared inputs
@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Valid inputs made once through the Python API: ico model + dataset + fit, simple model + dataset."""
    d = tmp_path_factory.mktemp("inputs")
    f = {
        "ico": d / "ico.xml", "data": d / "ico.npz", "fit": d / "ico.json",
        "simple": d / "simple.xml", "simple_data": d / "simple.npz",
    }
    write_model(f["ico"], "ico", preset="paper-nonuniform", seed=3)
    data = collect(f["ico"], CollectConfig(episodes=2, steps=60, seed=1, push_every=20))
    save_dataset(f["data"], data)
    save_model(f["fit"], identify(data, Topology.from_mjcf(f["ico"])))
    write_model(f["simple"], "simple", preset="paper")
    save_dataset(f["simple_data"], collect(f["simple"], CollectConfig(episodes=1, steps=40, seed=2)))
    return f


# ---------------------------------------------------------------------- happy path
def test_model_collect_summary_fit_predict(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["model", "ico", "--preset", "paper-nonuniform", "--seed", "3", "--out", "M.xml"]) == 0
    assert main(["collect", "--model", "M.xml", "--episodes", "2", "--steps", "200", "--seed", "1",
                 "--push-every", "50", "--out", "D.npz", "--quiet"]) == 0
    capsys.readouterr()

    assert main(["summary", "D.npz", "--json"]) == 0
    out = capsys.readouterr()
    info = json.loads(out.out)
    rods, tendons = mjcf_names(tmp_path / "M.xml")
    assert info["episodes"] == 2 and info["steps_per_episode"] == 200
    assert info["rods"] == rods and len(rods) == 6
    assert info["tendons"] == len(tendons) == 24
    assert info["dt"] == pytest.approx(1e-3)
    assert info["duration_s"] == pytest.approx(0.2)
    assert info["actuated"] == []
    assert info["gravity"] == pytest.approx([0.0, 0.0, -9.81])
    # pushes at steps 50, 100, 150, each held 10 steps on one rod, in each of the 2 episodes
    assert info["pushes"] == 2 * 3 * 10
    assert info["noise"] == [0.0, 0.0, 0.0, 0.0]
    assert out.err == ""

    assert main(["fit", "D.npz", "--model", "M.xml", "--out", "F.json", "--quiet"]) == 0
    capsys.readouterr()
    fit = json.loads((tmp_path / "F.json").read_text())
    for key in ("rods", "springs", "control_scale", "effects", "metrics"):
        assert key in fit, key
    assert [r["name"] for r in fit["rods"]] == rods
    assert [s["name"] for s in fit["springs"]] == tendons
    truth = preset_parameters("ico", "paper-nonuniform", 3)
    by_rod = {r["name"]: r for r in truth["rods"]}
    by_spring = {s["name"]: s for s in truth["springs"]}
    assert rel([s["stiffness"] for s in fit["springs"]], [by_spring[n]["stiffness"] for n in tendons]) < 1e-9
    assert rel([s["damping"] for s in fit["springs"]], [by_spring[n]["damping"] for n in tendons]) < 1e-9
    assert rel([r["mass"] for r in fit["rods"]], [by_rod[n]["mass"] for n in rods]) < 1e-9
    assert rel([r["inertia"] for r in fit["rods"]], [by_rod[n]["inertia"] for n in rods]) < 1e-6
    assert fit["control_scale"]["value"] == pytest.approx(1.0, abs=1e-9)
    assert fit["metrics"]["data"]["steps"] == 400
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".tmp-")]

    assert main(["predict", "D.npz", "--identified", "F.json", "--plot", "P.png", "--json"]) == 0
    pred = json.loads(capsys.readouterr().out)
    assert pred["horizon"] == 200 and pred["episodes"] == 2
    assert pred["pos_mean"] < 1e-9 and pred["quat_mean"] < 1e-9  # exact model of an Euler plant
    png = (tmp_path / "P.png").read_bytes()
    assert png.startswith(PNG_MAGIC) and len(png) > 1000
    assert sorted(os.listdir(tmp_path)) == ["D.npz", "F.json", "M.xml", "P.png"]


def test_fit_auto_integrator_on_an_implicitfast_plant(tmp_path, monkeypatch, capsys):
    """The fit recognises MuJoCo's implicitfast from the data; the twin model then steps like it
    and free-runs the held-out plant to rounding error."""
    monkeypatch.chdir(tmp_path)
    assert main(["model", "ico", "--preset", "paper-nonuniform", "--seed", "8", "--integrator", "implicitfast",
                 "--out", "M.xml"]) == 0
    for seed, out in ((1, "D.npz"), (2, "H.npz")):
        assert main(["collect", "--model", "M.xml", "--episodes", "2", "--steps", "300", "--seed", str(seed),
                     "--push-every", "50", "--out", out, "--quiet"]) == 0
    assert main(["fit", "D.npz", "--model", "M.xml", "--integrator", "auto", "--out", "F.json", "--quiet"]) == 0
    fit = json.loads((tmp_path / "F.json").read_text())
    assert fit["integrator"] == "implicit"
    scores = fit["metrics"]["integrator_selection"]
    assert scores["implicit"] < 1e-6 * min(scores["euler"], scores["rk4"])
    truth = preset_parameters("ico", "paper-nonuniform", 8)
    assert rel([s["damping"] for s in fit["springs"]], [s["damping"] for s in truth["springs"]]) < 1e-9
    capsys.readouterr()
    assert main(["predict", "H.npz", "--identified", "F.json", "--json"]) == 0
    pred = json.loads(capsys.readouterr().out)
    assert pred["pos_mean"] < 1e-9 and pred["quat_mean"] < 1e-9


def test_fit_refine_picks_the_plants_integrator(tmp_path, monkeypatch, capsys):
    """``fit --refine`` on an implicitfast plant, no --integrator given: refining Euler's model
    would keep its O(dt) bias (~5e-3); the refinement first picks the integrator from the data."""
    monkeypatch.chdir(tmp_path)
    assert main(["model", "ico", "--preset", "paper-nonuniform", "--seed", "9", "--integrator", "implicitfast",
                 "--out", "M.xml"]) == 0
    assert main(["collect", "--model", "M.xml", "--episodes", "2", "--steps", "200", "--seed", "4",
                 "--push-every", "50", "--out", "D.npz", "--quiet"]) == 0
    assert main(["fit", "D.npz", "--model", "M.xml", "--refine", "--out", "F.json", "--quiet"]) == 0
    assert "integrator implicit" in capsys.readouterr().out
    fit = json.loads((tmp_path / "F.json").read_text())
    assert fit["integrator"] == "implicit" and "refine" in fit["metrics"]
    truth = preset_parameters("ico", "paper-nonuniform", 9)
    for key in ("stiffness", "damping"):
        assert rel([s[key] for s in fit["springs"]], [s[key] for s in truth["springs"]]) < 1e-3, key
    assert rel([r["mass"] for r in fit["rods"]], [r["mass"] for r in truth["rods"]]) < 1e-3


def test_fit_effects_bad_names_are_refused_before_anything_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["model", "simple", "--out", "M.xml"]) == 0
    assert main(["collect", "--model", "M.xml", "--episodes", "2", "--steps", "50", "--out", "D.npz",
                 "--quiet"]) == 0
    capsys.readouterr()
    for bad, words in (("drag", "unknown effect 'drag'"), ("actuator_lag", "actuator_lag"),
                       ("linear_drag,linear_drag", "twice"), ("ground_contact", "ground plane"),
                       ("ground_contact,pyramid_contact", "ground_contact and pyramid_contact are two laws of one thing")):
        assert main(["fit", "D.npz", "--model", "M.xml", "--effects", bad, "--out", "F.json"]) == 2
        err = capsys.readouterr().err
        assert err.startswith("tensegrity: error: ") and words in err and err.count("\n") == 1, err
        assert not (tmp_path / "F.json").exists()


def test_fit_threads_runs_the_fit_on_that_many_and_gives_the_callers_back(files, tmp_path, monkeypatch, capsys):
    import torch

    from identified.fit import pipeline

    seen = []
    real = pipeline.fit_model

    def spy(*a, **k):
        seen.append(torch.get_num_threads())
        return real(*a, **k)

    monkeypatch.setattr(pipeline, "fit_model", spy)
    monkeypatch.chdir(tmp_path)
    before = torch.get_num_threads()
    want = 1 if before != 1 else 2
    assert main(["fit", str(files["data"]), "--model", str(files["ico"]), "--out", "F.json", "--quiet",
                 "--threads", str(want)]) == 0
    assert main(["fit", str(files["data"]), "--model", str(files["ico"]), "--out", "G.json", "--quiet"]) == 0
    assert seen == [want, before] and torch.get_num_threads() == before
    capsys.readouterr()
    assert main(["fit", str(files["data"]), "--model", str(files["ico"]), "--out", "H.json", "--threads", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tensegrity: error: ") and "--threads" in err and err.count("\n") == 1, err
    assert not (tmp_path / "H.json").exists()


# ---------------------------------------------------------------------- --help
@pytest.mark.parametrize("command", [None, *SUBCOMMANDS])
def test_help_exits_0_and_lists_options(command, capsys):
    argv = ["--help"] if command is None else [command, "--help"]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 0
    text = capsys.readouterr().out
    if command is None:
        for sub in SUBCOMMANDS:
            assert sub in text
    else:
        assert text.startswith(f"usage: tensegrity {command}")
        for opt in SUBCOMMANDS[command]:
            assert opt in text, f"{command} --help does not mention {opt}"


# ---------------------------------------------------------------------- bad input
def _broken_models(folder: Path, ico: Path) -> dict[str, Path]:
    text = ico.read_text()
    out = {}
    # a tendon that refers to a site nobody defines
    missing = text.replace('<site site="rod0_end0" />', '<site site="rod0_nowhere" />', 1)
    assert missing != text
    out["tendon_missing_site"] = folder / "missing_site.xml"
    out["tendon_missing_site"].write_text(missing)
    # a rod body without its end sites (the tendons that used them removed too, so the XML is consistent)
    root = ET.fromstring(text)
    body = next(b for b in root.iter("body") if b.get("name") == "rod5")
    for s in body.findall("site"):
        body.remove(s)
    tendon = root.find("tendon")
    for sp in list(tendon):
        if any(s.get("site", "").startswith("rod5_") for s in sp.findall("site")):
            tendon.remove(sp)
    out["body_without_sites"] = folder / "no_sites.xml"
    out["body_without_sites"].write_text(ET.tostring(root, encoding="unicode"))
    out["no_rods"] = folder / "no_rods.xml"
    out["no_rods"].write_text("<mujoco><worldbody/></mujoco>")
    out["not_xml"] = folder / "not_xml.xml"
    out["not_xml"].write_text("<mujoco><worldbody>")
    return out


def _bad_datasets(folder: Path, data: Path) -> dict[str, Path]:
    out = {}
    raw = data.read_bytes()
    out["truncated"] = folder / "truncated.npz"
    out["truncated"].write_bytes(raw[: len(raw) // 2])
    out["foreign"] = folder / "foreign.npz"
    np.savez(out["foreign"], weights=np.zeros((3, 3)))
    with np.load(data) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["vel"] = arrays["vel"].copy()
    arrays["vel"][1, 5, 2, 0] = np.nan
    out["nan"] = folder / "nan.npz"
    np.savez(out["nan"], **arrays)
    return out


def _bad_cases(tmp: Path, f: dict[str, Path]) -> dict[str, tuple[list[str], str | None]]:
    """name -> (argv, a fragment the one-line message must contain, or None)."""
    models = _broken_models(tmp, f["ico"])
    datas = _bad_datasets(tmp, f["data"])
    (tmp / "a_folder").mkdir()
    (tmp / "not_a_model.json").write_text(json.dumps({"weights": [1, 2, 3]}))
    (tmp / "a_list.json").write_text("[1, 2, 3]")
    ico, data, simple = str(f["ico"]), str(f["data"]), str(f["simple"])
    cases: dict[str, tuple[list[str], str | None]] = {
        "unknown system": (["model", "octahedron", "--out", "X.xml"], "octahedron"),
        "unknown preset": (["model", "ico", "--preset", "nope", "--out", "X.xml"], "nope"),
        "preset of the other system": (["model", "simple", "--preset", "robot", "--out", "X.xml"], "robot"),
        "output folder missing": (["model", "ico", "--out", "nowhere/X.xml"], "nowhere"),
        "output is a folder": (["model", "ico", "--out", "a_folder"], "a_folder"),
        "collect output folder missing": (["collect", "--model", ico, "--episodes", "1", "--steps", "5",
                                           "--out", "nowhere/D.npz"], "nowhere"),
        "collect model missing": (["collect", "--model", "nothing.xml", "--out", "D.npz"], "nothing.xml"),
        "collect episodes 0": (["collect", "--model", ico, "--episodes", "0", "--out", "D.npz"], "episodes"),
        "collect steps 0": (["collect", "--model", ico, "--steps", "0", "--out", "D.npz"], "steps"),
        "collect negative noise": (["collect", "--model", ico, "--episodes", "1", "--steps", "5",
                                    "--noise-pos", "-0.01", "--out", "D.npz"], "noise"),
        "collect nan noise": (["collect", "--model", ico, "--episodes", "1", "--steps", "5",
                               "--noise-vel", "nan", "--out", "D.npz"], "noise"),
        "collect push-every 0": (["collect", "--model", ico, "--push-every", "0", "--out", "D.npz"], "push"),
        "summary truncated": (["summary", str(datas["truncated"])], "truncated"),
        "summary foreign": (["summary", str(datas["foreign"])], "foreign.npz"),
        "summary missing": (["summary", "nothing.npz"], "nothing.npz"),
        "fit truncated": (["fit", str(datas["truncated"]), "--model", ico, "--out", "F.json"], "truncated"),
        "fit foreign": (["fit", str(datas["foreign"]), "--model", ico, "--out", "F.json"], "foreign.npz"),
        "fit nan": (["fit", str(datas["nan"]), "--model", ico, "--out", "F.json"], "'vel'"),
        "fit ico data on simple model": (["fit", data, "--model", simple, "--out", "F.json"], "rods"),
        "fit simple data on ico model": (["fit", str(f["simple_data"]), "--model", ico, "--out", "F.json"],
                                         "rods"),
        "fit mass of no rod": (["fit", data, "--model", ico, "--mass", "rod9=3", "--out", "F.json"], "rod9"),
        "fit mass not a number": (["fit", data, "--model", ico, "--mass", "rod0=abc", "--out", "F.json"],
                                  "abc"),
        "fit mass without kg": (["fit", data, "--model", ico, "--mass", "rod0", "--out", "F.json"], "NAME=KG"),
        "fit negative mass": (["fit", data, "--model", ico, "--mass", "rod0=-3", "--out", "F.json"], "positive"),
        "fit output folder missing": (["fit", data, "--model", ico, "--out", "nowhere/F.json"], "nowhere"),
        "fit output is a folder": (["fit", data, "--model", ico, "--out", "a_folder"], "a_folder"),
        "predict json not a model": (["predict", data, "--identified", "not_a_model.json"], "identified model"),
        "predict json list": (["predict", data, "--identified", "a_list.json"], "identified model"),
        "predict xml as model": (["predict", data, "--identified", ico], "JSON"),
        "predict model missing": (["predict", data, "--identified", "nothing.json"], "nothing.json"),
        "predict other system": (["predict", str(f["simple_data"]), "--identified", str(f["fit"])], None),
        "predict plot folder missing": (["predict", data, "--identified", str(f["fit"]), "--plot",
                                         "nowhere/P.png"], "nowhere"),
        "predict horizon 0": (["predict", data, "--identified", str(f["fit"]), "--horizon", "0"], "horizon"),
    }
    for name, path in models.items():
        cases[f"fit model {name}"] = (["fit", data, "--model", str(path), "--out", "F.json"], None)
        cases[f"collect model {name}"] = (["collect", "--model", str(path), "--episodes", "1", "--steps", "5",
                                           "--out", "D.npz"], None)
    return cases


BAD = [
    "unknown system", "unknown preset", "preset of the other system", "output folder missing",
    "output is a folder", "collect output folder missing", "collect model missing", "collect episodes 0",
    "collect steps 0", "collect negative noise", "collect nan noise", "collect push-every 0",
    "summary truncated", "summary foreign", "summary missing", "fit truncated", "fit foreign", "fit nan",
    "fit ico data on simple model", "fit simple data on ico model", "fit mass of no rod",
    "fit mass not a number", "fit mass without kg", "fit negative mass", "fit output folder missing",
    "fit output is a folder", "predict json not a model", "predict json list", "predict xml as model",
    "predict model missing", "predict other system", "predict plot folder missing", "predict horizon 0",
    *[f"{cmd} model {m}" for m in ("tendon_missing_site", "body_without_sites", "no_rods", "not_xml")
      for cmd in ("fit", "collect")],
]


@pytest.fixture(scope="module")
def bad_cases(files, tmp_path_factory) -> tuple[Path, dict[str, tuple[list[str], str | None]]]:
    tmp = tmp_path_factory.mktemp("bad")
    return tmp, _bad_cases(tmp, files)


@pytest.mark.parametrize("name", BAD)
def test_bad_input_one_line_exit_2_nothing_written(name, bad_cases, monkeypatch, capsys):
    monkeypatch.delenv("TENSEGRITY_DEBUG", raising=False)
    folder, cases = bad_cases
    argv, fragment = cases[name]
    monkeypatch.chdir(folder)
    before = sorted(os.listdir(folder))
    rc = main(argv)
    out = capsys.readouterr()
    lines = out.err.strip().splitlines()
    assert rc == 2, (name, out.err)
    assert len(lines) == 1, f"{name}: expected one line on stderr, got {out.err!r}"
    assert lines[0].startswith("tensegrity: error: "), lines[0]
    assert "Traceback" not in out.err and "Traceback" not in out.out
    if fragment is not None:
        assert fragment in lines[0], (fragment, lines[0])
    assert sorted(os.listdir(folder)) == before, "a failed command left a file behind"
    assert not (folder / "a_folder").exists() or not os.listdir(folder / "a_folder")


def test_fit_nan_names_key_and_index(files, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    nan = _bad_datasets(tmp_path, files["data"])["nan"]
    assert main(["fit", str(nan), "--model", str(files["ico"]), "--out", "F.json"]) == 2
    line = capsys.readouterr().err.strip()
    assert "'vel'" in line and "(1, 5, 2, 0)" in line, line


@pytest.mark.parametrize("extra", [["--mass", "rod9=3"], ["--mass", "rod0=abc"], ["--nan"], ["--simple"]])
def test_failed_fit_leaves_previous_output_intact(extra, files, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    previous = files["fit"].read_bytes()
    (tmp_path / "F.json").write_bytes(previous)
    data, model = str(files["data"]), str(files["ico"])
    if extra == ["--nan"]:
        data, extra = str(_bad_datasets(tmp_path, files["data"])["nan"]), []
    elif extra == ["--simple"]:
        model, extra = str(files["simple"]), []
    before = sorted(os.listdir(tmp_path))
    assert main(["fit", data, "--model", model, "--out", "F.json", "--quiet", *extra]) == 2
    assert capsys.readouterr().err.startswith("tensegrity: error: ")
    assert (tmp_path / "F.json").read_bytes() == previous
    assert sorted(os.listdir(tmp_path)) == before


@pytest.mark.parametrize("command", ["fit", "collect", "model"])
def test_interrupt_while_writing_keeps_old_file_and_no_temp(command, files, tmp_path, monkeypatch, capsys):
    """Ctrl-C at the last moment (the rename): the old output stays whole, no temporary file remains."""
    monkeypatch.chdir(tmp_path)
    out = {"fit": "F.json", "collect": "D.npz", "model": "M.xml"}[command]
    (tmp_path / out).write_bytes(b"previous contents")
    argv = {
        "fit": ["fit", str(files["data"]), "--model", str(files["ico"]), "--out", out, "--quiet"],
        "collect": ["collect", "--model", str(files["ico"]), "--episodes", "1", "--steps", "5", "--out", out,
                    "--quiet"],
        "model": ["model", "ico", "--preset", "paper-uniform", "--out", out],
    }[command]

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    monkeypatch.setattr(os, "rename", interrupted)
    rc = main(argv)
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert rc == 130 and "Traceback" not in err
    assert (tmp_path / out).read_bytes() == b"previous contents"
    assert sorted(os.listdir(tmp_path)) == [out]


def test_debug_env_shows_the_exception(files, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TENSEGRITY_DEBUG", "1")
    with pytest.raises(ValueError):
        main(["fit", str(files["data"]), "--model", str(files["ico"]), "--mass", "rod9=3", "--out", "F.json"])


def test_console_script_prints_one_line_and_no_traceback(files, tmp_path):
    script = Path(sys.executable).with_name("tensegrity")
    if not script.exists():
        pytest.skip("console script 'tensegrity' is not installed next to the interpreter")
    raw = files["data"].read_bytes()
    (tmp_path / "half.npz").write_bytes(raw[: len(raw) // 2])
    env = {k: v for k, v in os.environ.items() if k != "TENSEGRITY_DEBUG"}
    proc = subprocess.run(
        [str(script), "fit", "half.npz", "--model", str(files["ico"]), "--out", "F.json"],
        check=False, cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tensegrity: error: "), proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    assert sorted(os.listdir(tmp_path)) == ["half.npz"]


def test_every_bad_case_is_run(bad_cases):
    assert sorted(bad_cases[1]) == sorted(BAD)


@pytest.mark.parametrize("argv", [["collect", "--model", "M.xml", "--episodes", "abc", "--out", "D.npz"],
                                  ["model", "ico"], ["fit", "D.npz", "--model", "M.xml", "--out", "F.json",
                                                     "--solver", "sgd"], ["frobnicate"]])
def test_argument_errors_are_one_line_too(argv, tmp_path, monkeypatch, capsys):
    """argparse's own errors (bad int, missing option, bad choice, unknown command) follow the contract."""
    monkeypatch.chdir(tmp_path)
    try:
        rc = main(argv)
    except SystemExit as exc:
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("tensegrity: error: "), err


def test_outputs_get_the_usual_permissions(files, tmp_path, monkeypatch, capsys):
    """Atomic writes go through mkstemp (mode 0600): the result must still follow the umask."""
    monkeypatch.chdir(tmp_path)
    umask = os.umask(0o022)
    try:
        assert main(["model", "simple", "--out", "M.xml"]) == 0
        assert main(["collect", "--model", "M.xml", "--episodes", "1", "--steps", "20",
                     "--out", "D.npz", "--quiet"]) == 0
        assert main(["fit", "D.npz", "--model", "M.xml", "--out", "F.json", "--quiet"]) == 0
        assert main(["predict", "D.npz", "--identified", "F.json", "--plot", "P.png"]) == 0
    finally:
        os.umask(umask)
    for name in ("M.xml", "D.npz", "F.json", "P.png"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o644, name


def test_fit_refine_refuses_noise_on_some_channels_only(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["model", "simple", "--out", "M.xml"]) == 0
    assert main(["collect", "--model", "M.xml", "--episodes", "1", "--steps", "400", "--noise-pos", "0.001",
                 "--out", "D.npz", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["fit", "D.npz", "--model", "M.xml", "--refine", "--out", "F.json", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tensegrity: error: the dataset records noise") and err.count("\n") == 1
    assert not (tmp_path / "F.json").exists()
