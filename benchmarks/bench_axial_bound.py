"""Cramér-Rao bound of the parameters from noisy rod states, by MuJoCo sensitivities.

    python benchmarks/bench_axial_bound.py [--axis-pushes] [--episodes 4] [--of 20]
                                           [--model-seed 17] [--seed 1]

How precisely can *any* unbiased estimator recover the parameters from a dataset?  The reference
dataset (``paper-nonuniform`` icosahedron, 50 N pushes every 100 steps, 2000-step episodes) is
simulated without noise; every recorded output (position, orientation as a rotation vector,
velocity, angular velocity of every rod at every instant) is differentiated by central finite
differences of whole MuJoCo episodes with respect to the 72 parameters (K, c per spring, M and
Ixx, Iyy, Izz per rod; h = 1 is the anchor) and to each episode's initial state (72 more unknowns
per episode).  With the reference sensor noise (1 mm, 1 mrad, 1 cm/s, 0.01 rad/s, white) the
Fisher information is ``JᵀJ`` of the whitened sensitivities; the initial states are profiled out
per episode (projection, by QR) and the bound is ``sqrt(diag(F⁻¹))``, from the stacked triangular
factors (no normal equations).  It is the bound of output-error (simulation) fitting over whole
episodes with no process noise, the most optimistic setting.

``--axis-pushes`` applies the pushes on the rod axis (as ``collect`` did before pushes moved to
the rod surface): nothing then twists a rod about its axis and the axial inertia is seen only
through the gyroscopic coupling.  ``--episodes`` of the dataset are simulated and the bound is
also scaled to ``--of`` episodes (information adds up over episodes; the scaling assumes the
remaining episodes are alike).  About 20 s per episode on one core.  Figures, not assertions.
"""

from __future__ import annotations

import argparse

import mujoco
import numpy as np
import scipy.linalg as sla

from identified.rotation import quat_exp, quat_multiply, quat_to_matrix
from tensegrity_gym.collect import CollectConfig, collect
from tensegrity_gym.models import build_model, preset_parameters
from tensegrity_gym.plant import MujocoPlant

SIGMA = np.repeat([1e-3, 1e-3, 1e-2, 1e-2], 3)  # pos m, orientation rad, vel m/s, angvel rad/s


class Replay:
    """Replays a recorded episode on a MuJoCo model whose parameters can be changed."""

    def __init__(self, xml: str, data, episode: int) -> None:
        self.m = mujoco.MjModel.from_xml_string(xml)
        self.d = mujoco.MjData(self.m)
        self.data, self.e = data, episode
        self.bodies = [mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_BODY, n) for n in data.rod_names]
        self.tendons = [mujoco.mj_name2id(self.m, mujoco.mjtObj.mjOBJ_TENDON, n) for n in data.tendon_names]
        self.qadr = np.array([self.m.jnt_qposadr[self.m.body_jntadr[b]] for b in self.bodies])
        self.vadr = np.array([self.m.jnt_dofadr[self.m.body_jntadr[b]] for b in self.bodies])
        ls = self.m.tendon_lengthspring[self.tendons]
        self.push_pull = np.array(self.tendons)[ls[:, 0] >= ls[:, 1]]  # both ends of the dead band move

    def parameters(self) -> list[tuple[np.ndarray, object]]:
        """(array, index) of K, c per spring, M and the three inertias per rod, in the fit's order."""
        m = self.m
        return ([(m.tendon_stiffness, j) for j in self.tendons]
                + [(m.tendon_damping, j) for j in self.tendons]
                + [(m.body_mass, b) for b in self.bodies]
                + [(m.body_inertia, (b, a)) for b in self.bodies for a in range(3)])

    def run(self, x0: np.ndarray) -> np.ndarray:
        """Outputs (T + 1, R, 12) from the initial state x0 (R, 13: pos, quat, vel, world angvel)."""
        m, d, rec = self.m, self.d, self.data
        mujoco.mj_setConst(m, d)  # parameters changed in place (inertias) take effect only then
        mujoco.mj_resetData(m, d)
        qi, vi = self.qadr[:, None] + np.arange(7), self.vadr[:, None] + np.arange(6)
        d.qpos[qi] = x0[:, :7]
        d.qvel[vi[:, :3]] = x0[:, 7:10]
        d.qvel[vi[:, 3:]] = np.einsum("rji,rj->ri", quat_to_matrix(x0[:, 3:7]), x0[:, 10:13])
        T = rec.rest_length.shape[1]
        qpos, qvel = np.empty((T + 1,) + qi.shape), np.empty((T + 1,) + vi.shape)
        qpos[0], qvel[0] = d.qpos[qi], d.qvel[vi]
        for t in range(T):
            rest = rec.rest_length[self.e, t]
            m.tendon_lengthspring[self.tendons, 1] = rest
            m.tendon_lengthspring[self.push_pull, 0] = rest[np.isin(self.tendons, self.push_pull)]
            f, p = rec.push_force[self.e, t], rec.push_point[self.e, t]
            on = np.flatnonzero(f.any(-1))
            if on.size:
                lever = np.einsum("rij,rj->ri", quat_to_matrix(d.qpos[qi[on, 3:]]), p[on])
                wrench = np.concatenate([f[on], np.cross(lever, f[on])], -1)
                d.xfrc_applied[np.array(self.bodies)[on]] = wrench
            mujoco.mj_step(m, d)
            d.xfrc_applied[:] = 0.0
            qpos[t + 1], qvel[t + 1] = d.qpos[qi], d.qvel[vi]
        quat = qpos[..., 3:] / np.linalg.norm(qpos[..., 3:], axis=-1, keepdims=True)
        angvel = np.einsum("trij,trj->tri", quat_to_matrix(quat), qvel[..., 3:])
        return np.concatenate([qpos[..., :3], quat, qvel[..., :3], angvel], -1)


