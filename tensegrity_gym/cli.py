"""The ``tensegrity`` command: model, collect, fit, predict, summary.

Every sub-command explains itself with ``--help``, shows a progress bar on long work, writes its
output atomically, and on bad input prints one line ``tensegrity: error: ...`` to stderr and exits
with status 2 (no traceback; set ``TENSEGRITY_DEBUG=1`` to see one).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from identified.jsonsafe import json_safe
from tensegrity_gym.options import count, finite_float, jobs, names, noise, seed

if TYPE_CHECKING:
    from identified.fit.marker_model import MarkerRefineConfig

__all__ = ["build_parser", "main"]


class CommandError(Exception):
    """An expected failure with a one-line message for the user."""


# ---------------------------------------------------------------------- sub-commands
def cmd_model(args: argparse.Namespace) -> None:
    from tensegrity_gym.models import resolve_preset, write_model

    _check_writable(args.out)
    write_model(args.out, args.system, preset=args.preset, seed=args.seed, integrator=args.integrator)
    print(f"wrote {args.system}/{resolve_preset(args.system, args.preset)} model to {args.out}")


def cmd_collect(args: argparse.Namespace) -> None:
    from identified.dataset import save_dataset
    from tensegrity_gym.collect import CollectConfig, collect

    _check_readable(args.model)
    _check_writable(args.out, inputs={"--model": args.model})
    cfg = CollectConfig(
        episodes=args.episodes, steps=args.steps, seed=args.seed, push_every=args.push_every,
        push_magnitude=args.push_magnitude, push_duration=args.push_duration,
        noise_pos=args.noise_pos, noise_vel=args.noise_vel, noise_quat=args.noise_quat,
        noise_angvel=args.noise_angvel, integrator=args.integrator,
    )
    if args.record is not None:
        _collect_recording(args, cfg)
        return
    given = [o for o in _RECORD_OPTIONS if _given(args, o) not in (None, False)]
    if given:
        raise CommandError(f"{given[0]} is for a recording (`tensegrity collect --record markers --out R.csv`); "
                           "a dataset holds the plant's states at every step")
    data = collect(args.model, cfg, progress=not args.quiet)
    save_dataset(args.out, data)
    print(f"wrote {data.n_episodes} episodes x {data.n_steps} steps ({data.n_rods} rods, "
          f"{data.n_tendons} tendons) to {args.out}")


def _collect_recording(args: argparse.Namespace, cfg) -> None:
    """``collect --record markers``: what a lab's sensors would see, written as a recording CSV."""
    from identified.recording import save_recording
    from identified.topology import Topology
    from tensegrity_gym.collect import RecordConfig, collect, record_markers

    if args.record != "markers":
        raise CommandError(f"--record {args.record}: the one kind of recording is 'markers'")
    if not args.out.lower().endswith(".csv"):
        raise CommandError(f"--out '{args.out}': a recording is written as .csv")
    if args.push_every is not None:
        raise CommandError("--push-every: a recording has no column for pushes (a lab does not measure them); "
                           "leave pushes out when recording")
    if any((args.noise_vel, args.noise_quat, args.noise_angvel)):
        raise CommandError("--noise-vel/--noise-quat/--noise-angvel: a recording holds markers only; give "
                           "--noise-pos")
    if args.ghosts and not args.unlabelled:
        raise CommandError("--ghosts: spurious markers come with anonymous columns; add --unlabelled")
    if args.noise_length is not None and args.lengths is None:
        raise CommandError("--noise-length: the noise of length sensors; name the sensed cables with --lengths")
    options = {field: _given(args, name) for name, field in _RECORD_OPTIONS.items()}
    rec = RecordConfig(noise_pos=args.noise_pos, **{field: v for field, v in options.items() if v is not None})
    rec.validate(1e-12)  # option values before the plant runs (the rates against dt after)
    try:
        rec.length_sensors(Topology.from_mjcf(args.model).spring_names)  # the names before the plant runs
    except ValueError as exc:
        raise CommandError(str(exc)) from None
    clean = collect(args.model, cfg.__class__(**{**cfg.__dict__, "noise_pos": 0.0}), progress=not args.quiet)
    r = record_markers(clean, args.model, rec, seed=args.seed)
    save_recording(args.out, r)
    encoders = "" if rec.encoder_rate is None else f" at {rec.encoder_rate:g} Hz"
    lengths = f", {len(r.length_names)} cable lengths" if r.length_names else ""
    print(f"wrote {r.n_episodes} takes x {r.n_frames // max(r.n_episodes, 1)} frames at {rec.rate:g} Hz "
          f"({len(r.marker_names)} markers, {100 * r.missing_fraction():.1f} % missing, "
          f"{len(r.rest_names)} encoder rest lengths{encoders}{lengths}) to {args.out}")


#: ``collect``'s options for a recording -> their :class:`~tensegrity_gym.collect.RecordConfig` fields
#: (``None`` when not given: the config's default)
_RECORD_OPTIONS = {"--rate": "rate", "--encoder-rate": "encoder_rate", "--dropout": "dropout",
                   "--unlabelled": "unlabelled", "--ghosts": "ghosts", "--lengths": "lengths",
                   "--noise-length": "noise_length"}


def _summary_recording(args: argparse.Namespace) -> None:
    from identified.recording import check_recording
    from identified.topology import Topology

    r = _load_recording(args)
    if args.model is not None:
        _check_readable(args.model)
        topology = Topology.from_mjcf(args.model)
        check_recording(r, topology, tuple(a.name for a in topology.force_actuators))
    span = [float(r.time[i[-1]] - r.time[i[0]]) for i in r.episodes()]
    info = {"takes": r.n_episodes, "frames": r.n_frames, "rate_hz": r.rate_hz(), "duration_s": span,
            "markers": list(r.marker_names), "unlabelled": r.unlabelled, "missing": r.missing_fraction(),
            "rest": list(r.rest_names), "ctrl": list(r.ctrl_names), "length": list(r.length_names),
            "encoder_rate_hz": r.encoder_rate_hz(), "noise_pos": r.noise_pos, "checked_against": args.model}
    if args.json:
        print(json.dumps(json_safe(info), indent=2, allow_nan=False))
        return
    print(f"{args.data}: {r.n_episodes} takes, {r.n_frames} frames at {info['rate_hz']:.4g} Hz "
          f"({sum(span):.3g} s), {len(r.marker_names)} {'unlabelled ' if r.unlabelled else ''}markers, "
          f"{100 * info['missing']:.2f} % of samples missing")
    at = "" if r.encoders is None else f" at {info['encoder_rate_hz']:.4g} Hz"
    print(f"  {len(r.rest_names)} encoder rest lengths{at}, {len(r.ctrl_names)} commands, {len(r.length_names)} "
          f"cable lengths; marker noise {'not stated' if r.noise_pos is None else f'{r.noise_pos:g} m'}"
          + (f"; matches {args.model}" if args.model else ""))


def cmd_summary(args: argparse.Namespace) -> None:
    from identified.dataset import load_dataset

    if _is_recording(args.data_files[0]):
        _summary_recording(args)
        return
    d = load_dataset(args.data)
    speed = np.linalg.norm(d.vel, axis=-1)
    spin = np.linalg.norm(d.angvel, axis=-1)
    info = {
        "episodes": d.n_episodes,
        "steps_per_episode": d.n_steps,
        "dt": d.dt,
        "duration_s": d.n_steps * d.dt,
        "rods": list(d.rod_names),
        "tendons": d.n_tendons,
        "actuated": list(d.actuated_names),
        "gravity": d.gravity.tolist(),
        "speed_mean": float(speed.mean()),
        "speed_max": float(speed.max()),
        "angvel_mean": float(spin.mean()),
        "rest_length_range": [float(d.rest_length.min()), float(d.rest_length.max())],
        "pushes": int(np.count_nonzero(np.any(d.push_force != 0, axis=-1))),
        "noise": d.noise.tolist(),
    }
    if args.json:
        print(json.dumps(json_safe(info), indent=2, allow_nan=False))
        return
    print(f"{args.data}: {d.n_episodes} episodes x {d.n_steps} steps of {d.dt * 1e3:g} ms "
          f"({info['duration_s']:.3g} s each), {d.n_rods} rods, {d.n_tendons} tendons, "
          f"{len(d.actuated_names)} actuated")
    print(f"  rod speed mean {info['speed_mean']:.3g} m/s (max {info['speed_max']:.3g}), "
          f"angular speed mean {info['angvel_mean']:.3g} rad/s")
    print(f"  rest lengths {info['rest_length_range'][0]:.4g}..{info['rest_length_range'][1]:.4g} m, "
          f"push-steps {info['pushes']}, sensor noise {d.noise.tolist()}")


