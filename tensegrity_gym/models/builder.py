"""MJCF generation for the spring-rod presets (``tensegrity model ...``).

Conventions written into every model (the contract the identification side parses as XML):

* rod ``i`` is ``<body name="rod{i}">`` with ``<freejoint name="rod{i}_free"/>`` and an explicit
  ``<inertial pos="0 0 0" mass=M diaginertia="I11 I11 I33"/>`` (uniform solid cylinder of radius r:
  I11 = M (L^2/12 + r^2/4), I33 = M r^2 / 2; paper appendix), rod axis = body z, COM = body origin;
* end points are sites ``rod{i}_end0`` at (0, 0, -L/2) and ``rod{i}_end1`` at (0, 0, +L/2);
* fixed nails are worldbody sites ``anchor{k}``;
* every spring/cable is a ``<spatial>`` tendon joining exactly two sites, with ``stiffness``,
  ``damping`` and ``springlength`` (push-pull spring: ``"L0"``; pull-only cable: ``"0 L0"``), named
  ``spring{j}`` (paper presets) or ``cable{j}`` (robot);
* actuated cables and their motor limits live in ``<custom>``: ``tensegrity_actuated`` (text),
  ``tensegrity_motor_speed``, ``tensegrity_rest_min``, ``tensegrity_rest_max`` (numeric);
* the robot has ``<key name="nominal">``: its settled standing pose.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from identified.dataset import atomic_write
from identified.rotation import matrix_to_quat
from tensegrity_gym.models import presets as P

__all__ = [
    "INTEGRATORS",
    "build_model",
    "closed_faces",
    "ico_cable_pairs",
    "ico_rod_geometry",
    "preset_parameters",
    "resolve_preset",
    "rod_inertia",
    "write_model",
]

#: builder keyword -> MJCF ``<option integrator=...>``
INTEGRATORS: dict[str, str] = {
    "euler": "Euler",
    "rk4": "RK4",
    "implicit": "implicit",
    "implicitfast": "implicitfast",
}


# ---------------------------------------------------------------------- geometry
def rod_inertia(mass: float, length: float, radius: float) -> tuple[float, float, float]:
    """Principal inertia (I11, I11, I33) of a uniform solid cylinder about its COM, rod axis = z.

    I11 = M (L^2/12 + r^2/4) (transverse), I33 = M r^2/2 (axial); paper, appendix "Torque in Rod
    Local Frame".
    """
    it = mass * (length**2 / 12.0 + radius**2 / 4.0)
    return it, it, mass * radius**2 / 2.0


def ico_rod_geometry(length: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres (6, 3) and unit axes (6, 3) of the expanded-octahedron icosahedron tensegrity.

    Three parallel pairs along x, y, z; the rods of a pair are L/2 apart (offsets +-L/4):
    rod0/rod1 along x at z = -/+ L/4, rod2/rod3 along y at x = -/+ L/4, rod4/rod5 along z at
    y = -/+ L/4. Then each rod end is sqrt(6)/4 L from four ends of the two other pairs, the cable
    length of the classic self-stressed tensegrity icosahedron (0.637 m for L = 1.04 m).
    """
    s = length / 4.0
    centres = np.array(
        [[0, 0, -s], [0, 0, s], [-s, 0, 0], [s, 0, 0], [0, -s, 0], [0, s, 0]], dtype=float
    )
    axes = np.array([[1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1]], dtype=float)
    return centres, axes


def _ends(centres: np.ndarray, axes: np.ndarray, length: float) -> np.ndarray:
    """(R, 2, 3) end points: end0 = c - L/2 a, end1 = c + L/2 a."""
    h = 0.5 * length * axes
    return np.stack([centres - h, centres + h], axis=1)


def ico_cable_pairs(ends: np.ndarray, distance: float, rtol: float = 1e-6) -> list[tuple[int, int, int, int]]:
    """Every pair of end points of different rods that are ``distance`` apart.

    Returns ``(i, e, j, f)`` tuples (rod i end e -- rod j end f, i < j) in lexicographic order.
    The pairs are found by computing all end-point distances, not hard-coded.
    """
    R = ends.shape[0]
    pairs = []
    for i in range(R):
        for e in range(2):
            for j in range(i + 1, R):
                for f in range(2):
                    d = float(np.linalg.norm(ends[i, e] - ends[j, f]))
                    if abs(d - distance) <= rtol * distance:
                        pairs.append((i, e, j, f))
    return pairs


