"""Multi-step refinement: fit the parameters to whole stretches of trajectory (simulation error).

The regression fits one step at a time.  When its equations are only approximate (an RK4 plant,
fitted by central differences) or the data are noisy, the parameters that best predict *one* step
are not quite those that best predict *many*.  :func:`refine` starts from the regression result
and minimises the error of free runs of the differentiable engine over windows of ``horizon``
steps (started from recorded states, driven by the recorded rest lengths and pushes), by L-BFGS
on the logarithms of the parameters (they stay positive) -- the effects' parameters too, the signed
ones (a force field, a slack correction) as they are -- with gradients through the engine.

Noisy data (the dataset records its sensor noise): the recorded states are then measurements,
not exact states, and fitting free runs started from them with positions and orientations held
is biased (measured: every K, c, M within 0.4 % from the regression, 1.5-2.2 % after such a
refinement).  The refinement is then the output-error maximum-likelihood fit: every window's whole
initial state is free (in units of its noise), the cost is the sum of squared errors of all four
recorded channels, each divided by its noise variance, and the initial states are fitted first
with the parameters held (with the regression's parameters the ML cost per rod and step then
sits at its expected value, about 12: four channels of three components).  Every window of the
data is used, up to ``max_windows_noisy``.

The global scale is invisible to states (see :mod:`identified.fit.regression`); the anchor that
fixed it in the regression is kept: a known mass or ``h = 1`` are held fixed, a known or
normalised total mass is restored by rescaling at the end.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import torch

from identified.dataset import Dataset
from identified.engine import SpringRodEngine, SpringRodParams
from identified.model import IdentifiedModel
from identified.rotation import quat_exp, quat_multiply, quat_normalize, quat_to_matrix
from identified.twin import effects_from_model, params_from_model

__all__ = ["check_refinable", "refine", "window_starts"]


def check_refinable(data: Dataset) -> bool:
    """Whether ``data`` calls for the noisy-data refinement (it records sensor noise); raises
    ValueError when it records noise on some channels only (the cost needs all four)."""
    sigma = np.asarray(data.noise, dtype=np.float64)
    noisy = bool(np.any(sigma > 0))
    if noisy and not np.all(sigma > 0):
        raise ValueError(f"the dataset records noise {sigma.tolist()} on some channels only: the refinement's "
                         "maximum-likelihood cost needs the noise of pos, vel, quat and angvel")
    return noisy


def window_starts(data: Dataset, horizon: int, max_windows: int) -> tuple[np.ndarray, np.ndarray]:
    """Episode and start index of up to ``max_windows`` windows of ``horizon`` steps, spread evenly."""
    per = data.n_steps // horizon
    if per < 1:
        raise ValueError(f"episodes of {data.n_steps} steps are shorter than the refinement horizon ({horizon})")
    ep, st = np.meshgrid(np.arange(data.n_episodes), np.arange(per) * horizon, indexing="ij")
    ep, st = ep.ravel(), st.ravel()
    if ep.size > max_windows:
        keep = np.linspace(0, ep.size - 1, max_windows).round().astype(int)
        ep, st = ep[keep], st[keep]
    return ep, st


def refine(
    model: IdentifiedModel,
    data: Dataset,
    horizon: int = 100,
    max_windows: int = 128,
    iterations: int = 40,
    progress: bool = False,
    max_windows_noisy: int = 512,
) -> IdentifiedModel:
    """Refine ``model`` by minimising the free-run error over windows of ``horizon`` steps.

    At most ``iterations`` L-BFGS iterations (each one or more rollouts of every window, forward
    and backward); ``progress`` shows a bar over the rollouts.  The cost grows with ``max_windows``
    x ``horizon`` and with the integrator's stages (RK4: four dynamics evaluations per step).
    On data that record sensor noise, the output-error maximum-likelihood fit of the module
    docstring, over up to ``max_windows_noisy`` windows (and ``iterations`` more for the initial
    states first).
    """
    t0 = time.perf_counter()
    horizon = min(horizon, data.n_steps)
    noisy = check_refinable(data)
    ep, st = window_starts(data, horizon, max_windows_noisy if noisy else max_windows)
    idx = st[:, None] + np.arange(horizon + 1)[None, :]  # (W, H+1)
    take = lambda a, n: torch.as_tensor(a[ep[:, None], idx[:, :n]])
    pos, quat, vel, angvel = (take(getattr(data, k), horizon + 1) for k in ("pos", "quat", "vel", "angvel"))
    rest = take(data.rest_length, horizon)
    fu, ru = take(data.push_force, horizon), take(data.push_point, horizon)
    has_push = bool(torch.any(fu != 0))

    length = float(np.mean([r.length for r in model.topology.rods]))
    base = params_from_model(model)
    anchor = model.scale.get("anchor", "normalised")
    names = ["stiffness", "damping", "mass", "inertia"] + (["control_scale"] if has_push and anchor != "push" else [])
    def start(v: torch.Tensor) -> torch.Tensor:
        # a weakly identified value (e.g. a rod's axial inertia) may come out of the regression
        # non-positive: start it at a small positive value instead
        floor = 1e-3 * v.abs().max().clamp_min(1e-12)
        return torch.log(torch.where(v > 0, v, floor))

    logs = {n: start(getattr(base, n)).clone().requires_grad_(True) for n in names}
    # multiple shooting: each window's initial velocities are free too (they absorb the half-step
    # phase of another integrator and the noise of the recorded start); on noisy data its whole
    # initial state, each channel in units of its noise
    dv0 = torch.zeros_like(vel[:, 0], requires_grad=True)
    dw0 = torch.zeros_like(angvel[:, 0], requires_grad=True)
    dp0 = torch.zeros_like(pos[:, 0], requires_grad=noisy)
    dq0 = torch.zeros_like(pos[:, 0], requires_grad=noisy)  # rotation vector, world frame
    starts = [dp0, dq0, dv0, dw0] if noisy else [dv0, dw0]
    sp, sv, sq, sw = (float(x) for x in data.noise) if noisy else (1.0, 1.0, 1.0, 1.0)
    rot_rec = quat_to_matrix(quat)
    held_mass = None
    if anchor == "mass":
        held_mass = model.topology.rod_names.index(model.scale["rod"])

    def params() -> SpringRodParams:
        vals = {n: torch.exp(v) for n, v in logs.items()}
        if held_mass is not None:
            m = vals["mass"].clone()
            m[held_mass] = base.mass[held_mass]
            vals["mass"] = m
        return replace(base, **vals)


    # the effects' parameters refine with the rest: signed ones as they are, the others on their
    # logarithms (they stay non-negative), pinned ones held
    effects = effects_from_model(model)
    eff_vars: list[tuple] = []
    for e in effects:
        if e.values is None:
            continue
        v0 = torch.as_tensor(e.values, dtype=torch.float64)
        signed = torch.as_tensor(e.signed_mask())
        pinned = torch.as_tensor(e.pinned())
        raw = torch.where(signed, v0, start(v0)).clone().requires_grad_(True)
        eff_vars.append((e, raw, signed, pinned, v0))

    def bind_effects() -> None:
        for e, raw, signed, pinned, v0 in eff_vars:
            e.bind(torch.where(pinned, v0, torch.where(signed, raw, torch.exp(raw))))

    def loss_fn() -> torch.Tensor:
        bind_effects()
        eng = SpringRodEngine(model.topology, params(), data.dt, integrator=model.integrator, effects=effects)
        if not noisy:
            s0 = eng.state(pos[:, 0], quat[:, 0], vel[:, 0] + dv0, angvel[:, 0] + dw0)
            out = eng.rollout(s0, rest, fu, ru)
            ep_ = (out.pos - pos) / length
            # orientation error through rotation matrices: sign-free and smooth
            er = quat_to_matrix(out.quat) - rot_rec
            return ep_.square().mean() + er.square().mean()
        q0 = quat_normalize(quat_multiply(quat_exp(dq0 * sq), quat[:, 0]))
        s0 = eng.state(pos[:, 0] + dp0 * sp, q0, vel[:, 0] + dv0 * sv, angvel[:, 0] + dw0 * sw)
        out = eng.rollout(s0, rest, fu, ru)
        # ||R - R_rec||_F^2 = 2 |rotation error|^2 for small errors: per component, variance sq^2
        cost = ((out.pos - pos).square().sum() / sp**2 + (out.vel - vel).square().sum() / sv**2
                + (quat_to_matrix(out.quat) - rot_rec).square().sum() / (2 * sq**2)
                + (out.angvel - angvel).square().sum() / sw**2)
        return cost / pos[..., 0].numel()  # per rod and instant: ~12 at the optimum

    max_eval = iterations * 5 // 4  # LBFGS's own default, named so the progress bar counts the same
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=(2 if noisy else 1) * max_eval, desc="refine", unit="rollout", leave=False)

    def run(variables: list[torch.Tensor], norm: float) -> None:
        opt = torch.optim.LBFGS(variables, lr=1.0, max_iter=iterations, max_eval=max_eval,
                                line_search_fn="strong_wolfe", tolerance_grad=1e-12, tolerance_change=1e-14,
                                history_size=20)

        def closure() -> torch.Tensor:
            opt.zero_grad()
            loss = loss_fn() / norm
            loss.backward()
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{loss.item() * norm:.3g}")
            return loss

        opt.step(closure)

    with torch.no_grad():
        before = float(loss_fn())
    if noisy:  # the initial states first, the parameters held (they start far from optimal)
        for v in logs.values():
            v.requires_grad_(False)
        run(starts, 1.0)
        for v in logs.values():
            v.requires_grad_(True)
        with torch.no_grad():
            before = float(loss_fn())  # the regression's parameters at their best initial states
    run(list(logs.values()) + [v[1] for v in eff_vars] + starts, max(before, 1e-300))  # a loss of order one
    if bar is not None:
        bar.close()
    with torch.no_grad():
        p = params()
        after = float(loss_fn())
    keep = not np.isfinite(after) or after > before  # never return something worse than the start
    if keep:
        p, after = base, before
    stiffness, damping = p.stiffness.detach().numpy(), p.damping.detach().numpy()
    mass, inertia = p.mass.detach().numpy(), p.inertia.detach().numpy()
    h = float(p.control_scale.detach())
    lam = 1.0
    if anchor in ("total_mass", "normalised"):
        lam = float(model.mass.sum() / mass.sum())
    effect_json = []
    for e, raw, signed, pinned, v0 in eff_vars:
        with torch.no_grad():
            th = v0 if keep else torch.where(pinned, v0, torch.where(signed, raw, torch.exp(raw)))
        e.bind(None)
        e.values = th.numpy() * np.where(e.mass_scaled_mask(), lam, 1.0)
        e.stderr = None
        effect_json.append(e.to_json())
    effect_json += [x for x in model.effects if x.get("parameters") is None]
    out = replace(
        model,
        effects=effect_json if eff_vars else list(model.effects),
        stiffness=stiffness * lam, damping=damping * lam, mass=mass * lam, inertia=inertia * lam,
        control_scale=h * lam if anchor != "push" else h,
        stderr={},  # the regression's error bars no longer apply
        metrics=dict(model.metrics),
    )
    if model.full_inertia:  # the refined diagonal about the centre of mass, with the products it held
        out.set_inertia_about_com(out.inertia, p.inertia_products.detach().numpy() * lam)
    out.metrics["refine"] = {
        "horizon": horizon, "windows": int(ep.size), "loss_before": before, "loss_after": after,
        "cost": "output-error maximum likelihood (noise-weighted, free initial states)" if noisy
        else "free-run position and orientation error (free initial velocities)",
        "seconds": round(time.perf_counter() - t0, 3),
    }
    return out