def cmd_fit(args: argparse.Namespace) -> None:
    from identified.threads import torch_threads

    with torch_threads(args.threads):
        _fit(args)


def _fit(args: argparse.Namespace) -> None:
    from identified.dataset import load_dataset
    from identified.fit.identify import ScaleSpec
    from identified.fit.pipeline import fit_model, parse_effects
    from identified.model import save_model

    parse_effects(args.effects)  # a bad name fails before anything is read
    _check_readable(args.model)
    _check_writable(args.out, inputs={**_data_inputs(args), "--model": args.model})
    masses = tuple(_parse_mass(m) for m in (args.mass or []))
    scale = ScaleSpec(masses=masses, total_mass=args.total_mass, pushes_in_newton=not args.pushes_unscaled)
    if _is_recording(args.data_files[0]):
        _fit_recording(args, scale)
        return
    for name in _marker_options(args):
        raise CommandError(f"{name} is for a recording's marker fit (`tensegrity fit R.csv --refine`), not a dataset")
    data = load_dataset(args.data)
    weak = "auto" if args.weak_window is None else args.weak_window
    # --refine is for plants whose integrator may differ from the engine's: without an explicit
    # --integrator it first picks the one whose equations fit the data (fit_model)
    model = fit_model(data, args.model, effects=args.effects, regressors=args.regressors, scale=scale,
                      solver=args.solver, weak_window=weak, integrator=args.integrator, scheme=args.scheme,
                      refine=args.refine, progress=not args.quiet, jobs=args.jobs, inertia=args.inertia)
    save_model(args.out, model)
    if not args.quiet:
        print(model.summary())
    for w in model.metrics.get("warnings", []):
        print(f"tensegrity: warning: {w}", file=sys.stderr)
    refined = model.metrics.get("refine")
    extra = f", refine {refined['seconds']:.3g} s" if refined else ""
    added = ", ".join(e["name"] for e in model.effects) or "none"
    print(f"wrote identified model to {args.out} (fit {model.metrics['fit_seconds']:.3g} s{extra}, "
          f"integrator {model.integrator}, effects: {added})")
    _strict(args, model)


def _strict(args: argparse.Namespace, model) -> None:
    """``fit --strict``: an error when the fitted equations do not describe their own data."""
    res = model.metrics.get("residual") or {}
    if args.strict and res.get("large"):
        raise CommandError(f"--strict: the fit leaves {res['relative_one_step']:.3g} of the recorded wrench "
                           f"unexplained on its own data (above {res['threshold']:g}); '{args.out}' is written "
                           "for inspection")


def _takes(args: argparse.Namespace) -> None:
    """A command's ``data`` given as one file or several: several are the takes of one recording
    (``args.data_files``; ``args.data`` names them in messages)."""
    files = getattr(args, "data", None)
    if not isinstance(files, list):
        return
    if len(files) > 1:
        seen: set[str] = set()
        for p in files:
            if not _is_recording(p):
                raise CommandError(f"'{p}' is not a recording (.csv, .c3d): several files are the takes of one "
                                   "recording; give a dataset alone")
            if os.path.realpath(p) in seen:
                raise CommandError(f"'{p}' is given twice: each take once (its data would count twice)")
            seen.add(os.path.realpath(p))
    args.data_files = files
    args.data = files[0] if len(files) == 1 else " ".join(files)


def _load_recording(args: argparse.Namespace):
    """The recording the command was given: its files read and checked one by one, then joined as
    its takes (:func:`identified.recording.join_recordings`)."""
    from identified.recording import join_recordings, load_recording

    return join_recordings([load_recording(p) for p in args.data_files])


def _data_inputs(args: argparse.Namespace) -> dict[str, str]:
    """The command's data files as inputs an output must not overwrite."""
    if len(args.data_files) == 1:
        return {"the recording" if _is_recording(args.data_files[0]) else "the dataset": args.data_files[0]}
    return {f"the recording '{p}'": p for p in args.data_files}


def _is_recording(path: str) -> bool:
    """A recording (what a lab measures) rather than a dataset: ``.csv`` or ``.c3d``."""
    return os.path.splitext(path)[1].lower() in (".csv", ".c3d")


#: the marker fit's options (``fit R.csv --refine``) and the
#: :class:`~identified.fit.marker_model.MarkerRefineConfig` fields they set; their parser default is
#: ``None`` (not given: the config's default), so an option given at its default value is still seen
_MARKER_CONFIG = {"--windows": "windows", "--window-frames": "frames", "--window-step": "step",
                  "--state-iterations": "state_iterations", "--iterations": "iterations",
                  "--window-blocks": "blocks"}


def _marker_options(args: argparse.Namespace) -> list[str]:
    """The options of ``fit R.csv --refine`` (the marker fit) given on this command line."""
    return [name for name in (*_MARKER_CONFIG, "--start", "--checkpoint") if _given(args, name) is not None]


def _given(args: argparse.Namespace, option: str) -> Any:
    """The value of ``option`` (``--window-frames``) on this command line, ``None`` if not given."""
    return getattr(args, option[2:].replace("-", "_"))


def _marker_config(args: argparse.Namespace) -> MarkerRefineConfig:
    """The marker fit's :class:`~identified.fit.marker_model.MarkerRefineConfig`: the options given,
    the config's defaults for the others (``--windows 0``: all windows)."""
    from identified.fit.marker_model import MarkerRefineConfig

    given = {field: _given(args, name) for name, field in _MARKER_CONFIG.items()}
    config = MarkerRefineConfig(**{field: v for field, v in given.items() if v is not None})
    return dataclasses.replace(config, windows=None) if config.windows == 0 else config


def _fit_recording(args: argparse.Namespace, scale) -> None:
    """``tensegrity fit R.csv``: rod states reconstructed from the markers, then the fit."""
    from identified.fit.markers import fit_recording
    from identified.fit.pipeline import parse_effects
    from identified.model import save_model

    if args.solver != "lstsq" or args.integrator not in (None, "euler") or args.scheme:
        raise CommandError("--solver, --integrator and --scheme are for datasets; a recording is fitted "
                           "by least squares on the engine's Euler step (--refine: by its markers)")
    for name in ([] if args.refine else _marker_options(args)):
        raise CommandError(f"{name} is for the marker fit: add --refine")
    if args.start is not None:
        _check_readable(args.start)
    if args.checkpoint is not None:
        given = {**_data_inputs(args), "--model": args.model, "--out": args.out, "--start": args.start}
        _check_writable(args.checkpoint, "--checkpoint", inputs={k: v for k, v in given.items() if v})
    rec = _load_recording(args)

    def fit(effects: str | list[str]):
        return fit_recording(rec, args.model, dt=args.dt, weak_window=args.weak_window or None, effects=effects,
                             regressors=args.regressors, scale=scale, progress=not args.quiet, jobs=args.jobs)

    if args.refine:
        model = _refine_recording(args, rec, fit)
    else:
        model = fit(args.effects)
        if parse_effects(args.effects) == "auto":  # what the diagnosis of the recording finds missing (tensegrity_gym.loop)
            from tensegrity_gym.loop import close_loop

            model = close_loop(model, rec, args.model, fit, progress=not args.quiet)
    save_model(args.out, model)
    if not args.quiet:
        print(model.summary())
        for line in model.metrics.get("not_identifiable", []):
            print(f"not identifiable: {line}")
    for w in model.metrics.get("warnings", []):
        print(f"tensegrity: warning: {w}", file=sys.stderr)
    r = model.metrics["recording"]
    lengths = [v for v in r.get("cable_lengths", {}).values() if v["offset_m"] is not None]
    if lengths and not args.quiet:
        off = [1e3 * v["offset_m"] for v in lengths]
        print(f"measured cable lengths against the markers' ({len(lengths)} cables): offsets {min(off):.3g} to "
              f"{max(off):.3g} mm, RMS after them up to {1e3 * max(v['rms_m'] for v in lengths):.3g} mm")
    added = ", ".join(e["name"] for e in model.effects) or "none"
    print(f"wrote identified model to {args.out} (from {r['frames']} frames at {r['rate_hz']:.4g} Hz, "
          f"{100 * r['missing']:.1f} % missing; fit {model.metrics['fit_seconds']:.3g} s, effects: {added})")
    _strict(args, model)


