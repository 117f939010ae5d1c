"""NEO-5 NMEA output: byte-exact against a real u-blox 5 capture, decoded by the real driver."""

from __future__ import annotations

import math
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.gps_nmea import GpsDecoder
from drivers.nmea import KNOTS_PER_MPS, checksum
from sim_backend.epoch import GnssEpoch, SimSat
from sim_backend.nmea_out import NmeaFormatter, sentence, wire_time_s
from x6wd.core.errors import ConfigError
from x6wd.core.records import GpsFix, GpsSky

DATA = Path(__file__).resolve().parent / "data" / "nmea_out"


def _log_lines(name: str) -> list[str]:
    text = (DATA / name).read_text(encoding="ascii", errors="replace")
    return [ln.strip() for ln in text.splitlines() if ln.startswith("$")]


def _epoch(
    t_s: float = 0.0,
    *,
    valid: bool = True,
    lat: float = 51.7,
    lon: float = 19.5,
    speed: float = 0.0,
    course: float | None = None,
    sats: tuple[SimSat, ...] = (),
    utc: datetime | None = None,
    hdop: float = 1.2,
) -> GnssEpoch:
    if utc is None:
        utc = datetime(2020, 1, 1, 12, tzinfo=UTC) + timedelta(seconds=t_s)
    return GnssEpoch(
        t_s, utc, valid, lat, lon, 120.0, 34.0, speed, course, 1 if valid else 0,
        3 if valid else 1, hdop, 2.0, 1.6, sats,
    )  # fmt: skip


def _random_sats(rng: np.random.Generator, n: int) -> tuple[SimSat, ...]:
    prns = rng.choice(np.arange(1, 33), size=n, replace=False)
    return tuple(
        SimSat(
            int(p),
            float(rng.uniform(0, 90)),
            float(rng.uniform(0, 360)),
            None if rng.random() < 0.2 else float(rng.uniform(10, 50)),
            bool(rng.random() < 0.7),
        )
        for p in prns
    )


def test_checksum_agrees_with_every_sentence_of_a_real_capture() -> None:
    lines = _log_lines("ublox-lea-5h.log") + _log_lines("ublox-lea-5q.log")
    assert len(lines) > 100
    for line in lines:
        body, hh = line[1:].split("*")
        assert checksum(body.encode()) == int(hh, 16), line
        assert sentence(body) == (line + "\r\n").encode()


def test_banner_matches_u_blox_5_and_decodes_cleanly() -> None:
    f = NmeaFormatter()
    banner = f.banner()
    lines = banner.decode().split("\r\n")
    assert lines[0] == "$GPTXT,01,01,02,u-blox ag - www.u-blox.com*50"
    real = set(_log_lines("ublox-lea-5h.log"))
    assert sum(ln in real for ln in lines) >= 5  # all but the module name as a LEA-5H prints
    dec = GpsDecoder()
    dec.feed(banner, 0.0)
    c = dec.counters
    assert c.sentences == 7 and c.checksum_failures == 0 and c.invalid_fields == 0


def test_fix_epoch_is_byte_identical_to_a_real_lea_5h_epoch() -> None:
    # The first fixed epoch of ublox-lea-5h.log, rebuilt as a GnssEpoch.
    used = [27, 15, 9, 28, 18, 8]  # GSA lists them in this channel order
    gsv = [
        (5, 4, 187, None), (8, 11, 78, 29), (9, 43, 270, 37), (12, 3, 212, None),
        (15, 78, 214, 34), (17, 25, 106, 18), (18, 32, 294, 39), (22, 13, 324, 20),
        (24, 4, 342, None), (26, 55, 139, 24), (27, 62, 276, 36), (28, 39, 55, 26),
    ]  # fmt: skip
    by_prn = {p: SimSat(p, el, az, snr, p in used) for p, el, az, snr in gsv}
    sats = tuple(by_prn[p] for p in used) + tuple(s for p, s in by_prn.items() if p not in used)
    ep = GnssEpoch(
        0.0,
        datetime(2010, 8, 21, 8, 37, 23, tzinfo=UTC),
        True,
        51 + 55.55442 / 60,
        4 + 34.65873 / 60,
        -4.0,
        46.0,
        0.211 / KNOTS_PER_MPS,
        None,
        1,
        3,
        2.51,
        3.33,
        2.20,
        sats,
    )
    out = NmeaFormatter().format_epoch(ep).decode().split("\r\n")[:-1]
    lines = _log_lines("ublox-lea-5h.log")
    start = lines.index("$GPRMC,083723.00,A,5155.55442,N,00434.65873,E,0.211,,210810,,,A*7F")
    assert out == lines[start : start + 8]


