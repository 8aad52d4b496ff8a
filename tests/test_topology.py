"""The topology graph read from MJCF: structure and geometry, and a clear error for every breach."""

from __future__ import annotations

import numpy as np
import pytest

from identified.topology import Topology, TopologyError

ROD = """<body name="{name}" pos="{pos}" quat="{quat}"><freejoint name="{name}_free"/>
<inertial pos="0 0 0" mass="{mass}" diaginertia="1 1 0.01"/>
<site name="{name}_end0" pos="0 0 -0.5"/><site name="{name}_end1" pos="0 0 0.5"/></body>"""


def two_rod_xml(mass: float = 10.0, k: float = 100.0, extra_tendon: str = "", custom: str = "") -> str:
    rods = ROD.format(name="rod0", pos="0 0 1", quat="1 0 0 0", mass=mass) + ROD.format(
        name="rod1", pos="0.5 0 1", quat="0.7071068 0 0.7071068 0", mass=mass
    )
    return f"""<mujoco><worldbody><site name="anchor0" pos="0 0 3"/>
<body name="post" pos="1 0 0"><site name="anchor1" pos="0 0 2"/></body>{rods}</worldbody>
<tendon>
<spatial name="spring0" stiffness="{k}" damping="1" springlength="0.6"><site site="anchor0"/><site site="rod0_end1"/></spatial>
<spatial name="cable0" stiffness="{k}" damping="1" springlength="0 0.4"><site site="rod0_end0"/><site site="rod1_end0"/></spatial>
<spatial name="cable1" stiffness="{k}" damping="1" springlength="0 0.4"><site site="rod1_end1"/><site site="anchor1"/></spatial>
{extra_tendon}</tendon>{custom}</mujoco>"""


def test_structure_and_geometry():
    xml = two_rod_xml(custom='<custom><text name="tensegrity_actuated" data="cable1"/></custom>')
    topo = Topology.from_mjcf(xml)
    assert topo.rod_names == ("rod0", "rod1")
    assert topo.spring_names == ("spring0", "cable0", "cable1")
    assert topo.actuated_names == ("cable1",)
    np.testing.assert_array_equal(topo.pull_only, [False, True, True])
    np.testing.assert_array_equal(topo.endpoint_rods, [[-1, 0], [0, 1], [1, -1]])
    np.testing.assert_allclose(topo.endpoint_offsets[0, 0], [0, 0, 3])  # anchor: world position
    np.testing.assert_allclose(topo.endpoint_offsets[2, 1], [1, 0, 2])  # anchor on a static body
    np.testing.assert_allclose(topo.endpoint_offsets[1], [[0, 0, -0.5], [0, 0, -0.5]])  # rod frame
    assert topo.rods[0].length == pytest.approx(1.0)
    assert topo.springs_of_rod(0) == (0, 1) and topo.springs_of_rod(1) == (1, 2)


def test_physical_parameters_are_not_read():
    a = Topology.from_mjcf(two_rod_xml(mass=10.0, k=100.0))
    b = Topology.from_mjcf(two_rod_xml(mass=3.0, k=7.0))
    np.testing.assert_array_equal(a.endpoint_offsets, b.endpoint_offsets)
    assert a.spring_names == b.spring_names and a.rod_names == b.rod_names


def test_reads_a_file(tmp_path):
    p = tmp_path / "m.xml"
    p.write_text(two_rod_xml())
    assert Topology.from_mjcf(p).n_springs == 3


@pytest.mark.parametrize(
    "xml, message",
    [
        ("<mujoco><worldbody/>", "not a valid MJCF"),
        ("<robot/>", "root element is <robot>"),
        ("<mujoco/>", "no <worldbody>"),
        ("<mujoco><worldbody><body name='b'><site name='s'/></body></worldbody></mujoco>", "no rods"),
        (two_rod_xml().split("<tendon>")[0] + "</mujoco>", "no springs"),
        (two_rod_xml(extra_tendon='<spatial name="bad"><site site="rod0_end0"/><site site="nowhere"/></spatial>'),
         "site 'nowhere' not found"),
        (two_rod_xml(extra_tendon='<spatial name="three"><site site="rod0_end0"/><site site="rod1_end0"/>'
                     '<site site="anchor0"/></spatial>'), "tendon 'three' is routed over 3 sites"),
        (two_rod_xml(extra_tendon='<spatial name="self"><site site="rod0_end0"/><site site="rod0_end1"/></spatial>'),
         "tendon 'self' joins two sites of rod 'rod0'"),
        (two_rod_xml(custom='<custom><text name="tensegrity_actuated" data="ghost"/></custom>'),
         "names tendon 'ghost', which is not a tendon"),
        (two_rod_xml().replace('springlength="0 0.4"><site site="rod0_end0"/>',
                               'springlength="0.1 0.4"><site site="rod0_end0"/>'), "non-zero lower bound"),
    ],
)
def test_convention_errors(xml, message):
    with pytest.raises(TopologyError, match=message):
        Topology.from_mjcf(xml)


def test_missing_file(tmp_path):
    with pytest.raises(TopologyError, match="cannot read model file"):
        Topology.from_mjcf(tmp_path / "none.xml")