def _refine_recording(args: argparse.Namespace, rec, fit):
    """``fit R.csv --refine``: the output-error fit to the markers themselves
    (:func:`identified.fit.marker_model.refine_recording`) from ``--start`` or, without it, from the
    regression's estimate of the same recording."""
    from identified.fit.marker_model import refine_recording
    from identified.fit.regression import IdentifiabilityError
    from identified.model import load_model

    if args.effects != "none":
        raise CommandError(f"--effects {args.effects}: not with --refine on a recording; the marker fit models the "
                           "ground's contact law (pyramid_contact) itself")
    config = _marker_config(args)
    if config.windows and config.blocks * 2 > config.windows:
        raise CommandError(f"--window-blocks {config.blocks}: each block needs at least two of the --windows "
                           f"{config.windows}")
    if args.start is not None:
        start = load_model(args.start)
    else:
        try:
            start = fit("none")
        except IdentifiabilityError:
            # without a contact law the regression leaves out the rows of the rods near the ground;
            # where too few are left (rods on the ground most of the time), it keeps them through one
            print("tensegrity: note: the regression without effects cannot start the marker fit (too few rows "
                  "off the ground); starting from one with ground_contact", file=sys.stderr)
            try:
                start = fit("ground_contact")
            except IdentifiabilityError as exc:
                raise CommandError(f"'{args.data}': the regression cannot start the marker fit ({exc}); give "
                                   "--start MODEL.json, a model of this robot (an earlier fit, or its design values)"
                                   ) from None
    if args.total_mass is None and args.start is not None:
        print("tensegrity: note: no --total-mass: the marker fit keeps the start's total mass "
              f"({float(start.mass.sum()):.6g} kg), which the markers cannot check", file=sys.stderr)
    return refine_recording(rec, args.model, start, total_mass=args.total_mass, config=config,
                            progress=not args.quiet, checkpoint=args.checkpoint)


def cmd_diagnose(args: argparse.Namespace) -> None:
    from identified.dataset import load_dataset
    from identified.diagnose import diagnose, write_report
    from identified.diagnose.report import EXPLAINED_BY
    from identified.fit.identify import check_compatible
    from identified.model import load_model

    if args.out is not None:  # a report folder: never one of the inputs, never over a file
        inputs = [p for p in (*args.data_files, args.identified, args.model) if p]
        if any(os.path.realpath(args.out) == os.path.realpath(p) for p in inputs):
            raise CommandError(f"--out '{args.out}' is one of the command's inputs; give a new folder for the report")
        if os.path.exists(args.out) and not os.path.isdir(args.out):
            raise CommandError(f"--out '{args.out}' exists and is not a folder")
    model = load_model(args.identified)
    scoring: dict[str, int] = {}
    rec = None
    if _is_recording(args.data_files[0]):  # rod states reconstructed from the markers (identified.fit.markers)
        from identified.fit.markers import diagnosis_options, recording_states

        rec = _load_recording(args)
        states = recording_states(rec, model, noise=True)
        data = states.data
        scoring = diagnosis_options(rec, model.dt)  # the candidates scored as the fit reads a recording
    else:
        data = load_dataset(args.data)
    check_compatible(data, model.topology)
    if args.horizon <= 0:
        raise CommandError(f"--horizon {args.horizon}: must be a positive number of seconds")
    if round(args.horizon / data.dt) > data.n_steps:
        raise CommandError(f"--horizon {args.horizon} s is longer than the data's episodes "
                           f"({data.n_steps * data.dt:g} s): record longer episodes or shorten --horizon")
    mjcf = args.model
    if mjcf is not None:
        _check_readable(mjcf)
    null = None
    if rec is not None:
        from tensegrity_gym.loop import recording_null

        null = recording_null(model, data, rec, states.marker_noise, mjcf, scoring)
    result = diagnose(model, data, horizon_s=args.horizon, mjcf=mjcf, null=null, **scoring)
    paths = write_report(result, args.out) if args.out else []
    if args.json:
        keep = {k: v for k, v in result.items() if k != "plot_data"}
        print(json.dumps(json_safe(keep), indent=2, allow_nan=False))
        return
    fmt = lambda x: "diverged" if x is None else f"{x:.4g} m"
    print(f"free-run position error over {result['horizon_s']:g} s: without the model's effects "
          f"{fmt(result['error_before'])}, with them ({', '.join(result['added']) or 'none'}) {fmt(result['error_after'])}")
    missing = result.get("unexplained_by") or []
    on_null = lambda c: (f" ({c['score_held_out_null']:.0%} on the model's own motion recorded alike)"
                         if c.get("score_held_out_null") is not None else "")
    why = (", ".join(f"{c['name']} removes {c['score_held_out']:.0%} of it on held-out data{on_null(c)}"
                     for c in missing)
           if missing else ("; ".join(EXPLAINED_BY[x] for x in result.get("explained_by") or [])
                            or "structured residual left"))
    print(f"residual explained: {result['explained']} ({why})")
    if missing:  # the loop's next step: the named effect added to the model's, one at a time as the search adds them
        names = [*result["added"], missing[0]["name"]]
        print(f"next: refit with it, `tensegrity fit {args.data} --effects {','.join(names)} ...` (the fit's other "
              "options as before), then diagnose the new model")
    for e in result["one_step"].get("effect_rows") or []:
        pct = lambda v: "n/a" if v is None else (f"{v:.1%}" if v >= 1e-3 else f"{v:.2g}")
        print(f"  on the rods {e['effect']} acts on ({e['fraction']:.1%} of rod-instants): force residual "
              f"{pct(e['inside']['force'])}, torque {pct(e['inside']['torque'])} of the recorded; other rods "
              f"{pct(e['outside']['force'])}, {pct(e['outside']['torque'])}")
    for c in result["candidates"][:6]:
        score = "n/a" if c["score"] is None else f"{c['score']:.3f}"
        held = "" if c.get("score_held_out") is None else f"  held out {c['score_held_out']:.3f}"
        if c.get("score_held_out_null") is not None:
            held += f" (null {c['score_held_out_null']:.3f})"
        print(f"  candidate {c['name']:<16} score {score}{held}  {c.get('note') or ''}".rstrip())
    for p in paths:
        print(f"wrote {p}")


