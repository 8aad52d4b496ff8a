"""The paper's neural baselines as torch modules, and one fair training loop for all of them.

* :class:`MLP` — ``S_t → S_{t+1}`` (appendix A: 6 fully connected layers of 30 units), written as
  ``S_{t+1} = S_t + net(S_t)`` with standardised inputs and outputs (a residual parameterisation
  of the same map; a net that must copy ``S_t`` through six layers is a strawman);
* :class:`MLPInt` — the same net predicts the accelerations ``(a, α)``, the integration module
  (semi-implicit Euler) makes ``S_{t+1}`` (appendix A, "MLP+Int");
* :class:`Interaction` — the interaction network (Battaglia et al. 2016) improved as in the paper:
  a relational MLP maps each spring end's reduced features ``(Δp̂, Δv̂)`` (eq. 1) to an effect, the
  effects are summed per rod end, and an object MLP maps ``(S_t, f_+, f_-)`` to ``S_{t+1}``
  (residual, as the MLP);
* :class:`InteractionInt` — the object MLP takes ``(r, f_+, f_-)`` instead of ``S_t`` and predicts
  ``(a, α)``, then the integration module ("Interaction+Int").

:func:`train` is the same for every model: Adam on the one-step error of standardised targets,
mini-batches, early stopping on the validation set (the weights of the best validation epoch are
kept), the learning rate picked from a grid on the validation set.  The budget (epochs,
patience, batch, grid) is an argument and is returned with the result.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from identified.baselines.features import (
    EndSlots,
    acceleration_targets,
    end_features,
    integrate,
    state_vector,
    vector_state,
)
from identified.dataset import Dataset
from identified.engine.forces import SpringGraph
from identified.engine.integration import RodState
from identified.topology import Topology

__all__ = ["MLP", "Budget", "Interaction", "InteractionInt", "MLPInt", "NeuralStepModel", "Pairs", "make_pairs",
           "train"]


def mlp(n_in: int, n_out: int, hidden: int = 30, layers: int = 6) -> nn.Sequential:
    """``layers`` fully connected layers (``layers - 1`` hidden of width ``hidden``, SiLU)."""
    dims = [n_in] + [hidden] * (layers - 1) + [n_out]
    mods: list[nn.Module] = []
    for i in range(len(dims) - 1):
        mods.append(nn.Linear(dims[i], dims[i + 1]))
        if i < len(dims) - 2:
            mods.append(nn.SiLU())
    return nn.Sequential(*mods)


class _Scaler(nn.Module):
    """Fixed affine standardisation ``(x - mean) / std`` (buffers, set from the training data)."""

    def __init__(self, n: int) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(n))
        self.register_buffer("std", torch.ones(n))

    def set(self, x: torch.Tensor) -> None:
        x = x.reshape(-1, x.shape[-1]).double()
        self.mean.copy_(x.mean(0).float())
        self.std.copy_(x.std(0).clamp_min(1e-12).float())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / self.std

    def inverse(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.std + self.mean


class NeuralStepModel(nn.Module):
    """A learned one-step model: ``raw(state, rest)`` predicts the target (``"delta"``: ``S_{t+1} - S_t``
    (..., R, 13); ``"accel"``: world ``(a, α)`` (..., R, 6)); ``step`` turns it into ``S_{t+1}``."""

    target = "delta"

    def __init__(self, topology: Topology, dt: float) -> None:
        super().__init__()
        self.n_rods, self.dt = topology.n_rods, float(dt)
        self.n_out = 13 if self.target == "delta" else 6
        self.out_scale = _Scaler(self.n_out)

    def prepare(self, state: RodState, rest: torch.Tensor, y: torch.Tensor) -> None:
        """Set the standardisations from training inputs and targets."""
        self.out_scale.set(y)

    def normalised(self, state: RodState, rest: torch.Tensor) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError

    def raw(self, state: RodState, rest: torch.Tensor) -> torch.Tensor:
        return self.out_scale.inverse(self.normalised(state, rest))

    def step(self, state: RodState, rest: torch.Tensor, push_force=None, push_point=None) -> RodState:
        """``S_{t+1}`` from ``S_t`` (float64 in and out; the net runs in float32).  Pushes are not
        inputs of these baselines (the paper's comparison has none)."""
        s32 = RodState(*(x.float() for x in state))
        out = self.raw(s32, rest.float()).double()
        if self.target == "delta":
            return vector_state(state_vector(state) + out)
        return integrate(state, out[..., :3], out[..., 3:], self.dt)


class MLP(NeuralStepModel):
    """``S_t`` (all rods, flattened) → ``S_{t+1} - S_t``; 6 layers × 30 (appendix A)."""

    target = "delta"

    def __init__(self, topology: Topology, dt: float, hidden: int = 30, layers: int = 6) -> None:
        super().__init__(topology, dt)
        n = 13 * self.n_rods
        self.in_scale = _Scaler(n)
        self.net = mlp(n, self.n_out * self.n_rods, hidden, layers)

    def prepare(self, state, rest, y):
        super().prepare(state, rest, y)
        self.in_scale.set(state_vector(state).flatten(-2))

    def normalised(self, state, rest):
        x = self.in_scale(state_vector(state).flatten(-2))
        return self.net(x).unflatten(-1, (self.n_rods, self.n_out))


class MLPInt(MLP):
    """``S_t`` → world ``(a, α)``, then the integration module (appendix A, "MLP+Int")."""

    target = "accel"


class Interaction(NeuralStepModel):
    """Relational MLP on each spring end's ``(Δp̂, Δv̂)`` → effect; effects summed per rod end;
    object MLP on ``(S_t, f_+, f_-)`` → ``S_{t+1} - S_t`` (paper, Fig. "Interaction Network")."""

    target = "delta"
    object_input = "state"

    def __init__(self, topology: Topology, dt: float, hidden: int = 30, layers: int = 4, effect: int = 3) -> None:
        super().__init__(topology, dt)
        self.graph = SpringGraph.from_topology(topology, dtype=torch.float32)
        self.slots = EndSlots.from_topology(topology)
        self.rel_scale = _Scaler(6)
        self.relational = mlp(6, effect, hidden, layers)
        n_obj = 13 if self.object_input == "state" else 3
        self.obj_scale = _Scaler(n_obj)
        self.object = mlp(n_obj + 2 * effect, self.n_out, hidden, layers)

    def _features(self, state, rest):
        r, dp, dv = end_features(self.graph, self.slots, state, rest)
        obj = state_vector(state) if self.object_input == "state" else r
        return obj, torch.cat([dp, dv], dim=-1)

    def prepare(self, state, rest, y):
        super().prepare(state, rest, y)
        obj, rel = self._features(state, rest)
        self.obj_scale.set(obj)
        self.rel_scale.set(rel[..., self.slots.valid, :])

    def normalised(self, state, rest):
        obj, rel = self._features(state, rest)
        e = self.relational(self.rel_scale(rel)) * self.slots.valid.unsqueeze(-1).to(rel.dtype)
        plus = self.slots.plus.unsqueeze(-1).to(rel.dtype)
        f_plus, f_minus = (e * plus).sum(-2), (e * (1 - plus)).sum(-2)
        return self.object(torch.cat([self.obj_scale(obj), f_plus, f_minus], dim=-1))


class InteractionInt(Interaction):
    """The interaction network with the object MLP on ``(r, f_+, f_-)`` → ``(a, α)``, then the
    integration module ("Interaction+Int")."""

    target = "accel"
    object_input = "r"


# ---------------------------------------------------------------------- data and training
@dataclass
class Pairs:
    """(S_t, S_{t+1}) pairs as tensors: ``state`` (N, R, ·) float32 fields, ``rest`` (N, S),
    ``delta`` (N, R, 13) and ``accel`` (N, R, 6) targets (float32)."""

    state: RodState
    rest: torch.Tensor
    delta: torch.Tensor
    accel: torch.Tensor

    def __len__(self) -> int:
        return int(self.rest.shape[0])

    def take(self, idx: torch.Tensor) -> tuple[RodState, torch.Tensor, torch.Tensor, torch.Tensor]:
        return RodState(*(x[idx] for x in self.state)), self.rest[idx], self.delta[idx], self.accel[idx]


def make_pairs(data: Dataset) -> Pairs:
    """Every step of ``data`` as a training pair; targets computed in float64, stored as float32."""
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)
    flat = lambda a, k: t(a[:, k].reshape(-1, *a.shape[2:]))
    names = ("pos", "quat", "vel", "angvel")
    s0 = RodState(*(flat(getattr(data, n), slice(0, -1)) for n in names))
    s1 = RodState(*(flat(getattr(data, n), slice(1, None)) for n in names))
    a, alpha = acceleration_targets(s0, s1, data.dt)
    delta = state_vector(s1) - state_vector(s0)
    return Pairs(RodState(*(x.float() for x in s0)), flat(data.rest_length, slice(None)).float(),
                 delta.float(), torch.cat([a, alpha], dim=-1).float())


