"""Identification from recordings: the accuracy table.

For each dataset: the robot (the preset, or with its parameters drawn around the preset's), rolled
by the plant, recorded as a lab would (end-cap markers at ``--rate`` Hz, ``--noise`` m, ``--dropout``
missing in runs, the encoders' rest lengths), then fitted from the recording alone with the total
mass known, and -- for comparison -- from the plant's full rod states at every step (the same runs).
Prints per dataset the largest relative error of K, c and M, the z-scores of the estimates
against the truth (estimate - truth) / standard error, and the free-run error of both fits on one
more take of the same robot that neither fit sees (1 s runs from its state at every second); then the per-dataset table, and the RMS
and largest |z| over all datasets.

    python benchmarks/bench_recordings.py --datasets 10 --episodes 10 --seconds 10        # the full table
    python benchmarks/bench_recordings.py --datasets 2 --episodes 4 --seconds 5 --quick   # a look
    python benchmarks/bench_recordings.py --datasets 1 --episodes 4 --seconds 5 --quick --output-error
        # the regression, then the output-error refinement against the markers (both rows)
    python benchmarks/bench_recordings.py --datasets 3 --varied --marker-fit --rate 30 --noise 0.01 \
        --oe-frames 9 --oe-windows 32 --oe-iterations 6    # coarse markers: output error beside the bound
    python benchmarks/bench_recordings.py --datasets 3 --varied --bound --rate 10 --noise 0.001 --oe-frames 6 \
        --oe-windows 32                                     # the Cramer-Rao bound alone, per parameter
    python benchmarks/bench_recordings.py --first 2 --datasets 1 --varied --marker-fit --rate 30 --noise 0.01 \
        --oe-frames 9 --oe-windows 16 --oe-state-iterations 3 --oe-iterations 5 --bound-windows 8 --bound-steps 0 \
        --window-contact law   # the windows through the contact law, its parameters estimated too
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
import time
from dataclasses import replace

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from identified.evaluate import window_error
from identified.fit.identify import ScaleSpec
from identified.fit.markers import fit_recording
from identified.fit.pipeline import fit_model
from identified.fit.regression import IdentifiabilityError
from identified.predict import rollout_errors
from identified.recording import RecordingError
from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model


def varied_robot(path: str, seed: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Write the robot preset (``seed`` None) or the robot with every cable's K and c and every rod's
    M drawn as value * (1 + 0.15 N(0, 1)) (inertia scaled with the mass); returns the truth."""
    write_model(path, "ico", preset="robot")
    with open(path) as fh:
        text = fh.read()
    rng = np.random.default_rng(seed)
    draw = (lambda v: v) if seed is None else (lambda v: v * (1 + 0.15 * rng.normal()))
    K, c, M = [], [], []

    def spring(m: re.Match) -> str:
        k, d = draw(float(m.group(1))), draw(float(m.group(2)))
        K.append(k)
        c.append(d)
        return f'stiffness="{k!r}" damping="{d!r}"'

    def body(m: re.Match) -> str:
        mass = draw(float(m.group(1)))
        inertia = [float(x) * mass / float(m.group(1)) for x in m.group(2).split()]
        M.append(mass)
        return f'mass="{mass!r}" diaginertia="{" ".join(repr(x) for x in inertia)}"'

    text = re.sub(r'stiffness="([^"]+)" damping="([^"]+)"', spring, text)
    text = re.sub(r'mass="([^"]+)" diaginertia="([^"]+)"', body, text)
    with open(path, "w") as fh:
        fh.write(text)
    return np.array(K), np.array(c), np.array(M)


def values_model(path: str, total: float | None = None):
    """The MJCF's own K, c, M and inertia as a model (the truth, or with ``total`` the nominal values
    scaled to a known total mass: the start a lab has)."""
    import mujoco

    from identified.model import IdentifiedModel
    from identified.topology import Topology

    m = mujoco.MjModel.from_xml_path(path)
    topo = Topology.from_mjcf(path)
    tid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, n) for n in topo.spring_names]
    bid = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, n) for n in topo.rod_names]
    mass, inertia = m.body_mass[bid].copy(), m.body_inertia[bid].copy()
    if total is not None:
        inertia, mass = inertia * total / mass.sum(), mass * total / mass.sum()
    return IdentifiedModel(topology=topo, stiffness=m.tendon_stiffness[tid].copy(), damping=m.tendon_damping[tid].copy(),
                           rest_length=np.zeros(len(tid)), mass=mass, inertia=inertia, dt=float(m.opt.timestep),
                           gravity=m.opt.gravity.copy(), scale={"anchor": "total_mass"})


