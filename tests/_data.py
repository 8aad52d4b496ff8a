"""Paths of the test suite's stored data (``tests/data``)."""

from __future__ import annotations

from pathlib import Path

DATA = Path(__file__).resolve().parent / "data"
#: the robot fitted with ``ground_contact`` on the data of the shipped model (which names
#: ``pyramid_contact``): tests of mechanics that do not depend on the contact law step it, ~2x faster
GROUND = DATA / "robot_ground_contact.json"
