"""What the report figures draw: the diagnosis's bar chart is read from zero and its floor line is the floor the
gap is judged against; the demo's field-sphere coverage is drawn as the equal-area cells the rows reached (the
count the title states), not as a cloud of sample dots."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from matplotlib.collections import PathCollection, QuadMesh  # noqa: E402

from magstack.cli.demo.report import _coverage_figure, sphere_cells  # noqa: E402
from magstack.ground.diagnose.figures import _bars, headline_rows  # noqa: E402


def _diagnosis(baseline_nT=491.4, floor_nT=29.5, budget=None):
    ranking = [{"effect": "time_skew", "rmse_nT": 73.2, "significant": True},
               {"effect": "nonlinearity", "rmse_nT": 491.2, "significant": False},
               {"effect": "hysteresis", "rmse_nT": 544.9, "significant": False}]
    total = None if budget is None else float(np.hypot(floor_nT, budget))
    return {"baseline_rmse_nT": baseline_nT, "after_rmse_nT": 73.2, "noise_floor_nT": floor_nT, "ranking": ranking,
            "reference_budget": None if budget is None else {"total_nT": budget, "attitude_sd_deg": 0.1},
            "floor_with_reference_nT": floor_nT if total is None else total}


@pytest.mark.parametrize("baseline_nT", [491.4, 5.0e4])
def test_the_bar_chart_starts_at_zero(baseline_nT):
    """Bars whose values all lie far above zero still start at zero (a bar chart cut at 450 nT makes 491 look
    twice 470)."""
    ax = _bars(_diagnosis(baseline_nT=baseline_nT)).axes[0]
    assert ax.get_ylim()[0] == 0.0 and ax.get_yscale() == "linear"
    assert max(b.get_height() for b in ax.patches) == pytest.approx(max(baseline_nT, 544.9))


def test_bench_headline_and_floor_line_are_the_measured_white_level():
    d = _diagnosis()
    assert dict(headline_rows(d))["noise floor (from the data)"] == "29.5"
    ax = _bars(d).axes[0]
    assert [ln.get_label() for ln in ax.get_lines()] == ["noise floor"]
    assert ax.get_lines()[0].get_ydata()[0] == 29.5


def test_orbit_headline_states_the_reference_budget_in_the_floor():
    d = _diagnosis(budget=127.5)
    rows = dict(headline_rows(d))
    assert rows["reference error budget (IGRF + attitude 0.1 deg)"] == "127.5"
    assert rows["noise floor: sensor white + reference budget (root sum square)"] == f"{np.hypot(29.5, 127.5):.1f}"
    assert "noise floor (from the data)" not in rows


def test_field_sphere_coverage_is_drawn_as_the_cells_reached():
    rng = np.random.default_rng(5)
    u = rng.standard_normal((400, 3))
    u[:, 2] = np.abs(u[:, 2])                 # the upper hemisphere only: half the cells stay empty
    ref = 40.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    fig, hit, total = _coverage_figure(ref)
    ax = fig.axes[0]
    meshes = [c for c in ax.collections if isinstance(c, QuadMesh)]
    assert len(meshes) == 1 and not [c for c in ax.collections if isinstance(c, PathCollection)]
    counts = sphere_cells(ref)
    drawn = np.ma.getdata(meshes[0].get_array()).reshape(counts.shape)
    shown = ~np.ma.getmaskarray(meshes[0].get_array()).reshape(counts.shape)
    assert np.array_equal(shown, counts > 0) and np.array_equal(drawn[shown], counts[counts > 0])
    assert hit == int((counts > 0).sum()) < total and f"{hit} of {total} equal-area cells" in ax.get_title()