def law_truth(path: str) -> np.ndarray:
    """The plant's own contact as ``pyramid_contact``'s parameters (a benchmark's truth, for the
    bound at the truth; the estimator never reads it): MuJoCo's ``solref`` (time constant, damping
    ratio), ``solimp`` and ``friction`` of the ground plane, ``β = 2 / (d_w τ)``,
    ``κ = 1 / (d_w² τ² ζ²)``."""
    import mujoco

    m = mujoco.MjModel.from_xml_path(path)
    g = next(i for i in range(m.ngeom) if m.geom_type[i] == mujoco.mjtGeom.mjGEOM_PLANE)
    tc, zeta = m.geom_solref[g]
    d0, dw, width = m.geom_solimp[g][:3]
    f = m.geom_friction[g]
    return np.array([2 / (dw * tc), 1 / (dw ** 2 * tc ** 2 * zeta ** 2), d0, dw, width, f[0], f[1], f[2]])


def truth_window_args(ap: argparse.ArgumentParser) -> None:
    """The options of a probe of the marker windows at the truth (:func:`truth_windows`)."""
    ap.add_argument("--seed", type=int, default=7, help="the robot's, the runs' and the markers' seed")
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--noise", type=float, default=0.01, help="markers' noise (m)")
    ap.add_argument("--windows", type=int, default=8, help="windows spread over the recording (0: all)")
    ap.add_argument("--threads", type=int, default=1)


def truth_windows(tmp: str, args, frames: int = 9, law_free: bool = False):
    """The marker windows of a probe at the truth: the robot of ``args.seed``
    (:func:`varied_robot`), 10 takes of 10 s, markers at ``args.rate`` with ``args.noise`` and 2 %
    missing, ``args.windows`` windows of ``frames`` frames at the true K, c, M, I and the plant's
    own contact law (:func:`law_truth`, every law parameter free with ``law_free``), from the
    plant's own states.  Returns ``(truth, window_problem's five)``."""
    from identified.effects.pyramid_contact import PyramidContact
    from identified.fit.output_error import window_problem

    path = os.path.join(tmp, "robot.xml")
    varied_robot(path, args.seed)
    truth = values_model(path)
    t0 = time.perf_counter()
    data = collect(path, CollectConfig(episodes=10, steps=10000, seed=args.seed))
    rec = record_markers(data, path, RecordConfig(rate=args.rate, noise_pos=args.noise, dropout=0.02), seed=args.seed)
    law = PyramidContact.for_system(truth.topology, path)
    law.values = law_truth(path)
    held = [(i, 2) for i in range(truth.topology.n_rods)]  # end caps on the rods' axes
    out = window_problem(truth, rec, data, [0.0] * rec.n_episodes, path, args.noise, held, frames=frames,
                         max_windows=args.windows or 10 ** 9, contact=law,
                         law_free=tuple(b.name for b in law.blocks) if law_free else (), free_gains=law_free)
    print(f"plant and recording {time.perf_counter() - t0:.0f} s; {out[0].n_windows} of {out[1]} windows", flush=True)
    return (truth, *out)


def window_law(path: str, args, values: np.ndarray | None):
    """The windows' contact law of ``--window-contact law`` (``None`` for the free wrench): the
    effect ``--law`` with its geometry from the MJCF and the parameter ``values`` given (the truth
    for the bound), else its own generic start (``pyramid_contact.START``: a hard floor's order of
    magnitude, not the plant's); and the names of its parameters estimated jointly (``--law-free``)."""
    if args.window_contact != "law":
        return None, ()
    from identified.effects.pyramid_contact import START, PyramidContact
    from identified.topology import Topology

    law = PyramidContact.for_system(Topology.from_mjcf(path), path)
    law.values = np.array(list(START.values()) if values is None else values, dtype=float)
    names = [b.name for b in law.blocks]
    free = () if args.law_free == "none" else tuple(names if args.law_free == "all" else args.law_free.split(","))
    return law, free


