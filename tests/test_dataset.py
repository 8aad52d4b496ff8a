"""The dataset contract: round trip, and a precise error for every kind of bad file."""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np
import pytest

from identified.dataset import Dataset, DatasetError, load_dataset, save_dataset


def make_dataset(E: int = 2, T: int = 5, R: int = 2, S: int = 3, seed: int = 0) -> Dataset:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(E, T + 1, R, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return Dataset(
        dt=1e-3,
        gravity=np.array([0.0, 0.0, -9.81]),
        rod_names=tuple(f"rod{i}" for i in range(R)),
        tendon_names=tuple(f"cable{j}" for j in range(S)),
        actuated_names=("cable1",),
        pos=rng.normal(size=(E, T + 1, R, 3)),
        quat=q,
        vel=rng.normal(size=(E, T + 1, R, 3)),
        angvel=rng.normal(size=(E, T + 1, R, 3)),
        command=rng.uniform(0.5, 1.0, size=(E, T, 1)),
        rest_length=rng.uniform(0.5, 1.0, size=(E, T, S)),
        push_force=rng.normal(size=(E, T, R, 3)),
        push_point=rng.normal(size=(E, T, R, 3)),
        noise=np.array([0.001, 0.0, 0.0, 0.0]),
        seed=7,
    )


def test_round_trip(tmp_path):
    d = make_dataset()
    path = tmp_path / "d.npz"
    save_dataset(path, d)
    back = load_dataset(path)
    for key in ("pos", "quat", "vel", "angvel", "command", "rest_length", "push_force", "push_point", "gravity", "noise"):
        np.testing.assert_array_equal(getattr(back, key), getattr(d, key))
    assert back.rod_names == d.rod_names and back.tendon_names == d.tendon_names
    assert back.actuated_names == ("cable1",) and back.dt == d.dt and back.seed == 7
    assert (back.n_episodes, back.n_steps, back.n_rods, back.n_tendons) == (2, 5, 2, 3)
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".tmp")]


def test_select_keeps_alignment():
    d = make_dataset(E=3, T=6)
    s = d.select(episodes=[2], steps=4)
    assert s.pos.shape[:2] == (1, 5) and s.rest_length.shape[:2] == (1, 4)
    np.testing.assert_array_equal(s.pos[0], d.pos[2, :5])
    with pytest.raises(DatasetError, match="steps must be"):
        d.select(steps=0)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"pos": np.zeros((2, 6, 2, 2))}, r"'pos' has shape \(2, 6, 2, 2\), expected \(2, 6, 2, 3\)"),
        ({"command": np.zeros((2, 5, 2))}, r"'command' has shape"),
        ({"rest_length": np.zeros((2, 4, 3))}, r"'rest_length' has shape"),
        ({"rod_names": ("a",)}, r"'pos' has 2 rods but 'rod_names' names 1"),
        ({"actuated_names": ("nope",)}, r"subset"),
        ({"dt": 0.0}, r"'dt' must be a positive"),
        ({"gravity": np.array([0.0, np.nan, 1.0])}, r"'gravity' must be 3 finite"),
    ],
)
def test_shape_and_value_errors(change, message):
    with pytest.raises(DatasetError, match=message):
        replace(make_dataset(), **change).validate()


def test_non_finite_names_first_index():
    d = make_dataset()
    vel = d.vel.copy()
    vel[1, 3, 0, 2] = np.inf
    vel[1, 4, 1, 0] = np.nan
    with pytest.raises(DatasetError, match=r"'vel' holds a non-finite value \(inf\) at index \(1, 3, 0, 2\)"):
        replace(d, vel=vel).validate()


def test_non_unit_quaternion():
    d = make_dataset()
    q = d.quat.copy()
    q[0, 2, 1] *= 1.01
    with pytest.raises(DatasetError, match=r"not a unit quaternion at index \(0, 2, 1\)"):
        replace(d, quat=q, noise=np.zeros(4)).validate()


def test_negative_rest_length():
    d = make_dataset()
    r = d.rest_length.copy()
    r[0, 1, 2] = -0.1
    with pytest.raises(DatasetError, match=r"'rest_length' is negative at index \(0, 1, 2\)"):
        replace(d, rest_length=r).validate()


def test_single_instant_rejected():
    d = make_dataset(T=1).select(steps=1)
    with pytest.raises(DatasetError, match="fewer than 2 instants"):
        replace(d, pos=d.pos[:, :1], quat=d.quat[:, :1], vel=d.vel[:, :1], angvel=d.angvel[:, :1]).validate()


def test_missing_file(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        load_dataset(tmp_path / "none.npz")


def test_truncated_file(tmp_path):
    path = tmp_path / "d.npz"
    save_dataset(path, make_dataset())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match="not a readable .npz dataset"):
        load_dataset(path)


def test_foreign_npz(tmp_path):
    path = tmp_path / "x.npz"
    np.savez(path, a=np.zeros(3))
    with pytest.raises(DatasetError, match="not a tensegrity dataset"):
        load_dataset(path)


def test_missing_key(tmp_path):
    path = tmp_path / "d.npz"
    save_dataset(path, make_dataset())
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != "push_point"}
    np.savez(path, **arrays)
    with pytest.raises(DatasetError, match="lacks the key.*push_point"):
        load_dataset(path)


def test_failed_write_leaves_old_file_whole(tmp_path):
    path = tmp_path / "d.npz"
    save_dataset(path, make_dataset(seed=1))
    before = path.read_bytes()
    bad = replace(make_dataset(), dt=-1.0)
    with pytest.raises(DatasetError):
        save_dataset(path, bad)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["d.npz"]


def test_write_into_missing_folder(tmp_path):
    with pytest.raises(OSError, match="does not exist"):
        save_dataset(tmp_path / "no" / "d.npz", make_dataset())
