"""The validity box of a table's posterior (firmware/cal_uncertainty.py): its temperature ends found by
bisection equal the ones of a walk in 0.05 degC steps, with a handful of bound evaluations (issue 25)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from magstack.firmware import cal_uncertainty
from magstack.firmware.cal_uncertainty import validity_box, worst_sd_bound_uT

T0_C = 25.0
LIMITS_C = (-40.0, 85.0)
CURRENTS = {"battery": (-0.5, 1.0)}


def _posterior(seed: int) -> dict:
    """A random posterior with linear, temperature, cubic and current parameters on every axis."""
    rng = np.random.default_rng(seed)
    out = {}
    for a in "xyz":
        names = [f"S[{a},{j}]" for j in "xyz"] + [f"K_S[{a},{j}]" for j in "xyz"] + [
            f"O[{a}]", f"K_O[{a}]", f"c3[{a}]", f"D_battery[{a}]"]
        A = rng.normal(size=(len(names), len(names))) * np.array([1e-4] * 3 + [3e-6] * 3 + [5e-3, 2e-4, 1e-9, 1e-3])
        out[a] = {"names": names, "cov": (A @ A.T).tolist()}
    return out


def _walk(post: dict, bound_uT: float, field_uT: float, centre_c: float, step_c: float = 0.05):
    """The validity box by walking out from the centre one step at a time (the definition)."""
    lo_lim, hi_lim = LIMITS_C
    c = min(max(centre_c, lo_lim), hi_lim)
    if worst_sd_bound_uT(post, T0_C, c, field_uT, CURRENTS) > bound_uT:
        return None
    ends = []
    for d, lim in ((-1, lo_lim), (+1, hi_lim)):
        t = c
        while True:
            nxt = t + d * step_c
            if (d > 0 and nxt > lim) or (d < 0 and nxt < lim):
                ends.append(lim)
                break
            if worst_sd_bound_uT(post, T0_C, nxt, field_uT, CURRENTS) > bound_uT:
                ends.append(t)
                break
            t = nxt
    return math.ceil(ends[0] * 100 - 1e-9) / 100, math.floor(ends[1] * 100 + 1e-9) / 100


def _case(seed: int, kind: str) -> tuple[dict, float, float, float]:
    """(posterior, bound uT, field uT, centre degC): the centre at the coarse minimum of the bound; ``kind``
    "none": the bound below the centre's; "inside": both ends strictly inside the limits; "whole": the
    bound above every temperature's."""
    post, field = _posterior(seed), 50.0
    grid = np.linspace(*LIMITS_C, 26)
    worst = [worst_sd_bound_uT(post, T0_C, t, field, CURRENTS) for t in grid]
    centre = float(grid[int(np.argmin(worst))]) + 0.37
    at = worst_sd_bound_uT(post, T0_C, centre, field, CURRENTS)
    bound = {"none": 0.9 * at, "inside": min(worst[1], worst[-2]), "whole": 1.1 * max(worst)}[kind]
    return post, bound, field, centre


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("kind", ["none", "inside", "whole"])
def test_bisected_ends_equal_the_stepwise_walk(seed, kind):
    post, bound, field, centre = _case(seed, kind)
    box, at_c = validity_box(post, T0_C, bound, LIMITS_C, field, centre, CURRENTS)
    assert at_c == worst_sd_bound_uT(post, T0_C, centre, field, CURRENTS)
    assert box == _walk(post, bound, field, centre)
    if kind == "none":
        assert box is None
    elif kind == "whole":
        assert box == LIMITS_C
    else:
        assert LIMITS_C[0] < box[0] < centre < box[1] < LIMITS_C[1]


@pytest.mark.parametrize("kind", ["inside", "whole"])
def test_the_box_takes_a_few_bound_evaluations_not_one_per_step(monkeypatch, kind):
    post, bound, field, centre = _case(7, kind)
    calls = []

    def counted(*args, **kwargs):
        calls.append(args[2])
        return worst_sd_bound_uT(*args, **kwargs)

    monkeypatch.setattr(cal_uncertainty, "worst_sd_bound_uT", counted)
    validity_box(post, T0_C, bound, LIMITS_C, field, centre, CURRENTS)
    steps = (LIMITS_C[1] - LIMITS_C[0]) / 0.05      # 2500 evaluations when walking step by step
    assert len(calls) <= 3 + 2 * math.ceil(math.log2(steps))