def truth_bound(path: str, data, args, seed: int):
    """The Cramer-Rao bound of a recording at the truth (:func:`identified.fit.marker_bound.recording_bound`):
    the markers' noise ``args.noise``, the recording's rate and missing samples, the plant's own states
    and parameters, every window's initial state and the ground's wrench on the rods near it unknown;
    ``args.oe_windows`` windows of ``args.oe_frames`` frames, scaled to all the recording's windows."""
    from identified.fit.marker_bound import recording_bound

    clean = record_markers(data, path, RecordConfig(rate=args.rate, noise_pos=0.0, dropout=args.dropout), seed=seed)
    truth = values_model(path)
    held = [(i, 2) for i in range(truth.topology.n_rods)]  # end caps on the rods' axes
    law, free = window_law(path, args, law_truth(path))
    return recording_bound(truth, clean, data, [0.0] * data.n_episodes, path, args.noise, held,
                           frames=args.oe_frames, max_windows=args.bound_windows or args.oe_windows,
                           state_steps=args.bound_steps, order=args.wrench_order, contact=law, law_free=free,
                           substeps=args.oe_step)


def group_line(key: str, est: np.ndarray, se: np.ndarray, tru: np.ndarray, crb: np.ndarray, scale: float) -> str:
    """One parameter group: the identifiable estimates' largest error and z-scores (log scale), the
    bound and the estimator's standard error over it (both for the whole recording: the estimator's
    scaled by ``scale``, sqrt(windows used / available)); the not identifiable ones by name count."""
    from identified.fit.bound import NOT_IDENTIFIABLE

    ok = se <= NOT_IDENTIFIABLE
    z = np.log(est / tru) / se
    fin = np.isfinite(crb)
    ratio = se[fin] * scale / crb[fin] if fin.any() else np.array([np.nan])
    text = f"{key}: {ok.sum()}/{ok.size} identifiable"
    if ok.any():
        text += (f", max rel err {100 * np.max(np.abs(est[ok] / tru[ok] - 1)):.2f} %, RMS z "
                 f"{np.sqrt(np.mean(z[ok] ** 2)):.2f}, max |z| {np.max(np.abs(z[ok])):.2f}")
    text += (f"; bound (whole recording) {100 * np.min(crb):.2f}-{100 * np.max(crb):.2f} %, estimator's standard "
             f"error / bound {np.min(ratio):.2f}-{np.max(ratio):.2f} (median {np.median(ratio):.2f})")
    if (~ok).any():
        text += (f"; not identifiable at this rate/noise: {(~ok).sum()} (their standard errors "
                 f"{100 * np.min(se[~ok]):.0f}-{100 * np.max(se[~ok]):.0f} %, bound {100 * np.min(crb[~ok]):.1f}-"
                 f"{100 * np.max(crb[~ok]):.1f} %; no value printed)")
    return text


