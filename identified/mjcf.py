"""Reading MJCF files: the one place that reads the model files.

Two readers. :func:`read_system` compiles the MJCF with MuJoCo (to read it, never to step it) and
returns its :class:`SystemDescription`: rods, their sites in the rod frames, cables and actuators,
from the model as MuJoCo compiles it, so ``<default>`` classes, ``childclass``, ``euler``/
``xyaxes``/``axisangle`` frames, nested bodies and the compiler's frame alignment are resolved
exactly as the plant sees them. The topology (:mod:`identified.topology`) is built on it. This
module is the only one of ``identified`` that imports MuJoCo, and it only compiles.

The XML helpers below it (``custom_entries``, ``nominal_pose``, ``spring_lengths``) read the
project's own keys from the text, for the cable motors (:mod:`tensegrity_gym.cables`) and the
twin's nominal pose and neutral rest lengths (:mod:`tensegrity_gym.backends.identified_backend`).

MJCF conventions of the project (the README's "MJCF conventions"): every rod is a top-level
``<body>`` with a free joint (``<freejoint/>`` or ``<joint type="free"/>``); rod end points are
sites; every spring is a ``<spatial>`` tendon between two sites, a pull-only cable has the dead
band ``springlength="0 L"``; the project's own keys (actuated cables, motor speed and bounds) are
``<text>`` and ``<numeric>`` entries of ``<custom>``; the standing pose is keyframe ``nominal``.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from identified.state import RodState

__all__ = [
    "ACTUATED_KEY",
    "ActuatorInfo",
    "MjcfError",
    "RodInfo",
    "SystemDescription",
    "TendonInfo",
    "compile_mjcf",
    "custom_entries",
    "floats",
    "free_bodies",
    "is_free_body",
    "nominal_pose",
    "nominal_qpos",
    "parse_mjcf",
    "read_mjcf_text",
    "read_system",
    "spring_lengths",
]

#: ``<custom><text name=...>`` listing the actuated cables, space separated, in command order.
ACTUATED_KEY = "tensegrity_actuated"


def read_mjcf_text(source: str | os.PathLike, error: type[Exception] = ValueError) -> str:
    """The MJCF text of ``source``: a path, or MJCF text itself (it starts with ``<``).

    An unreadable file raises ``error`` ("cannot read model file ...")."""
    s = os.fspath(source)
    if s.lstrip().startswith("<"):
        return s
    try:
        with open(s, encoding="utf-8") as fh:
            return fh.read()
    except OSError as exc:
        raise error(f"cannot read model file '{s}': {exc.strerror}") from None


def parse_mjcf(text: str, error: type[Exception] = ValueError) -> ET.Element:
    """The root element of MJCF text; malformed XML raises ``error`` ("not a valid MJCF/XML ...")."""
    try:
        return ET.fromstring(text)
    except ET.ParseError as exc:
        raise error(f"not a valid MJCF/XML file: {exc}") from None


def floats(text: str | None) -> np.ndarray:
    """The numbers of an attribute (``"0 0 1"``) as a float64 array; empty for ``None``."""
    return np.array([float(x) for x in (text or "").split()], dtype=float)


def is_free_body(body: ET.Element) -> bool:
    """True when ``body`` has a free joint (``<freejoint/>`` or ``<joint type="free"/>``)."""
    if body.find("freejoint") is not None:
        return True
    j = body.find("joint")
    return j is not None and j.get("type") == "free"


def free_bodies(root: ET.Element) -> list[ET.Element]:
    """The top-level bodies of ``<worldbody>`` that have a free joint, in document order (the
    order of their 7 numbers in MuJoCo's ``qpos``)."""
    world = root.find("worldbody")
    if world is None:
        raise ValueError("MJCF has no <worldbody>")
    return [b for b in world.findall("body") if is_free_body(b)]


def custom_entries(root: ET.Element) -> tuple[dict[str, str], dict[str, np.ndarray]]:
    """The ``<custom>`` section: ``<text>`` entries (name -> data) and ``<numeric>`` entries
    (name -> numbers)."""
    texts: dict[str, str] = {}
    numerics: dict[str, np.ndarray] = {}
    custom = root.find("custom")
    if custom is not None:
        for t in custom.findall("text"):
            texts[t.get("name", "")] = t.get("data") or ""
        for n in custom.findall("numeric"):
            numerics[n.get("name", "")] = floats(n.get("data"))
    return texts, numerics


def spring_lengths(text: str) -> dict[str, float]:
    """Rest length written in every spatial tendon's ``springlength`` (the upper value of a dead band)."""
    root = parse_mjcf(text)
    out: dict[str, float] = {}
    tendon = root.find("tendon")
    for t in ([] if tendon is None else tendon.findall("spatial")):
        v = floats(t.get("springlength"))
        if t.get("name") and v.size:
            out[t.get("name")] = float(v[-1])  # type: ignore[index]
    return out


def nominal_pose(text: str, rod_names: Sequence[str]) -> RodState:
    """The nominal pose of the rods, from MJCF text alone (no MuJoCo): keyframe ``nominal``.

    A rod is a top-level body with a free joint; in MuJoCo's ``qpos`` every such body holds 7
    numbers (position, then quaternion w-x-y-z) in document order. Without a keyframe ``nominal``
    the bodies' ``pos``/``quat`` attributes are used (MuJoCo's ``qpos0``). Velocities are zero, as
    in the plant's reset. Quaternions are normalised exactly as ``MujocoPlant.states`` does, so
    the pose is bit-identical to the plant's nominal pose. Returns float64 (R, ·) arrays.
    """
    root = parse_mjcf(text)
    free = free_bodies(root)
    names = [b.get("name") for b in free]
    missing = [r for r in rod_names if r not in names]
    if missing:
        raise ValueError(f"the MJCF has no free body for the rods {missing}")
    key = None
    kf = root.find("keyframe")
    if kf is not None:
        key = next((k for k in kf.findall("key") if k.get("name") == "nominal"), None)
    if key is not None and key.get("qpos"):
        qpos = floats(key.get("qpos"))
        if qpos.size != 7 * len(free):
            raise ValueError(f"keyframe 'nominal' has {qpos.size} qpos values, expected {7 * len(free)} "
                             f"(7 per free body)")
        table = qpos.reshape(len(free), 7)
    else:
        rows = []
        for b in free:
            if any(b.get(k) for k in ("euler", "axisangle", "xyaxes", "zaxis")):
                raise ValueError(f"rod body '{b.get('name')}' gives its orientation other than as quat; "
                                 "add a keyframe 'nominal'")
            pos = floats(b.get("pos")) if b.get("pos") else np.zeros(3)
            quat = floats(b.get("quat")) if b.get("quat") else np.array([1.0, 0.0, 0.0, 0.0])
            rows.append(np.concatenate([pos, quat]))
        table = np.array(rows)
    idx = [names.index(r) for r in rod_names]
    q = table[idx]
    pos, quat = q[:, :3].copy(), q[:, 3:7].copy()
    quat /= np.sqrt(np.einsum("ri,ri->r", quat, quat))[:, None]
    zeros = np.zeros_like(pos)
    return RodState(pos=pos, quat=quat, vel=zeros, angvel=zeros.copy())


# ====================================================================== the compiled model
class MjcfError(ValueError):
    """An MJCF that cannot be read as a spring-rod system; the message names the element."""


@dataclass(frozen=True)
class RodInfo:
    """A rod: a free-jointed body with all its jointless descendants, one rigid body.

    Its frame is the free body's compiled frame (MuJoCo's ``xpos``/``xquat``, the frame its free
    joint's ``qpos`` describes). ``sites`` are every site of the rod's bodies, in model order, with
    ``site_pos`` their positions in that frame (m); ``attachments`` the sites tendons use.
    """

    name: str
    body: int
    bodies: tuple[str, ...]
    sites: tuple[str, ...]
    site_pos: np.ndarray = field(repr=False)  # (n, 3)
    attachments: tuple[str, ...]
    radius: float  # largest capsule/cylinder radius of its geoms, m (0 if none): geometry only
    #: the capsule its collision geoms span (rod frame, m): the two geom points farthest apart
    #: (capsule and cylinder ends, sphere centres) and the larger radius there; None without one
    contact_segment: np.ndarray | None = field(default=None, repr=False)  # (2, 3)
    contact_radius: float = 0.0


@dataclass(frozen=True)
class TendonInfo:
    """A spatial tendon: the sites it is routed over, in order, and its kind of spring.

    ``deadband`` is the kind of its ``springlength``: ``"none"`` (one rest length: pushes and
    pulls), ``"pull_only"`` (``"0 L"``: slack below L) or ``"two_sided"`` (``"a b"``, a > 0: slack
    between a and b). ``limited`` marks a length limit (a constraint). The values are not read.
    """

    name: str
    sites: tuple[str, ...]
    deadband: str
    limited: bool


@dataclass(frozen=True)
class ActuatorInfo:
    """A control input: a MuJoCo tendon actuator, or a rest-length motor of the project.

    ``kind``: ``"motor"`` (force = gain * act), ``"general"`` (force = gain * act + affine bias in
    the tendon's length and velocity: MuJoCo's ``position`` and biased ``general``) or
    ``"rest_length"`` (the project's motor: the command is the cable's rest length).
    ``dynamics``: ``"none"``, ``"filter"``, ``"filterexact"`` or ``"integrator"`` (the activation
    the force acts on). ``ctrlrange``: (low, high) of the command, ``None`` when unlimited. Gains,
    biases and time constants are physical values and are not read here.
    """

    name: str
    kind: str
    tendon: str
    dynamics: str
    ctrlrange: tuple[float, float] | None


@dataclass(frozen=True)
class SystemDescription:
    """Topology and geometry of a spring-rod system, from the model as MuJoCo compiles it.

    ``site_rod[s]`` is the rod index of site ``s`` (-1: fixed to the world), ``site_pos[s]`` its
    position in that rod's frame (in the world frame for a fixed site).
    """

    rods: tuple[RodInfo, ...]
    tendons: tuple[TendonInfo, ...]
    actuators: tuple[ActuatorInfo, ...]
    site_rod: dict[str, int]
    site_pos: dict[str, np.ndarray]
    ground: float | None  # height of a ground plane (a plane geom fixed to the world), m
    #: the first plane geom fixed to the world: its unit normal and its offset along it, m
    plane: tuple[np.ndarray, float] | None = None


_DYN = {"mjDYN_NONE": "none", "mjDYN_FILTER": "filter", "mjDYN_FILTEREXACT": "filterexact",
        "mjDYN_INTEGRATOR": "integrator"}


def compile_mjcf(source: str | os.PathLike, error: type[Exception] = MjcfError) -> Any:
    """``mujoco.MjModel`` of an MJCF path or text (compiled to read it: never stepped here).

    A file MuJoCo cannot load raises ``error`` with MuJoCo's own message on one line."""
    import mujoco

    s = os.fspath(source)
    text = s.lstrip().startswith("<")
    if not text and not os.path.isfile(s):
        raise error(f"cannot read model file '{s}': no such file")
    try:
        return mujoco.MjModel.from_xml_string(s) if text else mujoco.MjModel.from_xml_path(s)
    except ValueError as exc:
        lines = [x.strip() for x in str(exc).strip().splitlines() if x.strip()]
        where = "the model" if text else f"'{s}'"
        raise error(f"MuJoCo cannot load {where}: {'; '.join(lines) if lines else exc}") from None


def read_system(source: str | os.PathLike | Any, error: type[Exception] = MjcfError) -> SystemDescription:
    """The spring-rod system of an MJCF (path, text or compiled ``mujoco.MjModel``).

    Geometry comes from the compiled model (defaults, classes, ``childclass``, ``euler``/``xyaxes``
    /``axisangle`` frames, nested bodies and the compiler's frame alignment all resolved), topology
    from its structure: a rod is a free-jointed body with all its jointless descendants; a cable
    is a spatial tendon over sites on rods or fixed to the world; an actuator is a MuJoCo tendon
    actuator or a rest-length motor (``<custom>`` ``tensegrity_actuated``). Stiffness, damping,
    rest lengths, masses, inertias and gains are never read.

    Raises ``error`` with one line naming the element for anything that is not such a system: a
    body with a joint that is not a free rod, a tendon over a site on no rod, a tendon between two
    sites of one rod, a rod with fewer than two attachment sites, a rod no cable attaches (the
    model falls apart), an actuator that does not act on a tendon.
    """
    import mujoco

    m = source if isinstance(source, mujoco.MjModel) else compile_mjcf(source, error)
    obj = mujoco.mjtObj

    def name(kind: Any, i: int, fallback: str) -> str:
        return mujoco.mj_id2name(m, kind, i) or f"{fallback}#{i}"

    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)  # body and site poses at qpos0 (kinematics only, no dynamics)

    # rods: free bodies (children of the world), with every body welded to them
    rods_b = [b for b in range(1, m.nbody) if m.body_jntnum[b] == 1
              and m.jnt_type[m.body_jntadr[b]] == mujoco.mjtJoint.mjJNT_FREE]
    if not rods_b:
        raise error("the model has no rods: no body with a free joint")
    rod_of_body = np.full(m.nbody, -2)  # -2: moves but is no rod, -1: fixed to the world
    for b in range(m.nbody):
        w = m.body_weldid[b]
        if w == 0 and m.body_mocapid[m.body_rootid[b]] < 0:
            rod_of_body[b] = -1
        elif w in rods_b:
            rod_of_body[b] = rods_b.index(w)
    site_rod: dict[str, int] = {}
    site_pos: dict[str, np.ndarray] = {}
    site_names = [name(obj.mjOBJ_SITE, i, "site") for i in range(m.nsite)]
    for i, sname in enumerate(site_names):
        r = int(rod_of_body[m.site_bodyid[i]])
        site_rod[sname] = r
        if r >= 0:
            b = rods_b[r]
            rot = d.xmat[b].reshape(3, 3)
            site_pos[sname] = rot.T @ (d.site_xpos[i] - d.xpos[b])
        else:
            site_pos[sname] = d.site_xpos[i].copy()

    # tendons
    tendons: list[TendonInfo] = []
    used: dict[int, list[str]] = {r: [] for r in range(len(rods_b))}
    for t in range(m.ntendon):
        tname = name(obj.mjOBJ_TENDON, t, "tendon")
        a, n = m.tendon_adr[t], m.tendon_num[t]
        types = m.wrap_type[a:a + n]
        if not np.all(types == mujoco.mjtWrap.mjWRAP_SITE):
            kinds = {int(mujoco.mjtWrap.mjWRAP_JOINT): "a fixed tendon (joint coupling)",
                     int(mujoco.mjtWrap.mjWRAP_PULLEY): "routed over a pulley",
                     int(mujoco.mjtWrap.mjWRAP_SPHERE): "wrapped over a geom",
                     int(mujoco.mjtWrap.mjWRAP_CYLINDER): "wrapped over a geom"}
            what = next((kinds[int(k)] for k in types if int(k) in kinds), "not a chain of sites")
            raise error(f"tendon '{tname}' is {what}: a cable must be a spatial tendon over sites")
        sites = tuple(site_names[int(i)] for i in m.wrap_objid[a:a + n])
        for s in sites:
            if site_rod[s] == -2:
                body = name(obj.mjOBJ_BODY, int(m.site_bodyid[site_names.index(s)]), "body")
                raise error(f"tendon '{tname}' uses site '{s}' on body '{body}', which is neither on a rod "
                            "(a free body and its jointless descendants) nor fixed to the world")
        owners = [site_rod[s] for s in sites]
        for k in range(len(sites) - 1):
            if owners[k] == owners[k + 1]:
                where = "the world" if owners[k] < 0 else f"rod '{name(obj.mjOBJ_BODY, rods_b[owners[k]], 'body')}'"
                raise error(f"tendon '{tname}' joins two sites of {where} ('{sites[k]}', '{sites[k + 1]}'): "
                            "a cable must join two bodies")
        for s, r in zip(sites, owners, strict=True):
            if r >= 0 and s not in used[r]:
                used[r].append(s)
        lo, hi = m.tendon_lengthspring[t]
        deadband = "none" if lo == hi else ("pull_only" if lo <= 0 else "two_sided")
        tendons.append(TendonInfo(tname, sites, deadband, bool(m.tendon_limited[t])))

    # bodies that move but are not rods: their state would be missing from the rods'
    for b in range(1, m.nbody):
        if rod_of_body[b] == -2:
            bname = name(obj.mjOBJ_BODY, b, "body")
            if m.body_mocapid[b] >= 0:
                raise error(f"body '{bname}' is a mocap body: a spring-rod model has rods (free bodies) and "
                            "bodies fixed to the world only")
            j = m.body_jntadr[b] if m.body_jntnum[b] else m.body_jntadr[m.body_weldid[b]]
            jtype = str(mujoco.mjtJoint(m.jnt_type[j]).name).removeprefix("mjJNT_").lower()
            raise error(f"body '{bname}' moves on a {jtype} joint: a rod must be a free body with jointless "
                        "descendants (one rigid body)")

    rods: list[RodInfo] = []
    for r, b in enumerate(rods_b):
        rname = name(obj.mjOBJ_BODY, b, "body")
        bodies = [bb for bb in range(m.nbody) if rod_of_body[bb] == r]
        sites = [s for i, s in enumerate(site_names) if rod_of_body[m.site_bodyid[i]] == r]
        radius = 0.0
        rot_r, pos_r = d.xmat[b].reshape(3, 3), d.xpos[b]
        points: list[tuple[np.ndarray, float]] = []  # collision geom points in the rod frame, radius
        for g in range(m.ngeom):
            if rod_of_body[m.geom_bodyid[g]] != r:
                continue
            kind = int(m.geom_type[g])
            if kind in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
                radius = max(radius, float(m.geom_size[g, 0]))
            if not (m.geom_contype[g] or m.geom_conaffinity[g]):
                continue
            centre = rot_r.T @ (d.geom_xpos[g] - pos_r)
            if kind in (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
                axis = rot_r.T @ d.geom_xmat[g].reshape(3, 3)[:, 2]
                half = float(m.geom_size[g, 1])
                # in fromto's order: MuJoCo's compiled z axis points from the second point to the first
                points += [(centre + half * axis, float(m.geom_size[g, 0])),
                           (centre - half * axis, float(m.geom_size[g, 0]))]
            elif kind == int(mujoco.mjtGeom.mjGEOM_SPHERE):
                points.append((centre, float(m.geom_size[g, 0])))
        segment, seg_radius = None, 0.0
        if points:
            pts = np.array([p for p, _ in points])
            dist = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
            i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
            segment, seg_radius = pts[[i, j]], max(points[i][1], points[j][1])
        if not used[r]:
            raise error(f"rod '{rname}' is not attached by any cable: the model falls apart")
        if len(used[r]) < 2:
            raise error(f"rod '{rname}' has one attachment site ('{used[r][0]}'): a rod needs cables at two "
                        "or more sites")
        rods.append(RodInfo(rname, b, tuple(name(obj.mjOBJ_BODY, bb, "body") for bb in bodies), tuple(sites),
                            np.array([site_pos[s] for s in sites]).reshape(-1, 3), tuple(used[r]),
                            radius, segment, seg_radius))
    _check_connected(rods, tendons, site_rod, error)

    actuators = _read_actuators(m, [t.name for t in tendons], error)
    ground, plane = None, None
    for g in range(m.ngeom):
        if int(m.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE) and rod_of_body[m.geom_bodyid[g]] == -1:
            normal = d.geom_xmat[g].reshape(3, 3)[:, 2].copy()
            if plane is None:
                plane = (normal, float(normal @ d.geom_xpos[g]))
            if normal[2] > 1 - 1e-9:
                ground = float(d.geom_xpos[g, 2]) if ground is None else max(ground, float(d.geom_xpos[g, 2]))
    return SystemDescription(tuple(rods), tuple(tendons), tuple(actuators), site_rod, site_pos, ground, plane)


def _check_connected(rods: list[RodInfo], tendons: list[TendonInfo], site_rod: dict[str, int],
                     error: type[Exception]) -> None:
    """Every rod reaches every other (and the world, where anything is anchored) through cables."""
    n = len(rods)
    parent = list(range(n + 1))  # node n: the world

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    anchored = False
    for t in tendons:
        nodes = [n if site_rod[s] < 0 else site_rod[s] for s in t.sites]
        anchored |= n in nodes
        for a in nodes[1:]:
            parent[find(a)] = find(nodes[0])
    if anchored:
        root = find(n)
    else:  # the largest piece (the first rod's on a tie) is the structure, the others came apart
        sizes = [sum(find(j) == find(i) for j in range(n)) for i in range(n)]
        root = find(int(np.argmax(sizes)))
    apart = [r.name for i, r in enumerate(rods) if find(i) != root]
    if apart:
        first = next(r.name for i, r in enumerate(rods) if find(i) == root)
        to = "the world" if anchored else f"rod '{first}'"
        raise error(f"rods {apart} are not connected to {to} by any chain of cables: the model falls apart")


def _read_actuators(m: Any, tendon_names: list[str], error: type[Exception]) -> list[ActuatorInfo]:
    import mujoco

    out: list[ActuatorInfo] = []
    for i in range(m.nu):
        aname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"actuator#{i}"
        if int(m.actuator_trntype[i]) != int(mujoco.mjtTrn.mjTRN_TENDON):
            trn = str(mujoco.mjtTrn(m.actuator_trntype[i]).name).removeprefix("mjTRN_").lower()
            raise error(f"actuator '{aname}' drives a {trn}, not a tendon: a tensegrity's actuators act on cables")
        dyn = str(mujoco.mjtDyn(m.actuator_dyntype[i]).name)
        gain = int(m.actuator_gaintype[i])
        bias = int(m.actuator_biastype[i])
        if dyn not in _DYN or gain != int(mujoco.mjtGain.mjGAIN_FIXED) or bias not in (
                int(mujoco.mjtBias.mjBIAS_NONE), int(mujoco.mjtBias.mjBIAS_AFFINE)):
            raise error(f"actuator '{aname}': only fixed gains, affine biases and none/filter/filterexact/"
                        "integrator dynamics are modelled (muscle, user and length-dependent gains are not)")
        kind = "motor" if bias == int(mujoco.mjtBias.mjBIAS_NONE) else "general"
        rng = (float(m.actuator_ctrlrange[i, 0]), float(m.actuator_ctrlrange[i, 1])) \
            if m.actuator_ctrllimited[i] else None
        out.append(ActuatorInfo(aname, kind, tendon_names[int(m.actuator_trnid[i, 0])], _DYN[dyn], rng))
    texts = _custom_texts(m)
    for t in texts.get(ACTUATED_KEY, "").split():
        if t not in tendon_names:
            raise error(f"'{ACTUATED_KEY}' names tendon '{t}', which is not a tendon of the model")
        out.append(ActuatorInfo(t, "rest_length", t, "none", None))
    return out


def _custom_texts(m: Any) -> dict[str, str]:
    import mujoco

    out: dict[str, str] = {}
    for i in range(m.ntext):
        a, n = m.text_adr[i], m.text_size[i]
        out[mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_TEXT, i)] = \
            bytes(m.text_data[a:a + n]).decode().rstrip("\x00")
    return out


def nominal_qpos(m: Any) -> tuple[np.ndarray, str]:
    """The model's standing pose as ``qpos`` and where it came from: keyframe ``nominal``, else the
    first keyframe, else ``qpos0`` (the caller may settle it)."""
    import mujoco

    k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "nominal")
    if k >= 0:
        return m.key_qpos[k].copy(), "keyframe 'nominal'"
    if m.nkey:
        kname = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_KEY, 0) or "0"
        return m.key_qpos[0].copy(), f"keyframe '{kname}'"
    return m.qpos0.copy(), "qpos0"
