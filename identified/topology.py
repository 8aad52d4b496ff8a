"""The system topology graph (paper, Sec. "System Topology Graph"), read from an MJCF file.

Only *structure and geometry* are read: which bodies are rods, where their end points are in the
rod frame, which sites each spring joins, whether a spring is a pull-only cable (MuJoCo tendon
dead-band ``springlength="0 L"``) and which cables are actuated.  The physical parameters written
in the file (stiffness, damping, masses, inertias, rest lengths) are never read: identification
must find them from data.

MJCF conventions (:mod:`identified.mjcf`, which parses the file for this module):

* every rod is a top-level ``<body>`` with a ``<freejoint>``; its centre of mass is the body origin;
* rod end points are ``<site>`` elements of the rod body;
* every spring/cable is a ``<spatial>`` tendon between exactly two sites, each on a rod or fixed
  in the world (an anchor, e.g. a nail);
* actuated cables are listed in ``<custom><text name="tensegrity_actuated" data="..."/></custom>``.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from identified.mjcf import ACTUATED_KEY, custom_entries, is_free_body, parse_mjcf, read_mjcf_text
from identified.rotation import quat_to_matrix

__all__ = ["Rod", "Spring", "Topology", "TopologyError"]


class TopologyError(ValueError):
    """The MJCF file does not follow the spring-rod conventions."""


@dataclass(frozen=True)
class Rod:
    """A rigid rod: a free body whose centre of mass is the body origin."""

    name: str
    sites: tuple[str, ...]
    site_offsets: np.ndarray = field(repr=False)  # (n_sites, 3) positions in the rod frame, m

    @property
    def length(self) -> float:
        """Distance between the two outermost attachment sites, m."""
        d = self.site_offsets[:, None, :] - self.site_offsets[None, :, :]
        return float(np.max(np.linalg.norm(d, axis=-1)))


@dataclass(frozen=True)
class Spring:
    """A 1D spring or cable between two attachment points.

    ``rods[e]`` is the rod index of end ``e`` (or -1 for a fixed anchor); ``offsets[e]`` is the
    point in that rod's frame (or the anchor's world position).
    """

    name: str
    sites: tuple[str, str]
    rods: tuple[int, int]
    offsets: np.ndarray = field(repr=False)  # (2, 3)
    pull_only: bool
    actuated: bool


@dataclass(frozen=True)
class Topology:
    """Rods, springs and their connections: the graph the engine and the regression run on."""

    rods: tuple[Rod, ...]
    springs: tuple[Spring, ...]

    # ------------------------------------------------------------------ names and counts
    @property
    def n_rods(self) -> int:
        return len(self.rods)

    @property
    def n_springs(self) -> int:
        return len(self.springs)

    @property
    def rod_names(self) -> tuple[str, ...]:
        return tuple(r.name for r in self.rods)

    @property
    def spring_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.springs)

    @property
    def site_names(self) -> tuple[str, ...]:
        names: list[str] = []
        for s in self.springs:
            names.extend(x for x in s.sites if x not in names)
        return tuple(names)

    @property
    def actuated_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.springs if s.actuated)

    # ------------------------------------------------------------------ arrays for the engine
    @property
    def endpoint_rods(self) -> np.ndarray:
        """(S, 2) int: rod index of each spring end, -1 for a fixed anchor."""
        return np.array([s.rods for s in self.springs], dtype=np.int64).reshape(-1, 2)

    @property
    def endpoint_offsets(self) -> np.ndarray:
        """(S, 2, 3): each end point in its rod's frame, or the anchor's world position."""
        return np.array([s.offsets for s in self.springs], dtype=np.float64).reshape(-1, 2, 3)

    @property
    def pull_only(self) -> np.ndarray:
        """(S,) bool: cables that only pull (tension only when longer than the rest length)."""
        return np.array([s.pull_only for s in self.springs], dtype=bool)

    def springs_of_rod(self, i: int) -> tuple[int, ...]:
        """Indices of the springs attached to rod ``i``."""
        return tuple(j for j, s in enumerate(self.springs) if i in s.rods)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_mjcf(cls, source: str | os.PathLike) -> Topology:
        """Read the topology from an MJCF path or XML string (structure and geometry only)."""
        text = read_mjcf_text(source, TopologyError)
        if not os.fspath(source).lstrip().startswith("<"):
            try:  # name the user's file in every error
                return cls._from_text(text)
            except TopologyError as exc:
                msg = str(exc)
                raise TopologyError(msg if str(source) in msg else f"'{source}': {msg}") from None
        return cls._from_text(text)

    @classmethod
    def _from_text(cls, text: str) -> Topology:
        root = parse_mjcf(text, TopologyError)
        if root.tag != "mujoco":
            raise TopologyError(f"not an MJCF file: root element is <{root.tag}>, expected <mujoco>")
        world = root.find("worldbody")
        if world is None:
            raise TopologyError("MJCF has no <worldbody>")

        rods: list[Rod] = []
        site_where: dict[str, tuple[int, np.ndarray]] = {}  # site -> (rod index or -1, offset)
        _collect_world_sites(world, np.zeros(3), np.eye(3), site_where)
        for body in world.findall("body"):
            if not is_free_body(body):
                _collect_world_sites(body, *_frame(body), site_where, static=True)
                continue
            name = body.get("name")
            if not name:
                raise TopologyError("a body with a free joint has no name; every rod body must be named")
            if body.find("body") is not None:
                raise TopologyError(f"rod body '{name}' has child bodies; a rod must be a single rigid body")
            sites = [s for s in body.findall("site")]
            if not sites:
                raise TopologyError(f"rod body '{name}' has no sites for its end points")
            idx = len(rods)
            names, offsets = [], []
            for s in sites:
                sname = s.get("name")
                if not sname:
                    raise TopologyError(f"rod body '{name}' has an unnamed site")
                off = _vec(s.get("pos"), 3)
                names.append(sname)
                offsets.append(off)
                site_where[sname] = (idx, off)
            rods.append(Rod(name=name, sites=tuple(names), site_offsets=np.array(offsets)))
        if not rods:
            raise TopologyError("MJCF has no rods: no top-level body with a free joint")

        actuated = _actuated_names(root)
        springs: list[Spring] = []
        tendon = root.find("tendon")
        spatials = [] if tendon is None else tendon.findall("spatial")
        if not spatials:
            raise TopologyError("MJCF has no springs: no <spatial> tendon in <tendon>")
        for t in spatials:
            tname = t.get("name")
            if not tname:
                raise TopologyError("a spatial tendon has no name; every spring/cable must be named")
            refs = [s.get("site") for s in t.findall("site")]
            if len(refs) != 2 or len(t) != 2:
                raise TopologyError(f"tendon '{tname}' must join exactly two sites (found {len(refs)} sites)")
            ends = []
            for ref in refs:
                if ref not in site_where:
                    raise TopologyError(f"tendon '{tname}' uses site '{ref}', which is not on a rod or fixed")
                ends.append(site_where[ref])
            if ends[0][0] == ends[1][0]:
                raise TopologyError(f"tendon '{tname}' joins two points of the same body")
            springs.append(
                Spring(
                    name=tname,
                    sites=(refs[0], refs[1]),
                    rods=(ends[0][0], ends[1][0]),
                    offsets=np.array([ends[0][1], ends[1][1]]),
                    pull_only=_is_deadband(t, tname),
                    actuated=tname in actuated,
                )
            )
        unknown = set(actuated) - {s.name for s in springs}
        if unknown:
            raise TopologyError(f"'{ACTUATED_KEY}' names tendons that do not exist: {sorted(unknown)}")
        return cls(rods=tuple(rods), springs=tuple(springs))


# ---------------------------------------------------------------------- XML helpers
def _vec(text: str | None, n: int) -> np.ndarray:
    if text is None:
        return np.zeros(n)
    vals = np.array([float(x) for x in text.split()])
    if vals.size != n:
        raise TopologyError(f"expected {n} numbers, got '{text}'")
    return vals


def _frame(body: ET.Element) -> tuple[np.ndarray, np.ndarray]:
    """World position and rotation of a static (joint-less) top-level body."""
    pos = _vec(body.get("pos"), 3)
    q = _vec(body.get("quat"), 4) if body.get("quat") else np.array([1.0, 0, 0, 0])
    if any(body.get(k) for k in ("euler", "axisangle", "xyaxes", "zaxis")):
        raise TopologyError(f"static body '{body.get('name')}' must give its orientation as quat")
    return pos, quat_to_matrix(q)


def _collect_world_sites(
    elem: ET.Element, pos: np.ndarray, rot: np.ndarray, out: dict, static: bool = False
) -> None:
    for s in elem.findall("site"):
        if s.get("name"):
            out[s.get("name")] = (-1, pos + rot @ _vec(s.get("pos"), 3))
    if static:
        for child in elem.findall("body"):
            if child.find("joint") is not None or child.find("freejoint") is not None:
                raise TopologyError(f"body '{child.get('name')}' has a joint but is not a top-level rod")
            cpos, crot = _frame(child)
            _collect_world_sites(child, pos + rot @ cpos, rot @ crot, out, static=True)


def _is_deadband(t: ET.Element, name: str) -> bool:
    spec = t.get("springlength")
    if spec is None:
        return False
    vals = [float(x) for x in spec.split()]
    if len(vals) == 1 or vals[0] == vals[1]:
        return False
    if vals[0] > 0:
        raise TopologyError(
            f"tendon '{name}': a dead-band with a non-zero lower bound is not a spring or a cable"
        )
    return True


def _actuated_names(root: ET.Element) -> set[str]:
    texts, _ = custom_entries(root)
    return set(texts.get(ACTUATED_KEY, "").split())