def closed_faces(pairs: list[tuple[int, int, int, int]]) -> list[tuple[tuple[int, int], ...]]:
    """Triangles of end points joined pairwise by cables (the 8 closed faces of the icosahedron)."""
    nodes = sorted({(i, e) for i, e, _, _ in pairs} | {(j, f) for _, _, j, f in pairs})
    edges = {frozenset({(i, e), (j, f)}) for i, e, j, f in pairs}
    tri = []
    for a in range(len(nodes)):
        for b in range(a + 1, len(nodes)):
            for c in range(b + 1, len(nodes)):
                x, y, z = nodes[a], nodes[b], nodes[c]
                if {frozenset({x, y}), frozenset({y, z}), frozenset({x, z})} <= edges:
                    tri.append((x, y, z))
    return tri


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation matrix taking unit vector a to unit vector b (Rodrigues)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        # 180 degrees about any axis orthogonal to a
        perp = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 1.0, 0])
        perp /= np.linalg.norm(perp)
        return 2 * np.outer(perp, perp) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1.0 / (1.0 + c))


def _rotz(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _axis_frame(axis: np.ndarray) -> np.ndarray:
    """A rotation whose z column is ``axis``: the rod body frame (canonical choice per world axis)."""
    return _rotation_between(np.array([0.0, 0.0, 1.0]), axis)


# ---------------------------------------------------------------------- the model description
@dataclass
class _Rod:
    name: str
    mass: float
    inertia: tuple[float, float, float]
    length: float
    radius: float
    pos: np.ndarray
    rot: np.ndarray  # body frame -> world


@dataclass
class _Tendon:
    name: str
    sites: tuple[str, str]
    stiffness: float
    damping: float
    rest: float
    pull_only: bool


@dataclass
class _Spec:
    system: str
    preset: str
    seed: int | None
    rods: list[_Rod]
    tendons: list[_Tendon]
    anchors: dict[str, np.ndarray] = field(default_factory=dict)
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    timestep: float = 0.001
    ground: bool = False
    friction: float = 0.9
    torsional_friction: float = 0.02
    rolling_friction: float = 0.002
    actuated: list[str] = field(default_factory=list)
    motor_speed: float = 0.0
    rest_min: list[float] = field(default_factory=list)
    rest_max: list[float] = field(default_factory=list)
    settle_time: float = 0.0
    notes: str = ""


def resolve_preset(system: str, preset: str | None = None) -> str:
    """The preset name that ``preset`` means for ``system`` (``None`` -> the default).

    Raises:
        ValueError: unknown system or preset, naming the valid ones.
    """
    return _resolve(system, preset)[1]


def _resolve(system: str, preset: str | None) -> tuple[str, str]:
    if system not in P.SYSTEMS:
        raise ValueError(f"unknown system '{system}'; valid systems are: {', '.join(P.SYSTEMS)}")
    if preset is None:
        preset = P.DEFAULT_PRESET[system]
    if preset not in P.SYSTEMS[system]:
        raise ValueError(
            f"unknown preset '{preset}' for system '{system}'; valid presets are: "
            f"{', '.join(P.SYSTEMS[system])}"
        )
    return system, preset


def _check_overrides(overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    o = dict(overrides or {})
    bad = sorted(set(o) - set(P.OVERRIDE_KEYS))
    if bad:
        raise ValueError(
            f"unknown override(s) {', '.join(bad)}; valid overrides are: {', '.join(P.OVERRIDE_KEYS)}"
        )
    for k, v in o.items():
        if k == "gravity":
            g = np.asarray(v, dtype=float)
            if g.shape != (3,) or not np.all(np.isfinite(g)):
                raise ValueError(f"override gravity must be 3 finite numbers, got {v!r}")
            o[k] = tuple(float(x) for x in g)
        else:
            try:
                x = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"override {k} must be a number, got {v!r}") from None
            if k == "damping_scale":  # 0 is allowed: an undamped (energy-conserving) plant
                if not (math.isfinite(x) and x >= 0):
                    raise ValueError(f"override {k} must be a finite number >= 0, got {v!r}")
            elif not (math.isfinite(x) and x > 0):
                raise ValueError(f"override {k} must be a finite number > 0, got {v!r}")
            o[k] = x
    return o


def _make_spec(
    system: str, preset: str | None, seed: int | None, overrides: Mapping[str, Any] | None
) -> _Spec:
    system, preset = _resolve(system, preset)
    o = _check_overrides(overrides)
    ks, cs = o.get("stiffness_scale", 1.0), o.get("damping_scale", 1.0)
    ms, js, rs = o.get("mass_scale", 1.0), o.get("inertia_scale", 1.0), o.get("rest_scale", 1.0)

    def rod(name: str, mass: float, length: float, radius: float, pos: np.ndarray, rot: np.ndarray) -> _Rod:
        m = mass * ms
        inertia = tuple(js * x for x in rod_inertia(m, length, radius))
        return _Rod(name, m, inertia, length, radius, np.asarray(pos, float), rot)  # type: ignore[arg-type]

    if system == "simple":
        p = P.SIMPLE_PAPER
        L = p.rod_length
        # Rod along x at the origin: end0 at (-L/2, 0, 0), end1 at (+L/2, 0, 0). Nail anchor0 lies
        # 1.0 m beyond end0 along -x (spring0 straight along the rod); nail anchor1 lies 1.414 m from
        # end1 at 45 degrees in the x-y plane (spring1 diagonal). Both springs start exactly at their
        # rest length, so the built pose is an equilibrium (gravity is off).
        r0, r1 = p.rest_lengths
        e0, e1 = np.array([-L / 2, 0, 0]), np.array([L / 2, 0, 0])
        anchors = {
            "anchor0": e0 + r0 * np.array([-1.0, 0, 0]),
            "anchor1": e1 + r1 * np.array([1.0, 1.0, 0]) / math.sqrt(2.0),
        }
        rods = [rod("rod0", p.mass, L, p.rod_radius, np.zeros(3), _axis_frame(np.array([1.0, 0, 0])))]
        tendons = [
            _Tendon("spring0", ("rod0_end0", "anchor0"), p.stiffness * ks, p.damping * cs, r0 * rs, False),
            _Tendon("spring1", ("rod0_end1", "anchor1"), p.stiffness * ks, p.damping * cs, r1 * rs, False),
        ]
        return _Spec(system, preset, seed, rods, tendons, anchors=anchors,
                     gravity=o.get("gravity", p.gravity), timestep=o.get("timestep", p.timestep))

    if preset in ("paper-uniform", "paper-nonuniform"):
        p = P.ICO_PAPER
        L = p.rod_length
        centres, axes = ico_rod_geometry(L)
        pairs = ico_cable_pairs(_ends(centres, axes, L), math.sqrt(6.0) / 4.0 * L)
        masses = np.full(6, p.mass)
        K = np.full(len(pairs), p.stiffness)
        c = np.full(len(pairs), p.damping)
        if preset == "paper-nonuniform":
            seed = 0 if seed is None else int(seed)
            # 54 draws in one stream: 6 masses, then 24 K, then 24 c; value * (1 + 0.2 N(0, 1)),
            # clipped below at 0.2 * value (paper: "Gaussian noise ... sigma = 0.2 * parameter").
            z = np.random.default_rng(seed).standard_normal(6 + 2 * len(pairs))
            f = np.maximum(1.0 + P.NONUNIFORM_SIGMA * z, P.NONUNIFORM_FLOOR)
            masses = masses * f[:6]
            K = K * f[6 : 6 + len(pairs)]
            c = c * f[6 + len(pairs) :]
        else:
            seed = None
        rods = [rod(f"rod{i}", masses[i], L, p.rod_radius, centres[i], _axis_frame(axes[i]))
                for i in range(6)]
        tendons = [
            _Tendon(f"spring{j}", (f"rod{i}_end{e}", f"rod{k}_end{g}"), K[j] * ks, c[j] * cs,
                    p.rest_length * rs, False)
            for j, (i, e, k, g) in enumerate(pairs)
        ]
        return _Spec(system, preset, seed, rods, tendons,
                     gravity=o.get("gravity", p.gravity), timestep=o.get("timestep", p.timestep))

    # robot
    p = P.ICO_ROBOT
    L = p.rod_length
    centres, axes = ico_rod_geometry(L)
    ends = _ends(centres, axes, L)
    pairs = ico_cable_pairs(ends, p.nominal_cable_length)
    rot = _robot_rotation(ends, pairs)
    centres, axes = centres @ rot.T, axes @ rot.T
    ends = _ends(centres, axes, L)
    # lift so that the lowest end point sits one capsule radius above the ground
    lift = p.rod_radius - ends[..., 2].min()
    centres = centres + np.array([0.0, 0.0, lift])
    rods = [rod(f"rod{i}", p.mass, L, p.rod_radius, centres[i], _axis_frame(axes[i])) for i in range(6)]
    rest = p.rest_length * rs
    tendons = [
        _Tendon(f"cable{j}", (f"rod{i}_end{e}", f"rod{k}_end{g}"), p.stiffness * ks, p.damping * cs,
                rest, True)
        for j, (i, e, k, g) in enumerate(pairs)
    ]
    names = [t.name for t in tendons]
    return _Spec(
        system, preset, None, rods, tendons,
        gravity=o.get("gravity", p.gravity), timestep=o.get("timestep", p.timestep),
        ground=True, friction=o.get("friction", p.friction), torsional_friction=p.torsional_friction,
        rolling_friction=p.rolling_friction, actuated=names,
        motor_speed=p.motor_speed,
        rest_min=[p.rest_min_ratio * p.rest_length * rs] * len(names),
        rest_max=[p.rest_max_ratio * p.rest_length * rs] * len(names),
        settle_time=p.settle_time,
    )


#: the closed face the robot stands on: rod0 end0, rod2 end0, rod4 end0 (the (-,-,-) octant face)
ROBOT_BASE_FACE: tuple[tuple[int, int], ...] = ((0, 0), (2, 0), (4, 0))
#: yaw (about world z, rad) applied after putting the base face down; chosen so that the first
#: roll of :func:`tensegrity_gym.cables.scripted_roll_targets` goes along +x.
ROBOT_YAW: float = 0.0


def _robot_rotation(ends: np.ndarray, pairs: list[tuple[int, int, int, int]]) -> np.ndarray:
    """World rotation that puts the closed face ROBOT_BASE_FACE down, flat on the ground."""
    face = np.array([ends[i, e] for i, e in ROBOT_BASE_FACE])
    n = face.mean(axis=0)  # points from the centre through the face
    down = _rotation_between(n, np.array([0.0, 0.0, -1.0]))
    return _rotz(ROBOT_YAW) @ down


# ---------------------------------------------------------------------- ground truth as data
def preset_parameters(
    system: str,
    preset: str | None = None,
    seed: int | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The ground-truth parameters of a preset, as written into its MJCF.

    Returns a dict with ``system``, ``preset``, ``seed``, ``gravity`` (3,), ``timestep``,
    ``rods`` (list of ``{name, mass, inertia: [I11, I22, I33], length, radius}``), ``springs``
    (list of ``{name, sites: [a, b], stiffness, damping, rest_length, pull_only}``), ``actuated``
    (names) and ``motor`` (``{speed, rest_min, rest_max}``; empty lists when nothing is actuated).
    The ``rods``/``springs`` keys and fields match the identified-model JSON, so a test compares
    them name by name.
    """
    s = _make_spec(system, preset, seed, overrides)
    return {
        "system": s.system,
        "preset": s.preset,
        "seed": s.seed,
        "gravity": list(s.gravity),
        "timestep": s.timestep,
        "rods": [
            {"name": r.name, "mass": r.mass, "inertia": list(r.inertia), "length": r.length,
             "radius": r.radius}
            for r in s.rods
        ],
        "springs": [
            {"name": t.name, "sites": list(t.sites), "stiffness": t.stiffness, "damping": t.damping,
             "rest_length": t.rest, "pull_only": t.pull_only}
            for t in s.tendons
        ],
        "anchors": {k: v.tolist() for k, v in s.anchors.items()},
        "actuated": list(s.actuated),
        "motor": {"speed": s.motor_speed, "rest_min": list(s.rest_min), "rest_max": list(s.rest_max)},
    }


# ---------------------------------------------------------------------- XML
def _f(x: float) -> str:
    """Shortest text that reads back as the same float."""
    x = float(x)
    if x == 0.0:
        return "0"
    return repr(x)


def _v(xs: Any) -> str:
    return " ".join(_f(x) for x in np.asarray(xs, dtype=float).ravel())


def _to_xml(s: _Spec, integrator: str, keyframe: np.ndarray | None) -> str:
    root = ET.Element("mujoco", model=f"{s.system}-{s.preset}")
    root.append(ET.Comment(
        f" tensegrity-gym {s.system}/{s.preset}" + (f" seed {s.seed}" if s.seed is not None else "")
        + ": generated by tensegrity_gym.models.build_model; ground truth in preset_parameters() "
    ))
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "option", timestep=_f(s.timestep), gravity=_v(s.gravity), integrator=integrator)
    vis = ET.SubElement(root, "visual")
    ET.SubElement(vis, "global", offwidth="1280", offheight="960")
    ET.SubElement(vis, "headlight", ambient="0.4 0.4 0.4", diffuse="0.6 0.6 0.6")

    asset = ET.SubElement(root, "asset")
    ET.SubElement(asset, "texture", name="grid", type="2d", builtin="checker", rgb1="0.25 0.3 0.35",
                  rgb2="0.15 0.2 0.25", width="512", height="512")
    ET.SubElement(asset, "material", name="grid", texture="grid", texrepeat="1 1", texuniform="true")
    ET.SubElement(asset, "material", name="rod", rgba="0.85 0.45 0.15 1")

    friction = f"{_f(s.friction)} {_f(s.torsional_friction)} {_f(s.rolling_friction)}"
    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "light", name="sun", pos="0 0 6", dir="0 0 -1", directional="true")
    if s.ground:
        # The ground collides with rods only (conaffinity 1); rods never collide with each other
        # (rod contype 1, conaffinity 0). condim 6: sliding, torsional and rolling friction; without
        # the last two a rod end cap rolling on the ground spins the rod about its own axis
        # (axial inertia M r^2/2 is tiny) at tens of rad/s, and nothing in the cables damps that spin.
        ET.SubElement(world, "geom", name="ground", type="plane", size="0 0 0.05", material="grid",
                      contype="0", conaffinity="1", condim="6", friction=friction)
    for name, pos in s.anchors.items():
        ET.SubElement(world, "site", name=name, pos=_v(pos), size="0.04", rgba="0.2 0.2 0.2 1")
    for r in s.rods:
        b = ET.SubElement(world, "body", name=r.name, pos=_v(r.pos), quat=_v(matrix_to_quat(r.rot)))
        ET.SubElement(b, "freejoint", name=f"{r.name}_free")
        ET.SubElement(b, "inertial", pos="0 0 0", mass=_f(r.mass), diaginertia=_v(r.inertia))
        h = r.length / 2
        geom = {"name": f"{r.name}_geom", "type": "capsule", "fromto": _v([0, 0, -h, 0, 0, h]),
                "size": _f(r.radius), "material": "rod"}
        if s.ground:
            geom.update(contype="1", conaffinity="0", condim="6", friction=friction)
        else:
            geom.update(contype="0", conaffinity="0")
        ET.SubElement(b, "geom", **geom)
        ET.SubElement(b, "site", name=f"{r.name}_end0", pos=_v([0, 0, -h]), size=_f(1.2 * r.radius))
        ET.SubElement(b, "site", name=f"{r.name}_end1", pos=_v([0, 0, h]), size=_f(1.2 * r.radius))

    tendon = ET.SubElement(root, "tendon")
    for t in s.tendons:
        spring = f"0 {_f(t.rest)}" if t.pull_only else _f(t.rest)
        rgba = "0.2 0.5 0.9 1" if t.name in s.actuated else "0.3 0.8 0.3 1"
        sp = ET.SubElement(tendon, "spatial", name=t.name, stiffness=_f(t.stiffness), damping=_f(t.damping),
                           springlength=spring, width="0.008", rgba=rgba)
        ET.SubElement(sp, "site", site=t.sites[0])
        ET.SubElement(sp, "site", site=t.sites[1])

    if s.actuated:
        custom = ET.SubElement(root, "custom")
        ET.SubElement(custom, "text", name="tensegrity_actuated", data=" ".join(s.actuated))
        ET.SubElement(custom, "numeric", name="tensegrity_motor_speed", data=_f(s.motor_speed))
        ET.SubElement(custom, "numeric", name="tensegrity_rest_min", data=_v(s.rest_min))
        ET.SubElement(custom, "numeric", name="tensegrity_rest_max", data=_v(s.rest_max))

    if keyframe is not None:
        kf = ET.SubElement(root, "keyframe")
        ET.SubElement(kf, "key", name="nominal", qpos=_v(keyframe))

    ET.indent(root, space="  ")
    return ET.tostring(root, encoding="unicode") + "\n"


def _settle(xml: str, settle_time: float) -> np.ndarray:
    """qpos after ``settle_time`` seconds of simulation from the built pose with neutral cables."""
    import mujoco

    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    # The equilibrium does not depend on damping: first settle with 10x cable damping under the
    # (unconditionally stable) implicit integrator, then let the true model run for 1 s.
    integrator, damping = int(m.opt.integrator), m.tendon_damping.copy()
    m.opt.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    m.tendon_damping[:] = 10.0 * damping
    for _ in range(round(settle_time / m.opt.timestep)):
        mujoco.mj_step(m, d)
    m.opt.integrator, m.tendon_damping[:] = integrator, damping
    for _ in range(round(1.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    if not np.all(np.isfinite(d.qpos)):
        raise RuntimeError("the robot diverged while settling; check the preset parameters")
    q = d.qpos.copy()
    for i in range(m.njnt):  # unit quaternions, exactly
        a = m.jnt_qposadr[i]
        q[a + 3 : a + 7] /= np.linalg.norm(q[a + 3 : a + 7])
    return q


def build_model(
    system: str,
    preset: str | None = None,
    seed: int | None = None,
    integrator: str = "euler",
    overrides: Mapping[str, Any] | None = None,
) -> str:
    """MJCF text of a preset system.

    Args:
        system: ``"simple"`` or ``"ico"``.
        preset: ``simple``: ``"paper"``; ``ico``: ``"paper-uniform"``, ``"paper-nonuniform"``,
            ``"robot"``. ``None`` takes the default (``paper`` / ``robot``).
        seed: draws of ``paper-nonuniform`` (``None`` means 0); ignored by the other presets.
        integrator: ``"euler"`` (MuJoCo's default semi-implicit Euler), ``"rk4"``, ``"implicit"`` or
            ``"implicitfast"``.
        overrides: rescale the truth to make unseen plants, e.g. ``{"stiffness_scale": 2.0,
            "mass_scale": 0.5}``; keys in :data:`presets.OVERRIDE_KEYS`.

    Raises:
        ValueError: unknown system, preset, integrator or override.
    """
    key = str(integrator).lower()
    if key not in INTEGRATORS:
        raise ValueError(
            f"unknown integrator '{integrator}'; valid integrators are: {', '.join(INTEGRATORS)}"
        )
    spec = _make_spec(system, preset, seed, overrides)
    keyframe = None
    if spec.settle_time > 0:
        keyframe = _settle(_to_xml(spec, INTEGRATORS[key], None), spec.settle_time)
    return _to_xml(spec, INTEGRATORS[key], keyframe)


def write_model(
    path: str | os.PathLike,
    system: str,
    preset: str | None = None,
    seed: int | None = None,
    integrator: str = "euler",
    overrides: Mapping[str, Any] | None = None,
) -> str:
    """Build a preset (see :func:`build_model`) and write it to ``path`` atomically.

    The text goes to a temporary file in the same directory, which then replaces ``path``
    (``os.replace``), so ``path`` never holds half a model. Returns the XML text.
    """
    xml = build_model(system, preset, seed=seed, integrator=integrator, overrides=overrides)
    atomic_write(path, lambda fh: fh.write(xml))
    return xml