def cmd_predict(args: argparse.Namespace) -> None:
    from identified.dataset import load_dataset
    from identified.model import load_model
    from identified.predict import rollout_errors, write_error_plot

    if args.plot:
        _check_writable(args.plot, "--plot", {**_data_inputs(args), "--identified": args.identified})
    model = load_model(args.identified)
    if _is_recording(args.data_files[0]):
        from identified.fit.markers import recording_dataset

        data = recording_dataset(_load_recording(args), model)
    else:
        data = load_dataset(args.data)
    errs = rollout_errors(model, data, horizon=args.horizon)
    if args.plot:
        write_error_plot(args.plot, errs)
    out = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in errs.items() if k != "per_step"}
    if args.json:
        print(json.dumps(json_safe(out), indent=2, allow_nan=False))
    else:
        print(f"free-run error over {errs['horizon']} steps: position mean {errs['pos_mean']:.3g} m "
              f"(final {errs['pos_final']:.3g} m), quaternion mean {errs['quat_mean']:.3g} "
              f"(final {errs['quat_final']:.3g})")


def cmd_reproduce(args: argparse.Namespace) -> None:
    from tensegrity_gym.reproduce import run

    if args.seed < 0:
        raise CommandError(f"--seed must be >= 0, got {args.seed}")
    if args.json:
        _check_writable(args.json)
    if args.out:
        if os.path.exists(args.out) and not os.path.isdir(args.out):
            raise CommandError(f"--out '{args.out}' exists and is not a folder")
        parent = os.path.dirname(os.path.abspath(args.out))
        target = args.out if os.path.isdir(args.out) else parent
        if not os.path.isdir(target) or not os.access(target, os.W_OK):
            raise CommandError(f"--out '{args.out}': cannot write there (folder missing or not writable)")
    run(args.experiment, quick=args.quick, seed=args.seed, out=args.out, json_path=args.json,
        progress=not args.quiet)


def cmd_train(args: argparse.Namespace) -> None:
    from tensegrity_gym.training import (
        TrainConfig,
        divergence_warning,
        resolve_physics_dt,
        resolve_randomize,
        train,
    )

    if args.timesteps < 1:
        raise CommandError(f"--timesteps must be at least 1, got {args.timesteps}")
    if args.envs is not None and args.envs < 1:
        raise CommandError(f"--envs must be at least 1, got {args.envs}")
    if args.identified is None and not args.plant:
        raise CommandError("--identified F.json is needed to train on the twin (or train on the plant with --plant)")
    if args.identified is not None:
        _check_readable(args.identified)
    if args.seeds is None and (args.ray is not None or args.jobs is not None):
        raise CommandError(f"{'--ray' if args.ray is not None else '--jobs'} runs several seeds: give them with "
                           "--seeds (e.g. --seeds 0-4)")
    own = _xml_file_kwargs(args)
    physics_dt = _physics_dt(args)
    if args.seeds is None:
        _check_writable(args.out)
    cfg = TrainConfig(timesteps=args.timesteps, seed=0 if args.seed is None else args.seed, algo=args.algo,
                      identified=args.identified, plant=args.plant, envs=args.envs, rollout=args.rollout,
                      episode_steps=args.episode_steps, threads=args.threads, tensorboard=args.tensorboard,
                      randomize=args.randomize, physics_dt=physics_dt, **own)
    if not args.plant:
        try:
            resolve_randomize(cfg)
        except ValueError as exc:
            raise CommandError(f"--randomize {args.randomize}: {exc}") from None
        try:  # once here, not in each seed's process; the step goes into the policy's metadata
            step, why = resolve_physics_dt(cfg)
        except ValueError as exc:
            raise CommandError(f"--physics-dt {args.physics_dt}: {exc}") from None
        cfg.physics_dt = step
        print(f"tensegrity: {why}")
    if args.seeds is not None:
        _train_seeds(args, cfg)
        return
    r = train(cfg, args.out, progress=not args.quiet)
    last = ("" if r.mean_return is None else
            f"; last {min(r.episodes, 20)} episodes: return {r.mean_return:.4g}, progress {r.mean_progress_m:.3g} m")
    print(f"wrote {args.algo} policy to {args.out} ({r.timesteps} steps on the {'plant' if args.plant else 'twin'} "
          f"with {cfg.n_envs} envs in {r.wall_s:.1f} s, {r.env_steps_per_s:.0f} steps/s{last})")
    warning = divergence_warning(r.diverged_episodes, r.episodes, args.plant)
    if warning:
        print(f"tensegrity: warning: {warning}", file=sys.stderr)


def cmd_improve(args: argparse.Namespace) -> None:
    from tensegrity_gym.improve import ImproveConfig, improve

    for name in ("rounds", "episodes", "timesteps"):
        if getattr(args, name) < 1:
            raise CommandError(f"--{name} must be at least 1, got {getattr(args, name)}")
    if args.episode_steps is not None and args.episode_steps < 1:
        raise CommandError(f"--episode-steps must be at least 1, got {args.episode_steps}")
    for p in (args.identified, args.data, args.policy):
        _check_readable(p)
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise CommandError(f"--out '{args.out}' exists and is not a folder")
    cfg = ImproveConfig(rounds=args.rounds, episodes=args.episodes, timesteps=args.timesteps,
                        randomize=args.randomize, effects=args.effects, seed=args.seed,
                        episode_steps=args.episode_steps, actions=args.actions)
    rows = improve(args.identified, args.data, args.policy, args.out, cfg, mjcf=args.model, progress=not args.quiet)
    for r in rows:
        e = r["twin_error_on_policy_states"]
        print(f"round {r['round']}: plant {r['plant_progress_m']:.3f} m, twin {r['twin_progress_m']:.3f} m, twin on "
              f"the policy's states: one-step {e['one_step_vel_m_s']:.3g} m/s, free run {e['free_run_m']:.3g} m; "
              f"plant data {r['plant_data_s']:.0f} s")
    print(f"wrote {os.path.join(args.out, 'improve.json')}")


def _train_seeds(args: argparse.Namespace, cfg: Any) -> None:
    """``train --seeds``: ``cfg`` once per seed into the folder ``--out`` (tensegrity_gym/sweep.py)."""
    import dataclasses

    from tensegrity_gym.sweep import parse_seeds, run_sweep
    from tensegrity_gym.training import divergence_warning

    if args.seed is not None:
        raise CommandError("give either --seed or --seeds, not both")
    seeds = parse_seeds(args.seeds)
    if args.out.endswith(".zip"):
        raise CommandError(f"--out {args.out}: with --seeds, --out is a folder (one sub-folder per seed)")
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise CommandError(f"--out {args.out}: exists and is not a folder (with --seeds, --out is a folder)")
    parent = os.path.dirname(os.path.abspath(args.out))
    if not os.path.isdir(parent) or not os.access(parent, os.W_OK):
        raise CommandError(f"--out {args.out}: cannot write there (folder '{parent}' missing or not writable)")
    if args.tensorboard is not None:
        raise CommandError("--tensorboard takes one run: train one --seed at a time for TensorBoard logs")
    cfg = dataclasses.replace(cfg, seed=seeds[0])
    s = run_sweep(cfg, seeds, args.out, jobs=args.jobs, ray_address=args.ray, progress=not args.quiet,
                  log=print)
    sp = s["over_seeds"]["last_progress_m"]
    where = f"Ray ({args.ray})" if args.ray is not None else f"{s['jobs']} local process(es)"
    last = "" if sp["mean"] is None else (f"; last training episodes' progress {sp['mean']:.3f} m "
                                          f"(std {sp['std']:.3f}, {sp['min']:.3f} to {sp['max']:.3f})")
    print(f"wrote {len(seeds)} {args.algo} policies to {args.out}/seed_*/ ({where}, {s['wall_s']:.1f} s{last}); "
          f"summary: {os.path.join(args.out, 'summary.json')}")
    for r in s["runs"]:
        warning = divergence_warning(r["diverged_episodes"], r["episodes"], args.plant, r["seed"])
        if warning:
            print(f"tensegrity: warning: {warning}", file=sys.stderr)


