"""A small mutation test of the bad-input guards: plant one plausible bug at a time, run the tests
that should notice, count the mutants killed.

    .venv/bin/python scripts/mutation.py [--tests tests/test_bad_input.py] [--only N]

Each mutant is a one-line textual change; the file is restored after every run (also on Ctrl-C).
A mutant "survives" when the tests still pass with it: either the guard is untested or the
mutant is equivalent.  Prints one line per mutant and the kill rate.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: (file, original text, mutated text, what the bug would be)
MUTANTS = [
    ("identified/fit/checks.py", "    if dof <= 0 or (sol.cov is None", "    if dof < -1e9 or (sol.cov is None",
     "a fit without residual degrees of freedom is accepted"),
    ("identified/fit/checks.py", "dof < MIN_DOF_PER_PARAMETER * free:", "dof < 0:",
     "error bars of a nearly exact fit printed as if estimable"),
    ("identified/fit/checks.py", "np.full(np.shape(v), np.nan) for k, v", "v for k, v",
     "not-estimable error bars kept"),
    ("identified/fit/checks.py", "j not in fixed and not th[j] > 0:", "j not in fixed and th[j] < -1e300:",
     "non-positive inertias kept"),
    ("identified/fit/checks.py", "        if not mass[i] > 0:", "        if mass[i] < -1e300:",
     "negative masses not warned"),
    ("identified/fit/checks.py", "if I[a] - others > max(margin, 1e-6 * others):", "if False:",
     "triangle inequality not checked"),
    ("identified/fit/checks.py", "    return 1.0 + 2.0 * sum(", "    return 1.0 + 0.0 * sum(",
     "overlap of weak-form windows ignored"),
    ("identified/fit/checks.py", "worst > ADAM_TOLERANCE:", "worst > 1e9:",
     "unconverged Adam accepted silently"),
    ("identified/model.py", "np.isfinite(model.dt) and model.dt > 0)", "np.isfinite(model.dt) and model.dt > -1)",
     "negative dt loaded"),
    ("identified/model.py", "if not model.inertia[i, a] > 0:", "if not model.inertia[i, a] > -1:",
     "negative inertia loaded"),
    ("identified/model.py", "if name not in known_names():", "if name is None:", "unknown effect loaded"),
    ("tensegrity_gym/paths.py", "        return os.path.samefile(a, b)", "        return False",
     "hard link to an input overwritten"),
    ("tensegrity_gym/paths.py", "if ipath is not None and _same_file(path, ipath):", "if False:",
     "output equal to an input overwritten"),
    ("identified/dataset.py", "off = np.abs(norm - 1.0) > tol", "off = (norm - 1.0) > tol",
     "quaternion norm below 1 accepted"),
    ("identified/fit/uncertainty.py", "cov_z = (lin.residual / dof) * (", "cov_z = (1.0) * (",
     "few-episode error bars without the residual variance"),
    ("tensegrity_gym/envs/vector.py", "z_range = e.healthy_z_range if e.terminate_when_unhealthy else None",
     "z_range = e.healthy_z_range", "vector env ignores terminate_when_unhealthy=False"),
    ("tensegrity_gym/collect.py", "            if caught.messages:", "            if False:",
     "MuJoCo instability recorded silently"),
    ("tensegrity_gym/limits.py", "if nbytes > MEMORY_SHARE * avail:", "if nbytes > 1e30 * avail:",
     "collection too large for memory started"),
    ("tensegrity_gym/options.py", "        if v < minimum:", "        if v < minimum - 1:",
     "zero steps/durations accepted"),
    ("identified/jsonsafe.py", "isinstance(obj, float) and not math.isfinite(obj):",
     "isinstance(obj, float) and False:", "NaN written into JSON"),
    ("tensegrity_gym/envs/tensegrity_ico_v0.py", "            if not np.isfinite(w):", "            if False:",
     "NaN reward weight accepted"),
]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tests", nargs="*", default=["tests/test_bad_input.py"])
    ap.add_argument("--only", type=int, default=None, help="run mutant N only")
    args = ap.parse_args()
    killed = 0
    chosen = list(enumerate(MUTANTS)) if args.only is None else [(args.only, MUTANTS[args.only])]
    for k, (rel, old, new, what) in chosen:
        path = ROOT / rel
        text = path.read_text()
        if text.count(old) != 1:
            print(f"{k:2d} STALE  {rel}: the original text is not there exactly once ({what})")
            continue
        t0 = time.perf_counter()
        try:
            path.write_text(text.replace(old, new))
            r = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *args.tests],
                               cwd=ROOT, capture_output=True, text=True, check=False)
        finally:
            path.write_text(text)
        dead = r.returncode != 0
        killed += dead
        print(f"{k:2d} {'killed' if dead else 'SURVIVED'} ({time.perf_counter() - t0:.0f} s) {rel}: {what}",
              flush=True)
    print(f"kill rate: {killed} / {len(chosen)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
