"""Multi-step refinement: fit the parameters to whole stretches of trajectory (simulation error).

The regression fits one step at a time.  When its equations are only approximate (an RK4 plant,
fitted by central differences) or the data are noisy, the parameters that best predict *one* step
are not quite those that best predict *many*.  :func:`refine` starts from the regression result
and minimises the error of free runs of the differentiable engine over windows of ``horizon``
steps (started from recorded states, driven by the recorded rest lengths and pushes), by L-BFGS
on the logarithms of the parameters (they stay positive), with gradients through the engine.

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
from identified.rotation import quat_to_matrix

__all__ = ["refine", "window_starts"]


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
) -> IdentifiedModel:
    """Refine ``model`` by minimising the free-run error over windows of ``horizon`` steps.

    At most ``iterations`` L-BFGS iterations (each one or more rollouts of every window, forward
    and backward); ``progress`` shows a bar over the rollouts.  The cost grows with ``max_windows``
    x ``horizon`` and with the integrator's stages (RK4: four dynamics evaluations per step).
    """
    t0 = time.perf_counter()
    horizon = min(horizon, data.n_steps)
    ep, st = window_starts(data, horizon, max_windows)
    idx = st[:, None] + np.arange(horizon + 1)[None, :]  # (W, H+1)
    take = lambda a, n: torch.as_tensor(a[ep[:, None], idx[:, :n]])
    pos, quat, vel, angvel = (take(getattr(data, k), horizon + 1) for k in ("pos", "quat", "vel", "angvel"))
    rest = take(data.rest_length, horizon)
    fu, ru = take(data.push_force, horizon), take(data.push_point, horizon)
    has_push = bool(torch.any(fu != 0))

    length = float(np.mean([r.length for r in model.topology.rods]))
    base = SpringRodParams.from_model(model)
    anchor = model.scale.get("anchor", "normalised")
    names = ["stiffness", "damping", "mass", "inertia"] + (["control_scale"] if has_push and anchor != "push" else [])
    def start(v: torch.Tensor) -> torch.Tensor:
        # a weakly identified value (e.g. a rod's axial inertia) may come out of the regression
        # non-positive: start it at a small positive value instead
        floor = 1e-3 * v.abs().max().clamp_min(1e-12)
        return torch.log(torch.where(v > 0, v, floor))

    logs = {n: start(getattr(base, n)).clone().requires_grad_(True) for n in names}
    # multiple shooting: each window's initial velocities are free too (they absorb the half-step
    # phase of another integrator and the noise of the recorded start)
    dv0 = torch.zeros_like(vel[:, 0], requires_grad=True)
    dw0 = torch.zeros_like(angvel[:, 0], requires_grad=True)
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

    def loss_fn() -> torch.Tensor:
        eng = SpringRodEngine(model.topology, params(), data.dt, integrator=model.integrator)
        s0 = eng.state(pos[:, 0], quat[:, 0], vel[:, 0] + dv0, angvel[:, 0] + dw0)
        out = eng.rollout(s0, rest, fu, ru)
        ep_ = (out.pos - pos) / length
        # orientation error through rotation matrices: sign-free and smooth
        er = quat_to_matrix(out.quat) - quat_to_matrix(quat)
        return ep_.square().mean() + er.square().mean()

    opt = torch.optim.LBFGS(list(logs.values()) + [dv0, dw0], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-14, history_size=20)
    with torch.no_grad():
        before = float(loss_fn())
    norm = max(before, 1e-300)  # work on a loss of order one

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=opt.defaults["max_eval"], desc="refine", unit="rollout", leave=False)

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = loss_fn() / norm
        loss.backward()
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss.item() * norm:.3g}")
        return loss

    opt.step(closure)
    if bar is not None:
        bar.close()
    with torch.no_grad():
        p = params()
        after = float(loss_fn())
    if not np.isfinite(after) or after > before:  # never return something worse than the start
        p, after = base, before
    stiffness, damping = p.stiffness.detach().numpy(), p.damping.detach().numpy()
    mass, inertia = p.mass.detach().numpy(), p.inertia.detach().numpy()
    h = float(p.control_scale.detach())
    lam = 1.0
    if anchor in ("total_mass", "normalised"):
        lam = float(model.mass.sum() / mass.sum())
    out = replace(
        model,
        stiffness=stiffness * lam, damping=damping * lam, mass=mass * lam, inertia=inertia * lam,
        control_scale=h * lam if anchor != "push" else h,
        stderr={},  # the regression's error bars no longer apply
        metrics=dict(model.metrics),
    )
    out.metrics["refine"] = {
        "horizon": horizon, "windows": int(ep.size), "loss_before": before, "loss_after": after,
        "seconds": round(time.perf_counter() - t0, 3),
    }
    return out
