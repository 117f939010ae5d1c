"""Coordinates printed in decimal degrees (outside audit, 2026-12-05).

A receiver or logger that prints latitude and longitude in decimal degrees rounded to 5
decimals (1e-5 deg: 1.1 m north, 0.7 m east at 51.75 N; CSV loggers, phone apps, many data
sets) puts every fix on a lattice that also lies on the NMEA 1e-4-minute lattice (1e-5 deg =
6e-4 min). The gap tool knew minute lattices only and read such a log as "quantization
(decimals=4)" (a 0.19 m grid) plus a static hold imitating the fixes the coarse grid
repeats (the CLI: "quantization + static_hold, closure 0.91"; with a scenario "static_hold +
quantization, 0.99"). The quantization layer now has a unit (``unit = "deg"``), and the
tool looks for degree lattices as well, the coarsest one the fixes lie on first.
"""

from __future__ import annotations

import numpy as np
import pytest

from sim_backend.effects import (
    PositionSeries,
    Quantization,
    metres_per_degree,
    quantization_step_m,
    truth_track_m,
)
from sim_backend.world import loads_world
from tests.test_gap_unseen_round5 import _rounded_to_degrees  # a CSV logger's printing
from x6wd.core.errors import ConfigError
from x6wd.gap.diagnose import Options, diagnose, report_dict, verdict_text
from x6wd.gap.fit import fit_quantization
from x6wd.gap.report import _params_text, markdown
from x6wd.gap.stats import battery, layout_for
from x6wd.gap.surrogate import BASELINE_EFFECTS, surrogate_run

PRE = BASELINE_EFFECTS[:-1]  # the surrogate receiver before its NMEA printing (5 decimals)


def _lat_lon(series: PositionSeries) -> tuple[np.ndarray, np.ndarray]:
    e_per_deg, n_per_deg = metres_per_degree(series.origin_lat_deg)
    te, tn = truth_track_m(series)
    lat = series.origin_lat_deg + (tn + np.asarray(series.north_m)) / n_per_deg
    lon = series.origin_lon_deg + (te + np.asarray(series.east_m)) / e_per_deg
    return lat, lon


def _spread(seed: int, half_width_m: float, n: int = 400) -> PositionSeries:
    """A static series whose fixes scatter uniformly over +-``half_width_m`` (wide enough
    that even a 1 km lattice has many fixes on distinct points)."""
    base = surrogate_run(float(n), 1.0, np.random.default_rng(seed), effects=[])
    rng = np.random.default_rng(seed + 1)
    return base.with_(
        east_m=rng.uniform(-half_width_m, half_width_m, len(base)),
        north_m=rng.uniform(-half_width_m, half_width_m, len(base)),
    )


@pytest.fixture(scope="module")
def runs() -> list[PositionSeries]:
    """The surrogate receiver as the simulator prints it (NMEA minutes, 5 decimals)."""
    return [surrogate_run(900.0, 1.0, np.random.default_rng(40 + i)) for i in range(4)]


# --- the layer


def test_the_layer_prints_on_the_degree_grid_exactly() -> None:
    from x6wd.gap.stats import lattice_fraction

    real = _spread(3, 50.0)
    for decimals in (5, 6):
        out = Quantization(decimals=decimals, unit="deg").apply(real, np.random.default_rng(0))
        lat, lon = _lat_lon(out)
        want_lat, want_lon = _lat_lon(_rounded_to_degrees(real, decimals))
        assert np.max(np.abs(lat - want_lat)) < 1e-12 and np.max(np.abs(lon - want_lon)) < 1e-12
        assert np.max(np.abs(lat * 10**decimals - np.round(lat * 10**decimals))) < 1e-6
        assert lattice_fraction(out, decimals, "deg") == 1.0
        again = Quantization(decimals=decimals, unit="deg").apply(out, np.random.default_rng(0))
        assert np.max(np.abs(np.asarray(again.east_m) - np.asarray(out.east_m))) < 1e-9
    # the step: 1e-5 deg is 1.11 m north and 0.69 m east at 51.75 N, 6x the 1e-4 minute's
    east_m, north_m = quantization_step_m(5, 51.75, "deg")
    assert north_m == pytest.approx(1.113, abs=0.002) and east_m == pytest.approx(0.690, abs=0.002)
    assert quantization_step_m(5, 51.75, "deg")[1] == pytest.approx(
        6.0 * quantization_step_m(4, 51.75)[1]
    )


