"""Sky: geodesy, GPS time, almanac/RINEX readers, IS-GPS-200 positions, az/el, DOP.

Real data (tests/data/almanac, see SOURCE.md there): a YUMA almanac and the broadcast
ephemeris of the same day (2020-01-01), and two gnsstk almanacs from 2006/2007.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from sim_backend import geodesy, sky
from sim_backend.sky import Ephemeris, SatelliteSet
from x6wd.core.errors import ConfigError, ParseError

ALM = Path(__file__).resolve().parent / "data" / "almanac"
DAY = datetime(2020, 1, 1, tzinfo=UTC)


@pytest.fixture(scope="module")
def eph() -> list[Ephemeris]:
    return sky.read_rinex_nav(ALM / "sugl0010.20n")


@pytest.fixture(scope="module")
def eph_set(eph: list[Ephemeris]) -> SatelliteSet:
    return SatelliteSet.from_ephemeris(eph)


# ---------------------------------------------------------------- geodesy


def test_lla_ecef_known_points_and_round_trip() -> None:
    np.testing.assert_allclose(geodesy.lla_to_ecef(0.0, 0.0, 0.0), [geodesy.A_M, 0, 0])
    np.testing.assert_allclose(geodesy.lla_to_ecef(90.0, 0.0, 0.0), [0, 0, geodesy.B_M], atol=1e-6)
    rng = np.random.default_rng(5)
    lat = rng.uniform(-89.9, 89.9, 500)
    lon = rng.uniform(-180, 180, 500)
    alt = rng.uniform(-100, 2.1e7, 500)  # ground to GPS orbit
    la, lo, h = geodesy.ecef_to_lla(geodesy.lla_to_ecef(lat, lon, alt))
    np.testing.assert_allclose(la, lat, atol=1e-9)
    np.testing.assert_allclose(lo, lon, atol=1e-9)
    np.testing.assert_allclose(h, alt, atol=1e-3)


def test_enu_axes_and_round_trip() -> None:
    lat0, lon0, h0 = 51.7, -3.2, 40.0
    north = geodesy.lla_to_enu(lat0 + 0.001, lon0, h0, lat0, lon0, h0)
    assert north[1] == pytest.approx(111.25, abs=0.2)  # 0.001 deg of latitude at 51.7 N
    assert abs(north[0]) < 1e-6
    east = geodesy.lla_to_enu(lat0, lon0 + 0.001, h0, lat0, lon0, h0)
    assert east[0] == pytest.approx(111.32 * math.cos(math.radians(lat0)), abs=0.2)
    enu = np.array([[10.0, -20.0, 3.0], [-500.0, 800.0, -2.0]])
    back = geodesy.ecef_to_enu(geodesy.enu_to_ecef(enu, lat0, lon0, h0), lat0, lon0, h0)
    np.testing.assert_allclose(back, enu, atol=1e-6)


def test_gps_time_leap_seconds_and_weeks() -> None:
    assert geodesy.utc_to_gps_seconds(geodesy.GPS_EPOCH) == 0.0
    assert geodesy.leap_seconds(DAY) == 18
    assert geodesy.leap_seconds(datetime(2016, 12, 31, 23, 59, 59, tzinfo=UTC)) == 17
    week, tow = geodesy.gps_week_tow(geodesy.utc_to_gps_seconds(DAY))
    # 2020-01-01 was a Wednesday: 3 days into GPS week 2086, plus 18 leap seconds.
    assert (int(week), float(tow)) == (2086, 3 * 86400 + 18)
    for utc in (DAY, datetime(2006, 11, 5, 12, 30, 1, tzinfo=UTC)):
        assert geodesy.gps_seconds_to_utc(geodesy.utc_to_gps_seconds(utc)) == utc
    with pytest.raises(ConfigError, match="time zone"):
        geodesy.utc_to_gps_seconds(datetime(2020, 1, 1))


def test_week_rollover_resolution() -> None:
    assert geodesy.resolve_week(38, DAY) == 2086
    assert geodesy.resolve_week(377, datetime(2006, 11, 1, tzinfo=UTC)) == 1401
    # Across the April 2019 rollover (week 2047 -> 2048 = 0 mod 1024).
    assert geodesy.resolve_week(1023, datetime(2019, 4, 10, tzinfo=UTC)) == 2047
    assert geodesy.resolve_week(0, datetime(2019, 4, 1, tzinfo=UTC)) == 2048
    with pytest.raises(ConfigError):
        geodesy.resolve_week(1024, DAY)


# ---------------------------------------------------------------- readers


def test_read_yuma_2020() -> None:
    alm = sky.read_yuma(ALM / "almyuma_01jan2020.txt", reference=DAY)
    assert len(alm) == 31
    a1 = alm[0]
    assert a1.prn == 1 and a1.week == 2086 and a1.toa_s == 503808.0
    assert a1.e == pytest.approx(0.9250164032e-2)
    assert a1.sqrt_a_sqrtm == pytest.approx(5153.594238)
    with pytest.raises(ConfigError, match="reference"):
        sky.read_yuma(ALM / "almyuma_01jan2020.txt")


def test_read_yuma_and_sem_old_weeks() -> None:
    y = sky.read_yuma(ALM / "test_input_yuma377.txt", datetime(2006, 11, 1, tzinfo=UTC))
    s = sky.read_sem(ALM / "test_input_sem387.txt", datetime(2007, 1, 1, tzinfo=UTC))
    assert len(y) == 30 and {a.week for a in y} == {1401}
    assert len(s) == 30 and {a.week for a in s} == {1411}
    s1 = s[0]
    # SEM angles are semicircles; inclination is an offset from 0.30 semicircles.
    assert s1.i0_rad == pytest.approx((0.30 + 0.14945983886719e-1) * math.pi)
    assert s1.omega0_rad == pytest.approx(-0.57885289192200 * math.pi)
    assert s1.e == pytest.approx(0.67005157470703e-2)
    # Both describe GPS orbits: a (1 +- e) from the Earth's centre, within ~0.02 of 26,560 km.
    for alm in (y, s):
        sats = SatelliteSet.from_almanac(alm)
        r = np.linalg.norm(sats.positions_ecef(alm[0].toa_gps_s + 3600.0), axis=-1)
        by_prn = {x.prn: x for x in alm}
        a = np.array([by_prn[p].sqrt_a_sqrtm ** 2 for p in sats.prns])
        ecc = np.array([by_prn[p].e for p in sats.prns])
        assert np.all((r >= a * (1 - ecc) - 1.0) & (r <= a * (1 + ecc) + 1.0))


def test_read_rinex2_nonstandard_fields(eph: list[Ephemeris]) -> None:
    assert len(eph) == 418
    e0 = eph[0]
    assert e0.prn == 1 and e0.week == 2086 and e0.toe_s == 259200.0
    assert e0.toc_gps_s == geodesy.week_tow_to_gps_seconds(2086, 259200.0)
    assert e0.af0_s == pytest.approx(-2.479013055563e-04)
    assert e0.crs_m == pytest.approx(-1.956250000000e01)
    assert e0.sqrt_a_sqrtm == pytest.approx(5.153638690948e03)
    assert e0.i0_rad == pytest.approx(9.785100924501e-01)
    assert e0.tgd_s == pytest.approx(5.587935447693e-09)


def _fmt_d(x: float) -> str:
    # RINEX 3 style D19.12 with a leading-dot mantissa, as RTKCONV writes it.
    if x == 0:
        return " .000000000000D+00"
    m, ex = f"{x:.11E}".split("E")
    mant = float(m) / 10.0
    return f"{mant:.12f}".replace("0.", ".", 1).rjust(15) + f"D{int(ex) + 1:+03d}"


def test_read_rinex3_mixed_equals_rinex2(eph: list[Ephemeris], tmp_path: Path) -> None:
    e0 = eph[0]
    v = [e0.iode, e0.crs_m, e0.delta_n_rps, e0.m0_rad, e0.cuc_rad, e0.e, e0.cus_rad,
         e0.sqrt_a_sqrtm, e0.toe_s, e0.cic_rad, e0.omega0_rad, e0.cis_rad, e0.i0_rad,
         e0.crc_m, e0.w_rad, e0.omega_dot_rps, e0.idot_rps, 1.0, 2086.0, 0.0,
         e0.sv_accuracy_m, 0.0, e0.tgd_s, 72.0, 252000.0, 4.0]  # fmt: skip
    body = ["    " + "".join(_fmt_d(x) for x in v[i : i + 4]) for i in range(0, 26, 4)]
    gal = ["E08 2020 01 01 00 00 00" + _fmt_d(1e-3) * 3] + ["    " + _fmt_d(1.0) * 4] * 7
    text = "\n".join(
        [
            "     3.04           N: GNSS NAV DATA    M: Mixed            RINEX VERSION / TYPE",
            "                                                            END OF HEADER",
            *gal,
            "G01 2020 01 01 00 00 00" + "".join(_fmt_d(x) for x in (e0.af0_s, e0.af1_sps, 0.0)),
            *body,
        ]
    )
    path = tmp_path / "mixed.20p"
    path.write_text(text)
    (r3,) = sky.read_rinex_nav(path)
    assert r3.prn == 1 and r3.week == 2086 and r3.toc_gps_s == e0.toc_gps_s
    for name in ("m0_rad", "e", "sqrt_a_sqrtm", "omega0_rad", "i0_rad", "w_rad", "crs_m"):
        assert getattr(r3, name) == pytest.approx(getattr(e0, name), rel=1e-11), name


def test_read_rinex2_blank_fields(eph: list[Ephemeris], tmp_path: Path) -> None:
    lines = (ALM / "sugl0010.20n").read_text().splitlines()
    rec = lines[3:11]  # header is 3 lines; the first record is 8
    w = 20  # this file's field width after a 3-character indent (standard RINEX 2: 19)

    def blank(line: str, field: int) -> str:
        a, b = 3 + field * w, 3 + (field + 1) * w
        return line[:a] + " " * (b - a) + line[b:]

    # RINEX allows blank spare/flag fields: "codes on L2" (orbit line 5, field 2) blank.
    rec_ok = [*rec]
    rec_ok[5] = blank(rec[5], 1)
    path = tmp_path / "blank.20n"
    path.write_text("\n".join(lines[:3] + rec_ok) + "\n")
    (r,) = sky.read_rinex_nav(path)
    assert r == eph[0]
    # A blank required field (M0, orbit line 1, field 4) is an error naming the field.
    rec_bad = [*rec]
    rec_bad[1] = blank(rec[1], 3)
    path.write_text("\n".join(lines[:3] + rec_bad) + "\n")
    with pytest.raises(ParseError, match="m0_rad"):
        sky.read_rinex_nav(path)


def test_reader_errors(tmp_path: Path) -> None:
    bad = tmp_path / "bad.20n"
    bad.write_text("garbage\n")
    with pytest.raises(ParseError, match="RINEX VERSION"):
        sky.read_rinex_nav(bad)
    lines = (ALM / "sugl0010.20n").read_text().splitlines()
    short = tmp_path / "short.20n"
    short.write_text("\n".join(lines[:5]) + "\n")  # header + 2 lines of a record
    with pytest.raises(ParseError, match="numbers"):
        sky.read_rinex_nav(short)
    with pytest.raises(ConfigError, match="cannot read"):
        sky.read_sem(tmp_path / "missing.al3", DAY)


# ---------------------------------------------------------------- positions


def _scalar_position(e: Ephemeris, t: float) -> np.ndarray:
    """IS-GPS-200 Table 20-IV, written out plainly for one satellite and one time."""
    mu, we = 3.986005e14, 7.2921151467e-5
    a = e.sqrt_a_sqrtm**2
    tk = t - e.toe_gps_s
    m = e.m0_rad + (math.sqrt(mu / a**3) + e.delta_n_rps) * tk
    ea = m
    for _ in range(30):
        ea = m + e.e * math.sin(ea)
    nu = math.atan2(math.sqrt(1 - e.e**2) * math.sin(ea), math.cos(ea) - e.e)
    phi = nu + e.w_rad
    u = phi + e.cus_rad * math.sin(2 * phi) + e.cuc_rad * math.cos(2 * phi)
    r = a * (1 - e.e * math.cos(ea)) + e.crs_m * math.sin(2 * phi) + e.crc_m * math.cos(2 * phi)
    i = e.i0_rad + e.cis_rad * math.sin(2 * phi) + e.cic_rad * math.cos(2 * phi)
    i += e.idot_rps * tk
    x1, y1 = r * math.cos(u), r * math.sin(u)
    om = e.omega0_rad + (e.omega_dot_rps - we) * tk - we * e.toe_s
    return np.array(
        [
            x1 * math.cos(om) - y1 * math.cos(i) * math.sin(om),
            x1 * math.sin(om) + y1 * math.cos(i) * math.cos(om),
            y1 * math.sin(i),
        ]
    )


def test_broadcast_positions_exact_to_the_formulas(
    eph: list[Ephemeris], eph_set: SatelliteSet
) -> None:
    t0 = geodesy.utc_to_gps_seconds(DAY)
    times = t0 + np.arange(0.0, 86400.0, 3.0)  # dense: exercises the interpolated path
    st = eph_set.state(times)
    rng = np.random.default_rng(3)
    for _ in range(40):
        k = int(rng.integers(len(times)))
        s = int(rng.integers(eph_set.n_sats))
        prn = int(eph_set.prns[s])
        recs = [e for e in eph if e.prn == prn and e.health == 0]
        nearest = min(recs, key=lambda e: abs(times[k] - e.toe_gps_s))
        expect = _scalar_position(nearest, float(times[k]))
        np.testing.assert_allclose(st.ecef_m[k, s], expect, atol=1e-3)
        exact = eph_set.state(times[k : k + 1], exact=True).ecef_m[0, s]
        np.testing.assert_allclose(exact, expect, atol=1e-6)


def test_almanac_vs_broadcast_same_day(eph_set: SatelliteSet) -> None:
    alm = SatelliteSet.from_almanac(sky.read_yuma(ALM / "almyuma_01jan2020.txt", DAY))
    t = geodesy.utc_to_gps_seconds(DAY) + np.arange(0.0, 86400.0, 600.0)
    common, ia, ie = np.intersect1d(alm.prns, eph_set.prns, return_indices=True)
    assert len(common) >= 28
    d = np.linalg.norm(alm.positions_ecef(t)[:, ia] - eph_set.positions_ecef(t)[:, ie], axis=-1)
    ok = eph_set.available(t)[:, ie]
    assert 1100.0 <= float(np.median(d[ok])) <= 1350.0


def test_almanac_continuous_across_gps_week_boundary() -> None:
    alm = SatelliteSet.from_almanac(sky.read_yuma(ALM / "almyuma_01jan2020.txt", DAY))
    boundary = 2087 * geodesy.SECONDS_PER_WEEK  # toa is in week 2086: propagate across it
    t = boundary + np.array([-1.0, 0.0, 1.0])
    p = alm.positions_ecef(t)
    step1 = np.linalg.norm(p[1] - p[0], axis=-1)
    step2 = np.linalg.norm(p[2] - p[1], axis=-1)
    # Earth-fixed GPS satellite speeds are 1.5-3.9 km/s; no jump at the rollover.
    assert np.all((step1 > 1000.0) & (step1 < 4500.0))
    np.testing.assert_allclose(step1, step2, rtol=1e-3)


def test_ephemeris_validity_window(eph_set: SatelliteSet) -> None:
    t_day = geodesy.utc_to_gps_seconds(DAY)
    t = np.array([t_day + 43200.0, t_day + 86400.0 + 7200.0 + 60.0, t_day - 7200.0 - 60.0])
    avail = eph_set.available(t)
    assert avail[0].mean() > 0.9  # mid-day: every healthy satellite has a record
    assert not avail[1].any() and not avail[2].any()  # beyond +-2 h of any toe


# ---------------------------------------------------------------- az/el and DOP


def test_azel_directions() -> None:
    rx = geodesy.lla_to_ecef(0.0, 0.0, 0.0)
    overhead = geodesy.lla_to_ecef(0.0, 0.0, 2.0e7)
    north_horizon = rx + np.array([0.0, 0.0, 1.0e6])
    east_up = geodesy.enu_to_ecef(np.array([1000.0, 0.0, 1000.0]), 0.0, 0.0, 0.0)
    sats = np.stack([overhead, north_horizon, east_up])[None]
    az, el, rng_m = sky.look_angles(rx, sats)
    assert el[0, 0] == pytest.approx(90.0)
    assert (az[0, 1], el[0, 1]) == (pytest.approx(0.0, abs=1e-9), pytest.approx(0.0, abs=1e-9))
    assert (az[0, 2], el[0, 2]) == (pytest.approx(90.0), pytest.approx(45.0))
    assert rng_m[0, 0] == pytest.approx(2.0e7)
    assert sky.above_mask(el[0]).tolist() == [True, False, True]


def test_dop_open_sky_and_monotone(eph_set: SatelliteSet) -> None:
    t = geodesy.utc_to_gps_seconds(DAY) + np.arange(0.0, 86400.0, 300.0)
    st = eph_set.state(t)
    az, el = sky.azel(geodesy.lla_to_ecef(37.43, -122.17, 30.0), st.ecef_m)
    used = sky.above_mask(el) & st.available
    d = sky.dops(az, el, used)
    assert np.all(d.n_used >= 4)
    assert 0.7 <= float(np.median(d.hdop)) <= 1.5
    np.testing.assert_allclose(d.pdop**2, d.hdop**2 + d.vdop**2)
    np.testing.assert_allclose(d.gdop**2, d.pdop**2 + d.tdop**2)
    # Dropping a satellite never improves any DOP.
    drop = used.copy()
    first = np.argmax(used, axis=1)
    drop[np.arange(len(t)), first] = False
    d2 = sky.dops(az, el, drop)
    fin = np.isfinite(d2.hdop)
    assert np.all(d2.hdop[fin] >= d.hdop[fin] - 1e-12)
    assert np.all(d2.pdop[fin] >= d.pdop[fin] - 1e-12)
    # Fewer than 4 satellites: no DOP.
    three = np.zeros_like(used)
    three[:, :3] = True
    assert np.all(np.isnan(sky.dops(az, el, three).hdop))


def test_dop_against_direct_inverse() -> None:
    az = np.array([[0.0, 90.0, 180.0, 270.0, 45.0]])
    el = np.array([[10.0, 30.0, 50.0, 20.0, 85.0]])
    a, e = np.radians(az[0]), np.radians(el[0])
    g = np.column_stack([np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e), np.ones_like(a)])
    q = np.linalg.inv(g.T @ g)
    d = sky.dops(az, el)
    assert d.hdop[0] == pytest.approx(math.sqrt(q[0, 0] + q[1, 1]))
    assert d.vdop[0] == pytest.approx(math.sqrt(q[2, 2]))
    assert d.tdop[0] == pytest.approx(math.sqrt(q[3, 3]))


def test_state_input_checks(eph_set: SatelliteSet) -> None:
    with pytest.raises(ConfigError):
        eph_set.state(np.array([np.nan]))
    with pytest.raises(ConfigError):
        eph_set.state(np.zeros((2, 2)))
    one = eph_set.positions_ecef(geodesy.utc_to_gps_seconds(DAY + timedelta(hours=1)))
    assert one.shape == (1, eph_set.n_sats, 3)


def test_from_file_recognises_the_format() -> None:
    sizes = {
        "almyuma_01jan2020.txt": (DAY, 31),
        "sugl0010.20n": (None, 31),
        "test_input_sem387.txt": (datetime(2007, 1, 1, tzinfo=UTC), None),
        "test_input_yuma377.txt": (datetime(2006, 11, 1, tzinfo=UTC), None),
    }
    for name, (ref, n) in sizes.items():
        s = SatelliteSet.from_file(ALM / name, reference=ref)
        assert s.kind == ("ephemeris" if name.endswith(".20n") else "almanac")
        assert s.n_sats >= 26 and (n is None or s.n_sats <= n)
