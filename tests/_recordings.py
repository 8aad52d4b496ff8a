"""The robot recorded as a lab would, in still air and in viscous air (a drag nobody declares)."""

from __future__ import annotations

from tensegrity_gym.collect import CollectConfig, RecordConfig, collect, record_markers
from tensegrity_gym.models import write_model


def drag_recordings(folder) -> dict:
    """The robot preset in still air and in MuJoCo's viscosity 2 (a linear drag on every rod), 6
    takes of 2 s each (seed 11): end-cap markers at 100 Hz, 1 mm noise, 2 % missing. Keys ``xml``
    (the robot's MJCF, no viscosity), ``still``, ``viscous`` (recordings)."""
    xml = str(folder / "robot.xml")
    text = write_model(xml, "ico", preset="robot")
    out = {"xml": xml}
    for name, option in (("still", "<option "), ("viscous", '<option viscosity="2" ')):
        plant = str(folder / f"{name}.xml")
        with open(plant, "w", encoding="utf-8") as fh:
            fh.write(text.replace("<option ", option))
        data = collect(plant, CollectConfig(episodes=6, steps=2000, seed=11))
        out[name] = record_markers(data, plant, RecordConfig(rate=100, noise_pos=0.001, dropout=0.02), seed=11)
    return out
