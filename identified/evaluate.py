"""How well an identified model predicts recorded data: one place for each error measure.

Used by the fit (its effect search and metrics), ``predict`` and the diagnosis.

* **Free run** (:func:`rollout`, :func:`rollout_errors`): the model started from each episode's
  recorded initial state and driven by the recorded rest lengths and pushes; the error per step is
  the distance between predicted and recorded rod centres of mass (m) and the sign-invariant
  quaternion distance (:func:`quat_distance`), averaged over episodes and rods (the paper's
  curves).
* **Windows** (:func:`window_error`): the same from recorded states every ``stride`` steps, over
  short windows of ``steps`` steps (one batched rollout); a cheap short-horizon error.
* **k steps** (:func:`k_step_errors`): the error after exactly ``k`` free steps from recorded
  states spread over the data.
* **One step** (:func:`one_step_state_errors`): the RMS error of one engine step from every
  recorded state, per state component.
* **Residual wrench** (:func:`residual_wrench`, :func:`relative_one_step_errors`): the wrench the
  model misses at a recorded instant, ``M (a - a_model)`` (N, world) and ``I (α_b - α_b,model)``
  (N m, rod frame), with the recorded accelerations of :func:`identified.samples.iter_chunks`, beside
  the recorded inertial wrench ``M (a - g)``, ``I α_b + ω_b × I ω_b`` (Eqs. 3-4 read backwards,
  :func:`identified.engine.accelerations.inertial_wrench`).  For the Euler integrator the first is
  exactly the recorded inertial wrench less the model's forces.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np
import torch

from identified.dataset import Dataset
from identified.engine import SpringRodEngine
from identified.engine.accelerations import inertial_wrench
from identified.engine.actuators import tendon_forces
from identified.engine.engine import StepTerms
from identified.engine.integration import RodState
from identified.jsonsafe import finite_or_none
from identified.model import IdentifiedModel
from identified.rotation import matrix_apply
from identified.samples import Chunk, iter_chunks
from identified.twin import effects_from_model, engine_from_model

__all__ = [
    "OneStepParts",
    "ResidualWrench",
    "actuator_forces",
    "k_step_errors",
    "one_step_data",
    "one_step_parts",
    "one_step_state_errors",
    "push_points",
    "quat_distance",
    "recorded_samples",
    "relative_errors_from_parts",
    "relative_one_step_errors",
    "residual_wrench",
    "rollout",
    "rollout_errors",
    "window_error",
]


def quat_distance(q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """Sign-invariant quaternion distance ``min(|q - q_ref|, |q + q_ref|)`` over the last axis."""
    return np.minimum(np.linalg.norm(q - q_ref, axis=-1), np.linalg.norm(q + q_ref, axis=-1))


# ---------------------------------------------------------------------- free runs
def rollout(model: IdentifiedModel, data: Dataset, horizon: int | None = None,
            episodes: slice | list[int] = slice(None), effects: Sequence[Any] = ()) -> RodState:
    """Free-run the model from each recorded initial state: states (E, H + 1, R, .) as numpy-able tensors."""
    H = data.n_steps if horizon is None else min(int(horizon), data.n_steps)
    if H < 1:
        raise ValueError(f"horizon must be >= 1 step, got {horizon}")
    if data.rod_names != model.topology.rod_names or data.tendon_names != model.topology.spring_names:
        raise ValueError("the dataset's rods/tendons do not match the identified model's")
    eng = engine_from_model(model, effects=effects)
    ep = episodes
    s0 = eng.state(data.pos[ep, 0], data.quat[ep, 0], data.vel[ep, 0], data.angvel[ep, 0])
    with torch.no_grad():
        return eng.rollout(s0, data.rest_length[ep, :H], data.push_force[ep, :H], data.push_point[ep, :H])


def rollout_errors(model: IdentifiedModel, data: Dataset, horizon: int | None = None,
                   effects: Sequence[Any] = ()) -> dict[str, Any]:
    """Position (m) and quaternion error per step of the free run, averaged over episodes and rods.

    ``per_step``: the curves over steps ``0..H`` (step 0 is the recorded state: error 0);
    ``pos_mean``, ``quat_mean``: their means over ``0..H``, ``pos_final``, ``quat_final``: step
    ``H``'s; ``pos_mean_after_start``: the position error's mean over steps ``1..H`` (the
    diagnosis's free-run error).  Every summary is ``inf`` where a trajectory diverged.
    """
    states = rollout(model, data, horizon, effects=effects)
    H = states.pos.shape[1] - 1
    with np.errstate(all="ignore"):  # a diverged run is inf, not a warning
        pe = np.linalg.norm(states.pos.numpy() - data.pos[:, : H + 1], axis=-1).mean(axis=(0, 2))
        qe = quat_distance(states.quat.numpy(), data.quat[:, : H + 1]).mean(axis=(0, 2))
    finite = bool(np.all(np.isfinite(pe)) and np.all(np.isfinite(qe)))
    pos_finite = bool(np.all(np.isfinite(pe)))
    inf = float("inf")
    return {
        "horizon": H,
        "episodes": data.n_episodes,
        "dt": data.dt,
        "pos_mean": float(np.mean(pe)) if finite else inf,
        "pos_final": float(pe[-1]) if finite else inf,
        "quat_mean": float(np.mean(qe)) if finite else inf,
        "quat_final": float(qe[-1]) if finite else inf,
        "pos_mean_after_start": float(pe[1:].mean()) if pos_finite else inf,
        "per_step": {"pos": pe, "quat": qe},
    }


def window_error(model: IdentifiedModel, data: Dataset, steps: int, stride: int | None = None) -> float:
    """Mean position error (m) of free runs of ``steps`` steps from recorded states every ``stride``
    steps of every episode (one batched rollout; default stride ``max(steps, T // 20)``);
    ``inf`` when a run diverged or the episodes are shorter than ``steps``."""
    stride = stride or max(steps, data.n_steps // 20)
    starts = np.arange(0, data.n_steps - steps + 1, stride)
    if starts.size == 0:
        return float("inf")
    idx = starts[:, None] + np.arange(steps + 1)[None, :]
    take = lambda a, n: a[:, idx[:, :n]].reshape((-1, n) + a.shape[2:])
    eng = engine_from_model(model)
    s0 = eng.state(*(take(getattr(data, k), 1)[:, 0] for k in ("pos", "quat", "vel", "angvel")))
    with torch.no_grad():
        out = eng.rollout(s0, take(data.rest_length, steps), take(data.push_force, steps), take(data.push_point, steps))
    with np.errstate(over="ignore", invalid="ignore"):  # a diverged run is inf, not a warning
        err = np.linalg.norm(out.pos.numpy() - take(data.pos, steps + 1), axis=-1).mean()
    return float(err) if np.isfinite(err) else float("inf")


def k_step_errors(model: IdentifiedModel, data: Dataset, ks: Sequence[int] = (1, 10, 100),
                  max_starts: int = 256) -> dict[str, Any]:
    """Position (m) and quaternion error after exactly ``k`` free steps, for each ``k`` of ``ks``,
    from at most ``max_starts`` recorded states spread evenly over the (episode, step) pairs; means
    over starts and rods (``None`` where a run diverged; the entry ``None`` when ``k`` exceeds the
    episodes)."""
    eng = engine_from_model(model)
    E, T = data.n_episodes, data.n_steps
    out: dict[str, Any] = {}
    for k in ks:
        if k > T:
            out[str(k)] = None
            continue
        n_pairs = E * (T - k + 1)
        pick = np.unique(np.linspace(0, n_pairs - 1, min(n_pairs, max_starts)).round().astype(int))
        ep, t0 = np.divmod(pick, T - k + 1)
        span = t0[:, None] + np.arange(k)
        s0 = eng.state(data.pos[ep, t0], data.quat[ep, t0], data.vel[ep, t0], data.angvel[ep, t0])
        with torch.no_grad(), np.errstate(all="ignore"):
            st = eng.rollout(s0, data.rest_length[ep[:, None], span], data.push_force[ep[:, None], span],
                             data.push_point[ep[:, None], span])
            pe = np.linalg.norm(st.pos[:, -1].numpy() - data.pos[ep, t0 + k], axis=-1)
            qe = quat_distance(st.quat[:, -1].numpy(), data.quat[ep, t0 + k])
        out[str(k)] = {"pos": finite_or_none(pe.mean()), "quat": finite_or_none(qe.mean()), "starts": len(pick)}
    return out


# ---------------------------------------------------------------------- one step
def one_step_state_errors(model: IdentifiedModel, data: Dataset, max_steps: int = 20000,
                          effects: Sequence[Any] = ()) -> dict[str, float]:
    """RMS error of one engine step from every recorded state (the first ``max_steps // E`` steps
    of every episode): ``pos`` (m), ``vel`` (m/s), ``angvel`` (rad/s) as vector norms, ``quat``
    as :func:`quat_distance`."""
    eng = engine_from_model(model, effects=effects)
    T = min(data.n_steps, max(1, max_steps // max(data.n_episodes, 1)))
    sl = (slice(None), slice(0, T))
    flat = lambda a: a[sl].reshape(-1, *a.shape[2:])
    s = eng.state(flat(data.pos), flat(data.quat), flat(data.vel), flat(data.angvel))
    nxt = (slice(None), slice(1, T + 1))
    with torch.no_grad():
        out = eng.step(s, flat(data.rest_length), flat(data.push_force), flat(data.push_point))
    tgt = {k: getattr(data, k)[nxt].reshape(-1, *getattr(data, k).shape[2:]) for k in ("pos", "quat", "vel", "angvel")}
    res = {}
    for k in ("pos", "vel", "angvel"):
        res[k] = float(np.sqrt(np.mean(np.sum((getattr(out, k).numpy() - tgt[k]) ** 2, axis=-1))))
    res["quat"] = float(np.sqrt(np.mean(quat_distance(out.quat.numpy(), tgt["quat"]) ** 2)))
    return res


class ResidualWrench(NamedTuple):
    """The wrench a model misses at recorded instants (shapes (N, R, 3)).

    ``force``: ``M (a - a_model)`` N, world; ``torque_body``: ``I (α_b - α_b,model)`` N m, rod
    frame; ``inertial_force``, ``inertial_torque_body``: the recorded inertial wrench
    ``M (a - g)``, ``I α_b + ω_b × I ω_b`` (what every force but gravity must add); ``terms``: the
    model's dynamics at those states (its forces, accelerations and step context).
    """

    force: torch.Tensor
    torque_body: torch.Tensor
    inertial_force: torch.Tensor
    inertial_torque_body: torch.Tensor
    terms: StepTerms

    def missing_world(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The recorded inertial wrench less the model's forces, both world frame: what a force
        the model lacks must supply (force N, torque N m)."""
        rot = self.terms.ctx.rot
        return self.inertial_force - self.terms.force, matrix_apply(rot, self.inertial_torque_body) - self.terms.torque


def recorded_samples(data: Dataset, scheme: str, device: str = "cpu") -> tuple[Chunk, int, torch.Tensor | None]:
    """Every recorded instant of ``data`` as one :class:`~identified.samples.Chunk` (flattened over
    episode and time), the number of episodes, and the pushes' points for the engine (``None`` for
    the central scheme, whose chunk holds the pushes' torques itself)."""
    ch, n_ep = next(iter_chunks(data, data.n_episodes * data.n_steps + 1, scheme, device=device))
    return ch, n_ep, push_points(data, ch, n_ep, scheme)


def push_points(data: Dataset, ch: Chunk, n_ep: int, scheme: str) -> torch.Tensor | None:
    """The pushes' points of the instants of ``ch`` (``n_ep`` whole episodes of ``data``) for the
    engine, (N, R, 3); ``None`` for the central scheme."""
    if scheme != "forward":
        return None
    n_t = ch.pos.shape[0] // n_ep
    return torch.as_tensor(data.push_point[:, :n_t].reshape(-1, data.n_rods, 3), dtype=ch.pos.dtype,
                           device=ch.pos.device)


def residual_wrench(engine: SpringRodEngine, ch: Chunk, push_point: torch.Tensor | None,
                    tendon_force: torch.Tensor | None = None) -> ResidualWrench:
    """The model's residual wrench at the recorded instants of ``ch`` (:class:`ResidualWrench`).

    With ``push_point`` ``None`` (the central scheme) the engine applies the pushes at the centres
    of mass, and the recorded push torque (``ch.push_torque_body``) is taken out of the torque
    residual: the engine's dynamics did not see it, the record did.  ``tendon_force`` (N, S): the
    actuators' force on each tendon at those instants (:func:`model_inputs`), ``None``: none.
    """
    p = engine.params
    with torch.no_grad():
        terms = engine.dynamics(RodState(ch.pos, ch.quat, ch.vel, ch.angvel), ch.rest, ch.push_force, push_point,
                                tendon_force)
        force = p.mass[:, None] * (ch.acc - terms.lin_acc)
        torque_body = p.inertia * (ch.alpha_body - terms.ang_acc_body)
        if push_point is None:
            torque_body = torque_body - p.control_scale * ch.push_torque_body
        ref_f, ref_t = inertial_wrench(p.mass, p.inertia, p.gravity, ch.acc, ch.alpha_body, ch.angvel_body)
    return ResidualWrench(force, torque_body, ref_f, ref_t, terms)


def actuator_forces(model: IdentifiedModel, data: Dataset) -> np.ndarray | None:
    """(E, T, S) the force of ``model``'s MuJoCo actuators on each tendon at every step of
    ``data``, from its recorded commands (:func:`identified.engine.actuators.tendon_forces`: a
    filter's activation runs through each whole episode); ``None`` for a model without actuators."""
    if not model.actuators:
        return None
    return tendon_forces(data.ctrl, data.dt, data.actuator_names, model.actuators, model.topology.spring_names)


def model_inputs(model: IdentifiedModel, data: Dataset, ch: Chunk) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What a model's engine takes at the instants of ``ch`` (whole episodes of ``data``, from the
    start): every tendon's rest length -- the model's own for a passive spring, the recorded
    command for a motor-driven cable -- (N, S), and its actuators' tendon forces (N, S) from the
    recorded commands (:func:`actuator_forces`), ``None`` without actuators."""
    passive = torch.as_tensor([not s.actuated for s in model.topology.springs])
    rest = torch.where(passive, torch.as_tensor(model.rest_length, dtype=ch.rest.dtype), ch.rest)
    f = actuator_forces(model, data)
    if f is None:
        return rest, None
    n_t = ch.pos.shape[0] // data.n_episodes
    return rest, torch.as_tensor(f[:, data.n_steps - n_t:].reshape(-1, f.shape[-1]), dtype=ch.pos.dtype)


class OneStepParts(NamedTuple):
    """One model's share of :func:`relative_one_step_errors`, computed on its own (in a worker of
    the effect search) and combined with the other models' by :func:`relative_errors_from_parts`."""

    scheme: str
    residual: torch.Tensor  # (N, R, 6): residual force and rod-frame torque
    reference: torch.Tensor  # (N, R, 6): the recorded inertial wrench with the model's mass and inertia
    touched: torch.Tensor  # (N, R) bool: rows a residual-strategy effect of the model touches


def one_step_data(data: Dataset, max_steps: int = 20_000) -> Dataset:
    """The first episodes of ``data`` the one-step errors are measured on: at most ``max_steps``
    instants (at least one episode)."""
    per = max(1, min(data.n_episodes, max_steps // max(data.n_steps, 1)))
    return data.select(episodes=slice(0, per))


def one_step_parts(model: IdentifiedModel, data: Dataset, scheme: str | None = None) -> OneStepParts:
    """``model``'s residual and recorded wrench at every recorded instant of ``data`` (already cut
    by :func:`one_step_data`) and the rows its residual-strategy effects touch; ``scheme``: how the
    recorded accelerations are formed (default the model's own)."""
    scheme = scheme or model.metrics.get("scheme") or "forward"
    ch, _, point = recorded_samples(data, scheme)
    state = RodState(ch.pos, ch.quat, ch.vel, ch.angvel)
    touched = torch.zeros(ch.pos.shape[:2], dtype=torch.bool)
    with torch.no_grad():
        rest, tendon_force = model_inputs(model, data, ch)
        rw = residual_wrench(engine_from_model(model, dtype=torch.float64), replace(ch, rest=rest), point,
                             tendon_force)
        res = torch.cat((rw.force, rw.torque_body), -1)
        ref = torch.cat((rw.inertial_force, rw.inertial_torque_body), -1)
        for e in effects_from_model(model):
            rows = e.rows_affected(state, rw.terms.ctx) if e.stage != "joint" else None
            if rows is not None:
                touched |= rows
    return OneStepParts(scheme, res, ref, touched)


def relative_errors_from_parts(parts: Sequence[OneStepParts | None]) -> list[float]:
    """The relative one-step errors of :func:`relative_one_step_errors` from each model's
    :class:`OneStepParts` (``None``: no model, ``inf``), on the rows no model's residual-strategy
    effect touches."""
    fitted = [p for p in parts if p is not None]
    if not fitted:
        return [float("inf")] * len(parts)
    keep = torch.ones(fitted[0].touched.shape, dtype=torch.bool)
    for p in fitted:
        keep &= ~p.touched
    errs = []
    for p in parts:
        if p is None or not bool(keep.any()):
            errs.append(float("inf"))
            continue
        res, ref = p.residual[keep], p.reference[keep]
        e = float(res.square().mean().sqrt() / ref.square().mean().sqrt().clamp_min(1e-300))
        errs.append(e if np.isfinite(e) else float("inf"))
    return errs


def relative_one_step_errors(models: Sequence[IdentifiedModel | None], data: Dataset,
                             max_steps: int = 20_000) -> list[float]:
    """Each model's one-step error on ``data``: the RMS of its residual wrench (force and rod-frame
    torque together) relative to the RMS of the recorded inertial wrench, on the same rows for
    every model -- the rods no model's residual-strategy effect touches (ground contact's rows are
    left out: its law, not exact, would mask what another effect explains).

    ``inf`` for a model missing or whose residual is not finite; the first episodes, at most
    ``max_steps`` instants (at least one episode)."""
    data = one_step_data(data, max_steps)
    fitted = [m for m in models if m is not None]
    if not fitted:
        return [float("inf")] * len(models)
    scheme = fitted[0].metrics.get("scheme") or "forward"
    return relative_errors_from_parts([None if m is None else one_step_parts(m, data, scheme) for m in models])
