"""Bad inputs for the fuzz tests and for ``benchmarks/fuzz_bad_input.py``: corruptions of a valid
dataset and of a valid identified model, bad command-line flags, and the checks every outcome must
pass (exit 2 and one line, or success with finite output; no traceback; no input changed).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from tensegrity_gym.cli import main

# ---------------------------------------------------------------------- values
BAD_FLOATS = [float("nan"), float("inf"), -float("inf"), 1e300, -1e300, -1.0, 0.0, 1e-300, -1e-12]
DATASET_KEYS = ["dt", "gravity", "pos", "quat", "vel", "angvel", "command", "rest_length", "push_force",
                "push_point", "noise", "rod_names", "tendon_names", "actuated_names", "format", "seed"]
DATASET_KINDS = ["value", "drop", "empty", "shape", "text", "episodes0"]
MODEL_FIELDS = ["dt", "gravity", "mass", "inertia", "inertia_axial", "stiffness", "damping", "rest_length",
                "control_scale", "effects", "integrator", "topology", "format", "springs", "rods"]
MODEL_KINDS = ["value", "drop", "null", "text", "list"]
FILE_KINDS = ["truncate", "garbage", "empty", "text", "json_nan"]


# ---------------------------------------------------------------------- running the command
def run_cli(argv: list[str]) -> tuple[int, str, str]:
    """``tensegrity argv`` in-process: (status, stdout, stderr). An exception escaping is a traceback."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(argv)
    return rc, out.getvalue(), err.getvalue()