def test_no_fix_forms_before_time_are_the_receivers() -> None:
    text = NmeaFormatter().format_epoch(_epoch(valid=False)).decode()
    assert text.split("\r\n")[:-1] == [
        "$GPRMC,,V,,,,,,,,,,N*53",
        "$GPVTG,,,,,,,,,N*30",
        "$GPGGA,,,,,,0,00,99.99,,,,,,*48",
        "$GPGSA,A,1,,,,,,,,,,,,,99.99,99.99,99.99*30",
        "$GPGSV,1,1,00*79",
        "$GPGLL,,,,,,V,N*64",
    ]


def test_no_fix_forms_with_time_match_a_real_cold_start() -> None:
    f = NmeaFormatter()
    f.format_epoch(_epoch(valid=False, sats=(SimSat(7, 20.0, 100.0, 30.0, False),)))
    assert f.time_known  # a tracked satellite gave the receiver time
    ep = _epoch(valid=False, utc=datetime(2011, 2, 2, 0, 19, 2, tzinfo=UTC))
    out = f.format_epoch(ep).decode().split("\r\n")[:-1]
    real = set(_log_lines("ublox-lea-5q.log"))
    assert out[0] == "$GPRMC,001902.00,V,,,,,,,020211,,,N*77"
    assert all(line in real for line in out), [ln for ln in out if ln not in real]


def test_course_is_empty_at_rest_and_present_when_moving() -> None:
    f = NmeaFormatter()
    rest = f.format_epoch(_epoch(speed=0.1, course=None)).decode().split("\r\n")
    assert rest[0].split(",")[8] == "" and rest[1].startswith("$GPVTG,,T,")
    moving = f.format_epoch(_epoch(speed=2.0, course=123.456)).decode().split("\r\n")
    assert moving[0].split(",")[8] == "123.46" and moving[1].startswith("$GPVTG,123.46,T,")
    dec = GpsDecoder(emit_sentences=False)
    fixes = [r for r in dec.feed(b"".join(s.encode() + b"\r\n" for s in rest[:-1]), 0.0)]
    fixes += dec.flush()
    fix = next(r for r in fixes if isinstance(r, GpsFix))
    assert fix.course_deg is None and fix.valid


@pytest.mark.parametrize("decimals", [5, 4, 7])
def test_round_trip_through_the_real_decoder(decimals: int) -> None:
    rng = np.random.default_rng(7)
    f = NmeaFormatter(minute_decimals=decimals)
    epochs = []
    for i in range(60):
        lat = float(rng.uniform(-89, 89))
        lon = float(rng.uniform(-179.9, 179.9))
        moving = bool(rng.random() < 0.5)
        epochs.append(
            _epoch(
                float(i),
                lat=lat,
                lon=lon,
                speed=float(rng.uniform(0.5, 4.0)) if moving else 0.05,
                course=float(rng.uniform(0, 360)) if moving else None,
                sats=_random_sats(rng, int(rng.integers(0, 20))),
                hdop=float(rng.uniform(0.6, 20)),
            )
        )
    stream = f.banner() + b"".join(f.format_epochs(epochs))
    dec = GpsDecoder(emit_sentences=False)
    recs = dec.feed(stream, 0.0) + dec.flush()
    c = dec.counters
    assert c.checksum_failures == 0 and c.invalid_fields == 0 and c.framing_errors == 0
    fixes = [r for r in recs if isinstance(r, GpsFix)]
    skies = [r for r in recs if isinstance(r, GpsSky)]
    assert len(fixes) == len(epochs) and len(skies) == len(epochs)
    quantum_deg = 0.5 * 10.0**-decimals / 60.0 + 1e-12
    for ep, fix, sky in zip(epochs, fixes, skies, strict=True):
        assert fix.valid and fix.utc == ep.utc
        assert fix.lat_deg is not None and fix.lon_deg is not None
        assert abs(fix.lat_deg - ep.lat_deg) <= quantum_deg
        assert abs(fix.lon_deg - ep.lon_deg) <= quantum_deg
        assert fix.speed_mps == pytest.approx(ep.speed_mps, abs=0.0005 / KNOTS_PER_MPS + 1e-9)
        if ep.course_deg is None:
            assert fix.course_deg is None
        else:
            assert fix.course_deg == pytest.approx(ep.course_deg, abs=0.005 + 1e-9)
        assert fix.hdop == pytest.approx(round(ep.hdop, 2))
        shown = sorted(ep.satellites, key=lambda s: (not s.used, -(s.snr_dbhz or 0), s.prn))[:16]
        assert fix.sats_used == sum(s.used for s in ep.satellites)
        assert [s.prn for s in sky.satellites] == sorted(s.prn for s in shown)
        truth = {s.prn: s for s in shown}
        for s in sky.satellites:
            t = truth[s.prn]
            assert s.el_deg == round(t.el_deg) and s.az_deg == round(t.az_deg) % 360
            assert s.snr_dbhz == (None if t.snr_dbhz is None else round(t.snr_dbhz))
            # as gpsd: a satellite without a signal (empty SNR) is never marked used
            used = t.used and t.snr_dbhz is not None
            assert s.used == (used and s.prn in [x.prn for x in ep.satellites if x.used][:12])