def cmd_gap(args: argparse.Namespace) -> None:
    from tensegrity_gym.gap import measure_gap
    from tensegrity_gym.sweep import policies_in

    if args.episodes < 1:
        raise CommandError(f"--episodes must be at least 1, got {args.episodes}")
    if args.episode_steps is not None and args.episode_steps < 1:
        raise CommandError(f"--episode-steps must be at least 1, got {args.episode_steps}")
    if args.video_every < 1:
        raise CommandError(f"--video-every must be at least 1, got {args.video_every}")
    _check_readable(args.identified)
    policies = policies_in(args.policy)
    if args.video is not None:
        if os.path.exists(args.video) and not os.path.isdir(args.video):
            raise CommandError(f"--video {args.video}: not a folder")
        _check_writable(os.path.join(args.video, "plant.mp4") if os.path.isdir(args.video) else args.video)
    own = _xml_file_kwargs(args)
    if len(policies) > 1:
        _gap_over_policies(args, policies, own.get("backend_kwargs"))
        return
    r = measure_gap(policies[0], args.identified, args.episodes, seed=args.seed,
                    episode_steps=args.episode_steps, video_dir=args.video, progress=not args.quiet,
                    threads=args.threads, backend_kwargs=own.get("backend_kwargs"), video_every=args.video_every,
                    actions=args.actions)
    if args.json:
        print(json.dumps(r, indent=2))
        return
    print(f"{r['twin']['episodes']} episodes of up to {r['episode_steps']} steps, reset seeds "
          f"{r['seeds'][0]}..{r['seeds'][-1]}, {_ACTIONS_SAID[args.actions]}")
    print(f"  {'':14s}{'return':>10s}{'progress (m)':>14s}{'steps':>8s}")
    for key, label in (("twin", "twin"), ("plant", "plant"), ("random_plant", "random, plant")):
        b = r[key]
        print(f"  {label:14s}{b['return']:10.4g}{b['progress_m']:14.4g}{b['episode_steps']:8.0f}")
    tr = r["transfer"]

    def ratio(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.3g}"

    se = tr.get("plant_over_twin_stderr")
    pm = "" if se is None or tr["plant_over_twin"] is None else f" ± {se:.2g} (standard error over the episodes)"
    print(f"  plant progress / twin: {ratio(tr['plant_over_twin'])}{pm}; / random: {ratio(tr['plant_over_random'])}")
    ol = r["open_loop"]

    def metres(x: float | None) -> str:
        return "n/a" if x is None else f"{x:.3g} m"

    t01 = "never" if ol["time_to_0.1m_s"] is None else f"after {ol['time_to_0.1m_s']:.3g} s"
    print(f"  open loop (the plant's commands on the twin): centre-of-mass divergence over 0.1 m {t01}; "
          f"at 1 s {metres(ol['at']['1s'])}, final {metres(ol['final_m'])}")
    for name, path in r.get("videos", {}).items():
        print(f"  video {name}: {path}")


#: how ``gap`` says the way its policies acted (``--actions``)
_ACTIONS_SAID = {"sampled": "actions sampled from each policy (the same draws on twin and plant)",
                 "mean": "each policy's mean action"}


def _gap_over_policies(args: argparse.Namespace, policies: list[str],
                       backend_kwargs: dict[str, Any] | None = None) -> None:
    """``gap`` of several policies: one line each, then mean and spread over them."""
    from tensegrity_gym.gap import CLEAR_Z, against_line, measure_gaps

    r = measure_gaps(policies, args.identified, args.episodes, seed=args.seed, episode_steps=args.episode_steps,
                     video_dir=args.video, progress=not args.quiet, threads=args.threads,
                     backend_kwargs=backend_kwargs, video_every=args.video_every, actions=args.actions)
    if args.json:
        print(json.dumps(json_safe(r), indent=2))
        return
    print(f"{len(policies)} policies, {args.episodes} episodes each, reset seeds {r['seeds'][0]}..{r['seeds'][-1]}, "
          f"{_ACTIONS_SAID[args.actions]}; forward progress per episode (m), mean over the episodes")
    print(f"  {'policy':40s}{'twin':>9s}{'plant':>9s}{'plant/twin ± s.e.':>19s}  {'at 90 %'}")
    for path, rep in zip(policies, r["reports"], strict=True):
        ratio, se = rep["transfer"]["plant_over_twin"], rep["transfer"].get("plant_over_twin_stderr")
        cell = "n/a" if ratio is None else f"{ratio:.2f}" + ("" if se is None else f" ± {se:.2f}")
        print(f"  {path[-40:]:40s}{rep['twin']['progress_m']:9.3f}{rep['plant']['progress_m']:9.3f}{cell:>19s}  "
              f"{against_line(ratio, se) or 'n/a'}")
    o = r["over_policies"]

    def line(label: str, sp: dict) -> str:
        if sp["mean"] is None:
            return f"  {label}: n/a"
        return (f"  {label}: mean {sp['mean']:.3f}, std {sp['std']:.3f}, min {sp['min']:.3f}, max {sp['max']:.3f} "
                f"(over {sp['n']})")

    print("over the policies:")
    print(line("twin progress (m)", o["twin"]["progress_m"]))
    print(line("plant progress (m)", o["plant"]["progress_m"]))
    print(line("plant / twin", o["plant_over_twin"]))
    pooled = o["plant_over_twin_pooled"]
    if pooled["ratio"] is not None:
        se = "" if pooled["stderr"] is None else f" ± {pooled['stderr']:.2f}"
        print(f"  plant / twin over every policy's episodes together: {pooled['ratio']:.2f}{se}")
    print(f"  random policy on the plant: {o['random_plant']['progress_m']:.3f} m; "
          f"{o['plant_progress_at_least_0.5m']} of {len(policies)} policies roll >= 0.5 m on the plant, "
          f"{o['plant_over_twin_at_least_0.9']} reach 90 % of their twin progress, "
          f"{o['plant_over_twin_under_0.9_beyond_noise']} fall under it by more than {CLEAR_Z:g} standard errors")


