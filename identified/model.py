"""The identified model: physical parameters a person reads, stored as JSON.

Keys (README, "Identified model"): ``rods`` (name, mass, inertia), ``springs`` (name, stiffness, damping,
rest_length), ``control_scale`` (h), ``effects`` (name and parameters of every added effect),
``metrics`` (fit error, data used).  Besides these, ``topology`` stores the geometry the engine
needs (rod attachment points, which sites each spring joins), so that the twin stands on its own,
``dt`` and ``gravity`` the conditions of the data, ``integrator`` the engine's velocity update that
matches the plant (``euler``, ``implicit`` or ``rk4``), and ``scale`` how the global scale was fixed.
Every value carries its standard error where the fit gives one (``*_stderr``).

A rod's inertia: ``mass``, ``com`` (its centre of mass in the rod frame, m), ``inertia`` (its
principal moments about the centre of mass, kg m²) and ``inertia_frame`` (the principal axes as a
unit quaternion w-x-y-z from the rod frame, as MuJoCo's ``body_iquat``; each axis is the one
closest to the rod-frame axis of the same index, so a frame along the principal axes gives the
identity and the moments in x, y, z order).  A model without ``com``/``inertia_frame`` (the
diagonal model) has the rod frame at the centre of mass along the principal axes.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from identified.dataset import atomic_write
from identified.effects import known_names
from identified.jsonsafe import json_safe
from identified.rotation import matrix_to_quat, quat_to_matrix
from identified.topology import Rod, Spring, Topology

__all__ = [
    "IdentifiedModel",
    "ModelFileError",
    "check_effect_objects",
    "com_and_tensor",
    "inertia_tensor",
    "load_model",
    "principal_axes",
    "rigid_body_from_regression",
    "save_model",
    "validate_fields",
]

FORMAT = "tensegrity-identified/1"
INTEGRATORS = ("euler", "implicit", "rk4")  # as identified.engine.integration.INTEGRATORS


class ModelFileError(ValueError):
    """The identified-model file is missing, malformed or inconsistent."""


@dataclass
class IdentifiedModel:
    """Identified parameters and the topology they belong to."""

    topology: Topology
    stiffness: np.ndarray  # (S,) N/m
    damping: np.ndarray  # (S,) N s/m
    rest_length: np.ndarray  # (S,) m: identified for passive springs; an actuated cable's mean command
    mass: np.ndarray  # (R,) kg
    inertia: np.ndarray  # (R, 3) kg m^2, principal moments about the centre of mass (module docstring)
    control_scale: float = 1.0
    dt: float = 1e-3
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    stderr: dict[str, np.ndarray] = field(default_factory=dict)  # same keys/shapes as the values
    scale: dict[str, Any] = field(default_factory=dict)
    effects: list[dict[str, Any]] = field(default_factory=list)  # {name, parameters, stderr, options}
    loop: list[dict[str, Any]] = field(default_factory=list)  # effect search: added, error before/after
    metrics: dict[str, Any] = field(default_factory=dict)
    source_model: str | None = None
    integrator: str = "euler"  # how the engine steps: "euler", "implicit" or "rk4" (engine.integration)
    #: MuJoCo tendon actuators: {name, tendon, kind, dynamics, gain, gain_stderr, bias, bias_stderr,
    #: time_constant, time_constant_stderr} (identified.fit.actuation); ``held``: why the values are
    #: not this fit's estimates (the marker fit holds them at its start's), where they are not
    actuators: list[dict[str, Any]] = field(default_factory=list)
    #: (R, 3) m: each rod's centre of mass in its frame; None: at the origin
    com: np.ndarray | None = None
    #: (R, 4) w-x-y-z: the principal axes of ``inertia`` in the rod frame; None: the rod frame's axes
    inertia_frame: np.ndarray | None = None

    @property
    def full_inertia(self) -> bool:
        """Whether a rod's centre of mass or principal axes differ from its frame's."""
        return self.com is not None or self.inertia_frame is not None

    def inertia_about_com(self) -> tuple[np.ndarray, np.ndarray]:
        """Each rod's inertia tensor about its centre of mass in the rod frame: the diagonal (R, 3)
        and the products ``(Jxy, Jxz, Jyz)`` (R, 3), kg m² (the engine's parameters)."""
        J = inertia_tensor(self.inertia, self.inertia_frame)
        return np.einsum("rii->ri", J).copy(), J[:, [0, 0, 1], [1, 2, 2]].copy()

    def set_inertia_about_com(self, diagonal: np.ndarray, products: np.ndarray) -> None:
        """Set each rod's principal moments and axes from its inertia tensor about the centre of
        mass, rod frame: ``diagonal`` (R, 3) and ``products`` (R, 3) (as :meth:`inertia_about_com`)."""
        d, p = np.asarray(diagonal, dtype=float), np.asarray(products, dtype=float)
        J = np.einsum("ri,ij->rij", d, np.eye(3))
        J[:, [0, 0, 1], [1, 2, 2]] = J[:, [1, 2, 2], [0, 0, 1]] = p
        axes = [principal_axes(x) for x in J]
        self.inertia = np.array([a[0] for a in axes])
        self.inertia_frame = np.array([matrix_to_quat(a[1]) for a in axes])

    def summary(self) -> str:
        """The model in words: one line per rod and spring, with standard errors."""
        se = self.stderr
        # a fit that withheld its error bars (e.g. a marker fit short of its minimum) has values
        # without them, all of them (``metrics.stderr``) or those it names (``metrics.withheld``);
        # only the moments it names as not identifiable have none to print
        every = str(self.metrics.get("stderr", "")).startswith("withheld")
        named = set(self.metrics.get("withheld", {}))  # a fit parameter's name: K[cable3], I[rod2:xy]

        def missing(name: str) -> str:
            return "withheld" if every or name in named else "not estimable"

        unseen = set(self.metrics.get("not_identifiable", []))
        if every:  # read back from a file, a group of nulls is no group
            se = {k: np.full(np.shape(getattr(self, k)), np.nan) for k in ("mass", "stiffness", "damping")} | se
        moments = {a for n in named if n.startswith("I[") for a in _moments(n)}
        lines = []
        for i, r in enumerate(self.topology.rods):
            m = f"{self.mass[i]:.6g} kg" + _pm(se.get("mass"), i, missing(f"M[{r.name}]"))
            if every:
                held = np.array([unseen_moment(r.name, a) in unseen for a in range(3)])
            else:
                held = np.isnan(np.asarray(se["inertia"], dtype=float)[i]) if "inertia" in se else np.zeros(3, bool)
                held &= np.array([(r.name, a) not in moments for a in range(3)])
            # a moment the data cannot see (its spin unobservable: no standard error) has no value to print
            inert = ", ".join("not identifiable" if h else f"{x:.4g}" for x, h in zip(self.inertia[i], held))
            line = f"{r.name}: M = {m}; I = ({inert}) kg m^2"
            if self.full_inertia:
                c = np.zeros(3) if self.com is None else self.com[i]
                angle = 0.0 if self.inertia_frame is None else np.degrees(
                    2 * np.arccos(min(1.0, abs(float(self.inertia_frame[i][0])))))
                line += (f" (principal, axes turned {angle:.2f} deg from the rod frame); "
                         f"centre of mass ({', '.join(f'{1e3 * x:.2f}' for x in c)}) mm in the rod frame")
            lines.append(line)
        for j, s in enumerate(self.topology.springs):
            k = f"{self.stiffness[j]:.6g} N/m" + _pm(se.get("stiffness"), j, missing(f"K[{s.name}]"))
            c = f"{self.damping[j]:.6g} N s/m" + _pm(se.get("damping"), j, missing(f"c[{s.name}]"))
            kind = "cable" if s.pull_only else "spring"
            rest = (f"rest {self.rest_length[j]:.6g} m (its command, mean)" if s.actuated else
                    f"rest {self.rest_length[j]:.6g} m" + _pm(se.get("rest_length"), j))
            lines.append(f"{s.name} ({kind}): K = {k}; c = {c}; {rest}")
        lines.append(f"control scale h = {self.control_scale:.6g}" + _pm(se.get("control_scale"), None))
        for a in self.actuators:
            pm = lambda v: "" if v is None else f" ± {v:.2g}"
            line = (f"actuator {a['name']} on {a['tendon']}: gain {a['gain']:.6g} N{pm(a.get('gain_stderr'))}, "
                    f"bias {a['bias']:.4g} N{pm(a.get('bias_stderr'))}")
            if a.get("time_constant") is not None:
                line += f", time constant {a['time_constant']:.4g} s{pm(a.get('time_constant_stderr'))}"
            if a.get("held"):
                line += f" (held: {a['held']})"
            lines.append(line)
        if self.scale:
            lines.append(f"scale: {self.scale.get('description', '')}")
        from identified.effects import effect_from_json

        for e in self.effects:
            try:
                effect = effect_from_json(e, self.topology.n_rods, self.topology.n_springs)
                lines.append(effect.describe("withheld" if every else "not identifiable",
                                             withheld={b.name for b in effect.blocks if f"{e['name']}.{b.name}" in named}))
            except ValueError:
                lines.append(f"effect {e.get('name')}: {e.get('parameters')}")
        g = lambda x: "diverged" if x is None else f"{x:.4g}"
        for step in self.loop:
            if "share" in step:  # added after the search, on a recording's diagnosis (tensegrity_gym.loop)
                lines.append(f"loop: added {step.get('added')}: it removed {step['share']:.0%} of the held-out "
                             f"residual beyond the null ({step.get('evidence')}); free-run error from every take's "
                             f"start {g(step.get('error_before'))} m -> {g(step.get('error_after'))} m")
                continue
            line = (f"loop: added {step.get('added')}: held-out free-run error {g(step.get('error_before'))} m -> "
                    f"{g(step.get('error_after'))} m")
            if "one_step_before" in step:
                line += (f", one-step {g(step['one_step_before'])} -> {g(step.get('one_step_after'))} "
                         f"(evidence: {step.get('evidence')})")
            lines.append(line)
        res = self.metrics.get("residual") or {}
        if res.get("large"):
            lines.append(f"NOT A DESCRIPTION OF ITS DATA: the equations leave {res['relative_one_step']:.3g} of the "
                         "recorded wrench unexplained (the model lacks something the plant has; the parameters "
                         "above absorb it)")
        return "\n".join(lines)

    # ------------------------------------------------------------------ JSON
    def to_json(self) -> dict[str, Any]:
        se = self.stderr

        def err(key: str, idx) -> float | list | None:
            if key not in se:
                return None
            v = np.asarray(se[key])[idx] if idx is not None else np.asarray(se[key])
            return v.tolist()

        topo = self.topology
        return {
            "format": FORMAT,
            "rods": [
                {
                    "name": r.name,
                    "mass": float(self.mass[i]),
                    "mass_stderr": err("mass", i),
                    "inertia": self.inertia[i].tolist(),
                    "inertia_stderr": err("inertia", i),
                    "inertia_frame": ([1.0, 0.0, 0.0, 0.0] if self.inertia_frame is None
                                      else np.asarray(self.inertia_frame[i], dtype=float).tolist()),
                    "com": [0.0, 0.0, 0.0] if self.com is None else np.asarray(self.com[i], dtype=float).tolist(),
                    "com_stderr": err("com", i),
                }
                for i, r in enumerate(topo.rods)
            ],
            "springs": [
                {
                    "name": s.name,
                    "stiffness": float(self.stiffness[j]),
                    "stiffness_stderr": err("stiffness", j),
                    "damping": float(self.damping[j]),
                    "damping_stderr": err("damping", j),
                    "rest_length": float(self.rest_length[j]),
                    "rest_length_stderr": err("rest_length", j),
                    "pull_only": bool(s.pull_only),
                    "actuated": bool(s.actuated),
                }
                for j, s in enumerate(topo.springs)
            ],
            "control_scale": {"value": float(self.control_scale), "stderr": err("control_scale", None)},
            "actuators": self.actuators,
            "effects": self.effects,
            "loop": self.loop,
            "metrics": self.metrics,
            "scale": self.scale,
            "dt": float(self.dt),
            "integrator": self.integrator,
            "gravity": np.asarray(self.gravity, dtype=float).tolist(),
            "source_model": self.source_model,
            "topology": {
                "rods": [
                    {"name": r.name, "sites": list(r.sites), "site_offsets": r.site_offsets.tolist()}
                    for r in topo.rods
                ],
                "springs": [
                    {"name": s.name, "sites": list(s.sites), "rods": list(s.rods), "offsets": s.offsets.tolist()}
                    for s in topo.springs
                ],
            },
        }

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> IdentifiedModel:
        try:
            if obj.get("format") != FORMAT:
                raise ModelFileError(f"not an identified model (format '{obj.get('format')}', expected '{FORMAT}')")
            t = obj["topology"]
            springs_json = {s["name"]: s for s in obj["springs"]}
            rods = tuple(
                Rod(name=r["name"], sites=tuple(r["sites"]), site_offsets=np.array(r["site_offsets"], dtype=float))
                for r in t["rods"]
            )
            springs = tuple(
                Spring(
                    name=s["name"],
                    sites=(s["sites"][0], s["sites"][1]),
                    rods=(int(s["rods"][0]), int(s["rods"][1])),
                    offsets=np.array(s["offsets"], dtype=float),
                    pull_only=bool(springs_json[s["name"]]["pull_only"]),
                    actuated=bool(springs_json[s["name"]]["actuated"]),
                )
                for s in t["springs"]
            )
            topo = Topology(rods=rods, springs=springs)
            sp = [springs_json[s.name] for s in springs]
            stderr: dict[str, np.ndarray] = {}
            for key, src, n in (("stiffness", sp, "stiffness_stderr"), ("damping", sp, "damping_stderr"),
                                ("rest_length", sp, "rest_length_stderr"),
                                ("mass", obj["rods"], "mass_stderr"), ("inertia", obj["rods"], "inertia_stderr"),
                                ("com", obj["rods"], "com_stderr")):
                vals = [x.get(n) for x in src]
                if any(v is not None for v in vals):  # null: that one's the data cannot tell (NaN)
                    stderr[key] = np.array([np.nan if v is None else v for v in vals], dtype=float)
            cs = obj.get("control_scale", {"value": 1.0})
            if cs.get("stderr") is not None:
                stderr["control_scale"] = np.array(cs["stderr"], dtype=float)
            model = cls(
                topology=topo,
                stiffness=np.array([s["stiffness"] for s in sp], dtype=float),
                damping=np.array([s["damping"] for s in sp], dtype=float),
                rest_length=np.array([s["rest_length"] for s in sp], dtype=float),
                mass=np.array([r["mass"] for r in obj["rods"]], dtype=float),
                inertia=np.array([r["inertia"] for r in obj["rods"]], dtype=float).reshape(-1, 3),
                control_scale=float(cs["value"]),
                dt=float(obj["dt"]),
                gravity=np.array(obj["gravity"], dtype=float),
                stderr=stderr,
                scale=dict(obj.get("scale", {})),
                effects=list(obj.get("effects", [])),
                loop=list(obj.get("loop", [])),
                metrics=dict(obj.get("metrics", {})),
                source_model=obj.get("source_model"),
                integrator=str(obj.get("integrator", "euler")),
                actuators=list(obj.get("actuators", [])),
            )
            com = np.array([r.get("com", [0.0, 0.0, 0.0]) for r in obj["rods"]], dtype=float).reshape(-1, 3)
            frame = np.array([r.get("inertia_frame", [1.0, 0.0, 0.0, 0.0]) for r in obj["rods"]],
                             dtype=float).reshape(-1, 4)
            if np.any(com != 0):
                model.com = com
            if np.any(frame != np.array([1.0, 0.0, 0.0, 0.0])):
                model.inertia_frame = frame
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise ModelFileError(f"malformed identified model: {type(exc).__name__}: {exc}") from None
        model.validate()
        return model

    def validate(self) -> None:
        """Check shapes and finiteness; raise ModelFileError naming the problem."""
        S, R = self.topology.n_springs, self.topology.n_rods
        for key, shape in (("stiffness", (S,)), ("damping", (S,)), ("rest_length", (S,)),
                           ("mass", (R,)), ("inertia", (R, 3))):
            arr = getattr(self, key)
            if arr.shape != shape:
                raise ModelFileError(f"'{key}' has shape {arr.shape}, expected {shape}")
            if not np.all(np.isfinite(arr)):
                raise ModelFileError(f"'{key}' holds a non-finite value")
        for key, width in (("com", 3), ("inertia_frame", 4)):
            arr = getattr(self, key)
            if arr is not None and (arr.shape != (R, width) or not np.all(np.isfinite(arr))):
                raise ModelFileError(f"'{key}' must be {width} finite numbers per rod, got shape {arr.shape}")
        if self.inertia_frame is not None and np.any(np.abs(np.linalg.norm(self.inertia_frame, axis=1) - 1) > 1e-6):
            raise ModelFileError("'inertia_frame' must be unit quaternions (w, x, y, z)")
        if self.integrator not in INTEGRATORS:
            raise ModelFileError(f"'integrator' is '{self.integrator}', expected one of {', '.join(INTEGRATORS)}")
        if np.any(self.mass <= 0) or np.any(self.inertia[:, :2] <= 0):
            raise ModelFileError("rod masses and transverse inertias must be positive")
        from identified.effects import effect_from_json

        for e in self.effects:
            if not isinstance(e, dict):
                raise ModelFileError("'effects' must hold objects {name, parameters, stderr, options}")
            try:
                effect_from_json(e, R, S)
            except (ValueError, KeyError, TypeError) as exc:
                raise ModelFileError(f"effect '{e.get('name')}': {exc}") from None


def unseen_moment(rod: str, axis: int) -> str:
    """The ``metrics.not_identifiable`` line of a rod's moment of inertia about body ``axis`` (0-2)
    whose spin the data do not show (its value is a placeholder, never an estimate)."""
    return f"{rod}: moment of inertia about body axis {'xyz'[axis]} (its spin is not observable)"


def _moments(name: str) -> list[tuple[str, int]]:
    """The (rod, body axis) pairs of a fit's moment-of-inertia parameter ``I[rod2:xy]``."""
    rod, axes = name[2:-1].rsplit(":", 1)
    return [(rod, "xyz".index(a)) for a in axes]


def _pm(se: np.ndarray | None, idx, missing: str = "not estimable") -> str:
    """`` ± se`` of entry ``idx`` (``None``: the scalar), or what it is without one (``missing``)."""
    if se is None:
        return ""
    v = np.asarray(se)[idx] if idx is not None else np.asarray(se)
    return f" ± {float(v):.2g}" if np.all(np.isfinite(v)) else f" ± {missing}"


def save_model(path: str | os.PathLike, model: IdentifiedModel) -> None:
    """Write the model as JSON atomically.  A model :func:`load_model` would refuse (e.g. a fit that
    gave a rod a negative mass) is not written: ModelFileError naming the path and the field."""
    try:
        validate_fields(model)
    except ModelFileError as exc:
        raise ModelFileError(f"'{os.fspath(path)}' not written: the model is not valid: {exc}") from None
    text = json.dumps(json_safe(model.to_json()), indent=2, allow_nan=False)
    atomic_write(path, lambda fh: fh.write(text + "\n"))


def load_model(path: str | os.PathLike) -> IdentifiedModel:
    """Read and validate an identified-model JSON file."""
    p = os.fspath(path)
    try:
        with open(p, encoding="utf-8") as fh:
            obj = json.load(fh)
    except FileNotFoundError:
        raise ModelFileError(f"identified model '{p}' does not exist") from None
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ModelFileError(f"'{p}' is not a readable JSON model: {exc}") from None
    if not isinstance(obj, dict):
        raise ModelFileError(f"'{p}' is not an identified model (top level is not an object)")
    try:
        model = IdentifiedModel.from_json(obj)
        validate_fields(model)
    except ModelFileError as exc:
        raise ModelFileError(f"'{p}': {exc}") from None
    return model


def validate_fields(model: IdentifiedModel) -> None:
    """Check the values a loaded model steps with; raise ModelFileError naming the field.

    ``dt`` positive and finite, ``gravity`` three finite numbers, every mass and moment of inertia
    positive, stiffness, damping, rest lengths and the control scale finite (rest lengths >= 0),
    every effect a known name.
    """
    if not (np.isfinite(model.dt) and model.dt > 0):
        raise ModelFileError(f"'dt' must be a positive, finite time step, got {model.dt}")
    g = np.asarray(model.gravity, dtype=float)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise ModelFileError(f"'gravity' must be 3 finite numbers, got {g.tolist()}")
    if not np.isfinite(model.control_scale):
        raise ModelFileError(f"'control_scale' must be finite, got {model.control_scale}")
    for i, r in enumerate(model.topology.rods):
        if not model.mass[i] > 0:
            raise ModelFileError(f"rod '{r.name}': mass {model.mass[i]:.4g} kg is not positive")
        for a, axis in enumerate(("x", "y", "z")):
            if not model.inertia[i, a] > 0:
                raise ModelFileError(f"rod '{r.name}': inertia about {axis} {model.inertia[i, a]:.4g} kg m^2 "
                                     "is not positive")
    if np.any(model.rest_length < 0):
        raise ModelFileError("'rest_length' holds a negative value")
    if not isinstance(model.effects, list):
        raise ModelFileError("'effects' must be a list")
    for e in model.effects:
        name = e.get("name") if isinstance(e, dict) else None
        if name not in known_names():
            raise ModelFileError(f"unknown effect {name!r} (known: {', '.join(known_names())})")


def check_effect_objects(effects: list) -> None:
    """Raise ValueError for an engine effect that is not one (a name, a number): before any step."""
    for k, e in enumerate(effects):
        if isinstance(e, str):
            why = ("an effect's name: pass the effect object" if e in known_names()
                   else f"an unknown name (known effects: {', '.join(known_names())})")
            raise ValueError(f"effects[{k}] = {e!r} is {why}")  # noqa: TRY004 (bad input: one ValueError line)
        if not callable(e):
            raise ValueError(  # noqa: TRY004 (bad input: one ValueError line)
                f"effects[{k}] = {e!r} is not an effect (a callable (state, ctx) -> (force, torque))")


# ---------------------------------------------------------------------- rigid-body inertia
def inertia_tensor(moments: np.ndarray, frame: np.ndarray | None) -> np.ndarray:
    """(R, 3, 3) inertia tensors in the rod frame from principal ``moments`` (R, 3) along the axes
    ``frame`` (R, 4) w-x-y-z (``None``: the rod frame's axes)."""
    moments = np.asarray(moments, dtype=float)
    if frame is None:
        return np.einsum("ri,ij->rij", moments, np.eye(3))
    Q = quat_to_matrix(np.asarray(frame, dtype=float))
    return np.einsum("rij,rj,rkj->rik", Q, moments, Q)


def principal_axes(J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The principal moments (3,) and axes (a rotation, its columns the axes in the rod frame, 3x3)
    of a symmetric inertia tensor ``J`` (3, 3); axis ``k`` is the eigenvector closest to the rod
    frame's axis ``k`` (turned to point the same way), so a diagonal ``J`` keeps its order."""
    lam, V = np.linalg.eigh(0.5 * (J + J.T))
    perms = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    best = max(perms, key=lambda p: sum(abs(V[a, p[a]]) for a in range(3)))
    Q, lam = V[:, best].copy(), lam[list(best)]
    Q *= np.where(np.diag(Q) < 0, -1.0, 1.0)
    if np.linalg.det(Q) < 0:  # a proper rotation: turn the axis least aligned with its own
        k = int(np.argmin(np.abs(np.diag(Q))))
        Q[:, k] = -Q[:, k]
    return lam, Q


def com_and_tensor(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The centre of mass (3,) and inertia tensor about it (3, 3, rod frame) from the ten inertial
    parameters ``[M, Ixx, Iyy, Izz, Mcx, Mcy, Mcz, Jxy, Jxz, Jyz]`` about the rod frame's origin
    (the parallel-axis theorem: ``J_c = J_o - M (|c|² E - c cᵀ)``)."""
    m, d, h, p = x[0], x[1:4], x[4:7], x[7:10]
    J_o = np.diag(d) + np.array([[0, p[0], p[1]], [p[0], 0, p[2]], [p[1], p[2], 0]])
    c = h / m
    return c, J_o - m * (c @ c * np.eye(3) - np.outer(c, c))


def rigid_body_from_regression(theta: np.ndarray, cov: np.ndarray | None, cols: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Each rod's centre of mass (R, 3), principal moments (R, 3) and axes (R, 4 w-x-y-z) from
    the regression's ten parameters per rod (``cols`` (R, 10): their full-vector indices in the
    order of :func:`com_and_tensor`), with standard errors (R, 3) each propagated to first order
    from ``cov`` (the moments' derivative at fixed axes: exact to first order, also for nearly
    equal moments); ``None`` without a covariance."""
    R = cols.shape[0]
    com, moments, frame = np.zeros((R, 3)), np.zeros((R, 3)), np.zeros((R, 4))
    com_se = moments_se = None
    if cov is not None:
        com_se, moments_se = np.zeros((R, 3)), np.zeros((R, 3))
    for i in range(R):
        x = np.asarray(theta[cols[i]], dtype=float)
        c, J = com_and_tensor(x)
        lam, Q = principal_axes(J)
        com[i], moments[i], frame[i] = c, lam, matrix_to_quat(Q)
        if cov is None:
            continue

        def g(y: np.ndarray, Q: np.ndarray = Q) -> np.ndarray:
            cy, Jy = com_and_tensor(y)
            return np.concatenate([cy, np.einsum("ji,jk,ki->i", Q, Jy, Q)])

        steps = 1e-6 * np.maximum(np.abs(x), 1e-6 * max(np.max(np.abs(x)), 1e-300))
        jac = np.stack([(g(x + e) - g(x - e)) / (2 * h) for h, e in zip(steps, np.diag(steps))], axis=1)
        C = np.asarray(cov)[np.ix_(cols[i], cols[i])]
        var = np.clip(np.einsum("ij,jk,ik->i", jac, C, jac), 0.0, None)
        com_se[i], moments_se[i] = np.sqrt(var[:3]), np.sqrt(var[3:])
    return com, moments, frame, com_se, moments_se
