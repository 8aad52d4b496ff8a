"""Bring your own robot: the three lab-style models of ``examples/`` through collect and fit, against
the truth the plant holds.

    python benchmarks/bench_byor.py [--episodes 10] [--steps 1000] [--effects auto] [--models prism3,...]

For each model (a 3-bar prism with motor actuators; a 6-bar of composite rods with an electronics
box 6 cm off the axis; a 6-bar of nested bodies with filtered general actuators): collect
``episodes x steps`` with pushes of 5 N every 50 steps, then fit with the total mass given
(``--total-mass``, the truth's) from a copy of the MJCF whose physical values (stiffness, damping,
rest lengths, masses, gains, biases, time constants) are all 30 % wrong: the fit reads only
structure and geometry. Printed against the plant's own values (read here from the compiled
MuJoCo model: the benchmark knows the truth, the fit never sees it), each the largest error over
the model's elements:

* ``K``, ``c``: stiffness and damping of every tendon, relative;
* ``l0``: rest length of every passive tendon (not driven by a rest-length motor), relative;
* ``M``: mass of every rod (all its bodies), relative;
* ``com mm``: distance of the fitted centre of mass from the true one, rod frame, mm (a fit with
  the diagonal model puts it at the rod frame's origin; composite rods get all ten inertial
  parameters);
* ``I_t``: the two transverse (largest) principal moments of inertia about the centre of mass,
  relative (the fitted principal moments, sorted, against the true ones);
* ``gain``, ``tau``: every MuJoCo actuator's force per unit activation and filter time constant,
  relative;
* ``effects``: what ``--effects`` found; ``residual``: the fit's own verdict, ``metrics.residual``
  (the one-step residual wrench relative to the recorded one; above 1 % the fit says it does not
  describe its data).

Figures, not assertions.
"""

from __future__ import annotations

import argparse
import os
import re
import tempfile
import time

import mujoco
import numpy as np

from identified.fit.identify import ScaleSpec
from identified.fit.pipeline import fit_model
from identified.topology import Topology
from tensegrity_gym.collect import CollectConfig, collect

EXAMPLES = os.path.join(os.path.dirname(os.path.abspath(__file__)), os.pardir, "examples")
MODELS = ("prism3", "six_bar_composite", "six_bar_nested")
#: attributes holding physical values, all scaled in the copy the fit is given
PHYSICAL = ("stiffness", "damping", "springlength", "mass", "gainprm", "biasprm", "dynprm", "gear")


def truth(path: str) -> dict[str, np.ndarray]:
    """The compiled model's values in topology order: K, c, rest length (tendon's upper dead-band
    bound), passive mask; per rod M, com (rod frame) and principal inertia about the com; per
    actuator gain (gainprm x gear) and time constant (NaN without a filter)."""
    m = mujoco.MjModel.from_xml_path(path)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    topo = Topology.from_mjcf(path)
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, n) for n in topo.spring_names]
    out = {"K": m.tendon_stiffness[tid].copy(), "c": m.tendon_damping[tid].copy(),
           "l0": m.tendon_lengthspring[tid, 1].copy(), "passive": ~np.array([s.actuated for s in topo.springs])}
    M, com, inert = [], [], []
    for r in topo.rods:
        b0 = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, r.name)
        R0, p0 = d.xmat[b0].reshape(3, 3), d.xpos[b0]
        bodies = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in (r.bodies or (r.name,))]
        mass = sum(m.body_mass[b] for b in bodies)
        c = sum(m.body_mass[b] * R0.T @ (d.xipos[b] - p0) for b in bodies) / mass
        J = np.zeros((3, 3))
        for b in bodies:  # each body's inertia about the rod's centre of mass, rod frame
            Rb = R0.T @ d.ximat[b].reshape(3, 3)
            r_b = R0.T @ (d.xipos[b] - p0) - c
            J += Rb @ np.diag(m.body_inertia[b]) @ Rb.T + m.body_mass[b] * (r_b @ r_b * np.eye(3) - np.outer(r_b, r_b))
        M.append(mass)
        com.append(c)
        inert.append(np.sort(np.linalg.eigvalsh(J)))
    out.update(M=np.array(M), com=np.array(com), I=np.array(inert))
    gains, taus = {}, {}
    for i in range(m.nu):
        n = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i)
        gains[n] = m.actuator_gainprm[i, 0] * m.actuator_gear[i, 0]
        filt = int(m.actuator_dyntype[i]) in (int(mujoco.mjtDyn.mjDYN_FILTER), int(mujoco.mjtDyn.mjDYN_FILTEREXACT))
        taus[n] = m.actuator_dynprm[i, 0] if filt else np.nan
    out.update(gain=gains, tau=taus)
    return out


