"""The system topology graph (paper, Sec. "System Topology Graph"), read from an MJCF file.

Only *structure and geometry* are read, from the model as MuJoCo compiles it
(:func:`identified.mjcf.read_system`): which bodies are rods, where their sites are in the rod
frame, which sites each spring joins, whether a spring is a pull-only cable (MuJoCo tendon
dead-band ``springlength="0 L"``), which cables have rest-length motors and which MuJoCo actuators
act on which tendon. The physical parameters written in the file (stiffness, damping, masses,
inertias, rest lengths, gains) are never read: identification must find them from data.

What a model may hold:

* a rod is a body with a free joint together with all its jointless descendant bodies (one rigid
  body); its frame is the free body's compiled frame, its centre of mass anywhere in it;
* every spring/cable is a ``<spatial>`` tendon between two sites, each on a rod or fixed to the
  world (an anchor, e.g. a nail), never two sites of one body;
* rest-length motors are listed in ``<custom><text name="tensegrity_actuated" data="..."/></custom>``;
  MuJoCo actuators (``motor``, ``position``, ``general``) act on tendons.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from identified.mjcf import SystemDescription, compile_mjcf, parse_mjcf, read_mjcf_text, read_system

__all__ = ["Actuator", "Rod", "Spring", "Topology", "TopologyError"]


class TopologyError(ValueError):
    """The MJCF file does not follow the spring-rod conventions."""


@dataclass(frozen=True)
class Rod:
    """A rigid rod: a free body with its jointless descendants; its frame is the free body's.

    ``sites`` are all sites of the rod's bodies with ``site_offsets`` their positions in the rod
    frame; ``attachments`` the sites cables use (all sites when not given); ``radius`` its largest
    capsule or cylinder radius (geometry, m; 0 when unknown).
    """

    name: str
    sites: tuple[str, ...]
    site_offsets: np.ndarray = field(repr=False)  # (n_sites, 3) positions in the rod frame, m
    attachments: tuple[str, ...] = ()
    bodies: tuple[str, ...] = ()
    radius: float = 0.0

    def site_offset(self, site: str) -> np.ndarray:
        """(3,) position of one of the rod's sites in the rod frame, m."""
        return self.site_offsets[self.sites.index(site)]

    @property
    def ends(self) -> np.ndarray:
        """(2, 3) the two attachment sites farthest apart (the rod's ends), rod frame, m."""
        names = self.attachments or self.sites
        p = np.array([self.site_offset(s) for s in names]).reshape(-1, 3)
        d = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
        i, j = np.unravel_index(int(np.argmax(d)), d.shape)
        return p[[i, j]]

    @property
    def length(self) -> float:
        """Distance between the two outermost attachment sites, m."""
        e = self.ends
        return float(np.linalg.norm(e[1] - e[0]))


@dataclass(frozen=True)
class Actuator:
    """A control input of the system (see :class:`identified.mjcf.ActuatorInfo`): ``kind``
    ``"motor"``, ``"general"`` (affine bias) or ``"rest_length"``; the ``tendon`` it acts on; its
    activation ``dynamics``; its command range ``ctrlrange`` (``None``: unlimited)."""

    name: str
    kind: str
    tendon: str
    dynamics: str = "none"
    ctrlrange: tuple[float, float] | None = None


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
    actuators: tuple[Actuator, ...] = ()
    ground: float | None = None  # height of the model's ground plane, m (None: no ground)

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
    def force_actuators(self) -> tuple[Actuator, ...]:
        """The MuJoCo tendon actuators (a force on their tendon; a recording's ``.ctrl`` columns),
        not the project's rest-length motors (a command that is the rest length, ``.rest``)."""
        return tuple(a for a in self.actuators if a.kind != "rest_length")

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

    @property
    def site_rod(self) -> dict[str, int]:
        """Rod index of every site on a rod and of every cable end (-1: fixed to the world)."""
        out = {s: i for i, r in enumerate(self.rods) for s in r.sites}
        for sp in self.springs:
            for s, r in zip(sp.sites, sp.rods, strict=True):
                out.setdefault(s, r)
        return out

    def site_position(self, site: str) -> np.ndarray:
        """(3,) a site in its rod's frame (a fixed site: in the world frame), m."""
        for r in self.rods:
            if site in r.sites:
                return r.site_offset(site).copy()
        for sp in self.springs:
            if site in sp.sites:
                return sp.offsets[sp.sites.index(site)].copy()
        raise KeyError(f"no site '{site}' in the topology")

    @property
    def routes(self) -> dict[str, tuple[str, ...]]:
        """The sites every cable is routed over, in order."""
        return {s.name: s.sites for s in self.springs}

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
                return cls._from_text(text, source)
            except TopologyError as exc:
                msg = str(exc)
                raise TopologyError(msg if str(source) in msg else f"'{source}': {msg}") from None
        return cls._from_text(text)

    @classmethod
    def _from_text(cls, text: str, source: str | os.PathLike | None = None) -> Topology:
        root = parse_mjcf(text, TopologyError)
        if root.tag != "mujoco":
            raise TopologyError(f"not an MJCF file: root element is <{root.tag}>, expected <mujoco>")
        if root.find("worldbody") is None:
            raise TopologyError("MJCF has no <worldbody>")
        model = compile_mjcf(text if source is None else source, TopologyError)
        if not any(model.jnt_type == 0):  # mjJNT_FREE
            raise TopologyError("MJCF has no rods: no body with a free joint")
        if model.ntendon == 0:
            raise TopologyError("MJCF has no springs: no <spatial> tendon in <tendon>")
        return cls.from_system(read_system(model, TopologyError))

    @classmethod
    def from_system(cls, system: SystemDescription) -> Topology:
        """The topology of a :class:`~identified.mjcf.SystemDescription` (read by
        :func:`identified.mjcf.read_system`), refusing what the identified engine does not model:
        cables routed over more than two sites, tendon length limits and two-sided dead bands."""
        rods = tuple(Rod(name=r.name, sites=r.sites, site_offsets=r.site_pos, attachments=r.attachments,
                         bodies=r.bodies, radius=r.radius) for r in system.rods)
        motors = {a.tendon for a in system.actuators if a.kind == "rest_length"}
        springs: list[Spring] = []
        for t in system.tendons:
            if len(t.sites) != 2:
                raise TopologyError(f"tendon '{t.name}' is routed over {len(t.sites)} sites: the identified "
                                    "engine models a cable between exactly two sites")
            if t.limited:
                raise TopologyError(f"tendon '{t.name}' has a length limit (limited/range): the identified "
                                    "engine does not model tendon limits; remove it or the range")
            if t.deadband == "two_sided":
                raise TopologyError(f"tendon '{t.name}': a dead-band with a non-zero lower bound "
                                    "(springlength=\"a b\", a > 0) is not modelled; use \"0 L\" for a cable")
            ends = [(system.site_rod[s], system.site_pos[s]) for s in t.sites]
            springs.append(Spring(name=t.name, sites=(t.sites[0], t.sites[1]),
                                  rods=(ends[0][0], ends[1][0]),
                                  offsets=np.array([ends[0][1], ends[1][1]], dtype=float),
                                  pull_only=t.deadband == "pull_only", actuated=t.name in motors))
        actuators = tuple(Actuator(name=a.name, kind=a.kind, tendon=a.tendon, dynamics=a.dynamics,
                                   ctrlrange=a.ctrlrange) for a in system.actuators)
        return cls(rods=rods, springs=tuple(springs), actuators=actuators, ground=system.ground)
