"""Domain randomization of the batched twin: what the identified model does not know, drawn per env.

A :class:`Randomization` is a distribution over the twin's physical parameters and over the
disturbances a policy meets on a robot. Each sub-env of the batched twin
(:class:`~tensegrity_gym.envs.vector.TensegrityIcoVectorEnv`, ``randomize=``) draws its own sample
at every reset from its own seeded generator (:meth:`Randomization.draw`), so a draw is
reproducible from the reset seed. ``tensegrity train --randomize auto|none|FILE`` builds one.

What is drawn (every width a half-width; ``0`` leaves that quantity at the identified value):

=================== ============================================================================
``stiffness``       each spring's ``K`` times ``1 + U(-w, w)`` (relative)
``damping``         each spring's ``c`` times ``1 + U(-w, w)``
``mass``            each rod's ``M`` times ``1 + U(-w, w)``
``inertia``         each rod's ``I`` (all three moments) times ``1 + U(-w, w)``
``rest_offset``     each cable's rest length plus ``U(-w, w)`` m: the spool's calibration
``contact``         per parameter of the model's ground-contact law (``ground_contact``: ``kappa``,
                    ``beta_n``, ``gamma_n``, ``beta_a``, ``gamma_a``, ``beta_p``, ``gamma_p``,
                    ``mu``, ``epsilon``, ``mu_torsion``, ``mu_rolling``, ``omega_slip``;
                    ``pyramid_contact``: ``beta``, ``kappa``, ``imp_min``, ``imp_max``,
                    ``imp_width``, ``mu``, ``mu_torsion``, ``mu_rolling``): times ``1 + U(-w, w)``
``motor_speed``     the cable motors' speed times ``1 + U(-w, w)`` (one factor per env)
``latency``         the command takes effect after ``k`` control steps, ``k`` uniform in
                    ``0..latency`` (drawn per env and episode)
``obs_noise``       Gaussian noise added to every observation, std per group in SI units:
                    ``pos`` (m: COM height and rod positions), ``rot`` (rotation-matrix entries),
                    ``vel`` (m/s), ``angvel`` (rad/s), ``rest`` (the normalised rest lengths)
``push_force``      a random horizontal push of ``U(0, w)`` N on one random rod for one control
                    step, with probability ``push_probability`` per step and env
``reset_yaw``       the start pose turned about the vertical through its centre of mass by
                    ``U(-w, w)`` rad at each reset (the heading; the ground is the same in every
                    direction, the task's +x is not)
=================== ============================================================================

``auto`` (:func:`auto_randomization`) derives the widths from the identified model alone, never
from the plant's MJCF:

* every fitted parameter: ``3`` standard errors (the fit's own uncertainty), relative;
* the contact law: what its fit leaves unexplained. The law is fitted on the residual wrench of
  the rods in contact and explains a fraction ``EV`` of its variance (``metrics.residual_stage.
  ground_contact.explained_variance``, measured on the fit's own data); the unexplained
  relative amplitude ``sqrt(1 - EV)`` times :data:`CONTACT_FACTOR` (4: the contact's remaining
  error sits where the policy's search goes, rolling over an edge, not spread evenly over the
  fit's data; measured, a factor 2 left the policies relying on the twin's contact) is the
  relative width of each contact parameter, between :data:`CONTACT_FLOOR` and 0.5; the
  dimensionless gains ``gamma_*`` (near 1: the contact cancels what pushes the rod into the
  ground) at most :data:`GAMMA_MAX`. The friction coefficient ``mu`` and the regulariser
  ``epsilon``, scanned without a standard error, get the same width. The contact torques
  (torsional and rolling friction, ``mu_torsion``, ``mu_rolling``, and their saturation speed
  ``omega_slip``) are fitted on the residual torque about the contact point and explain a fraction
  ``EV_t`` of it (``torque_explained_variance``): their width is ``CONTACT_FACTOR sqrt(1 - EV_t)``
  the same way (or 3 standard errors), between the floor and 0.5. A coefficient the fit holds at 0
  (the data show none) stays 0: a relative width cannot move it. ``pyramid_contact``'s parameters,
  fitted together on the residual wrench, all take its ``EV`` the same way; its impedances
  (``imp_min``, ``imp_max``, below 1) at most half their distance to 1;
* observation noise: what the twin gets wrong over one control period. Velocities: its one-step
  error (``metrics.one_step_rms``, one physics step, on the fit's data) grown as a random walk
  over the control period (``sqrt(frame_skip)``); positions and orientations, whose one-step
  error is nil by construction: its free-run error (``metrics.free_run``, mean over its horizon)
  scaled the same way to one control period (``sqrt(control period / horizon)``);
* springs and rods: the larger of 3 standard errors and :data:`PRIOR_WIDTH`, and cable rest
  offsets of :data:`PRIOR_REST_OFFSET` (priors: no fit of a lab's robot knows its parameters to
  better than a few percent or its spools to better than millimetres, although a noise-free fit on
  a simulated plant reports errors at machine precision);
* motors and latency (not identified): :data:`PRIOR_MOTOR_SPEED` and one control step of latency;
* no pushes and no random heading: measured over five training seeds each, pushes sized from
  the free-run error (one a second on a random rod, mean kick ``2 e_H / H``) and a random start
  heading (``reset_yaw`` = pi) did not make the policies transfer more reliably (README,
  "Randomized twins"); a FILE can ask for both.

A FILE (JSON, or YAML when PyYAML is installed) holds the same keys as :meth:`Randomization.to_json`
(missing keys are 0, unknown keys are an error), e.g.::

    {"stiffness": 0.05, "damping": 0.05, "mass": 0.05, "inertia": 0.05, "rest_offset": 0.002,
     "contact": {"kappa": 0.3, "mu": 0.3}, "motor_speed": 0.1, "latency": 1,
     "obs_noise": {"pos": 0.001, "vel": 0.01, "angvel": 0.05}, "push_force": 0.0,
     "push_probability": 0.0}
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

__all__ = [
    "CONTACT_FACTOR",
    "CONTACT_FLOOR",
    "CONTACT_PARAMETERS",
    "GAMMA_MAX",
    "OBS_GROUPS",
    "PRIOR_MOTOR_SPEED",
    "PRIOR_REST_OFFSET",
    "PRIOR_WIDTH",
    "Draw",
    "Randomization",
    "auto_randomization",
    "load_randomization",
    "resolve_randomization",
]

#: the ground-contact laws' parameters (``ground_contact``'s, then those only ``pyramid_contact`` has)
CONTACT_PARAMETERS = ("kappa", "beta_n", "gamma_n", "beta_a", "gamma_a", "beta_p", "gamma_p", "mu", "epsilon",
                      "mu_torsion", "mu_rolling", "omega_slip", "beta", "imp_min", "imp_max", "imp_width")
#: the impedances (``pyramid_contact``'s ``imp_min``, ``imp_max``): below 1, their width at most half
#: the way to 1
IMPEDANCES = ("imp_min", "imp_max")
#: the contact torques' parameters (their width comes from the torque's unexplained variance)
CONTACT_TORQUE_PARAMETERS = ("mu_torsion", "mu_rolling", "omega_slip")
OBS_GROUPS = ("pos", "rot", "vel", "angvel", "rest")
#: the contact's unexplained relative amplitude is multiplied by this to give a parameter's width
CONTACT_FACTOR = 4.0
#: the largest relative width of the contact's dimensionless gains (gamma_n, gamma_a, gamma_p)
GAMMA_MAX = 0.3
#: the least relative width of a contact parameter under ``auto``
CONTACT_FLOOR = 0.1
#: the least relative width of a spring or rod parameter under ``auto`` (a prior, see the module)
PRIOR_WIDTH = 0.05
#: the cables' rest-length offsets under ``auto``, m (a prior, see the module)
PRIOR_REST_OFFSET = 0.002
#: the relative width of the motors' speed under ``auto`` (a prior: it is not identified)
PRIOR_MOTOR_SPEED = 0.1
#: the ground-contact laws whose parameters ``contact`` draws
CONTACT_LAWS = ("ground_contact", "pyramid_contact")
_SCALARS = ("stiffness", "damping", "mass", "inertia", "rest_offset", "motor_speed", "push_force",
            "push_probability", "reset_yaw")


@dataclass
class Randomization:
    """Half-widths of the per-env draws (see the module docstring); all zero: no randomization."""

    stiffness: float = 0.0
    damping: float = 0.0
    mass: float = 0.0
    inertia: float = 0.0
    rest_offset: float = 0.0
    contact: dict[str, float] = field(default_factory=dict)
    motor_speed: float = 0.0
    latency: int = 0
    obs_noise: dict[str, float] = field(default_factory=dict)
    push_force: float = 0.0
    push_probability: float = 0.0
    reset_yaw: float = 0.0
    #: where the widths came from (``"auto"``, a file, ``"none"``) and how, for the policy's metadata
    source: str = "none"
    notes: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ checks and JSON
    def validate(self) -> None:
        """ValueError (one line) for a width out of range or an unknown key."""
        for name in _SCALARS:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"randomization '{name}' must be a finite number >= 0, got {v!r}")
        for name in ("stiffness", "damping", "mass", "inertia", "motor_speed"):
            if getattr(self, name) >= 1:
                raise ValueError(f"randomization '{name}' is a relative half-width and must be < 1, "
                                 f"got {getattr(self, name)}")
        if self.push_probability > 1:
            raise ValueError(f"randomization 'push_probability' must be <= 1, got {self.push_probability}")
        if self.reset_yaw > math.pi:
            raise ValueError(f"randomization 'reset_yaw' is a half-width in rad and must be <= pi, got {self.reset_yaw}")
        if isinstance(self.latency, bool) or int(self.latency) != self.latency or self.latency < 0:
            raise ValueError(f"randomization 'latency' must be an integer >= 0 (control steps), got {self.latency!r}")
        self.latency = int(self.latency)
        for group, allowed, what in ((self.contact, CONTACT_PARAMETERS, "contact"),
                                     (self.obs_noise, OBS_GROUPS, "obs_noise")):
            if not isinstance(group, dict):
                raise ValueError(f"randomization '{what}' must be a mapping of {', '.join(allowed)} to widths")  # noqa: TRY004 - a bad file
            for k, v in group.items():
                if k not in allowed:
                    raise ValueError(f"randomization '{what}' has an unknown key '{k}' (allowed: {', '.join(allowed)})")
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                    raise ValueError(f"randomization '{what}.{k}' must be a finite number >= 0, got {v!r}")
                if what == "contact" and v >= 1:
                    raise ValueError(f"randomization 'contact.{k}' is a relative half-width and must be < 1, got {v}")

    @property
    def active(self) -> bool:
        """True when anything is drawn."""
        return bool(any(getattr(self, n) for n in _SCALARS) or self.latency
                    or any(self.contact.values()) or any(self.obs_noise.values()))

    @property
    def physical(self) -> bool:
        """True when a parameter of the engine (springs, rods, contact, rest offsets, motors) is drawn."""
        return bool(self.stiffness or self.damping or self.mass or self.inertia or self.rest_offset
                    or self.motor_speed or any(self.contact.values()))

    def to_json(self) -> dict[str, Any]:
        """Every width, the source and the notes (what ``auto`` read): the policy's metadata."""
        return asdict(self)

    @classmethod
    def from_json(cls, obj: Any, source: str = "file") -> Randomization:
        """From a mapping of the :meth:`to_json` keys (missing keys 0); ValueError for others."""
        if not isinstance(obj, dict):
            raise ValueError("a randomization file holds a mapping of names to widths")  # noqa: TRY004 - a bad file
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(obj) - known)
        if unknown:
            raise ValueError(f"unknown randomization key(s) {', '.join(map(repr, unknown))} "
                             f"(allowed: {', '.join(sorted(known - {'source', 'notes'}))})")
        kw = {k: v for k, v in obj.items() if k not in ("source", "notes")}
        for k in ("contact", "obs_noise"):
            if k in kw and kw[k] is None:
                kw[k] = {}
        return cls(**kw, source=obj.get("source", source), notes=dict(obj.get("notes") or {}))

    # ------------------------------------------------------------------ drawing
    def draw(self, rng: np.random.Generator, n_rods: int, n_springs: int) -> Draw:
        """One env's sample: factors and offsets (:class:`Draw`). The generator is advanced by the
        same number of values whatever the widths, so that changing one width leaves the others'
        draws the same."""
        u = lambda *shape: rng.uniform(-1.0, 1.0, shape)
        k, c, m, i = u(n_springs), u(n_springs), u(n_rods), u(n_rods)
        off, ms, lat = u(n_springs), u(), rng.integers(0, self.latency + 1)
        cont = u(len(CONTACT_PARAMETERS))
        w = np.array([self.contact.get(name, 0.0) for name in CONTACT_PARAMETERS])
        return Draw(stiffness=1 + self.stiffness * k, damping=1 + self.damping * c, mass=1 + self.mass * m,
                    inertia=1 + self.inertia * i, rest_offset=self.rest_offset * off,
                    motor_speed=float(1 + self.motor_speed * ms), latency=int(lat), contact=1 + w * cont)