def whitened(out: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Outputs relative to ``ref`` (orientation as a world rotation vector), divided by the noise."""
    dq = quat_multiply(out[..., 3:7], ref[..., 3:7] * np.array([1, -1, -1, -1]))
    rv = 2 * dq[..., 1:] * np.sign(dq[..., :1])
    diff = np.concatenate([out[..., :3] - ref[..., :3], rv, out[..., 7:] - ref[..., 7:]], -1)
    return (diff / SIGMA).ravel()


def episode_factor(rep: Replay, x0: np.ndarray) -> np.ndarray:
    """Triangular factor of the episode's Fisher information on the parameters, initial state profiled."""
    ref = rep.run(x0)
    cols = []
    for arr, j in rep.parameters():
        v0, h = arr[j], 1e-5
        arr[j] = v0 * (1 + h)
        up = whitened(rep.run(x0), ref)
        arr[j] = v0 * (1 - h)
        down = whitened(rep.run(x0), ref)
        arr[j] = v0
        cols.append((up - down) / (2 * h))  # d output / d log(parameter)
    for i in range(x0.shape[0]):
        for kind in range(4):
            for a in range(3):
                h = 1e-2 * SIGMA[3 * kind]
                ys = []
                for s in (1.0, -1.0):
                    x = x0.copy()
                    if kind == 1:
                        x[i, 3:7] = quat_multiply(quat_exp(s * h * np.eye(3)[a]), x[i, 3:7])
                    else:
                        x[i, {0: 0, 2: 7, 3: 10}[kind] + a] += s * h
                    ys.append(whitened(rep.run(x), ref))
                cols.append((ys[0] - ys[1]) / (2 * h))
    J = np.array(cols).T
    n = len(rep.parameters())
    Q, _ = np.linalg.qr(J[:, n:])
    Jp = J[:, :n] - Q @ (Q.T @ J[:, :n])
    return np.linalg.qr(Jp, mode="r")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--axis-pushes", action="store_true")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--of", type=int, default=20)
    ap.add_argument("--model-seed", type=int, default=17)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    xml = build_model("ico", "paper-nonuniform", seed=args.model_seed)
    if args.axis_pushes:
        MujocoPlant.rod_radii = lambda self: np.zeros(self.n_rods)  # the push point on the axis
    data = collect(xml, CollectConfig(episodes=args.episodes, steps=2000, seed=args.seed, push_every=100))
    p = preset_parameters("ico", "paper-nonuniform", args.model_seed)
    S = len(p["springs"])
    groups = {"K": range(S), "c": range(S, 2 * S), "M": range(2 * S, 2 * S + 6),
              "Ixx,Iyy": [2 * S + 6 + 3 * i + a for i in range(6) for a in range(2)],
              "Izz": [2 * S + 6 + 3 * i + 2 for i in range(6)]}
    print(f"pushes {'on the rod axis' if args.axis_pushes else 'on the rod surface'}; model seed "
          f"{args.model_seed}, data seed {args.seed}; bound on the relative standard error (%)")
    R = np.zeros((0, 2 * S + 24))
    for e in range(args.episodes):
        rep = Replay(xml, data, e)
        x0 = np.concatenate([data.pos[e, 0], data.quat[e, 0], data.vel[e, 0], data.angvel[e, 0]], -1)
        if e == 0:
            replay = rep.run(x0)
            gap = max(np.abs(replay[..., :3] - data.pos[e]).max(),
                      np.abs(replay[..., 10:] - data.angvel[e]).max())
            print(f"replay of the recorded episode: max deviation {gap:.1e}")
        R = np.linalg.qr(np.vstack([R, episode_factor(rep, x0)]), mode="r")
        sc = np.linalg.norm(R, axis=0)
        se = 100 * np.linalg.norm(sla.solve_triangular(R / sc, np.eye(R.shape[1])), axis=1) / sc
        scaled = se * np.sqrt((e + 1) / args.of)
        worst = ", ".join(f"{g} {se[list(ix)].max():.3g}" for g, ix in groups.items())
        worst_scaled = ", ".join(f"{g} {scaled[list(ix)].max():.3g}" for g, ix in groups.items())
        print(f"{e + 1} episodes: {worst} | scaled to {args.of}: {worst_scaled} | Izz per rod "
              + " ".join(f"{x:.2f}" for x in scaled[list(groups["Izz"])]), flush=True)


if __name__ == "__main__":
    main()
