"""Reading MJCF files as XML, without MuJoCo: the one place that parses the model files.

The topology (:mod:`identified.topology`), the cable motors (:mod:`tensegrity_gym.cables`) and the
twin's nominal pose and neutral rest lengths (:mod:`tensegrity_gym.backends.identified_backend`)
all read an MJCF through these functions, so one convention is parsed one way. Structure only:
MuJoCo is never imported here (the twin must stand on its own); the plant compiles its MJCF with
MuJoCo itself.

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

import numpy as np

from identified.state import RodState

__all__ = [
    "ACTUATED_KEY",
    "custom_entries",
    "floats",
    "free_bodies",
    "is_free_body",
    "nominal_pose",
    "parse_mjcf",
    "read_mjcf_text",
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