@dataclass
class Draw:
    """One env's draw: relative factors (``stiffness``, ``damping`` (S,), ``mass``, ``inertia``
    (R,), ``contact`` (16,) in :data:`CONTACT_PARAMETERS` order, ``motor_speed``), the cables' rest
    offsets (S,) m and the latency in control steps."""

    stiffness: np.ndarray
    damping: np.ndarray
    mass: np.ndarray
    inertia: np.ndarray
    rest_offset: np.ndarray
    motor_speed: float
    latency: int
    contact: np.ndarray


# ---------------------------------------------------------------------- auto
def _rel_se(values: Any, stderr: Any) -> float:
    """The largest relative standard error of a parameter group (0 where none is given)."""
    v = np.abs(np.asarray(values, dtype=float)).ravel()
    if stderr is None:
        return 0.0
    s = np.asarray(stderr, dtype=float).ravel()
    ok = np.isfinite(s) & (v > 0)
    return float(np.max(s[ok] / v[ok])) if ok.any() else 0.0


def auto_randomization(model: Any, frame_skip: int = 20) -> Randomization:
    """The ``auto`` widths of an :class:`identified.model.IdentifiedModel` (module docstring): from
    its standard errors, its contact law's unexplained variance and its one-step error, never from
    the MJCF."""
    notes: dict[str, Any] = {}
    se = getattr(model, "stderr", None) or {}

    def width(name: str, values: Any) -> float:
        rel = 3.0 * _rel_se(values, se.get(name) if isinstance(se, dict) else None)
        notes[f"{name}_3se_rel"] = rel
        return min(max(rel, PRIOR_WIDTH), 0.5)

    r = Randomization(stiffness=width("stiffness", model.stiffness), damping=width("damping", model.damping),
                      mass=width("mass", model.mass), inertia=width("inertia", model.inertia),
                      rest_offset=PRIOR_REST_OFFSET, motor_speed=PRIOR_MOTOR_SPEED, latency=1, source="auto")
    metrics = getattr(model, "metrics", None) or {}
    contact = next((e for e in getattr(model, "effects", []) if e.get("name") in CONTACT_LAWS), None)
    if contact is not None and contact.get("parameters"):
        stage = (metrics.get("residual_stage", {}) or {}).get(contact["name"], {}) or {}

        def base_width(key: str) -> float:
            ev = stage.get(key)
            notes[f"contact_{key}"] = ev
            if ev is None:
                return CONTACT_FLOOR
            return max(CONTACT_FACTOR * math.sqrt(max(0.0, 1.0 - float(ev))), CONTACT_FLOOR)

        force_base = base_width("explained_variance")
        torque_base = base_width("torque_explained_variance") if contact["name"] == "ground_contact" else force_base
        widths = {}
        vals, ses = contact["parameters"], contact.get("stderr") or {}
        for name in CONTACT_PARAMETERS:
            if name not in vals:  # a model file written before the contact torques: none to draw
                continue
            v, s = vals.get(name), ses.get(name)
            rel = 3.0 * abs(float(s) / float(v)) if s is not None and v not in (None, 0) else 0.0
            cap = GAMMA_MAX if name.startswith("gamma") else 0.5
            if name in IMPEDANCES and v is not None:
                cap = min(cap, 0.5 * (1.0 - float(v)) / float(v))
            base = torque_base if name in CONTACT_TORQUE_PARAMETERS else force_base
            widths[name] = float(min(max(base, rel), cap))
        r.contact = widths
    step = metrics.get("one_step_rms") or {}
    free = metrics.get("free_run") or {}
    walk = math.sqrt(max(int(frame_skip), 1))
    noise = {}
    for key in ("vel", "angvel"):
        if step.get(key) is not None and math.isfinite(float(step[key])):
            noise[key] = float(step[key]) * walk
    horizon = free.get("horizon")
    if horizon:
        per_control = math.sqrt(max(int(frame_skip), 1) / float(horizon))
        for key, group in (("pos_mean", "pos"), ("quat_mean", "rot")):
            if free.get(key) is not None and math.isfinite(float(free[key])):
                noise[group] = float(free[key]) * per_control
    r.obs_noise = noise
    notes["free_run"] = {k: free.get(k) for k in ("horizon", "pos_mean", "quat_mean")}
    notes["one_step_rms"] = {k: step.get(k) for k in ("pos", "vel", "angvel", "quat")}
    notes["frame_skip"] = int(frame_skip)
    r.notes = notes
    r.validate()
    return r


