"""``unbatch_infos``: Gymnasium's vector info as SB3's per-env dicts, checked value by value."""

from __future__ import annotations

import numpy as np

from tensegrity_gym.envs.sb3 import unbatch_infos


def test_unbatch_infos_values_types_masks_and_nesting():
    n = 4
    infos = {
        "x_position": np.array([0.5, -1.25, 2.0, 3.5]),
        "steps": np.array([1, 2, 3, 4], dtype=np.int64),
        "healthy": np.array([True, False, True, True]),
        "com": np.arange(12.0).reshape(n, 3),
        "reason": np.array(["", "collapsed", "", ""], dtype=object),
        "_reason": np.array([False, True, False, False]),
        "final_info": {"x_position": np.array([0.0, 9.0, 0.0, 0.0]), "_x_position": np.array([0, 1, 0, 0], bool)},
        "_final_info": np.array([False, True, False, False]),
    }
    out = unbatch_infos(infos, n)
    assert [d["x_position"] for d in out] == [0.5, -1.25, 2.0, 3.5]
    assert all(type(d["x_position"]) is float and type(d["steps"]) is int and type(d["healthy"]) is bool
               for d in out)
    assert [d["steps"] for d in out] == [1, 2, 3, 4] and [d["healthy"] for d in out] == [True, False, True, True]
    for i, d in enumerate(out):
        np.testing.assert_array_equal(d["com"], [3 * i, 3 * i + 1, 3 * i + 2])
        assert not np.shares_memory(d["com"], infos["com"])  # a copy: the env may reuse its buffer
    assert ["reason" in d for d in out] == [False, True, False, False] and out[1]["reason"] == "collapsed"
    assert ["final_info" in d for d in out] == [False, True, False, False]
    assert out[1]["final_info"] == {"x_position": 9.0}
    assert not any(k.startswith("_") for d in out for k in d)
