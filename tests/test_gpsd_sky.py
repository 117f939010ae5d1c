"""Satellites and fix status as gpsd reports them, checked against gpsd's own output for real
logs (tests/data/nmea/chk, see tests/data/nmea/SOURCE.md), through both writers: the daemon's
gpsd port (``GpsDecoder`` records through ``tpv_obj``/``sky_obj``) and ``x6wd decode``.

- NMEA 4.10 GSVs end in a signal id: one field after the satellites' groups of four, never a
  satellite (it was read as PRN 0, 1, 7 ...).
- gpsd numbers satellites across systems (BeiDou 13 is PRN 413, Galileo 24 is 324, GLONASS
  65-96) and gives each its ``gnssid`` and ``svid``; a GSA's "used" marks its own system's
  satellites (a GN talker's GSA names its system in its last field).
- TPV ``status`` (2 DGPS, 3 RTK fixed, ...) from the GGA quality.
"""

from __future__ import annotations

import collections
import io
import json
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from drivers.gps_nmea import GpsDecoder, fix_status
from drivers.nmea import checksum
from x6wd.app import decode
from x6wd.app.gpsd import geometry_dops, sky_obj, tpv_obj
from x6wd.core.records import GpsFix, GpsSky, SatInfo

NMEA_DIR = Path(__file__).resolve().parent / "data" / "nmea"
_SAT_KEYS = ("PRN", "gnssid", "svid", "used")


def _line(body: str) -> bytes:
    return f"${body}*{checksum(body.encode()):02X}\r\n".encode()


def _tod(sentence: str) -> str | None:
    """The time field of a time-bearing sentence (GGA, RMC, ZDA, GLL), else None."""
    f = sentence.split("*")[0].split(",")
    kind = f[0][3:]
    if kind in ("GGA", "RMC", "ZDA") and len(f) > 1:
        return f[1] or None
    if kind == "GLL" and len(f) > 5:
        return f[5] or None
    return None


def _sat_set(sky: dict) -> list[tuple]:
    return sorted(
        tuple(-1 if s.get(k) is None else s[k] for k in _SAT_KEYS) for s in sky["satellites"]
    )