def load_randomization(path: str | os.PathLike) -> Randomization:
    """A randomization FILE (JSON, or YAML with PyYAML installed); ValueError naming the path."""
    p = os.fspath(path)
    if not os.path.isfile(p):
        raise ValueError(f"randomization file '{p}' does not exist or is not a file")
    with open(p, encoding="utf-8") as fh:
        text = fh.read()
    try:
        if p.endswith((".yaml", ".yml")):
            try:
                import yaml
            except ImportError:
                raise ValueError(f"'{p}': reading YAML needs PyYAML (pip install pyyaml), or give JSON") from None
            obj = yaml.safe_load(text)
        else:
            obj = json.loads(text)
    except (json.JSONDecodeError, ValueError) as exc:
        if "PyYAML" in str(exc):
            raise
        raise ValueError(f"randomization file '{p}' is not valid {'YAML' if p.endswith(('.yaml', '.yml')) else 'JSON'}: "
                         f"{str(exc).splitlines()[0]}") from None
    except Exception as exc:  # noqa: BLE001 - yaml's own error types
        raise ValueError(f"randomization file '{p}' is not valid YAML: {str(exc).splitlines()[0]}") from None
    try:
        return Randomization.from_json(obj, source=os.path.abspath(p))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"randomization file '{p}': {exc}") from None


def resolve_randomization(spec: str | Randomization | dict | None, model: Any, frame_skip: int = 20
                          ) -> Randomization | None:
    """``"auto"`` / ``"none"`` / ``None`` / a FILE path / a mapping / a :class:`Randomization` ->
    the randomization to train with (``None`` when nothing is drawn)."""
    if spec is None or (isinstance(spec, str) and spec == "none"):
        return None
    if isinstance(spec, Randomization):
        r = spec
    elif isinstance(spec, dict):
        r = Randomization.from_json(spec, source="mapping")
    elif spec == "auto":
        r = auto_randomization(model, frame_skip)
    else:
        r = load_randomization(spec)
    return r if r.active else None