def marker_fit_row(path: str, data, rec, truth, args, k: int) -> dict:
    """The output-error fit from the nominal values (:func:`identified.fit.marker_fit.fit_markers`)
    beside the recording's bound at the truth; printed per parameter group."""
    from identified.fit.marker_fit import fit_markers
    from identified.fit.markers import states_from_recording

    nominal = os.path.join(os.path.dirname(path), f"nominal{k}.xml")
    varied_robot(nominal, None)
    start = values_model(nominal, total=float(truth[2].sum()))
    t0 = time.perf_counter()
    ms = states_from_recording(rec, start.topology, 0.001)
    law, free = window_law(path, args, None)
    fit = fit_markers(start, rec, ms.data, ms.starts, path, args.noise, ms.unobservable, frames=args.oe_frames,
                      max_windows=args.oe_windows, state_iters=args.oe_state_iterations, joint_iters=args.oe_iterations,
                      contact_margin=args.contact_margin, wrench_order=args.wrench_order, contact=law, law_free=free,
                      substeps=args.oe_step, progress=args.progress)
    secs = time.perf_counter() - t0
    b = truth_bound(path, data, args, k)
    scale = np.sqrt(fit.windows / fit.available)
    model = ("the free ground wrench" if law is None else
             f"the contact law {law.name} (estimated: {', '.join(free) or 'none'}; start: its generic START)")
    print(f"dataset {k}: output error from the nominal values, windows through {model}, {fit.windows} of "
          f"{fit.available} windows of "
          f"{args.oe_frames} frames stepped at up to {args.oe_step} ms, marker residual {1e3 * fit.residual_rms:.2f} mm, {secs:.0f} s; bound at the truth "
          f"from {b.windows} of {b.available} windows ({b.seconds:.0f} s, clean markers left at "
          f"{1e3 * b.residual_rms:.2f} mm)", flush=True)
    out = {}
    for key, tru in zip("KcM", truth):
        est, se = fit.group(key)
        print("  " + group_line(key, est, se, tru, b.group(key), scale), flush=True)
        out[key] = (est, se, tru)
    if free:
        est, se = fit.group("law")
        tl = law_truth(path)[[i for i, b in enumerate(law.blocks) if b.name in free]]
        crb = b.group("law")
        print("  contact law (estimate, plant's value; standard error and bound of log, logit for imp_*): " + "; ".join(
            f"{n} " + (f"{e:.4g} ({t:.4g}; se {s:.2g}, bound {c:.2g})" if s <= 0.3 else
                       f"not identifiable at this rate/noise (se {s:.2g}, bound {c:.2g})")
            for n, e, t, s, c in zip(free, est, tl, se, crb)), flush=True)
    axial = [i for i, n in enumerate(b.bound.names) if n.startswith("I[") and n.endswith(":z]")]
    rel = b.bound.rel_se[axial]
    why = ("the contact law's friction at the capsule's surface couples the spin, and the bound holds the spin as "
           "reconstructed: optimistic" if args.window_contact == "law" else
           "the engine's discretisation couples the unseen spin at 1e-3")
    print(f"  I about the rods' axes ({len(axial)}): not estimated, every rod's markers lie on its axis (bound "
          f"{100 * rel.min():.0f}-{100 * rel.max():.0f} %: {why})", flush=True)
    return out


def free_runs(model, held) -> tuple[float, float]:
    """The held-out take's free-run error (m): the mean over 1 s runs from its state at every whole
    second, and the 1 s run from its start alone."""
    first = held.select(steps=min(1000, held.n_steps))
    return (float(window_error(model, held, min(1000, held.n_steps), stride=1000)),
            float(rollout_errors(model, first, horizon=first.n_steps)["pos_mean"]))