def test_southern_western_hemispheres_and_minute_rounding_carry() -> None:
    f = NmeaFormatter()
    # 59.999999' must carry into the degrees, not print "60.00000".
    ep = _epoch(lat=-(33 + 59.9999999 / 60), lon=-(70 + 59.9999999 / 60))
    rmc = f.format_epoch(ep).decode().split("\r\n")[0].split(",")
    assert rmc[3:7] == ["3400.00000", "S", "07100.00000", "W"]


def test_time_rounds_with_carry_and_three_decimals() -> None:
    utc = datetime(2020, 1, 1, 12, 0, 0, 999000, tzinfo=UTC)
    assert NmeaFormatter().format_epoch(_epoch(utc=utc)).startswith(b"$GPRMC,120001.00,")
    f3 = NmeaFormatter(time_decimals=3)
    assert f3.format_epoch(_epoch(utc=utc)).startswith(b"$GPRMC,120000.999,")


@pytest.mark.parametrize("n,messages", [(0, 1), (1, 1), (4, 1), (5, 2), (12, 3), (16, 4), (25, 4)])
def test_gsv_message_count_and_sentence_length(n: int, messages: int) -> None:
    rng = np.random.default_rng(n)
    sats = tuple(
        SimSat(p, float(rng.uniform(5, 90)), float(rng.uniform(0, 359)), 40.0, p % 2 == 0)
        for p in range(1, n + 1)
    )
    lines = NmeaFormatter().format_epoch(_epoch(sats=sats)).decode().split("\r\n")[:-1]
    gsv = [ln for ln in lines if ln.startswith("$GPGSV")]
    assert len(gsv) == messages
    assert all(ln.split("*")[0].split(",")[3] == f"{min(n, 16):02d}" for ln in gsv)
    assert all(len(ln) + 2 <= 82 for ln in lines)
    assert [ln[3:6] for ln in lines] == ["RMC", "VTG", "GGA", "GSA", *["GSV"] * messages, "GLL"]


def test_batch_formatting_equals_one_epoch_at_a_time() -> None:
    rng = np.random.default_rng(3)
    epochs = [
        _epoch(
            float(i),
            valid=bool(i % 7),
            lat=51.7 + float(rng.normal(0, 1e-4)),
            speed=float(rng.uniform(0, 3)),
            course=None if i % 3 == 0 else float(rng.uniform(0, 360)),
            sats=_random_sats(rng, int(rng.integers(0, 18))),
        )
        for i in range(50)
    ]
    one = NmeaFormatter()
    batch = NmeaFormatter()
    assert batch.format_epochs(epochs) == [one.format_epoch(e) for e in epochs]
    assert batch.format_epochs([]) == []


