"""The effect search's rules, each on its own numbers (milliseconds, not a search of minutes).

The search adds a candidate on the free-run evidence (:func:`halves`), failing that on the
one-step evidence (:func:`one_step_evidence`), and calls what it leaves explained by
:func:`search_explained`; each rule is checked at and beside its thresholds.
"""

from __future__ import annotations

import math

from identified.fit.checks import ROUNDING
from identified.fit.pipeline import (
    FREE_RUN_FLOOR,
    ONE_STEP_FLOOR,
    halves,
    one_step_evidence,
    search_explained,
)

INF = math.inf


def test_free_run_evidence_halves_from_above_rounding():
    assert halves(0.2, 0.1) and halves(0.2, 0.1, min_gain=2.0)
    assert not halves(0.2, 0.1000001)
    assert halves(1.0, 0.25, min_gain=4.0) and not halves(0.99, 0.25, min_gain=4.0)
    assert not halves(FREE_RUN_FLOOR / 2, 0.0)  # both at rounding: no evidence, whatever the ratio
    assert halves(FREE_RUN_FLOOR, 0.0)
    assert not halves(1.0, INF) and not halves(1.0, math.nan)
    assert halves(INF, 1.0)  # a base model whose free run diverged, a candidate whose does not


def test_one_step_evidence_cuts_the_one_step_error_without_spoiling_the_free_run():
    # one-step 0.022 -> 6e-14 (the robot's exact drag), free run 0.0185 -> 0.026 m: within 2x, added
    assert one_step_evidence(0.022, 6e-14, 0.0185, 0.026)
    # the one-step error must fall by min_gain ...
    assert one_step_evidence(0.02, 0.01, 0.1, 0.1) and not one_step_evidence(0.02, 0.0100001, 0.1, 0.1)
    assert not one_step_evidence(0.02, 0.01, 0.1, 0.1, min_gain=3.0)
    # ... from above the floor (rounding: no evidence)
    assert not one_step_evidence(ONE_STEP_FLOOR, 0.0, 0.1, 0.1)
    assert one_step_evidence(2 * ONE_STEP_FLOOR, 0.0, 0.1, 0.1)
    # ... and the free run may not get min_gain worse, nor diverge
    assert one_step_evidence(0.02, 0.0, 0.1, 0.2) and not one_step_evidence(0.02, 0.0, 0.1, 0.2000001)
    assert not one_step_evidence(0.02, 0.0, 0.1, INF) and not one_step_evidence(0.02, 0.0, INF, INF)
    assert one_step_evidence(0.02, 0.0, INF, 5.0)  # a diverging model made finite


def test_search_explained_by_rounding_or_a_fivefold_cut():
    assert search_explained(ROUNDING / 2, 1.0, 1.0)  # rounding-level residual
    assert not search_explained(ROUNDING, 1.0, 1.0)
    assert search_explained(None, 1.0, 0.2) and not search_explained(None, 1.0, 0.2000001)
    assert search_explained(0.5, 0.0, 0.0)  # nothing to explain
    assert not search_explained(0.5, 1.0, 0.5)
    assert search_explained(None, INF, 1.0)
