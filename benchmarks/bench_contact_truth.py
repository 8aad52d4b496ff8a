"""What the ground-contact law's form misses, against the plant's own contact forces.

    python benchmarks/bench_contact_truth.py [--episodes 4] [--steps 3000] [--stride 20] [--seed 99]

A developer's check of the law, not identification (it reads MuJoCo's internals, which the fit
never does): the robot preset is collected as ``tensegrity collect`` does (random commands, 50 N
pushes every 200 steps); at every ``--stride``-th step the plant is put in the recorded state and
``mj_forward`` gives MuJoCo's contact wrench on each rod (``mj_contactForce``, summed over its
contacts, torque about its centre of mass) and the acceleration every other force gives it
(``qacc_smooth``). Each law (:class:`identified.effects.ground_contact.GroundContact`,
:class:`identified.effects.pyramid_contact.PyramidContact`) is then fitted *directly* to that wrench with the true masses, inertias and ``qacc_smooth``, so everything it
leaves is its form's: printed as the relative RMS error of force and torque over the rod-instants
in contact, split into normal and tangential force and by the state of MuJoCo's pyramidal friction
cone (a friction or rolling edge at zero force: the contact slides or rolls at its bound).
About 2 min on one core. Figures, not assertions.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import NamedTuple

import numpy as np
import torch

from identified.effects.ground_contact import GroundContact, read_contact_geometry
from identified.effects.pyramid_contact import PyramidContact
from identified.rotation import quat_to_matrix
from identified.state import RodState
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import build_model
from tensegrity_gym.plant import MujocoPlant


@dataclasses.dataclass
class _Params:
    """The plant's rods as the laws read them (true masses and principal inertias)."""

    mass: torch.Tensor
    inertia: torch.Tensor
    com: torch.Tensor | None = None
    inertia_products: torch.Tensor | None = None


class _Context(NamedTuple):
    """The step context the laws read: the rods, their rotations and every other force's accelerations."""

    params: _Params
    rot: torch.Tensor
    angvel_body: torch.Tensor | None
    base_lin_acc: torch.Tensor
    base_ang_acc_body: torch.Tensor