def test_wire_time_of_a_burst() -> None:
    assert wire_time_s(960, 9600) == pytest.approx(1.0)
    assert wire_time_s(b"x" * 96, 9600) == pytest.approx(0.1)
    sats = tuple(SimSat(p, 30.0, 10.0 * p, 35.0, True) for p in range(1, 13))
    burst = NmeaFormatter().format_epoch(_epoch(speed=1.0, course=90.0, sats=sats))
    # REFERENCE §4: a full epoch takes about half a second at 9600 baud.
    assert 0.3 < wire_time_s(burst, 9600) < 0.8
    with pytest.raises(ConfigError, match="baud"):
        wire_time_s(10, 0)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"minute_decimals": 3}, "minute_decimals"),
        ({"minute_decimals": 8}, "minute_decimals"),
        ({"time_decimals": 1}, "time_decimals"),
        ({"rate_hz": 5.0}, "rate_hz"),
        ({"rate_hz": 0.5}, "rate_hz"),
        ({"talker": "gp"}, "talker"),
    ],
)
def test_bad_settings_are_named(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        NmeaFormatter(**kwargs)  # type: ignore[arg-type]


def test_dop_is_capped_like_the_receiver() -> None:
    text = NmeaFormatter().format_epoch(_epoch(hdop=math.inf)).decode()
    assert ",99.99," in text.split("\r\n")[2]


def test_four_hz_epochs_carry_their_hundredths_and_decode_in_order() -> None:
    f = NmeaFormatter(rate_hz=4.0)
    epochs = [_epoch(0.25 * k, speed=1.0, course=90.0) for k in range(8)]
    text = b"".join(f.format_epochs(epochs))
    assert b"$GPRMC,120000.25,A," in text and b"$GPRMC,120001.75,A," in text
    dec = GpsDecoder(emit_sentences=False)
    fixes = [r for r in dec.feed(text, 0.0) + dec.flush() if isinstance(r, GpsFix)]
    assert [fx.utc for fx in fixes] == [ep.utc for ep in epochs]


def test_format_batch_equals_per_epoch_formatting_on_the_real_model() -> None:
    from sim_backend.buildings import Walls, building
    from sim_backend.gnss import GnssBatch, GnssModel
    from sim_backend.sky import SatelliteSet, read_yuma
    from sim_backend.world import DEFAULT_ALMANAC

    start = datetime(2020, 1, 1, 12, tzinfo=UTC)
    sky = SatelliteSet.from_almanac(read_yuma(DEFAULT_ALMANAC, reference=start))
    model = GnssModel(
        sky, 51.75, -1.25, 60.0, start, walls=Walls(building(-10, 3, 10, 13, 12.0)),
        rng=np.random.default_rng(4),
    )  # fmt: skip
    n = 120
    t = np.arange(n, dtype=float)
    batch = model.batch(t, np.full(n, 51.75), np.full(n, -1.25), np.full(n, 60.0), np.zeros((n, 3)))
    assert NmeaFormatter().format_batch(batch) == NmeaFormatter().format_epochs(batch.epochs())
    # A crafted batch: more than 16 satellites in view, no fix, satellites without signal.
    s, e = 20, 3
    rng = np.random.default_rng(1)
    crafted = GnssBatch(
        t_s=np.arange(e, dtype=float), start_utc=start, valid=np.array([True, False, True]),
        lat_deg=np.full(e, 51.75), lon_deg=np.full(e, -1.25), alt_m=np.full(e, 60.0),
        speed_mps=np.full(e, 1.0), course_deg=np.array([10.0, np.nan, np.nan]),
        hdop=np.full(e, 1.1), pdop=np.full(e, 1.9), vdop=np.full(e, 1.5),
        n_used=np.full(e, 12), prns=np.arange(s, 0, -1),
        az_deg=rng.uniform(0, 360, (e, s)), el_deg=rng.uniform(0, 90, (e, s)),
        snr_dbhz=np.where(rng.random((e, s)) < 0.3, np.nan, rng.uniform(20, 45, (e, s))),
        in_view=np.array([[True] * s, [True] * 5 + [False] * 15, [False] * s]),
        used=rng.random((e, s)) < 0.6, err_enu_m=np.zeros((e, 3)), sigma_uere_m=np.ones(e),
    )  # fmt: skip
    out = NmeaFormatter().format_batch(crafted)
    assert out == NmeaFormatter().format_epochs(crafted.epochs())
    assert out[0].count(b"$GPGSV") == 4 and b"$GPGSV,1,1,00*79" in out[2]


def test_bulk_dop_text_is_the_receivers() -> None:
    """The batch formatter's DOP texts against the per-value rule (cap, NaN, infinities,
    negative zero, rounding edges)."""
    from sim_backend.nmea_out import _dop, dop_texts

    edges = [math.nan, math.inf, -math.inf, -0.0, 0.0, -1.0, 0.005, 0.015, 99.99, 99.990001, 1e-300]
    values = edges + np.random.default_rng(0).uniform(-5.0, 120.0, 5000).tolist()
    assert dop_texts(values) == [_dop(v) for v in values]


@pytest.mark.parametrize("minute_decimals", [4, 5, 6, 7])
def test_batch_text_on_odd_values_equals_per_epoch_formatting(minute_decimals: int) -> None:
    """The batch's text is built by numpy column by column; against the per-epoch path on
    what a robot standing in the open never prints: altitudes below the sea and far above,
    fast speeds, courses about any turn, DOPs on rounding edges and capped, both hemispheres,
    epochs without a fix before the receiver has time, and consecutive batches."""
    from dataclasses import replace

    from sim_backend.gnss import GnssModel
    from sim_backend.sky import SatelliteSet, read_yuma
    from sim_backend.world import DEFAULT_ALMANAC

    start = datetime(2020, 12, 31, 23, 59, 0, tzinfo=UTC)  # the date changes at epoch 60
    sky = SatelliteSet.from_almanac(read_yuma(DEFAULT_ALMANAC, reference=start))
    model = GnssModel(sky, 51.75, -1.25, 60.0, start, rng=np.random.default_rng(2))
    n = 200
    batch = model.batch(
        np.arange(n, dtype=float), np.full(n, 51.75), np.full(n, -1.25), np.full(n, 60.0),
        np.zeros((n, 3)),
    )  # fmt: skip
    rng = np.random.default_rng(minute_decimals)
    edges = [math.nan, math.inf, -0.0, 0.0, 0.005, 0.015, 99.99, 99.990001, 1e-300, 1.125, 2.675]
    odd = replace(
        batch,
        alt_m=np.where(rng.random(n) < 0.5, -rng.uniform(0, 2000, n), rng.uniform(0, 1e5, n)),
        speed_mps=np.where(rng.random(n) < 0.5, rng.uniform(0, 500, n), rng.uniform(0, 5, n)),
        course_deg=np.where(rng.random(n) < 0.3, np.nan, rng.uniform(-720, 720, n)),
        hdop=rng.choice(edges, n),
        pdop=np.round(rng.uniform(0, 120, n), 3),
        vdop=rng.uniform(-5, 120, n),
        valid=np.where(np.arange(n) < 10, False, batch.valid),
        snr_dbhz=np.where(np.arange(n)[:, None] < 5, np.nan, batch.snr_dbhz),
        lat_deg=np.where(rng.random(n) < 0.5, -batch.lat_deg, batch.lat_deg),
        lon_deg=np.where(rng.random(n) < 0.5, -batch.lon_deg - 100, batch.lon_deg),
    )
    cells = NmeaFormatter(minute_decimals=minute_decimals)
    one = NmeaFormatter(minute_decimals=minute_decimals)
    got = [cells.format_batch(_rows(odd, s)) for s in (slice(0, 70), slice(70, n))]
    assert got[0] + got[1] == one.format_epochs(odd.epochs())
    assert got[0][0].startswith(b"$GPRMC,,V,")  # no time yet


def _rows(batch: Any, rows: slice) -> Any:
    """``batch`` (a GnssBatch) cut to ``rows`` of epochs."""
    from dataclasses import replace

    skip = {"start_utc", "prns", "geoid_sep_m"}
    cut = {
        k: v[rows] for k, v in vars(batch).items() if k not in skip and isinstance(v, np.ndarray)
    }
    return replace(batch, **cut)


def _steady_batch(start: datetime, t_s: np.ndarray) -> Any:
    """A crafted ``GnssBatch``: a fix at every epoch ``t_s`` (s after ``start``), 6 satellites."""
    from sim_backend.gnss import GnssBatch

    e, s = t_s.shape[0], 6
    return GnssBatch(
        t_s=t_s, start_utc=start, valid=np.ones(e, dtype=bool),
        lat_deg=np.full(e, 51.75), lon_deg=np.full(e, -1.25), alt_m=np.full(e, 60.0),
        speed_mps=np.zeros(e), course_deg=np.full(e, np.nan),
        hdop=np.full(e, 1.1), pdop=np.full(e, 1.9), vdop=np.full(e, 1.5),
        n_used=np.full(e, s), prns=np.arange(1, s + 1),
        az_deg=np.full((e, s), 90.0), el_deg=np.full((e, s), 45.0), snr_dbhz=np.full((e, s), 40.0),
        in_view=np.ones((e, s), dtype=bool), used=np.ones((e, s), dtype=bool),
        err_enu_m=np.zeros((e, 3)), sigma_uere_m=np.ones(e),
    )  # fmt: skip


@pytest.mark.parametrize(
    "start,time_decimals,rate_hz",
    [
        ("2020-01-01T23:59:58.997", 2, 1.0),  # midnight
        ("2020-01-01T23:59:58.9996", 3, 1.0),
        ("2020-12-31T23:59:58.995", 2, 1.0),  # year end (a half rounds up)
        ("2020-12-31T23:59:59.4996", 3, 4.0),
        # the GPS week-number rollover (week 2047 -> 2048 at 23:59:42 UTC), then midnight
        ("2019-04-06T23:59:41.997", 2, 1.0),
        ("2019-04-06T23:59:41.9996", 3, 2.0),
    ],
)
def test_a_time_rounded_up_to_midnight_carries_into_the_date(
    start: str, time_decimals: int, rate_hz: float
) -> None:
    """RMC's time and date are those of the rounded time: an epoch a few ms before midnight
    prints the next day's 000000.00 and date (it printed the old date, a 24 h step back), in
    the per-epoch and the batch paths, and the decoder sees time only move forward."""
    t0 = datetime.fromisoformat(start).replace(tzinfo=UTC)
    t_s = np.arange(0.0, 20.0, 1.0 / rate_hz)
    batch = _steady_batch(t0, t_s)
    unit = timedelta(microseconds=10 ** (6 - time_decimals))
    expected = []
    for t in t_s.tolist():
        exact = t0 + timedelta(seconds=t)
        # round half up to the printed unit (utc - epoch in whole microseconds)
        us = (exact - datetime(1970, 1, 1, tzinfo=UTC)) // timedelta(microseconds=1)
        q = unit // timedelta(microseconds=1)
        expected.append(
            datetime(1970, 1, 1, tzinfo=UTC) + timedelta(microseconds=(us + q // 2) // q * q)
        )
    assert any(
        e.date() != (t0 + timedelta(seconds=float(t))).date()
        for e, t in zip(expected, t_s, strict=True)
    )
    for bursts in (
        NmeaFormatter(time_decimals=time_decimals, rate_hz=rate_hz).format_batch(batch),
        NmeaFormatter(time_decimals=time_decimals, rate_hz=rate_hz).format_epochs(batch.epochs()),
    ):
        printed = []
        for burst in bursts:
            rmc = burst.decode().split("\r\n")[0].split(",")
            printed.append(
                datetime.strptime(rmc[9] + rmc[1], "%d%m%y%H%M%S.%f").replace(tzinfo=UTC)
            )
        assert printed == expected
        dec = GpsDecoder(emit_sentences=False)
        fixes = [r for r in dec.feed(b"".join(bursts), 0.0) + dec.flush() if isinstance(r, GpsFix)]
        assert [fx.utc for fx in fixes] == expected


def test_gsa_lists_the_models_used_satellites_in_ascending_prn_order() -> None:
    """What the docstrings say: the model has no tracking channels, so GSA's used satellites
    come in ascending PRN order (a real NEO-5 prints its channel order), in both paths."""
    from sim_backend.gnss import GnssModel
    from sim_backend.sky import SatelliteSet, read_yuma
    from sim_backend.world import DEFAULT_ALMANAC

    start = datetime(2020, 1, 1, 12, tzinfo=UTC)
    sky = SatelliteSet.from_almanac(read_yuma(DEFAULT_ALMANAC, reference=start))
    model = GnssModel(sky, 51.75, -1.25, 60.0, start, rng=np.random.default_rng(5))
    n = 30
    batch = model.batch(
        np.arange(n, dtype=float), np.full(n, 51.75), np.full(n, -1.25), np.full(n, 60.0),
        np.zeros((n, 3)),
    )  # fmt: skip
    for bursts in (
        NmeaFormatter().format_batch(batch),
        NmeaFormatter().format_epochs(batch.epochs()),
    ):
        for burst in bursts:
            gsa = next(ln for ln in burst.decode().split("\r\n") if ln.startswith("$GPGSA"))
            prns = [int(p) for p in gsa.split(",")[3:15] if p]
            assert len(prns) >= 4 and prns == sorted(prns)