# ---------------------------------------------------------------------- parser
class _Parser(argparse.ArgumentParser):
    """argparse with the project's one-line error format (no usage dump)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        print(f"tensegrity: error: {self.prog.removeprefix('tensegrity').strip() or 'usage'}: {message}"
              f" (see '{self.prog} --help')", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    from identified.effects import search_labels

    p = _Parser(
        prog="tensegrity",
        description="Identify a spring-rod (tensegrity) robot from rollouts and train on its twin.",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    m = sub.add_parser("model", help="write an MJCF model of a preset system",
                       description="Write an MJCF model of the simple spring-rod system or the icosahedron.")
    m.add_argument("system", help="simple or ico")
    m.add_argument("--preset", default=None,
                   help="simple: paper; ico: paper-uniform, paper-nonuniform, robot (default: paper / robot)")
    m.add_argument("--seed", type=seed, default=None, help="seed for randomised presets (paper-nonuniform)")
    m.add_argument("--integrator", default="euler", help="MuJoCo integrator: euler (default), implicit, implicitfast, rk4")
    m.add_argument("--out", required=True, help="output .xml path")
    m.set_defaults(func=cmd_model)

    c = sub.add_parser("collect", help="roll the plant with exciting inputs and record a dataset",
                       description="Roll the MuJoCo plant with random initial states, smooth random cable "
                       "commands and optional pushes; record rod states, commands, rest lengths and pushes.")
    c.add_argument("--model", required=True, help="MJCF file following the tensegrity conventions")
    c.add_argument("--episodes", type=count(1), default=10, help="number of trajectories (default 10)")
    c.add_argument("--steps", type=count(1), default=2000, help="physics steps per trajectory (default 2000)")
    c.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    c.add_argument("--push-every", type=count(1), default=None, metavar="K", help="push a random rod every K steps")
    c.add_argument("--push-magnitude", type=finite_float(0.0, 1e6, "N", True), default=50.0, help="push force in N (default 50)")
    c.add_argument("--push-duration", type=count(1), default=10, help="steps a push is held (default 10)")
    c.add_argument("--noise-pos", type=noise(1.0, "m"), default=0.0, metavar="SIGMA", help="position noise std, m")
    c.add_argument("--noise-vel", type=noise(100.0, "m/s"), default=0.0, metavar="SIGMA", help="velocity noise std, m/s")
    c.add_argument("--noise-quat", type=noise(3.2, "rad"), default=0.0, metavar="SIGMA", help="orientation noise std, rad")
    c.add_argument("--noise-angvel", type=noise(1000.0, "rad/s"), default=0.0, metavar="SIGMA",
                   help="angular velocity noise std, rad/s")
    c.add_argument("--integrator", default=None, help="override the model's MuJoCo integrator")
    c.add_argument("--out", required=True, help="output .npz path (a .csv recording with --record)")
    c.add_argument("--record", default=None, metavar="markers",
                   help="write a recording (CSV of end-cap markers and encoder rest lengths) instead of a dataset: "
                   "what a lab measures, to rehearse the lab pipeline")
    c.add_argument("--rate", type=finite_float(0.0, 1e6, "Hz", True), default=None, metavar="HZ",
                   help="with --record: marker sampling rate (default 100 Hz)")
    c.add_argument("--encoder-rate", type=finite_float(0.0, 1e6, "Hz", True), default=None, metavar="HZ",
                   help="with --record: the encoders' own rate, written as rows between the camera frames "
                   "(default: read at the frames)")
    c.add_argument("--dropout", type=finite_float(0.0, 0.99, "", False), default=None, metavar="P",
                   help="with --record: share of marker samples missing, in runs of ~5 frames (default 0)")
    c.add_argument("--unlabelled", action="store_true",
                   help="with --record: anonymous marker columns (marker<N>) whose identities swap every 0.5 s")
    c.add_argument("--ghosts", type=count(0), default=None, metavar="N",
                   help="with --record --unlabelled: spurious markers per frame (default 0)")
    c.add_argument("--lengths", type=names, default=None, metavar="CABLES",
                   help="with --record: cables whose length a sensor of their own measures (stretch sensors), "
                   "written as <tendon>.length columns at the encoders' rate: 'all' or names, comma-separated")
    c.add_argument("--noise-length", type=noise(1.0, "m"), default=None, metavar="SIGMA",
                   help="with --record --lengths: the length sensors' noise std, m (default 0)")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=cmd_collect)

    s = sub.add_parser("summary", help="summarise a dataset", description="Validate a dataset and summarise it.")
    s.add_argument("data", nargs="+", help="dataset .npz, or a recording .csv/.c3d (several files: the takes of one "
                   "recording)")
    s.add_argument("--model", default=None, help="for a recording: check it against this MJCF (names, units)")
    s.add_argument("--json", action="store_true", help="machine-readable output")
    s.set_defaults(func=cmd_summary)

    f = sub.add_parser("fit", help="identify K, c, M, I (and h) from a dataset",
                       description="Identify spring stiffness and damping, rod mass and inertia and the "
                       "control-force scale from rod states alone, by linear least squares on 1D-reduced features.")
    f.add_argument("data", nargs="+", help="dataset .npz, or a recording .csv/.c3d (markers, encoder rest lengths; "
                   "several files: the takes of one recording)")
    f.add_argument("--model", required=True, help="MJCF file: only topology and geometry are read")
    f.add_argument("--out", required=True, help="output identified-model .json")
    f.add_argument("--regressors", choices=("single", "multiple"), default="multiple",
                   help="one shared K, c, M, I (single) or one per spring and rod (multiple, default)")
    f.add_argument("--solver", choices=("lstsq", "adam"), default="lstsq",
                   help="closed-form least squares (default) or the paper's Adam training")
    f.add_argument("--mass", action="append", metavar="NAME=KG", help="a known rod mass (fixes the scale)")
    f.add_argument("--total-mass", type=finite_float(0.0, 1e9, "kg", True), default=None, metavar="KG", help="known total rod mass")
    f.add_argument("--pushes-unscaled", action="store_true",
                   help="do not trust the recorded push magnitudes as newtons (fit h freely)")
    f.add_argument("--weak-window", type=count(0), default=None, metavar="STEPS",
                   help="sum the equations over windows of STEPS steps (weak form, for noisy data); "
                   "0: step by step; default: weak form (~0.3 s) when the dataset records sensor noise")
    f.add_argument("--integrator", choices=("euler", "implicit", "implicitfast", "rk4", "auto"), default=None,
                   help="how the plant steps, and so how the identified engine will: MuJoCo's euler, "
                   "implicit or implicitfast (the same for free rods), rk4, or auto: chosen from the data "
                   "by the equation residual of each (default: euler; auto with --refine)")
    f.add_argument("--inertia", choices=("auto", "full", "diagonal"), default="auto",
                   help="each rod's inertia: full (mass, centre of mass in the rod frame and the whole inertia "
                   "tensor, for rods whose centre of mass or principal axes the frame does not give), diagonal "
                   "(the paper's M, Ixx, Iyy, Izz about the frame's origin), or auto: full for rods made of "
                   "several bodies (default)")
    f.add_argument("--scheme", choices=("forward", "central"), default=None,
                   help="accelerations by forward differences (exact for euler and implicit plants; the "
                   "default for them) or central differences (second order for any integrator; the default "
                   "for rk4)")
    f.add_argument("--refine", action="store_true",
                   help="refine by multi-step simulation error (picks the integrator from the data unless "
                   "--integrator is given); on a recording: fit K, c, M, I and the ground's contact law to the "
                   "markers themselves through the engine (for low rates and coarse markers, e.g. 30 Hz / 1 cm)")
    f.add_argument("--start", default=None, metavar="MODEL.json",
                   help="recording with --refine: the model the marker fit starts from (default: the regression's "
                   "estimate of the same recording)")
    f.add_argument("--windows", type=count(0), default=None, metavar="N",
                   help="recording with --refine: windows spread over the recording (default 64; 0: all)")
    f.add_argument("--window-frames", type=count(2), default=None, metavar="N",
                   help="recording with --refine: frames per window (default 10)")
    f.add_argument("--window-step", type=finite_float(0.0, 0.1, "s", True), default=None, metavar="SECONDS",
                   help="recording with --refine: the windows' Jacobians stepped at up to this (default 0.005 s; "
                   "the cost always at the model's own step)")
    f.add_argument("--state-iterations", type=count(0), default=None, metavar="N",
                   help="recording with --refine: steps in the windows' states alone before the joint ones "
                   "(default 3)")
    f.add_argument("--iterations", type=count(1), default=None, metavar="N",
                   help="recording with --refine: joint steps at most, each followed by a step of the windows' states "
                   "alone (default 8)")
    f.add_argument("--window-blocks", type=count(1), default=None, metavar="B",
                   help="recording with --refine: fit the windows in B interleaved blocks, each on its own (its "
                   "checkpoint FILE.block<b>), and combine their estimates by their information, with a test that "
                   "they agree (default 1: all windows in one fit)")
    f.add_argument("--checkpoint", default=None, metavar="FILE",
                   help="recording with --refine: save the fit here after every step and resume from it when it "
                   "holds this fit (an interrupted fit goes on where it stopped)")
    f.add_argument("--effects", default="none", metavar="none|auto|NAME,...",
                   help="none: the spring-rod model alone (default); auto: search the effect library for what "
                   "the data show (held-out free-run error, see the README); or effect names: "
                   + ", ".join(search_labels()))
    f.add_argument("--jobs", type=jobs, default="auto", metavar="N|auto",
                   help="processes the effect search fits its candidates in (default auto: one per core "
                   "this process may use; the model is the same with any N)")
    f.add_argument("--strict", action="store_true",
                   help="exit with an error when the fitted equations leave a large residual on their own "
                   "(clean) data: the model cannot describe the plant")
    f.add_argument("--dt", type=finite_float(0.0, 1.0, "s", True), default=0.001, metavar="SECONDS",
                   help="for a recording: the step of the identified engine (default 0.001 s)")
    f.add_argument("--threads", type=count(1), default=None, metavar="N",
                   help="torch threads for the fit (default: torch's own, one per core); fewer beside other jobs, "
                   "whose cores torch's spinning threads would fight for")
    f.add_argument("--quiet", action="store_true", help="no progress bar and no summary")
    f.set_defaults(func=cmd_fit)

    dg = sub.add_parser("diagnose", help="residual analysis: where the model is wrong and which effect explains it",
                        description="One-step, k-step and free-run errors of an identified model on data (best "
                        "data it was not fitted on), by rod, axis and region of state; residual whiteness "
                        "(Ljung-Box); each effect of the library scored by the share of the residual it would "
                        "remove; the error without and with the model's own effects.")
    dg.add_argument("data", nargs="+", help="dataset .npz, or a recording .csv/.c3d (rod states reconstructed from its "
                    "markers; several files: the takes of one recording)")
    dg.add_argument("--identified", required=True, help="identified-model .json")
    dg.add_argument("--model", default=None, help="MJCF for geometry (ground plane); default: the model's source")
    dg.add_argument("--horizon", type=finite_float(0.0, 1e6, "s", True), default=1.0, metavar="SECONDS", help="free-run horizon (default 1 s)")
    dg.add_argument("--json", action="store_true", help="print the result as JSON")
    dg.add_argument("--out", default=None, metavar="DIR", help="write a report (report.md and PNG plots) here")
    dg.set_defaults(func=cmd_diagnose)

    pr = sub.add_parser("predict", help="free-run the identified model against recorded data",
                        description="Roll the identified model from each recorded initial state with the "
                        "recorded rest lengths and pushes; report position and quaternion error per step.")
    pr.add_argument("data", nargs="+", help="dataset .npz, or a recording .csv/.c3d (rod states reconstructed from its "
                    "markers; several files: the takes of one recording)")
    pr.add_argument("--identified", required=True, help="identified-model .json")
    pr.add_argument("--horizon", type=count(1), default=None, help="steps to roll (default: the whole episode)")
    pr.add_argument("--plot", default=None, help="write an error-vs-step PNG here")
    pr.add_argument("--json", action="store_true", help="machine-readable output")
    pr.set_defaults(func=cmd_predict)

    from tensegrity_gym.reproduce import EXPERIMENTS

    rp = sub.add_parser("reproduce", help="rerun one experiment of the paper: every method a row",
                        description="Rerun one experiment of the paper (Wang et al., L4DC 2020) on data from the "
                        "plant: print its table, write its figures (--out) and rows (--json). Paper-scale data "
                        "by default; --quick scales them down to a few minutes on two cores.")
    rp.add_argument("experiment", choices=tuple(EXPERIMENTS), metavar="EXPERIMENT",
                    help="one of: " + ", ".join(EXPERIMENTS))
    rp.add_argument("--quick", action="store_true", help="small data and budgets (minutes, not hours)")
    rp.add_argument("--seed", type=int, default=0, help="seed of the data and the training (default 0)")
    rp.add_argument("--json", default=None, metavar="OUT", help='write {"experiment", "rows": [...]} here')
    rp.add_argument("--out", default=None, metavar="DIR", help="write the PNG figures into this folder")
    rp.add_argument("--quiet", action="store_true", help="no progress lines")
    rp.set_defaults(func=cmd_reproduce)

    from tensegrity_gym.training import DEFAULT_PHYSICS_DT, DEFAULT_RANDOMIZE, DEFAULT_TIMESTEPS

    t = sub.add_parser("train", help="train an SB3 policy on the identified twin (or on the plant)",
                       description="Train a Stable-Baselines3 policy to roll the robot forward on the identified "
                       "twin, stepped natively batched (one engine call for all envs; MuJoCo is never stepped), "
                       "with observation normalisation saved inside the policy file. --plant trains the same "
                       "algorithm on the MuJoCo plant instead (one process per env), the upper bound to compare "
                       "with. Hyperparameters and why: tensegrity_gym/training.py. While training, the last "
                       "complete policy is kept in OUT's .ckpt.zip (removed at the end; kept on Ctrl-C).")
    t.add_argument("--identified", default=None, metavar="F.json",
                   help="identified model of the twin; with --plant it names the plant (the MJCF it was fitted "
                   "against; default with --plant: the robot preset)")
    t.add_argument("--algo", choices=("ppo", "sac"), default="ppo", help="algorithm (default ppo)")
    t.add_argument("--timesteps", type=int, default=DEFAULT_TIMESTEPS, metavar="N",
                   help=f"environment steps to train for (default {DEFAULT_TIMESTEPS:,}: the budget at which "
                   "policies trained on the twin transfer, README 'Training on the twin')")
    t.add_argument("--seed", type=int, default=None,
                   help="random seed: the same seed gives the same policy (default 0)")
    t.add_argument("--seeds", default=None, metavar="A-B",
                   help="train several seeds (e.g. 0-4 or 0,3,7) in parallel into the folder --out: one "
                   "sub-folder per seed (policy.zip, vecnormalize.pkl, config.json, progress.csv, "
                   "learning_curve.png) and summary.json")
    t.add_argument("--jobs", type=int, default=None, metavar="J",
                   help="with --seeds: local processes at a time (default: one per seed, at most one per core)")
    t.add_argument("--ray", default=None, metavar="ADDRESS",
                   help="with --seeds: run the seeds as Ray tasks on the cluster at ADDRESS (HOST:PORT, 'auto', "
                   "or 'local' for a Ray instance on this machine; pip install 'tensegrity-gym[ray]')")
    t.add_argument("--out", required=True, metavar="P.zip",
                   help="output policy file (with --seeds: output folder)")
    t.add_argument("--plant", action="store_true", help="train on the MuJoCo plant (SubprocVecEnv) instead of the twin")
    t.add_argument("--envs", type=int, default=None, metavar="K",
                   help="envs stepped in parallel (default: ppo 64 on the twin, 8 on the plant; sac 8 / 4)")
    t.add_argument("--rollout", type=int, default=4096, metavar="N",
                   help="ppo: transitions per update over all envs (default 4096 = 64 x 64 twins or 512 x 8 "
                   "plants; a shorter run makes one rollout of its length)")
    t.add_argument("--episode-steps", type=int, default=1000, metavar="T",
                   help="time limit of an episode, control steps (default 1000 = 20 s)")
    t.add_argument("--threads", type=int, default=1, help="torch threads while training (default 1)")
    t.add_argument("--physics-dt", default=DEFAULT_PHYSICS_DT, metavar="auto|S",
                   help="the twin's integration step: 'auto' (default: the coarsest whole multiple of the model's "
                   "dt dividing the 20 ms control period at which the model, linearised at its standing pose, is "
                   "stable at 2.5 times the step; 4 ms for the robot preset), or seconds (e.g. 0.001, the model's "
                   "own dt and the plant's step). README 'Training on the twin' measures what it costs in transfer")
    t.add_argument("--tensorboard", default=None, metavar="DIR", help="write TensorBoard logs here")
    t.add_argument("--randomize", default=DEFAULT_RANDOMIZE, metavar="auto|none|FILE",
                   help="domain randomization of the twin, drawn per env at every reset: 'auto' (default: "
                   "widths from the fit's standard errors, its contact law's unexplained variance and its "
                   "one-step error; never from the plant's MJCF), 'none', or a JSON/YAML FILE of widths "
                   "(tensegrity_gym/randomize.py documents the keys); recorded in the policy file")
    t.add_argument("--xml-file", default=None, metavar="PATH",
                   help="your robot's MJCF (any tensegrity: rods are free bodies, cables spatial tendons, "
                   "actions its actuators or rest-length motors): the plant, and the twin's motors, pose and "
                   "drawing; health derives from it (healthy_z_range='auto')")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=cmd_train)

    im = sub.add_parser("improve", help="rounds of: policy on the plant -> refit with its data -> train on",
                        description="Close the loop through the policy: each round rolls the current policy on the "
                        "plant (recorded in the collect format), measures the twin's error on those states, refits "
                        "the model with them added to the fit's data, and continues training the policy on the new "
                        "twin. Writes OUT/round<k>/ (plant.npz, model.json, policy.zip) and OUT/improve.json "
                        "(per round: plant and twin progress, the twin's one-step and free-run error on the "
                        "policy's states, plant data used so far).")
    im.add_argument("--identified", required=True, metavar="F.json", help="the model the policy was trained on")
    im.add_argument("--data", required=True, metavar="D.npz", help="the dataset the model was fitted on")
    im.add_argument("--policy", required=True, metavar="P.zip", help="the policy to improve")
    im.add_argument("--model", default=None, metavar="M.xml",
                    help="the plant's MJCF (default: the one the model was fitted against)")
    im.add_argument("--rounds", type=int, default=2, help="rounds (default 2)")
    im.add_argument("--episodes", type=int, default=2, help="plant episodes recorded per round (default 2)")
    im.add_argument("--episode-steps", type=int, default=None, metavar="T",
                    help="control steps of each recorded plant episode (default: the policy's own episode, 1000 = "
                    "20 s); shorter episodes spend less robot time a round")
    im.add_argument("--timesteps", type=int, default=100_000, metavar="N",
                    help="training steps on each new twin (default 100,000)")
    im.add_argument("--randomize", default=DEFAULT_RANDOMIZE, metavar="auto|none|FILE",
                    help="randomization while training on (default auto, as 'train')")
    im.add_argument("--effects", default="same", help="effects of the refit: 'same' (the model's, default) or as "
                    "'fit --effects'")
    im.add_argument("--seed", type=int, default=0, help="seed of the plant episodes and the training (default 0)")
    im.add_argument("--out", required=True, metavar="DIR", help="output folder")
    im.add_argument("--actions", choices=("sampled", "mean"), default="sampled",
                    help="how the policy acts on the plant and the twin, as for gap (default sampled)")
    im.add_argument("--quiet", action="store_true", help="no progress lines")
    im.set_defaults(func=cmd_improve)

    g = sub.add_parser("gap", help="the sim-to-sim gap of a policy: twin, plant, random, open loop",
                       description="Run the policy on the twin and on the plant from the same reset seeds, a random "
                       "policy on the plant (the floor), and the open-loop gap (the policy's commands on the plant "
                       "replayed on the twin: centre-of-mass divergence versus time). --json prints twin, plant, "
                       "random_plant (each with return and progress_m, the mean forward distance of the centre of "
                       "mass per episode) and open_loop.")
    g.add_argument("--identified", required=True, metavar="F.json",
                   help="identified model of the twin (the plant is the MJCF it was fitted against)")
    g.add_argument("--policy", required=True, nargs="+", metavar="P.zip",
                   help="policy written by 'tensegrity train', several, or a folder of seeds written by "
                   "'tensegrity train --seeds' (then: each policy's gap, and mean and spread over them)")
    g.add_argument("--episodes", type=int, default=10, metavar="K", help="episodes on each (default 10)")
    g.add_argument("--seed", type=int, default=0, help="episode k resets with seed + k on every env (default 0)")
    g.add_argument("--episode-steps", type=int, default=None, metavar="T",
                   help="time limit of an episode (default: the policy's training limit)")
    g.add_argument("--json", action="store_true", help="machine-readable output")
    g.add_argument("--video", default=None, metavar="DIR",
                   help="write twin.mp4, plant.mp4 and random_plant.mp4 of the first episode here, and "
                   "twin_plant.mp4: the twin (left) beside the plant (right)")
    g.add_argument("--video-every", type=int, default=2, metavar="K",
                   help="one video frame every K control steps, played at 25 fps (default 2: real time; "
                   "K > 2: a time-lapse, fewer frames to render)")
    g.add_argument("--actions", choices=("sampled", "mean"), default="sampled",
                   help="sampled: each action drawn from the policy's distribution, as PPO trained it (the "
                        "same draws on twin and plant; default); mean: the distribution's mean")
    g.add_argument("--threads", type=int, default=1, help="torch threads for the twin (default 1)")
    g.add_argument("--xml-file", default=None, metavar="PATH",
                   help="your robot's MJCF (any tensegrity: rods are free bodies, cables spatial tendons, "
                   "actions its actuators or rest-length motors): the plant, and the twin's motors, pose and "
                   "drawing; health derives from it (healthy_z_range='auto')")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    g.set_defaults(func=cmd_gap)
    return p


# ---------------------------------------------------------------------- helpers
def _physics_dt(args: argparse.Namespace) -> float | str:
    """``--physics-dt auto|S`` parsed: ``"auto"`` or seconds (checked against the model by
    :func:`tensegrity_gym.training.resolve_physics_dt`); CommandError in the option's words."""
    if args.physics_dt == "auto":
        return "auto"
    try:
        h = float(args.physics_dt)
    except ValueError:
        raise CommandError(f"--physics-dt {args.physics_dt}: give 'auto' or a step in seconds (e.g. 0.004)") from None
    if args.plant:
        raise CommandError("--physics-dt sets the twin's integration step: the plant (--plant) steps at its own")
    return h