def digest(folder: Path) -> dict[str, str]:
    """Name -> sha256 of every file in ``folder`` (to prove nothing that existed was changed)."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.is_file()}


def check_outcome(rc: int, out: str, err: str, before: dict[str, str], folder: Path) -> list[str]:
    """Every way an outcome breaks the contract (empty: it holds)."""
    problems = []
    after = digest(folder)
    changed = [n for n, h in before.items() if after.get(n) != h]
    if changed:
        problems.append(f"damaged files: {changed}")
    if any(n.startswith(".tmp-") for n in after):
        problems.append("a temporary file was left behind")
    if "Traceback" in out + err:
        problems.append("traceback")
    if rc == 2:
        lines = [ln for ln in err.strip().splitlines() if ln.strip()]
        errors = [ln for ln in lines if ln.startswith("tensegrity: error: ")]
        if len(errors) != 1:
            problems.append(f"expected one error line, got {err!r}")
    elif rc == 0:
        if "nan" in out.lower().split() or "NaN" in out:
            problems.append(f"silent NaN in the output: {out[:200]!r}")
    else:
        problems.append(f"exit status {rc}")
    return problems


# ---------------------------------------------------------------------- datasets
def corrupt_dataset(src: Path, dst: Path, key: str, kind: str, value: float, index: int) -> None:
    """Write ``src`` with one key corrupted: a bad ``value`` at position ``index``, dropped, emptied,
    reshaped, replaced by text, or 0 episodes."""
    with np.load(src) as z:
        arrays = {k: z[k] for k in z.files}
    a = arrays.get(key)
    if kind == "drop":
        arrays.pop(key, None)
    elif kind == "empty":
        arrays[key] = np.zeros((0,))
    elif kind == "text":
        arrays[key] = np.array("bad")
    elif kind == "episodes0":
        for k in ("pos", "quat", "vel", "angvel", "command", "rest_length", "push_force", "push_point"):
            arrays[k] = arrays[k][:0]
    elif a is not None and a.dtype.kind in "fiu":
        if kind == "shape":
            arrays[key] = a.reshape(-1)[: max(a.size - 1, 0)]
        else:
            b = a.astype(float).copy().reshape(-1)
            if b.size:
                b[index % b.size] = value
            arrays[key] = b.reshape(a.shape)
    elif a is not None:
        arrays[key] = np.array(["x"] * max(a.size, 1)) if kind != "shape" else np.array([], dtype=str)
    with open(dst, "wb") as fh:
        np.savez(fh, **arrays)


def corrupt_file(src: Path, dst: Path, kind: str, index: int) -> None:
    """A file that is not what it claims to be: truncated, garbage, empty, text, JSON with NaN."""
    raw = src.read_bytes()
    if kind == "truncate":
        dst.write_bytes(raw[: (index % max(len(raw) - 1, 1)) + 1])
    elif kind == "garbage":
        rng = np.random.default_rng(index)
        dst.write_bytes(rng.integers(0, 256, 200 + index % 500, dtype=np.uint8).tobytes())
    elif kind == "empty":
        dst.write_bytes(b"")
    elif kind == "text":
        dst.write_text("hello, this is not a dataset\n")
    else:
        dst.write_text('{"format": NaN, "dt": Infinity}')


# ---------------------------------------------------------------------- identified models
def corrupt_model(src: Path, dst: Path, field: str, kind: str, value: float, index: int) -> None:
    """Write the model JSON ``src`` with one field corrupted (``json`` writes NaN/Infinity as is)."""
    obj: dict[str, Any] = json.loads(src.read_text())
    rods, springs = obj["rods"], obj["springs"]

    def bad(v: Any) -> Any:
        return {"value": value, "null": None, "text": "abc", "list": [value, value]}.get(kind, v)

    if field in ("mass", "inertia", "inertia_axial"):
        r = rods[index % len(rods)]
        if kind == "drop":
            r.pop("inertia" if field.startswith("inertia") else "mass")
        elif field == "mass":
            r["mass"] = bad(r["mass"])
        else:
            r["inertia"][2 if field == "inertia_axial" else index % 2] = bad(0)
    elif field in ("stiffness", "damping", "rest_length"):
        s = springs[index % len(springs)]
        if kind == "drop":
            s.pop(field)
        else:
            s[field] = bad(s[field])
    elif field == "gravity":
        if kind == "drop":
            obj.pop("gravity")
        else:
            obj["gravity"][index % 3] = bad(0)
    elif field == "control_scale":
        if kind == "drop":
            obj.pop("control_scale")
        else:
            obj["control_scale"]["value"] = bad(1.0)
    elif field == "effects":
        obj["effects"] = ({"value": [{"name": "ground"}], "null": None, "text": "ground_contact",
                           "list": [{"name": "ground_contact", "parameters": {}}, 3], "drop": [{}]}[kind])
    elif kind == "drop":
        obj.pop(field, None)
    else:
        obj[field] = bad(obj.get(field))
    dst.write_text(json.dumps(obj))


# ---------------------------------------------------------------------- flags
#: (command, option, bad value): every one must be refused with the option's name
BAD_FLAGS = [
    *[("collect", opt, v) for opt in ("--episodes", "--steps", "--push-every", "--push-duration")
      for v in ("0", "-3", "1.5", "abc", "nan")],
    *[("collect", "--seed", v) for v in ("-1", "abc", "1e3", str(2**64))],
    *[("collect", opt, v) for opt in ("--noise-pos", "--noise-vel", "--noise-quat", "--noise-angvel")
      for v in ("-0.1", "nan", "inf", "1e300", "abc")],
    *[("collect", "--push-magnitude", v) for v in ("nan", "inf", "-5", "0", "1e300", "x")],
    *[("fit", "--total-mass", v) for v in ("nan", "inf", "-1", "0", "1e300", "x")],
    *[("fit", "--weak-window", v) for v in ("-5", "-1", "x", "2.5")],
    *[("fit", "--jobs", v) for v in ("0", "-2", "x", "1.5", "")],
    *[("fit", "--mass", v) for v in ("rod0=nan", "rod0=inf", "rod0=-1", "rod0=0", "rod0", "rod0=x",
                                     "rod99=3")],
    *[("fit", opt, v) for opt in ("--regressors", "--solver", "--integrator", "--scheme", "--effects")
      for v in ("bogus",)],
    *[("record", opt, v) for opt in ("--rate", "--encoder-rate") for v in ("0", "-1", "nan", "inf", "x", "5000")],
    *[("record", "--dropout", v) for v in ("-0.1", "1", "nan", "x")],
    *[("record", "--ghosts", v) for v in ("-1", "1.5", "x")],
    *[("record", "--lengths", v) for v in ("", ",", "cable0,,cable1", "rope9", "cable0,cable0")],
    *[("record", "--noise-length", v) for v in ("-0.1", "nan", "inf", "1e300", "x")],
    *[("predict", "--horizon", v) for v in ("0", "-1", "x")],
    *[("model", "--seed", v) for v in ("-1", "x")],
]


def flag_argv(cmd: str, opt: str, value: str, files: dict[str, str]) -> list[str]:
    """A command line that is valid except for ``opt value``."""
    base = {
        "collect": ["collect", "--model", files["ico"], "--episodes", "1", "--steps", "5", "--out", "new.npz",
                    "--quiet"],
        "record": ["collect", "--model", files["ico"], "--episodes", "1", "--steps", "5", "--record", "markers",
                   "--out", "new.csv", "--quiet"],
        "fit": ["fit", files["data"], "--model", files["ico"], "--out", "new.json", "--quiet"],
        "predict": ["predict", files["data"], "--identified", files["fit"]],
        "model": ["model", "ico", "--preset", "paper-nonuniform", "--out", "new.xml"],
    }[cmd]
    return base + [opt, value]


def finite_json(text: str) -> bool:
    """Whether ``text`` parses as strict JSON (no NaN or Infinity)."""
    def refuse(c: str) -> float:
        raise ValueError(c)

    try:
        json.loads(text, parse_constant=refuse)
        return True
    except ValueError:
        return False


def finite(x: Any) -> bool:
    return all(math.isfinite(v) for v in np.asarray(x, dtype=float).reshape(-1))


__all__ = [n for n in dir() if not n.startswith("_") and n not in ("annotations", "os")]