def wrong_copy(path: str, factor: float = 1.3) -> str:
    """A copy of the MJCF (beside it, so includes resolve) with every physical value scaled."""
    with open(path, encoding="utf-8") as fh:
        text = fh.read()

    def scale(match: re.Match) -> str:
        nums = " ".join(f"{float(x) * factor:.6g}" for x in match.group(2).split())
        return f'{match.group(1)}="{nums}"'

    text = re.sub(rf'\b({"|".join(PHYSICAL)})="([^"]*)"', scale, text)
    fd, out = tempfile.mkstemp(suffix=".xml", prefix=".wrong_", dir=os.path.dirname(path))
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        fh.write(text)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--effects", default="auto")
    ap.add_argument("--models", default=",".join(MODELS), help="comma-separated subset of " + ", ".join(MODELS))
    args = ap.parse_args()
    cols = ("collect s", "fit s", "K", "c", "l0", "M", "com mm", "I_t", "gain", "tau", "residual")
    print(f"{'model':19s}" + "".join(f"{c:>10s}" for c in cols) + "  effects")
    for name in args.models.split(","):
        path = os.path.join(EXAMPLES, f"{name}.xml")
        t = truth(path)
        t0 = time.perf_counter()
        data = collect(path, CollectConfig(episodes=args.episodes, steps=args.steps, seed=1, push_every=50,
                                           push_magnitude=5.0))
        t1 = time.perf_counter()
        wrong = wrong_copy(path)
        try:
            model = fit_model(data, wrong, effects=args.effects, scale=ScaleSpec(total_mass=float(t["M"].sum())),
                              jobs=1)
        except ValueError as exc:
            print(f"{name:19s}{t1 - t0:10.1f}  fit refused: {exc}")
            continue
        finally:
            os.unlink(wrong)
        t2 = time.perf_counter()
        rel = lambda est, true: float(np.max(np.abs(np.asarray(est) - true) / np.abs(true))) if np.size(true) else np.nan
        com_fit = np.zeros_like(t["com"]) if model.com is None else model.com  # None: the frame's origin
        com_mm = 1e3 * float(np.max(np.linalg.norm(com_fit - t["com"], axis=1)))
        I_fit = np.sort(model.inertia, axis=1)[:, 1:]
        acts = {a["name"]: a for a in model.actuators}
        gains = [(acts[n]["gain"], g) for n, g in t["gain"].items() if n in acts]
        taus = [(acts[n]["time_constant"], x) for n, x in t["tau"].items() if n in acts and np.isfinite(x)]
        g_err = rel(*zip(*gains)) if gains else (np.nan if not t["gain"] else np.inf)
        tau_err = rel(*zip(*taus)) if taus else np.nan
        p = t["passive"]
        vals = (t1 - t0, t2 - t1, rel(model.stiffness, t["K"]), rel(model.damping, t["c"]),
                rel(model.rest_length[p], t["l0"][p]), rel(model.mass, t["M"]), com_mm,
                rel(I_fit, t["I"][:, 1:]), g_err, tau_err, model.metrics["residual"]["relative_one_step"])
        found = ",".join(e["name"] for e in model.effects) or "none"
        print(f"{name:19s}" + "".join(f"{v:10.3g}" for v in vals) + f"  {found}", flush=True)


if __name__ == "__main__":
    main()