# ---------------------------------------------------------------------- helpers
def _xml_file_kwargs(args: argparse.Namespace) -> dict:
    """``--xml-file PATH``: the MJCF of the plant and of the twin's source (``backend_kwargs['mjcf']``),
    with the env's health derived from it; ``{}`` without the option."""
    if args.xml_file is None:
        return {}
    _check_readable(args.xml_file)
    from identified.mjcf import read_system

    read_system(args.xml_file)  # a model that is no tensegrity fails here, in one line
    return {"backend_kwargs": {"mjcf": os.path.abspath(args.xml_file)},
            "env_kwargs": {"healthy_z_range": "auto"}}


def _parse_mass(text: str) -> tuple[str, float]:
    name, sep, kg = text.partition("=")
    if not sep:
        raise CommandError(f"--mass expects NAME=KG, got '{text}'")
    try:
        value = float(kg)
    except ValueError:
        raise CommandError(f"--mass {text}: '{kg}' is not a number") from None
    if not (np.isfinite(value) and value > 0):
        raise CommandError(f"--mass {text}: a mass must be finite and positive (kg)")
    return name.strip(), value


def _check_readable(path: str) -> None:
    if not os.path.isfile(path):
        raise CommandError(f"'{path}' does not exist or is not a file")


def _check_writable(path: str, option: str = "--out", inputs: dict[str, str] | None = None) -> None:
    """Refuse an output that is an input of the command, a folder, or in a missing folder."""
    from tensegrity_gym.paths import OutputPathError, check_outputs

    try:
        check_outputs({option: path}, inputs or {})
    except OutputPathError as exc:
        raise CommandError(str(exc)) from None


def _expected_errors() -> tuple[type[BaseException], ...]:
    from identified.dataset import DatasetError
    from identified.model import ModelFileError
    from identified.topology import TopologyError

    # MemoryError: numpy's message names the size it could not allocate
    return (CommandError, DatasetError, TopologyError, ModelFileError, ValueError, OSError, RuntimeError,
            MemoryError)


def _close_progress_bars() -> None:
    """Clear any progress bar left open by the failure, so the error starts its own line."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", None) or []):
        bar.close()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``tensegrity`` console script."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # a bad option (its one line is printed): the status, like any bad input
        if exc.code == 2:
            return 2
        raise
    func: Callable[[argparse.Namespace], None] = args.func
    try:
        _takes(args)
        func(args)
    except KeyboardInterrupt:
        print("tensegrity: interrupted (nothing half-written was kept)", file=sys.stderr)
        return 130
    except _expected_errors() as exc:
        if os.environ.get("TENSEGRITY_DEBUG"):
            raise
        _close_progress_bars()
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"tensegrity: error: {msg}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