def test_the_layer_table_round_trips_and_minutes_read_as_before() -> None:
    deg = Quantization(decimals=5, unit="deg")
    assert deg.to_params() == {"name": "quantization", "decimals": 5, "unit": "deg"}
    assert Quantization.from_params(deg.to_params()) == deg
    # minutes stay the default, and their table is written as before (no unit key)
    assert Quantization(decimals=4).to_params() == {"name": "quantization", "decimals": 4}
    assert Quantization.from_params({"decimals": 4}) == Quantization(decimals=4, unit="min")
    world = loads_world(
        'name = "x"\n[origin]\nlat_deg = 51.75\nlon_deg = -1.25\n'
        '[[effects]]\nname = "quantization"\ndecimals = 5\nunit = "deg"\n'
    )
    assert world.effect_objects() == [deg]


@pytest.mark.parametrize("unit", ["degrees", "minutes", "", "DEG"])
def test_the_layer_unit_is_validated_naming_the_key(unit: str) -> None:
    with pytest.raises(ConfigError, match=r"unit="):
        Quantization(decimals=5, unit=unit)
    with pytest.raises(ConfigError, match=r"effects\[0\].*unit"):
        loads_world(
            'name = "x"\n[origin]\nlat_deg = 51.75\nlon_deg = -1.25\n'
            f'[[effects]]\nname = "quantization"\ndecimals = 5\nunit = "{unit}"\n'
        )
    with pytest.raises(ConfigError, match=r"effects\[0\]\.unit"):
        loads_world(
            'name = "x"\n[origin]\nlat_deg = 51.75\nlon_deg = -1.25\n'
            '[[effects]]\nname = "quantization"\ndecimals = 5\nunit = 60\n'
        )


# --- the lattice the gap tool finds


def test_lattices_are_ordered_coarsest_step_first() -> None:
    from x6wd.gap.stats import LATTICES

    steps = [10.0**-d / (60.0 if unit == "min" else 1.0) for d, unit in LATTICES]
    assert steps == sorted(steps, reverse=True)
    assert {(d, "deg") for d in range(2, 7)} | {(d, "min") for d in range(1, 6)} == set(LATTICES)


@pytest.mark.parametrize("decimals", [2, 3, 4, 5, 6])
def test_a_degree_rounded_log_is_found_on_its_degree_lattice(decimals: int) -> None:
    from x6wd.gap.stats import find_lattice

    # fixes over +-5 km, so that even the 1.1 km lattice of 2 decimals has many points
    real = _rounded_to_degrees(_spread(decimals, 5000.0), decimals)
    assert find_lattice([real]) == Quantization(decimals=decimals, unit="deg")


@pytest.mark.parametrize("decimals", [4, 5, 6])
def test_fit_quantization_names_the_degree_lattice_not_the_finer_minute_one(
    runs: list[PositionSeries], decimals: int
) -> None:
    # before: 1e-5 deg was read as "decimals=4" of minutes (0.19 m), 1e-4 deg as 3, 1e-6 as 5
    real = _rounded_to_degrees(
        surrogate_run(900.0, 1.0, np.random.default_rng(3), effects=PRE), decimals
    )
    fit = fit_quantization(real, runs, layout_for(real))
    assert fit is not None
    assert getattr(fit.effect, "unit", "min") == "deg" and fit.effect.decimals == decimals
    assert fit.effect == Quantization(decimals=decimals, unit="deg")