@dataclass(frozen=True)
class Budget:
    """The training budget every neural baseline gets (recorded with its row)."""

    lrs: tuple[float, ...] = (3e-3, 1e-3, 3e-4)
    max_epochs: int = 60
    patience: int = 6
    batch: int = 256
    max_seconds_per_lr: float = 120.0
    seed: int = 0


@dataclass
class TrainResult:
    model: NeuralStepModel
    lr: float
    val_loss: float
    epochs: int
    seconds: float
    per_lr: dict[float, dict] = field(default_factory=dict)


def _loss(model: NeuralStepModel, batch) -> torch.Tensor:
    s, rest, delta, accel = batch
    y = delta if model.target == "delta" else accel
    z = model.normalised(s, rest)
    return torch.mean((z - model.out_scale(y)) ** 2)


def _val_loss(model: NeuralStepModel, val: Pairs, chunk: int = 65536) -> float:
    with torch.no_grad():
        tot = 0.0
        for i in range(0, len(val), chunk):
            idx = torch.arange(i, min(i + chunk, len(val)))
            tot += float(_loss(model, val.take(idx))) * len(idx)
    return tot / max(len(val), 1)


def train(factory, train_set: Pairs, val_set: Pairs, budget: Budget = Budget(), progress=None) -> TrainResult:
    """Train ``factory()`` models with Adam for every learning rate of the budget; early stopping on
    the validation loss (patience in epochs, best weights kept); returns the best on validation."""
    best: TrainResult | None = None
    per_lr: dict[float, dict] = {}
    t_all = time.perf_counter()
    for lr in budget.lrs:
        torch.manual_seed(budget.seed)
        model = factory()
        model.prepare(train_set.state, train_set.rest,
                      train_set.delta if model.target == "delta" else train_set.accel)
        opt = torch.optim.Adam(model.parameters(), lr=lr)
        gen = torch.Generator().manual_seed(budget.seed)
        best_val, best_state, best_epoch, stale = float("inf"), None, 0, 0
        t0 = time.perf_counter()
        epoch, stop = 0, "max_epochs"
        for epoch in range(1, budget.max_epochs + 1):
            perm = torch.randperm(len(train_set), generator=gen)
            for i in range(0, len(perm), budget.batch):
                loss = _loss(model, train_set.take(perm[i:i + budget.batch]))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
            v = _val_loss(model, val_set)
            if progress is not None:
                progress(lr, epoch, v)
            if v < best_val:
                best_val, best_state, best_epoch, stale = v, copy.deepcopy(model.state_dict()), epoch, 0
            else:
                stale += 1
            if stale >= budget.patience:
                stop = "patience"
                break
            if time.perf_counter() - t0 > budget.max_seconds_per_lr:
                stop = "time"
                break
        if best_state is not None:
            model.load_state_dict(best_state)
        per_lr[lr] = {"val_loss": best_val, "best_epoch": best_epoch, "epochs": epoch, "stopped_by": stop,
                      "seconds": round(time.perf_counter() - t0, 2)}
        if best is None or best_val < best.val_loss:
            best = TrainResult(model, lr, best_val, best_epoch, 0.0)
    assert best is not None
    best.seconds = time.perf_counter() - t_all
    best.per_lr = per_lr
    best.model.eval()
    return best