def contact_wrenches(plant: MujocoPlant, data, stride: int) -> dict[str, np.ndarray]:
    """MuJoCo's contact wrench per rod at every ``stride``-th recorded step, with ``qacc_smooth``
    and, per rod, the number of contacts and whether a sliding or rolling edge is at zero force."""
    d = plant.data
    R, out = plant.n_rods, {k: [] for k in ("force", "torque", "lin", "ang", "count", "slide", "roll", "state", "episode")}
    E, T = data.rest_length.shape[:2]
    for e in range(E):
        for t in range(0, T, stride):
            plant._write_rest(data.rest_length[e, t])
            d.xfrc_applied[:] = 0.0
            d.xfrc_applied[plant._bid] = plant._push_wrench(data.push_force[e, t], data.push_point[e, t])
            state = RodState(data.pos[e, t], data.quat[e, t], data.vel[e, t], data.angvel[e, t])
            plant.set_states(state)
            f, tau, contacts = plant.contact_wrenches()
            count, slide, roll = np.array([len(c) for c in contacts]), np.zeros(R, bool), np.zeros(R, bool)
            for r, rod in enumerate(contacts):
                for i in rod:
                    con = d.contact[i]
                    edges = d.efc_force[con.efc_address:con.efc_address + 2 * (con.dim - 1)]
                    slide[r] |= bool((edges[:4] <= 1e-12).any())
                    roll[r] |= con.dim == 6 and bool((edges[6:] <= 1e-12).any())
            for k, v in (("force", f), ("torque", tau), ("lin", d.qacc_smooth[plant._vadr[:, :3]].copy()),
                         ("ang", d.qacc_smooth[plant._vadr[:, 3:]].copy()), ("count", count), ("slide", slide),
                         ("roll", roll), ("state", state), ("episode", e)):
                out[k].append(v)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--stride", type=int, default=20)
    ap.add_argument("--seed", type=int, default=99)
    args = ap.parse_args()
    torch.set_num_threads(1)
    xml = build_model("ico", "robot")
    data = collect(xml, CollectConfig(episodes=args.episodes, steps=args.steps, seed=args.seed, push_every=200))
    plant = MujocoPlant(xml)
    w = contact_wrenches(plant, data, args.stride)
    t = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float64)
    st = w["state"]
    state = RodState(*(t([getattr(s, k) for s in st]) for k in ("pos", "quat", "vel", "angvel")))
    ctx = _Context(_Params(t(plant.masses), t(plant.model.body_inertia[plant._bid])),
                   t(quat_to_matrix(np.array([s.quat for s in st]))), None, t(w["lin"]), t(w["ang"]))
    law = GroundContact(plant.n_rods, len(plant.tendon_names),
                        options=read_contact_geometry(xml, plant.rod_names))
    F, T = t(w["force"]), t(w["torque"])
    touching = torch.as_tensor(np.array(w["count"]) > 0)
    stats = law.fit_residual(state, ctx, F, T, np.array(w["episode"]), touching)
    with torch.no_grad():
        f, tau = law.wrench(state, ctx)
    names = law.param_names(plant.rod_names, plant.tendon_names)
    print("law fitted to MuJoCo's contact wrench:", ", ".join(f"{n.split('.')[-1]} {v:.4g}" for n, v in zip(names, law.values)))
    print(f"explained variance: force law {stats['explained_variance']:.4f}, torques about the contact point "
          f"{stats['torque_explained_variance']:.4f}")

    pyramid = PyramidContact(plant.n_rods, len(plant.tendon_names), options=law.options)
    pstats = pyramid.fit_residual(state, ctx, F, T, np.array(w["episode"]), touching)
    with torch.no_grad():
        fp, taup = pyramid.wrench(state, ctx)
    print("pyramid_contact fitted to the same wrench:", ", ".join(
        f"{n.split('.')[-1]} {v:.6g}" for n, v in zip(pyramid.param_names(plant.rod_names, plant.tendon_names),
                                                      pyramid.values)), f"(explained variance {pstats['explained_variance']:.12f})")
    slide, roll = torch.as_tensor(np.array(w["slide"])), torch.as_tensor(np.array(w["roll"]))
    for name, (fl, taul) in (("ground_contact", (f, tau)), ("pyramid_contact", (fp, taup))):
        table(name, F, T, fl, taul, touching, slide, roll, t(w["count"]))


def rel(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float:
    return float(((a - b)[mask] ** 2).sum() / (a[mask] ** 2).sum()) ** 0.5


def table(name: str, F: torch.Tensor, T: torch.Tensor, f: torch.Tensor, tau: torch.Tensor, touching: torch.Tensor,
          slide: torch.Tensor, roll: torch.Tensor, count: torch.Tensor) -> None:
    """The relative residual of one law's fit, by the state of MuJoCo's cone."""
    print(f"{name + ': rod-instants in contact':34s} {'n':>6s} {'force':>9s} {'normal':>9s} {'tangent':>9s} {'torque':>9s}")
    for label, mask in (("all", touching), ("two contacts on the rod", touching & count.ge(2)),
                        ("a friction edge at zero (sliding)", touching & slide),
                        ("no friction edge at zero", touching & ~slide),
                        ("a rolling edge at zero (rolling)", touching & roll),
                        ("no rolling edge at zero", touching & ~roll)):
        n = int(mask.sum())
        if n == 0:
            print(f"{label:34s} {0:6d}")
            continue
        print(f"{label:34s} {n:6d} {rel(F, f, mask):9.2e} {rel(F[..., 2], f[..., 2], mask):9.2e} "
              f"{rel(F[..., :2], f[..., :2], mask):9.2e} {rel(T, tau, mask):9.2e}")


if __name__ == "__main__":
    main()