def scores(model, truth) -> dict:
    out = {}
    for key, attr, se_key, tru in zip("KcM", ("stiffness", "damping", "mass"), ("stiffness", "damping", "mass"), truth):
        v = getattr(model, attr)
        se = np.asarray(model.stderr.get(se_key, np.full_like(v, np.nan)), dtype=float)
        out[key] = {"rel": float(np.max(np.abs(v / tru - 1))), "z": (v - tru) / se}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", type=int, default=10)
    ap.add_argument("--first", type=int, default=0, help="the first dataset's number (its seeds), to split a table")
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--noise", type=float, default=0.001)
    ap.add_argument("--dropout", type=float, default=0.02)
    ap.add_argument("--effects", default="ground_contact")
    ap.add_argument("--regressors", choices=("single", "multiple"), default="multiple",
                    help="single: one K, c shared by the cables and one M, I by the rods (the preset's are equal)")
    ap.add_argument("--varied", action="store_true", help="robots with other parameter values (one per dataset)")
    ap.add_argument("--unlabelled", action="store_true",
                    help="anonymous markers, identities shuffled every 0.5 s, one ghost per frame (labelled by the fit)")
    ap.add_argument("--quick", action="store_true", help="skip the fit on full states")
    ap.add_argument("--output-error", action="store_true",
                    help="refine against the markers (identified.fit.output_error) and print the regression too")
    ap.add_argument("--oe-windows", type=int, default=256, help="windows the output-error refinement uses")
    ap.add_argument("--oe-frames", type=int, default=10, help="frames per output-error window")
    ap.add_argument("--bound", action="store_true",
                    help="only the Cramer-Rao bound of each recording at the truth (no fit; truth_bound)")
    ap.add_argument("--marker-fit", action="store_true",
                    help="output error from the nominal values beside the bound (marker_fit_row; needs --varied)")
    ap.add_argument("--oe-iterations", type=int, default=8, help="joint steps of --marker-fit")
    ap.add_argument("--contact-margin", type=float, default=None,
                    help="--marker-fit: a rod this close to the ground (m, reconstructed) feels a free wrench (0.01)")
    ap.add_argument("--wrench-order", type=int, default=3,
                    help="terms of the ground's free wrench in time (bound and --marker-fit): 2 linear, 3 quadratic")
    ap.add_argument("--window-contact", choices=("free", "law"), default="free",
                    help="the ground in the output-error windows (bound and --marker-fit): a free wrench per window "
                         "and rod near it (polynomial in time), or the contact law pyramid_contact (every rod "
                         "simulated; the estimator starts the law at its generic START, the bound takes the plant's)")
    ap.add_argument("--law-free", default="all",
                    help="--window-contact law: the law's parameters estimated with K, c, M ('all', 'none' or names)")
    ap.add_argument("--oe-state-iterations", type=int, default=4, help="--marker-fit: steps in the windows' states first")
    ap.add_argument("--oe-step", type=int, default=1,
                    help="--marker-fit and the bound: the windows' step, at most this many of the reconstruction's "
                         "1 ms (output_error.coarse_steps: frames still on steps)")
    ap.add_argument("--progress", action="store_true", help="--marker-fit: print every step")
    ap.add_argument("--bound-windows", type=int, default=None, help="windows of the bound (default --oe-windows)")
    ap.add_argument("--bound-steps", type=int, default=5,
                    help="steps in the windows' nuisances alone before the bound's Jacobian (marker_bound.settle)")
    args = ap.parse_args()
    if args.marker_fit and not args.varied:
        ap.error("--marker-fit starts from the preset's values: with the preset robot they are the truth (add --varied)")
    effects = args.effects if args.effects in ("auto", "none") else args.effects.split(",")
    steps = round(args.seconds / 0.001)
    rows, zs = [], {k: [] for k in "KcM"}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.first, args.first + args.datasets):
            path = os.path.join(tmp, f"robot{k}.xml")
            truth = varied_robot(path, 100 + k if args.varied else None)
            rolled = collect(path, CollectConfig(episodes=args.episodes + 1, steps=steps, seed=k))
            data = rolled.select(episodes=slice(0, args.episodes))  # the last take is held out of both fits
            held = rolled.select(episodes=slice(args.episodes, args.episodes + 1))
            rec = record_markers(data, path, RecordConfig(rate=args.rate, noise_pos=args.noise, dropout=args.dropout,
                                                              unlabelled=args.unlabelled, ghosts=int(args.unlabelled)),
                                 seed=k)
            if args.bound:
                b = truth_bound(path, data, args, k)
                print(f"dataset {k}: Cramer-Rao bound (relative standard error, whole recording) K "
                      f"{100 * b.group('K').max():.2f} %, c {100 * b.group('c').max():.2f} %, M "
                      f"{100 * b.group('M').max():.2f} % at worst ({b.windows} of {b.available} windows of "
                      f"{args.oe_frames} frames; clean markers left at {1e3 * b.residual_rms:.3f} mm; {b.seconds:.0f} s); "
                      + "; ".join(b.bound.describe(i) for i in np.flatnonzero(~b.bound.identifiable())), flush=True)
                continue
            if args.marker_fit:
                marker_fit_row(path, data, rec, truth, args, k)
                continue
            scale = ScaleSpec(total_mass=float(truth[2].sum()))
            t0 = time.perf_counter()
            try:
                oe = {"max_windows": args.oe_windows, "frames": args.oe_frames} if args.output_error else False
                m = fit_recording(rec, path, effects=effects, scale=scale, jobs=1, output_error=oe,
                                  regressors=args.regressors)
            except IdentifiabilityError as exc:  # what the recording cannot tell, said as the fit says it
                print(f"dataset {k}: not identifiable from the recording ({time.perf_counter() - t0:.1f} s): {exc}",
                      flush=True)
                continue
            except RecordingError as exc:  # e.g. markers that could not be labelled: the row, not a traceback
                print(f"dataset {k}: recording refused ({time.perf_counter() - t0:.1f} s): {exc}", flush=True)
                continue
            secs = time.perf_counter() - t0
            if args.output_error:
                o = m.metrics["output_error"]
                reg = replace(m, stiffness=np.array(o["regression"]["stiffness"]),
                              damping=np.array(o["regression"]["damping"]), mass=np.array(o["regression"]["mass"]),
                              stderr={k: np.array(o["regression"][f"{k}_stderr"]) for k in ("stiffness", "damping", "mass")})
                rs = scores(reg, truth)
                zr = np.concatenate([rs[key]["z"] for key in "KcM"])
                print(f"dataset {k} regression: K {100 * rs['K']['rel']:.2f} %, c {100 * rs['c']['rel']:.2f} %, "
                      f"M {100 * rs['M']['rel']:.2f} %, RMS z {np.sqrt(np.nanmean(zr ** 2)):.2f}, max |z| "
                      f"{np.nanmax(np.abs(zr)):.2f}; output error: {o['windows']} windows of {o['frames_per_window']} "
                      f"frames, {o['seconds']:.1f} s, marker residual {1e3 * o['residual_rms_m']:.3f} mm"
                      + (f"; kept the regression: {o['kept_regression']}" if "kept_regression" in o else ""), flush=True)
            sc = scores(m, truth)
            for key in "KcM":
                zs[key].append(sc[key]["z"])
            err, err1 = free_runs(m, held)
            full, full1 = float("nan"), float("nan")
            if not args.quick:
                f = fit_model(data, path, effects=effects, scale=scale, weak_window=None, jobs=1,
                              regressors=args.regressors)
                full, full1 = free_runs(f, held)
            z_all = np.concatenate([sc[key]["z"] for key in "KcM"])
            rows.append((k, sc["K"]["rel"], sc["c"]["rel"], sc["M"]["rel"], float(np.sqrt(np.nanmean(z_all ** 2))),
                         float(np.nanmax(np.abs(z_all))), err, full, secs))
            print(f"dataset {k}: K {100 * rows[-1][1]:.2f} %, c {100 * rows[-1][2]:.2f} %, M {100 * rows[-1][3]:.2f} %, "
                  f"RMS z {rows[-1][4]:.2f}, max |z| {rows[-1][5]:.2f}, held-out free runs (1 s, mean over the take) "
                  f"{err:.4g} m vs full states {full:.4g} m (from the take's start alone {err1:.4g} vs {full1:.4g} m), "
                  f"fit {secs:.1f} s; effects {[e['name'] for e in m.effects]}", flush=True)
    print()
    print(f"{args.datasets} datasets of {args.episodes} x {args.seconds:g} s, markers at {args.rate:g} Hz, "
          f"{args.noise * 1e3:g} mm noise, {100 * args.dropout:g} % missing{', unlabelled' if args.unlabelled else ''}; "
          f"{'varied robots' if args.varied else 'robot preset'}")
    print("| | K max rel | c max rel | M max rel | RMS z | max abs z | free run, recording / full states | fit |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    if not rows:
        return
    for k, K, c, M, rz, mz, err, full, secs in rows:
        ratio = f" ({err / full:.2f}x)" if np.isfinite(full) else ""
        print(f"| dataset {k} | {100 * K:.2f} % | {100 * c:.2f} % | {100 * M:.2f} % | {rz:.2f} | {mz:.2f} | "
              f"{err:.3f} / {full:.3f} m{ratio} | {secs:.0f} s |")
    r = np.array([x[1:6] for x in rows])
    print(f"| worst | {100 * r[:, 0].max():.2f} % | {100 * r[:, 1].max():.2f} % | {100 * r[:, 2].max():.2f} % | "
          f"{r[:, 3].max():.2f} | {r[:, 4].max():.2f} | | |")
    z = np.concatenate([np.concatenate(zs[key]) for key in "KcM"])
    print(f"all K, c, M: RMS z over all datasets {np.sqrt(np.nanmean(z ** 2)):.2f}, max |z| {np.nanmax(np.abs(z)):.2f}")
    for key in "KcM":
        z = np.concatenate(zs[key])
        print(f"{key}: RMS z over all datasets {np.sqrt(np.nanmean(z ** 2)):.2f}, max |z| {np.nanmax(np.abs(z)):.2f}")


if __name__ == "__main__":
    main()
