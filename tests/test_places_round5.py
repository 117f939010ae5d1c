"""Places and dates nobody tuned for (outside audit, round 5): the scenarios shipped for
Oxford, moved elsewhere on the Earth."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from sim_backend.effects import PositionSeries, metres_per_degree
from sim_backend.mission import run_mission
from sim_backend.receiver import build_receiver
from sim_backend.world import load_world, loads_world

SCENARIOS = Path(__file__).resolve().parents[1] / "config" / "scenarios"


def _moved(name: str, lat: float, lon: float, extra: str = "") -> str:
    """A shipped scenario's text with its origin moved (everything else as shipped)."""
    text = (SCENARIOS / name).read_text()
    text = re.sub(r"(?m)^lat_deg = .*$", f"lat_deg = {lat!r}", text, count=1)
    text = re.sub(r"(?m)^lon_deg = .*$", f"lon_deg = {lon!r}", text, count=1)
    return text + extra


def test_receiver_errors_at_an_origin_on_the_180th_meridian_are_metres() -> None:
    # The gap tool's baseline (build_receiver(...).errors) of a static log at 179.99999 E:
    # a fix printed at -179.99999 was an east error of -360 deg (-3.8e7 m at 16.5 S), so the
    # validation read a simulated mean error of 1e5 m against the log's 1.8 m.
    world = loads_world(_moved("open_field.toml", -16.5, 179.99999), source="anti.toml")
    n = 200
    z = np.zeros(n)
    tpl = PositionSeries(
        np.arange(n, dtype=float), z, z, z, np.ones(n, dtype=bool), -16.5, 179.99999
    )
    e = build_receiver(world, 5).errors(tpl)
    horizontal = np.hypot(e.east_m[e.valid], e.north_m[e.valid])
    assert e.valid.sum() > 150
    assert float(np.max(horizontal)) < 30.0, float(np.max(horizontal))


def test_an_error_layer_on_a_mission_across_the_180th_meridian_keeps_the_fix_in_place() -> None:
    # zigzag.toml moved to Fiji, its route crossing 180 deg 53 m east of the start, with the
    # gap tool's SBAS-style layer (correction factor 0.5): each fix beyond the meridian moved
    # by half the Earth's circumference, the robot's geofence failsafe fired at 62 s and the
    # mission ended 2/8 with a raw CEP50 of 3,641 km. At Oxford the same run completes.
    layer = '\n[[effects]]\nname = "correction"\nfactor = 0.5\n'
    world = loads_world(_moved("zigzag.toml", -16.5, 179.9995, layer), source="fiji.toml")
    s = run_mission(world, None, seed=1, duration_s=120.0)
    assert s.extra["failsafes"] == [], s.extra["failsafes"]
    assert s.raw_error.max_m < 30.0, s.raw_error
    # the route crosses the meridian within the 120 s: waypoint 3 (88 m east) lies beyond it
    assert s.waypoints_reached >= 3
    assert s.extra["geofence_breaches"] == 0


def test_the_wrap_leaves_differences_under_180_degrees_bit_for_bit() -> None:
    # The short-way-round difference applies only beyond +-180 deg: at Oxford the errors are
    # exactly the plain difference's (the shipped runs' figures do not move).
    world = load_world(SCENARIOS / "open_field.toml")
    n = 50
    z = np.zeros(n)
    rx = build_receiver(world, 3)
    b = rx.batch(np.arange(n, dtype=float), np.zeros((n, 3)), np.zeros((n, 3)))
    s = rx._series(b, z, z, z, z, z)
    ok = np.asarray(b.valid, dtype=bool)
    e_per, _n_per = metres_per_degree(world.origin.lat_deg)
    assert ok.sum() > 40
    assert np.array_equal(s.east_m[ok], ((b.lon_deg - world.origin.lon_deg) * e_per)[ok])


def test_the_log_viewers_largest_error_is_the_short_way_round_the_180th_meridian() -> None:
    # x6wd plot keeps, of a long log, the fix furthest from the true track (the error panel's
    # axis spans the whole log). It took the longitude difference plainly and interpolated
    # the truth across +-180: a fix 2 m from a truth on the other side of the meridian was
    # 360 deg off, and the truth between 179.99999 and -179.99999 passed through 0 deg.
    from x6wd.app.logview import _Raw

    t = np.array([0.0, 1.0, 2.0])
    lat = np.full(3, -16.5)
    lon = np.array([179.99998, -179.99999, -179.99996])  # crosses between t 0 and 1
    raw = _Raw(truth=(t, lat, lon))
    near = raw.off_truth_deg(1.0, -16.5, 179.99999)  # 2 m west of the truth, across 180
    mid = raw.off_truth_deg(0.5, -16.5, 179.999995)  # on the truth, half-way
    assert near is not None and mid is not None
    assert near < 1e-4 and mid < 1e-5, (near, mid)


def test_the_constellation_filter_averages_two_fixes_the_short_way_round() -> None:
    # The filter keeps one fix at a mission start, so the second makes a two-sample mean:
    # 179.999995 and -179.999995 averaged to 0.0 deg, 16,000 km away (code review, round 5).
    from x6wd.core.geodesy import great_circle_m
    from x6wd.core.records import GpsFix
    from x6wd.nav.position import ConstellationSource

    src = ConstellationSource(5, True)
    lons = [179.999995, -179.999995, 179.999993, -179.999992, -179.999999, 179.999991]
    for k, lon in enumerate(lons):
        src.on_fix(GpsFix(t_s=k, lat_deg=-16.5, lon_deg=lon, valid=True, quality=1, mode=3))
        pos = src.position(float(k))
        assert pos is not None and -180.0 < pos[1] <= 180.0
        assert great_circle_m(-16.5, lon, *pos) < 5.0, (k, pos)
    # away from the meridian every fix goes in as it is
    from x6wd.nav.constellation import Constellation

    plain, alone = ConstellationSource(5, True), Constellation(5, True)
    for k, lon in enumerate((10.1, 10.3, 10.2, 10.25)):
        plain.on_fix(GpsFix(t_s=k, lat_deg=1.0, lon_deg=lon, valid=True, quality=1, mode=3))
        alone.add(lon)
        assert plain.position(float(k)) == (1.0, alone.filter())


def test_a_receiver_standing_on_the_180th_meridian_is_not_read_as_moving() -> None:
    # Half the fixes on each side: their plain median was about 0 deg, so the static check
    # refused the recording as moving (code review, round 5).
    from x6wd.calibrate.gnss import FixSeries, _check_standing

    rng = np.random.default_rng(3)
    n = 600
    # exactly half on each side (an even count split evenly: the plain median is their mean)
    off = np.abs(rng.normal(0.0, 1e-5, n))  # about a metre, random order
    lon = np.where(rng.permutation(n) < n // 2, 180.0 - off, -180.0 + off)
    lat = -16.5 + rng.normal(0.0, 1e-5, n)
    fixes = FixSeries(
        t_s=np.arange(n, dtype=float),
        t_gpst_s=np.full(n, np.nan),
        lat_deg=lat,
        lon_deg=lon,
        hdop=np.ones(n),
        hdop_known=True,
    )
    assert np.any(lon > 0) and np.any(lon < 0)
    _check_standing(fixes, -16.5, 180.0)  # raises ConfigError "the recording moves" before
