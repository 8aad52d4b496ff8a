"""Preset parameter tables: the ground truth that the built MJCF models carry.

Every number here is a physical quantity in SI units. The tables are the *known truth* that
identification is tested against (see :func:`tensegrity_gym.models.preset_parameters`).

Sources
-------
* ``simple/paper`` and ``ico/paper-*``: Wang et al., "A First Principles Approach for Data-Efficient
  System Identification of Spring-Rod Systems via Differentiable Physics Engines" (L4DC 2020),
  Sec. Experiments: simple system "Each rod is 2 meters long. The rest length of each spring is 1 m
  and 1.414 m. Gravity is ignored"; K, c, M "set to 100, 10 and 10"; the icosahedron "6 rods and 24
  springs. Each rod is connected to 8 springs and has a length of 1.04m. Each spring's rest length is
  0.637m ... g=-9.81"; non-uniform parameters "Gaussian noise ... mu=0, sigma=0.2*parameter".
  The paper gives no rod radius; it only enters the inertia (appendix: uniform solid cylinder,
  I11 = M(l^2/12 + R^2/4), I33 = M R^2/2), so we fix a thin rod, R = 0.05 m, and document it.
* ``ico/robot``: a SUPERball-like six-bar robot (NASA Ames; Bruce et al. 2014, Sabelhaus et al.,
  ICRA 2015, "System design and locomotion of SUPERball"; Vespignani et al. 2018, "Design of
  SUPERball v2"). Approximate published figures: rods of about 1.5-1.7 m, about 3.5 kg per rod end-cap
  assembly pair (robot about 21 kg in total), cables in series with springs of the order of 1-3 kN/m
  pretensioned to the order of 100 N, cable motors that reel at a few tenths of a metre per second.
  The values chosen below sit inside those ranges; they are a plausible robot, not a replica of one.
  Why each value, and what was tuned, is written beside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = [
    "DEFAULT_PRESET",
    "ICO_PAPER",
    "ICO_ROBOT",
    "NONUNIFORM_FLOOR",
    "NONUNIFORM_SIGMA",
    "OVERRIDE_KEYS",
    "SIMPLE_PAPER",
    "SYSTEMS",
    "IcoPaper",
    "IcoRobot",
    "SimplePaper",
]


@dataclass(frozen=True)
class SimplePaper:
    """One rod held by two push-pull springs to two fixed nails (paper, Fig. 1 left)."""

    rod_length: float = 2.0  # m (paper)
    rod_radius: float = 0.05  # m (not in the paper; enters the inertia only)
    mass: float = 10.0  # kg (paper)
    stiffness: float = 100.0  # N/m (paper)
    damping: float = 10.0  # N s/m (paper)
    rest_lengths: tuple[float, float] = (1.0, 1.414)  # m (paper): spring0 at end0, spring1 at end1
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)  # "Gravity is ignored in this case"
    timestep: float = 0.001  # s


@dataclass(frozen=True)
class IcoPaper:
    """Six-rod icosahedron ("expanded octahedron") with 24 push-pull springs, free-floating."""

    rod_length: float = 1.04  # m (paper)
    rod_radius: float = 0.05  # m (not in the paper; enters the inertia only)
    mass: float = 10.0  # kg (paper)
    stiffness: float = 100.0  # N/m (paper)
    damping: float = 10.0  # N s/m (paper)
    # (paper) 0.637 m; equals the built spring length sqrt(6)/4 * 1.04 = 0.6369 m to 1e-4, so the
    # paper structure carries (almost) no pretension and oscillates about its built shape.
    rest_length: float = 0.637
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)  # (paper) g = -9.81, no ground
    timestep: float = 0.001  # s


@dataclass(frozen=True)
class IcoRobot:
    """SUPERball-like six-bar robot standing on a ground plane; pull-only, motor-driven cables.

    Geometry: the same expanded octahedron as the paper (rod spacing L/2, cable length
    sqrt(6)/4 L = 1.041 m for L = 1.7 m), which is the self-stressed equilibrium of 24 equal cables.
    It is placed resting on a closed triangular face. Every cable is a pull-only spring (MuJoCo
    dead-band ``springlength="0 L0"``) whose rest length L0 is shorter than the nominal length by
    ``pretension / stiffness``, so at the nominal shape each cable pulls with ``pretension`` newtons.
    """

    rod_length: float = 1.7  # m: SUPERball v2 scale (v1: 1.5 m)
    rod_radius: float = 0.025  # m: ~50 mm end caps; also the collision capsule radius
    mass: float = 3.5  # kg per rod (SUPERball ~21 kg in total)
    # N/m: middle of the 1-3 kN/m range; stiff enough that the robot keeps its shape under its own
    # weight (tendon lengths stay within a few per cent of nominal), soft enough for dt = 1 ms.
    stiffness: float = 2000.0
    # N s/m per cable: with 4 cables per rod end (effective end mass M/4 = 0.875 kg, end stiffness
    # ~4K) the local modes are damped at about 0.3-0.5 of critical, so motion after a roll dies
    # within ~1 s, as on the real robot.
    damping: float = 30.0
    pretension: float = 100.0  # N at the nominal shape (SUPERball order of magnitude)
    friction: float = 0.9  # sliding friction rod-ground
    # Contact torsional and rolling friction (MuJoCo condim 6; lengths, m): a rubber end cap's
    # contact patch. They stop an end cap that rolls on the ground from spinning its rod about the
    # rod axis (I33 = M r^2/2 is tiny and no cable can damp that spin).
    torsional_friction: float = 0.02
    rolling_friction: float = 0.002
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    timestep: float = 0.001  # s
    # Motors: every cable is actuated (SUPERball v2 actuates all 24). A motor changes the rest length
    # at most ``motor_speed`` m/s, within [rest_min_ratio, rest_max_ratio] times the neutral rest
    # length L0 = 0.991 m, i.e. [0.545, 1.140] m. Reeling one edge of the supporting triangle to
    # rest_min tips the robot onto the next face (tensegrity_gym.cables.scripted_roll_targets);
    # the cable then pulls up to ~1 kN. rest_max > nominal length lets a cable go slack. At
    # 0.3 m/s the full contraction takes 1.5 s, a roll about 2 s.
    motor_speed: float = 0.3  # m/s
    rest_min_ratio: float = 0.55
    rest_max_ratio: float = 1.15
    # s of simulation with neutral cables that finds the keyframe "nominal" (10x damping under
    # implicitfast, then 1 s of the true model): the robot standing on its closed face
    # (rod0_end0, rod2_end0, rod4_end0), centre of mass 0.72 m above the ground.
    settle_time: float = 3.0

    @property
    def nominal_cable_length(self) -> float:
        """sqrt(6)/4 L: the cable length of the ideal expanded octahedron, m."""
        return math.sqrt(6.0) / 4.0 * self.rod_length

    @property
    def rest_length(self) -> float:
        """Neutral rest length L0 = nominal - pretension / K, m."""
        return self.nominal_cable_length - self.pretension / self.stiffness


SIMPLE_PAPER = SimplePaper()
ICO_PAPER = IcoPaper()
ICO_ROBOT = IcoRobot()

#: valid presets per system, in the order they are listed in error messages
SYSTEMS: dict[str, tuple[str, ...]] = {
    "simple": ("paper",),
    "ico": ("paper-uniform", "paper-nonuniform", "robot"),
}
#: preset used when none is given
DEFAULT_PRESET: dict[str, str] = {"simple": "paper", "ico": "robot"}

#: paper-nonuniform: each parameter is value * (1 + NONUNIFORM_SIGMA * N(0, 1)) ...
NONUNIFORM_SIGMA = 0.2
#: ... clipped below at NONUNIFORM_FLOOR * value (keeps every mass, K and c positive)
NONUNIFORM_FLOOR = 0.2

#: keys accepted in ``overrides`` (see :func:`tensegrity_gym.models.build_model`)
OVERRIDE_KEYS: dict[str, str] = {
    "stiffness_scale": "multiply every spring/cable stiffness K",
    "damping_scale": "multiply every spring/cable damping c (0 allowed: no damping)",
    "mass_scale": "multiply every rod mass (inertia follows the mass)",
    "inertia_scale": "multiply every rod inertia (on top of mass_scale)",
    "rest_scale": "multiply every rest length (and the motor bounds)",
    "gravity": "gravity vector (3 numbers, m/s^2)",
    "timestep": "physics time step, s",
    "friction": "rod-ground sliding friction (robot only)",
}