def _per_epoch(name: str, of: Callable[[dict], Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``of`` the last SKY with satellites of each epoch (keyed by the last time field read),
    gpsd's and the port's. The .chk interleaves the log's sentences with gpsd's JSON (and
    gpsd's own NMEA output, which is not fed): both sides see the same sentences in the same
    order."""
    raw = (NMEA_DIR / name).read_bytes().decode("ascii", "replace")
    in_log = collections.Counter(re.findall(r"\$[^$\r\n]*", raw))
    dec = GpsDecoder(emit_sentences=False)
    epoch = None
    gpsd: dict[str, Any] = {}
    ours: dict[str, Any] = {}
    for line in (NMEA_DIR / "chk" / f"{name}.chk").read_text(errors="replace").splitlines():
        if line.startswith("$"):
            if in_log[line] <= 0:
                continue  # gpsd's own NMEA output
            in_log[line] -= 1
            epoch = _tod(line) or epoch
            for r in dec.feed_sentence(line, 0.0):
                if isinstance(r, GpsSky) and r.satellites:
                    ours[str(epoch)] = of(sky_obj(r))
        elif line.startswith('{"class":"SKY"') and '"satellites"' in line:
            gpsd[str(epoch)] = of(json.loads(line))
    return gpsd, ours


def _epoch_skies(name: str) -> tuple[dict[str, list], dict[str, list]]:
    """Each epoch's satellites (:func:`_sat_set`), gpsd's and the port's."""
    return _per_epoch(name, _sat_set)


# Epochs whose satellites gpsd took from elsewhere than the NMEA: the L76K's CASIC binary
# (GLONASS 77) and the end of the Teseo log, edge-case sentences after which gpsd drops the
# other systems' groups of the epoch (its reset on a GPS GSV of u-blox signal 0).
_NOT_FROM_NMEA = {
    "quectel-l76k-dual.log": {"071720.000", "071721.000"},
    "st-teseo-liv4f.log": {"135817.000"},
}


@pytest.mark.parametrize(
    "name",
    [
        "st-teseo-liv4f.log",  # GP/GA/BD, NMEA 4.10 signal ids, GN GSA with system ids
        "skytraq-dgps.log",  # GP and BD (201-237) GSV and GSA, SBAS, QZSS 193
        "quectel-l76k-dual.log",  # GP/BD/GL with signal ids, GN GSA with system ids
        "ublox-8.log",  # GP and GL GSV, GN GSA without system ids, SBAS
        "bundg_zeus_9.log",  # GLONASS 65-96 in GP GSVs
    ],
)
def test_sky_satellites_per_epoch_are_gpsds(name: str) -> None:
    gpsd, ours = _epoch_skies(name)
    assert gpsd and set(ours) == set(gpsd)
    differ = {e for e in gpsd if ours[e] != gpsd[e]}
    assert differ == _NOT_FROM_NMEA.get(name, set())


def test_ublox8_sky_is_gpsds_less_what_gpsd_read_from_ubx() -> None:
    # The log's UBX NAV messages give gpsd satellites its NMEA never lists; the rest agree.
    gpsd, ours = _epoch_skies("ublox8-uniqid-monhw.log")
    assert ours and set(ours) <= set(gpsd)
    for epoch, sats in ours.items():
        assert not collections.Counter(sats) - collections.Counter(gpsd[epoch]), epoch
        assert any(s[1] == 6 for s in sats)  # GLONASS, gnssid 6


def test_signal_id_is_no_satellite() -> None:
    body = "GPGSV,1,1,03,01,19,045,31,06,16,156,29,13,05,272,30,1"
    for text in (body, body[:-1] + "7"):
        dec = GpsDecoder(emit_sentences=False)
        dec.feed(_line("GPGSA,A,3,01,06,13,,,,,,,,,,1.5,1.0,1.1"), 0.0)
        (sky,) = [r for r in dec.feed(_line(text), 0.0) if isinstance(r, GpsSky)]
        assert [(s.prn, s.used) for s in sky.satellites] == [(1, True), (6, True), (13, True)]
    # The real L76K log (signal id 0 on every GSV): no phantom PRN 0, gpsd's nSat.
    out = io.StringIO()
    decode.decode_path(str(NMEA_DIR / "quectel-l76k-dual.log"), out)
    skies = [json.loads(x) for x in out.getvalue().splitlines() if '"class":"SKY"' in x]
    assert skies and all(s["PRN"] > 0 for sky in skies for s in sky["satellites"])
    assert max(sky["nSat"] for sky in skies) == 24  # gpsd's: 11 GPS, 4 BeiDou, 9 GLONASS


def test_gsa_marks_its_own_systems_satellites() -> None:
    dec = GpsDecoder(emit_sentences=False)
    for body in (
        "GNGSA,A,3,13,,,,,,,,,,,,1.3,0.8,1.1,4",  # NMEA 4.10: BeiDou 13 used
        "GPGSV,1,1,01,13,40,100,30",
        "GBGSV,1,1,02,13,41,062,19,24,10,100,25",
        "GAGSV,1,1,01,13,20,200,33",
    ):
        records = dec.feed(_line(body), 0.0)
    sky = [r for r in records if isinstance(r, GpsSky)][-1]
    got = [(s.prn, s.gnssid, s.svid, s.used) for s in sky.satellites]
    assert got == [
        (13, 0, 13, False),  # GPS 13 is another satellite
        (413, 3, 13, True),
        (424, 3, 24, False),
        (313, 2, 13, False),
    ]
    line = decode.ReportEncoder().sky(sky)
    assert '{"PRN":413,"gnssid":3,"svid":13,"used":true,"el":41.0,"az":62.0,"ss":19.0}' in line


# ------------------------------------------------------------------------- TPV status


def test_fix_status_of_each_gga_quality() -> None:
    # gpsd's processGGA: 0 no fix, 1 and 3 (PPS) a fix, 2 DGPS, 4 RTK fixed (3),
    # 5 RTK float (4), 6 dead reckoning (5), 7 manual (7, "time"), 8 simulated (8).
    assert [fix_status(q) for q in range(9)] == [0, 1, 2, 1, 3, 4, 5, 7, 8]
    fix = GpsFix(0.0, None, 1.0, 2.0, 3.0, 2, 8, 1.0, None, None, True, 3)
    assert tpv_obj(fix)["status"] == 2
    assert list(tpv_obj(fix))[:3] == ["class", "status", "mode"]  # gpsd's order
    assert "status" not in tpv_obj(GpsFix(0.0, None, 1.0, 2.0, None, 1, valid=True, mode=2))
    assert "status" not in tpv_obj(GpsFix(0.0, None, None, None, None, 2, valid=False))


@pytest.mark.parametrize("name", ["isync.log", "skytraq-dgps.log", "nmea-fuzzy-cases.log"])
def test_tpv_status_is_gpsds(name: str) -> None:
    chk = (NMEA_DIR / "chk" / f"{name}.chk").read_text(errors="replace").splitlines()
    theirs = [json.loads(x) for x in chk if x.startswith('{"class":"TPV"')]
    statuses: dict[str, set] = collections.defaultdict(set)
    for o in theirs:
        if "time" in o and o.get("mode", 0) >= 2:
            statuses[o["time"]].add(o.get("status"))
    dec = GpsDecoder(emit_sentences=False)
    data = (NMEA_DIR / name).read_bytes()
    fixes = [r for r in dec.feed(data, 0.0) + dec.flush() if isinstance(r, GpsFix)]
    port = [tpv_obj(f) for f in fixes]
    out = io.StringIO()
    decode.decode_path(str(NMEA_DIR / name), out, with_sky=False)
    command = [json.loads(x) for x in out.getvalue().splitlines()]
    assert command == [json.loads(json.dumps(o)) for o in port]
    checked = 0
    for o in port:
        if "lat" in o and o.get("time") in statuses:
            assert statuses[o["time"]] == {o.get("status")}, o["time"]
            checked += 1
    assert checked >= 4
    assert any("status" in o for o in port)


_DOP_KEYS = ("xdop", "ydop", "tdop", "gdop")


def _epoch_dops(name: str) -> tuple[dict[str, dict], dict[str, dict]]:
    """Each epoch's geometry DOPs, gpsd's and the port's."""
    return _per_epoch(name, lambda sky: {k: sky.get(k) for k in _DOP_KEYS})


# The first sky of these logs: gpsd took its DOPs from the satellites of the cycle's first
# GSV group(s) and kept them (it never overwrites a DOP within a cycle); the port's are the
# whole used set's. On logs with one GSV group per system (the L76K, SkyTraq, Teseo) gpsd's
# are that partial set's at every epoch, so they are not compared.
_PARTIAL_FIRST_SKY = {
    "bt451.log": {"143306.00"},
    "bundg_zeus_9.log": {"094926"},
    "ublox-8.log": {"000941.00"},
    "ublox8-uniqid-monhw.log": {"204221.00"},
}


@pytest.mark.parametrize(
    "name",
    ["ublox-lea-5h.log", "ublox-lea-4h.log", "isync.log", "nl402u.log", "nl551e.log",
     "triton400.log", "gp-320fw-2019-04-07-coldboot.log", *_PARTIAL_FIRST_SKY],
)  # fmt: skip
def test_sky_geometry_dops_are_gpsds(name: str) -> None:
    # xdop, ydop, tdop and gdop were missing: gpsd computes them from the used satellites'
    # azimuths and elevations, and cgps or a libgps program shows them
    gpsd, ours = _epoch_dops(name)
    compared = [e for e in gpsd if e in ours]  # none where gpsd had none (under 4 used)
    assert compared, name
    differ = set()
    for e in compared:
        for k in _DOP_KEYS:
            g, o = gpsd[e][k], ours[e][k]
            if (g is None) != (o is None) or (g is not None and abs(o - g) > 0.011):
                differ.add(e)
    assert differ == _PARTIAL_FIRST_SKY.get(name, set())


def _sat(prn: int, el_deg: float | None, az_deg: float | None, used: bool = True) -> SatInfo:
    return SatInfo(prn=prn, el_deg=el_deg, az_deg=az_deg, snr_dbhz=40.0, used=used)


def test_sky_keeps_the_receivers_dops_and_needs_four_usable_satellites() -> None:
    # one at the zenith, three on the horizon 120 deg apart: hdop 2 sqrt(2)/3 ... by hand
    sats = (_sat(1, 90.0, 0.0), _sat(2, 0.0, 0.0), _sat(3, 0.0, 120.0), _sat(4, 0.0, 240.0))
    dops = geometry_dops(sats)
    assert dops is not None
    assert dops["xdop"] == pytest.approx(dops["ydop"]) == pytest.approx(math.sqrt(2 / 3))
    assert dops["hdop"] ** 2 == pytest.approx(dops["xdop"] ** 2 + dops["ydop"] ** 2)
    assert dops["gdop"] ** 2 == pytest.approx(dops["pdop"] ** 2 + dops["tdop"] ** 2)
    given = sky_obj(GpsSky(t_s=0.0, satellites=sats, hdop=1.5, vdop=2.5, pdop=2.9))
    assert (given["hdop"], given["vdop"], given["pdop"]) == (1.5, 2.5, 2.9)  # as reported
    assert given["xdop"] == pytest.approx(0.82, abs=0.005)
    filled = sky_obj(GpsSky(t_s=0.0, satellites=sats))  # a receiver without a GSA
    assert filled["hdop"] == pytest.approx(dops["hdop"], abs=0.005)
    # fewer than 4 usable: no geometry DOPs (an unused one, no azimuth, an elevation of 95)
    for odd in (_sat(4, 0.0, 240.0, used=False), _sat(4, 0.0, None), _sat(4, 95.0, 240.0)):
        sky = sky_obj(GpsSky(t_s=0.0, satellites=(*sats[:3], odd)))
        assert not set(_DOP_KEYS) & set(sky), odd
    # all on one circle of elevation: no height from them, a singular geometry
    ring = tuple(_sat(k, 30.0, 90.0 * k) for k in range(1, 6))
    assert geometry_dops(ring) is None
