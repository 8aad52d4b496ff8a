"""The batched twin env takes actions as the single env does: clipped into [-1, 1] (an action
beyond the box commands the same as its clipped value), and its stepped quaternions stay unit."""

from __future__ import annotations

import numpy as np

from tensegrity_gym.envs.vector import TensegrityIcoVectorEnv


def test_vector_env_clips_actions_into_the_box():
    runs = []
    a = np.stack([np.linspace(-1.0, 1.0, 24), -np.ones(24)]).astype(np.float32)
    beyond = np.where(np.abs(a) >= 1.0, 3.0 * a, a)  # the saturated entries pushed beyond the box
    for action in (a, beyond):
        v = TensegrityIcoVectorEnv(2, None, backend_kwargs={"compile": False})
        v.reset(seed=[3, 4])
        out = [v.step(action) for _ in range(3)]
        runs.append(out)
        quat = v.physics.states_numpy()[1]
        assert np.allclose(np.linalg.norm(v._quat, axis=-1), 1.0, atol=1e-12) and np.isfinite(quat).all()
    for (o1, r1, *_), (o3, r3, *_) in zip(*runs):
        np.testing.assert_array_equal(o1, o3)
        np.testing.assert_array_equal(r1, r3)
