"""The effect plug-in: a force the spring-rod model lacks, one small class per effect.

An :class:`Effect` (in the spirit of PySINDy's ``feature_library/base.py``) knows

* its ``name`` (the key in the model JSON) and its parameter blocks (:class:`ParamBlock`: names,
  per rod / per spring / global, signed or not, in units that scale with mass or not);
* its regression *features*: the force and torque it puts on every rod per unit of each
  parameter (:meth:`Effect.features`), linear in the parameters, so that the fit adds columns to
  the paper's linear regression (:mod:`identified.fit.features`);
* the wrench it adds in the engine (:meth:`Effect.wrench`): by default the same features
  contracted with the parameter values, so the fit and the twin cannot disagree;
* whether the implicit integrator may treat it explicitly (every effect here is explicit);
* its JSON round trip with standard errors (:meth:`Effect.to_json`, :func:`effect_from_json`).

Inputs: the engine's :class:`~identified.engine.StepContext` and the rod state; the fit builds the
same context from recorded states (:func:`identified.fit.features.step_context`).

Parameter layout of an effect: its blocks concatenated, each block flattened in (element,
component) order, e.g. ``linear_drag`` per rod ``[b_lin, b_rot]`` -> ``rod0.b_lin, rod0.b_rot,
rod1.b_lin, ...``.

How the fit identifies an effect is declared on its class, ``fit_strategy`` (a strategy of
:mod:`identified.fit`, as PySINDy keeps its optimizers apart from its feature libraries):

* ``"joint"`` (default): its columns join the main regression, fitted together with K, c, M, I, h;
* ``"classification"``: joint columns that depend on a classification of every instant made from
  the effect's own values (cable friction sticks or slips): the fit iterates
  (:mod:`identified.fit.classification`), and the twin evaluates the law at the accelerations it
  produces, not the columns at recorded ones;
* ``"residual"``: the law needs the accelerations under every other force (ground contact), so it
  is fitted on the residual wrench of the jointly fitted model, on the rods it touches
  (:meth:`Effect.rows_affected`), which the joint fit leaves out
  (:func:`identified.fit.identify.fit_residual_effects`; the effect's own least squares,
  :meth:`Effect.fit_residual`).

The engine's fused step (the twin's compiled substep) needs an effect's law in component form:
``component_form = True`` declares :meth:`Effect.wrench_components`; an engine holding an effect
without it steps through the tensor form (:attr:`identified.engine.SpringRodEngine.fused`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch

__all__ = ["Effect", "ParamBlock"]

KINDS = ("rod", "spring", "global")


@dataclass(frozen=True)
class ParamBlock:
    """One named group of an effect's parameters.

    ``per``: ``"rod"`` (one set per rod), ``"spring"`` (one per spring/cable) or ``"global"``;
    ``width``: components per element (e.g. 3 axes); ``signed``: may be negative (else a
    non-negative physical quantity); ``mass_scaled``: its unit contains kg (it scales with the
    global mass scale when only ratios are identified); ``unit``: for reports.
    """

    name: str
    per: str
    width: int = 1
    signed: bool = False
    mass_scaled: bool = True
    unit: str = ""

    def size(self, n_rods: int, n_springs: int) -> int:
        return self.width * {"rod": n_rods, "spring": n_springs, "global": 1}[self.per]

    def shape(self, n_rods: int, n_springs: int) -> tuple[int, ...]:
        n = {"rod": (n_rods,), "spring": (n_springs,), "global": ()}[self.per]
        return n + ((self.width,) if self.width > 1 else ())


class Effect(ABC):
    """Base class of the effect library.

    Subclasses set ``name``, ``blocks`` (all of one ``per`` kind, :attr:`kind`), ``description``,
    and implement :meth:`features` (or :meth:`end_features` for per-spring effects).  An effect
    holds its fitted ``values`` (P,) and ``stderr`` (P,) (``None`` before the fit) and its
    non-fitted ``options`` (geometry, smoothing widths).
    """

    name: ClassVar[str]
    description: ClassVar[str] = ""
    blocks: ClassVar[tuple[ParamBlock, ...]]
    #: how the fit identifies it: "joint", "classification" or "residual" (module docstring)
    fit_strategy: ClassVar[str] = "joint"
    explicit: ClassVar[bool] = True  # the implicit integrator treats its force as explicit
    #: a constraint-like law that reads the accelerations under every other force
    #: (``StepContext.base_lin_acc``): the engine adds it after the others
    needs_base_acceleration: ClassVar[bool] = False
    #: a law that switches at a spring's rest length (``StepContext.rest_length``): the fit
    #: reclassifies its rows while it identifies passive springs' rest lengths
    reads_rest_length: ClassVar[bool] = False
    #: whether it has :meth:`wrench_components`, the law in component form the twin's fused step runs
    component_form: ClassVar[bool] = False
    #: the region of the system its force acts in, where it has one (``"near_ground"``): the rods
    #: :meth:`rows_affected` names, which the diagnosis reports apart
    region: ClassVar[str | None] = None
    #: whether the fit's effect search (``--effects auto``) tries it
    searched: ClassVar[bool] = True
    #: whether the search also tries it on rod states reconstructed from markers (a recording)
    searched_on_markers: ClassVar[bool] = True
    #: what it models where the library has several laws of one thing (``"ground"``: the two
    #: ground-contact laws): a model holds at most one of them, the search and the diagnosis do not
    #: try a second (:func:`identified.effects.rival`)
    phenomenon: ClassVar[str | None] = None
    #: variants the search also tries and a user may name as ``name:variant``: options of each
    variants: ClassVar[dict[str, dict[str, Any]]] = {}
    #: parameters its own fit settles by a profile scan (not by least squares); a refit of a model
    #: that holds the effect keeps them (the effect search's later rounds)
    profiled: ClassVar[tuple[str, ...]] = ()
    #: how long its fit takes relative to a plain linear effect's: the effect search starts the
    #: slowest candidates first when it fits them side by side (:mod:`identified.fit.workers`)
    fit_cost: ClassVar[float] = 1.0
    #: a non-linear fit that starts from the values it holds (else from several fixed starts): the
    #: effect search's final fit on all the data starts from the values of the fit that chose it
    warm_starts: ClassVar[bool] = False

    def __init__(self, n_rods: int, n_springs: int, values: Any = None, stderr: Any = None,
                 options: dict[str, Any] | None = None) -> None:
        self.n_rods, self.n_springs = int(n_rods), int(n_springs)
        self.options: dict[str, Any] = dict(options or {})
        P = self.n_params
        self._cache: dict[tuple, Any] = {}
        self.values = None if values is None else np.asarray(values, dtype=float).reshape(P)
        self.stderr = None if stderr is None else np.asarray(stderr, dtype=float).reshape(P)
        #: a classification effect given ``values``: search its classification anyway, the given
        #: values one start among its own (else the fit starts from them alone)
        self.search_too = False

    @property
    def values(self) -> np.ndarray | None:
        """The fitted parameters (P,), ``None`` before the fit; setting them drops cached tensors."""
        return self._values

    @values.setter
    def values(self, v: np.ndarray | None) -> None:
        self._values = v
        self._cache = {k: x for k, x in self._cache.items() if k[0] != "theta"}

    @property
    def stage(self) -> str:
        """``"residual"`` for an effect fitted on the joint model's residual, else ``"joint"`` (its
        columns join the main regression)."""
        return "residual" if self.fit_strategy == "residual" else "joint"

    # ------------------------------------------------------------------ layout
    @property
    def kind(self) -> str:
        kinds = {b.per for b in self.blocks}
        assert len(kinds) == 1, f"{self.name}: blocks of one kind only"
        return kinds.pop()

    @property
    def width(self) -> int:
        """Parameters per element (rod or spring), or all of them for a global effect."""
        return sum(b.width for b in self.blocks)

    @property
    def n_params(self) -> int:
        return sum(b.size(self.n_rods, self.n_springs) for b in self.blocks)

    def param_names(self, rod_names: tuple[str, ...], spring_names: tuple[str, ...]) -> list[str]:
        """Full names in the effect's parameter order, e.g. ``linear_drag.rod0.b_lin``."""
        comps = [f"{b.name}{'' if b.width == 1 else '_' + 'xyz'[k] if b.width == 3 else f'_{k}'}"
                 for b in self.blocks for k in range(b.width)]
        if self.kind == "global":
            return [f"{self.name}.{c}" for c in comps]
        elems = rod_names if self.kind == "rod" else spring_names
        return [f"{self.name}.{e}.{c}" for e in elems for c in comps]

    def signed_mask(self) -> np.ndarray:
        per = np.array([b.signed for b in self.blocks for _ in range(b.width)])
        n = 1 if self.kind == "global" else (self.n_rods if self.kind == "rod" else self.n_springs)
        return np.tile(per, n)

    # ------------------------------------------------------------------ physics
    def features(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Force and WORLD torque on each rod per unit of each parameter.

        Per-rod effects: (..., R, W, 3) each, column k of rod i is parameter ``i W + k``; global
        effects: (..., R, P, 3).  Per-spring effects implement :meth:`end_features` instead.
        """
        raise NotImplementedError

    def end_features(self, state: Any, ctx: Any) -> torch.Tensor:
        """Per-spring effects: the force on each spring end per unit of the spring's parameter,
        (..., S, 2, 3), or per unit of each of its W parameters, (..., S, 2, W, 3)."""
        raise NotImplementedError

    def theta(self, like: torch.Tensor) -> torch.Tensor:
        """The fitted values as a tensor in ``like``'s dtype and device (cached; the cache is read
        first, so a compiled step never touches the numpy ``values``)."""
        key = ("theta", like.dtype, like.device)
        th = self._cache.get(key)
        if th is None:
            if self.values is None:
                raise ValueError(f"effect '{self.name}' has no fitted values")
            th = self._cache[key] = torch.as_tensor(self.values, dtype=like.dtype, device=like.device)
        return th

    def pinned(self) -> np.ndarray:
        """(P,) bool: parameters the fit holds at :meth:`pinned_values` (none by default)."""
        return np.zeros(self.n_params, dtype=bool)

    def pinned_values(self) -> np.ndarray:
        """(P,) the values of the held parameters (0 by default)."""
        return np.zeros(self.n_params)

    def bind(self, theta: torch.Tensor | None) -> None:
        """Let the engine use ``theta`` (P,) -- e.g. a tensor being optimised, gradients flow --
        instead of :attr:`values`; ``None`` goes back to the values."""
        self._cache = {k: x for k, x in self._cache.items() if k[0] != "theta"}
        if theta is not None:
            self._cache[("theta", theta.dtype, theta.device)] = theta

    def mass_scaled_mask(self) -> np.ndarray:
        """(P,) bool: parameters whose unit holds kg (they follow a rescaling of every mass)."""
        per = np.array([b.mass_scaled for b in self.blocks for _ in range(b.width)])
        n = 1 if self.kind == "global" else (self.n_rods if self.kind == "rod" else self.n_springs)
        return np.tile(per, n)

    def wrench(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """The force and WORLD torque the effect adds to each rod, (..., R, 3) each."""
        th = self.theta(state.pos)
        if self.kind == "spring":
            from identified.engine.accelerations import rod_wrench

            f = self.end_features(state, ctx)
            if self.width == 1:  # one parameter per spring: (..., S, 2, 3)
                f = f * th.view(-1, 1, 1)
            else:  # (..., S, 2, W, 3)
                f = (f * th.view(self.n_springs, 1, -1, 1)).sum(-2)
            return rod_wrench(ctx.graph, f, ctx.ends.lever)
        force, torque = self.features(state, ctx)
        w = th.view(self.n_rods, -1, 1) if self.kind == "rod" else th.view(-1, 1)
        return (force * w).sum(-2), (torque * w).sum(-2)

    def __call__(self, state: Any, ctx: Any) -> tuple[torch.Tensor, torch.Tensor]:
        return self.wrench(state, ctx)

    def implicit_damping(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(b_lin (R,), b_rot (R,))`` when the integrator takes this effect implicitly as a damping
        (the engine scales the accelerations by ``M / (M + dt b)``), else None (explicit: default)."""
        return None

    def rows_affected(self, state: Any, ctx: Any) -> torch.Tensor | None:
        """(..., R) bool: rods whose equations this effect touches (residual-stage effects); None: all."""
        return None

    def wrench_components(self, pos: Any, vel: Any, angvel: Any, rot: Any, base_lin_acc: Any,
                          base_ang_acc_body: Any, mass: torch.Tensor, inertia: Any, com: Any = None,
                          products: Any = None) -> tuple[Any, Any]:
        """The law in component form for the engine's fused step (``component_form = True``);
        every argument's components (..., R) (``com``, ``products``: the rods' centres of mass in
        their frames and products of inertia, ``None``: 0)."""
        raise NotImplementedError(f"effect '{self.name}' has no component form (component_form = False)")

    def fit_residual(self, state: Any, ctx: Any, force: torch.Tensor, torque: torch.Tensor,
                     groups: np.ndarray, rows: torch.Tensor) -> dict[str, Any]:
        """A residual-strategy effect's own least squares on the residual wrench ``force``/``torque``
        (N, R, 3) world of the rows ``rows`` (N, R) (:func:`identified.fit.identify.fit_residual_effects`):
        sets ``values``
        and ``stderr``, returns fit statistics."""
        raise NotImplementedError(f"effect '{self.name}' is not fitted on a residual (fit_strategy = "
                                  f"{self.fit_strategy!r})")

    # ------------------------------------------------------------------ JSON
    def structured(self, flat: np.ndarray | None) -> dict[str, Any] | None:
        """``{block: nested list}`` from a flat parameter vector (None stays None)."""
        if flat is None:
            return None
        flat = np.where(np.isfinite(flat), flat, np.nan).astype(object)
        flat[[not np.isfinite(x) for x in flat]] = None  # not estimable -> null in JSON
        out: dict[str, Any] = {}
        W = self.width
        if self.kind == "global":
            off = 0
            for b in self.blocks:
                v = flat[off: off + b.width]
                out[b.name] = v[0] if b.width == 1 else v.tolist()
                off += b.width
            return out
        n = self.n_rods if self.kind == "rod" else self.n_springs
        mat = flat.reshape(n, W)
        off = 0
        for b in self.blocks:
            v = mat[:, off: off + b.width]
            out[b.name] = (v[:, 0] if b.width == 1 else v).tolist()
            off += b.width
        return out

    def flatten(self, obj: dict[str, Any]) -> np.ndarray:
        """The flat parameter vector from ``{block: nested list}``; raises ValueError on bad shapes."""
        parts = []
        for b in self.blocks:
            if b.name not in obj:
                raise ValueError(f"effect '{self.name}' lacks parameter '{b.name}'")
            v = np.asarray(obj[b.name], dtype=float)
            want = b.shape(self.n_rods, self.n_springs)
            if v.shape != want:
                raise ValueError(f"effect '{self.name}' parameter '{b.name}' has shape {v.shape}, expected {want}")
            if not np.all(np.isfinite(v)):
                raise ValueError(f"effect '{self.name}' parameter '{b.name}' is not finite")
            parts.append(v.reshape(-1, b.width) if self.kind != "global" else v.reshape(1, b.width))
        return np.concatenate(parts, axis=1).reshape(-1)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "parameters": self.structured(self.values),
                "stderr": self.structured(self.stderr), "options": self.options}

    def describe(self, missing: str = "not identifiable", withheld: set[str] = frozenset()) -> str:
        """One line in words (for the fit report); ``missing``: what a parameter without a standard
        error is said to be (``"withheld"`` where the fit withheld them all); the blocks named in
        ``withheld`` say "withheld" for theirs."""
        if self.values is None:
            return f"effect {self.name}: not fitted"
        se = self.stderr
        parts = []
        for b in self.blocks:
            idx = self._block_index(b)
            v = self.values[idx]
            s = "" if se is None else _pm(se[idx], "withheld" if b.name in withheld else missing)
            if v.size <= 3:
                parts.append(f"{b.name} = {np.array2string(v, precision=4)}{s} {b.unit}".rstrip())
            else:
                parts.append(f"{b.name} in [{v.min():.4g}, {v.max():.4g}]{s} {b.unit}".rstrip())
        return f"effect {self.name}: " + "; ".join(parts)

    def _block_index(self, block: ParamBlock) -> np.ndarray:
        off = 0
        for b in self.blocks:
            if b is block:
                break
            off += b.width
        n = 1 if self.kind == "global" else (self.n_rods if self.kind == "rod" else self.n_springs)
        return (np.arange(n)[:, None] * self.width + off + np.arange(block.width)).reshape(-1)

    @classmethod
    @abstractmethod
    def for_system(cls, topology: Any, mjcf: str | None = None) -> Effect:
        """An unfitted instance for this system (reads the geometry it needs from the MJCF)."""


def _pm(se: np.ndarray, missing: str = "not identifiable") -> str:
    """`` ± worst`` of a block's standard errors; says which have none (NaN) and why (``missing``)."""
    if np.all(np.isnan(se)):
        return f" ± {missing}"
    worst = f" ± {np.nanmax(se):.2g}"
    return worst + f" ({int(np.isnan(se).sum())} {missing})" if np.isnan(se).any() else worst