@pytest.mark.parametrize("decimals", [4, 5])
def test_an_nmea_log_keeps_its_minute_lattice(runs: list[PositionSeries], decimals: int) -> None:
    from x6wd.gap.stats import find_lattice

    real = surrogate_run(
        900.0, 1.0, np.random.default_rng(3), effects=[*PRE, Quantization(decimals)]
    )
    assert find_lattice([real]) == Quantization(decimals=decimals, unit="min")
    assert find_lattice(runs) == Quantization(decimals=5, unit="min")
    fit = fit_quantization(real, runs, layout_for(real))
    if decimals == 5:
        assert fit is None  # the baseline prints on it already
    else:
        assert fit is not None and fit.params == {"decimals": 4}  # as before: no unit key
        assert _params_text(fit) == "decimals=4"
    # the battery's lattice cells are the minute ones, unchanged
    cells = [c for c in battery(real, layout_for(real)) if c.statistic == "lattice"]
    assert [c.scale for c in cells] == [f"1e-{d} min" for d in (1, 2, 3, 4, 5)]


@pytest.mark.slow  # a whole diagnosis: 8-17 s
def test_a_degree_rounded_log_is_quantization_on_the_degree_lattice_not_a_static_hold(
    runs: list[PositionSeries],
) -> None:
    # the audit's case on the surrogate: a receiver's log rounded to 1e-5 deg. Before, the
    # tool selected quantization (decimals=4, minutes) and a static hold beside it.
    baseline = [
        *runs,
        *(surrogate_run(900.0, 1.0, np.random.default_rng(50 + i)) for i in range(4)),
    ]
    real = _rounded_to_degrees(surrogate_run(900.0, 1.0, np.random.default_rng(3), effects=PRE), 5)
    d = diagnose(real, baseline, np.random.default_rng(1), Options())
    names = [f.name for f in d.selected]
    assert names and names[0] == "quantization", names
    assert "static_hold" not in names, names
    lattice = d.selected[0].effect
    assert (lattice.decimals, getattr(lattice, "unit", "min")) == (5, "deg")
    assert "quantization (1e-5 deg)" in verdict_text(d)
    table = markdown(d, report_dict(d), "rounded.csv", figures=False)
    assert "| 1 | quantization (1e-5 deg) | decimals=5, unit=deg |" in table


def test_seven_decimals_of_a_degree_are_no_lattice_the_simulator_can_print() -> None:
    # 1e-7 deg is finer than the simulator's finest NMEA printing (1e-5 min = 1.7e-7 deg):
    # named as an effect (code review of 5d93994: "quantization (1e-7 deg)", closure 0.93),
    # the written scenario's run did not lie on it (16 % of latitudes)
    from x6wd.gap.stats import LATTICES, find_lattice

    assert (7, "deg") not in LATTICES
    real = _rounded_to_degrees(_spread(7, 50.0), 7)
    found = find_lattice([real])
    assert found is None or found.unit == "min", found


def test_a_receiver_holding_one_fix_is_not_on_a_degree_lattice() -> None:
    # one held position of an NMEA 4-decimal log lies on 1e-5 deg one time in 36: over 400
    # places 12 read "quantization (1e-5 deg)" (code review of 5d93994); a degree lattice
    # now needs MIN_DEG_LATTICE_POSITIONS distinct positions
    from sim_backend.effects import Quantization as Q
    from x6wd.gap.stats import MIN_DEG_LATTICE_POSITIONS, find_lattice

    rng = np.random.default_rng(5)
    held = 0
    for _ in range(200):
        one = _spread(1, 0.0)
        lat0 = float(rng.uniform(-60.0, 60.0))
        lon0 = float(rng.uniform(-179.0, 179.0))
        one = one.with_(origin_lat_deg=lat0, origin_lon_deg=lon0)
        printed = Q(decimals=4).apply(one, np.random.default_rng(0))
        found = find_lattice([printed])
        held += found is not None and found.unit == "deg"
    assert held == 0
    assert MIN_DEG_LATTICE_POSITIONS >= 3
