"""The NMEA sentence table (drivers.nmea) that the decoder and the simulator's writer share."""

from __future__ import annotations

import functools
import operator
import subprocess
import sys
from datetime import date
from pathlib import Path

import pynmea2
import pytest

from drivers.nmea import (
    GGA,
    GLL,
    GSA,
    GSV,
    RMC,
    SENTENCES,
    STANDARD_MAX_CHARS,
    TRAILERS,
    VTG,
    ZDA,
    Field,
    FieldError,
    Sentence,
    checksum,
    field_parser,
    sentence,
    with_checksum,
)

NEO5_LOG = Path(__file__).resolve().parent / "data" / "nmea_out" / "ublox-lea-5h.log"


def _xor(data: bytes) -> int:
    return functools.reduce(operator.xor, data, 0)


# pynmea2's own field names, an independent account of where each field sits.
_PYNMEA2_NAMES = {
    "GGA": {"time": "timestamp", "lat": "lat", "lat_hemi": "lat_dir", "lon": "lon",
            "lon_hemi": "lon_dir", "quality": "gps_qual", "sats_used": "num_sats",
            "hdop": "horizontal_dil", "alt": "altitude", "alt_unit": "altitude_units",
            "geoid_sep": "geo_sep", "geoid_sep_unit": "geo_sep_units",
            "dgps_age": "age_gps_data", "dgps_station": "ref_station_id"},
    "RMC": {"time": "timestamp", "status": "status", "lat": "lat", "lon": "lon",
            "speed": "spd_over_grnd", "course": "true_course", "date": "datestamp",
            "mag_var": "mag_variation", "mode": "mode_indicator", "nav_status": "nav_status"},
    "GSA": {"op_mode": "mode", "fix_type": "mode_fix_type", "prn": "sv_id01", "pdop": "pdop",
            "hdop": "hdop", "vdop": "vdop"},
    "GSV": {"messages": "num_messages", "message": "msg_num", "in_view": "num_sv_in_view",
            "prn": "sv_prn_num_1", "elevation": "elevation_deg_1", "azimuth": "azimuth_1",
            "snr": "snr_1"},
    "GLL": {"lat": "lat", "lon": "lon", "time": "timestamp", "status": "status",
            "mode": "faa_mode"},
    "VTG": {"course": "true_track", "course_mag": "mag_track", "speed_kn": "spd_over_grnd_kts",
            "speed_kmh": "spd_over_grnd_kmph", "mode": "faa_mode"},
    "ZDA": {"time": "timestamp", "day": "day", "month": "month", "year": "year",
            "zone_hours": "local_zone", "zone_minutes": "local_zone_minutes"},
}  # fmt: skip


@pytest.mark.parametrize("kind", sorted(_PYNMEA2_NAMES))
def test_field_positions_agree_with_pynmea2(kind: str) -> None:
    cls = pynmea2.TalkerSentence.sentence_types[kind]
    table = SENTENCES[kind]
    for ours, theirs in _PYNMEA2_NAMES[kind].items():
        assert table.pos(ours) == cls.name_to_idx[theirs], (kind, ours)


def test_pynmea2_knows_every_type_of_the_table() -> None:
    # The decoder asks pynmea2 only about other types; its counters rely on this.
    assert set(SENTENCES) <= set(pynmea2.TalkerSentence.sentence_types)


def test_decoding_a_neo5_stream_loads_neither_pynmea2_nor_numpy() -> None:
    # Start-up time of `x6wd decode`: pynmea2 only for sentences outside the table, numpy
    # only for the core's array wraps.
    code = (
        "import sys, pathlib; from x6wd.app.decode import report_lines;"
        "from drivers.gps_nmea import GpsDecoder; d = GpsDecoder();"
        f"out = list(report_lines(d.feed(pathlib.Path({str(NEO5_LOG)!r}).read_bytes(), 0.0)));"
        "assert out and d.counters.unknown_types == 0;"
        "print(sorted(m for m in ('pynmea2', 'numpy') if m in sys.modules))"
    )
    got = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert got.stdout.strip() == "[]"


def test_fix_layouts_match_a_real_neo5_burst() -> None:
    # Every field of the table, in a real u-blox 5 capture: as many fields as the table has.
    widths = {s.type: sum(f.count for f in s.fields) for s in SENTENCES.values()}
    seen = set()
    for line in NEO5_LOG.read_text(errors="replace").splitlines():
        if not line.startswith("$GP") or "*" not in line:
            continue
        kind = line[3:6]
        n = line[7 : line.index("*")].count(",") + 1
        if kind == "GSV":
            assert (n - widths["GSV"]) % len(GSV.group) == 0 and n <= GSV.pos("signal_id")
        elif kind in widths:
            assert n == widths[kind], line
        seen.add(kind)
    assert {"RMC", "VTG", "GGA", "GSA", "GSV", "GLL"} <= seen


def test_templates_write_the_receivers_no_fix_forms() -> None:
    # REFERENCE.md §4, byte for byte.
    rmc = RMC.template("GP", "time", "status", "date", "mode", units=False)
    gga = GGA.template("GP", "time", "quality", "sats_used", "hdop", units=False)
    gsa = GSA.template("GP", "op_mode", "fix_type", "pdop", "hdop", "vdop", units=False)
    assert sentence(rmc % ("", "V", "", "N")) == b"$GPRMC,,V,,,,,,,,,,N*53\r\n"
    # The same with the writer's constants bound in.
    bound = RMC.template("GP", "time", "date", status="V", mode="N", units=False)
    assert bound == "GPRMC,%s,V,,,,,,,%s,,,N" and bound % ("", "") == rmc % ("", "V", "", "N")
    assert sentence(gga % ("", 0, "00", "99.99")) == b"$GPGGA,,,,,,0,00,99.99,,,,,,*48\r\n"
    assert (
        sentence(gsa % ("A", 1, "99.99", "99.99", "99.99"))
        == b"$GPGSA,A,1,,,,,,,,,,,,,99.99,99.99,99.99*30\r\n"
    )


def test_templates_keep_unit_letters_and_unnamed_fields() -> None:
    vtg = VTG.template("GN", "course", "speed_kn", "speed_kmh", "mode")
    assert vtg == "GNVTG,%s,T,,M,%s,N,%s,K,%s"
    assert VTG.template("GN", "mode", units=False) == "GNVTG,,,,,,,,,%s"
    gga = GGA.template("GP", *(n for n in GGA.names if n not in ("alt_unit", "geoid_sep_unit")))
    assert gga.count(",") == len(GGA.fields) and ",M," in gga
    # A counted field takes its fields already joined; left out, it is that many empties.
    assert GSA.template("GP", "prn") == "GPGSA,,,%s,,,"
    assert GSA.template("GP", "pdop") == "GPGSA,,," + "," * 11 + ",%s,,"
    assert GSV.template("GP", "messages", "message", "in_view") == "GPGSV,%s,%s,%s"


def test_template_names_are_checked() -> None:
    with pytest.raises(KeyError, match="no field 'altitude'"):
        GGA.template("GP", "altitude")
    with pytest.raises(ValueError, match="out of order"):
        GGA.template("GP", "lat", "time")
    with pytest.raises(ValueError, match="twice"):
        GGA.template("GP", "time", "time")
    with pytest.raises(ValueError, match="twice"):
        GGA.template("GP", "time", time="123519")
    with pytest.raises(KeyError, match="no field 'state'"):
        RMC.template("GP", state="A")
    with pytest.raises(KeyError):  # group fields are appended by the writer
        GSV.template("GP", "prn")
    odd = Sentence("X%Y", "odd", (Field("a", "int", "x", fixed="%"), Field("b", "text", "c--c")))
    assert odd.template("GP", b="5%") % () == "GPX%Y,%,5%"


def test_positions_count_repeated_fields_and_groups() -> None:
    assert (GSA.pos("prn"), GSA.pos("pdop"), GSA.pos("system_id")) == (2, 14, 17)
    assert (GSV.pos("prn"), GSV.pos("snr"), GSV.pos("signal_id")) == (3, 6, 19)
    assert RMC.pos("nav_status") == 12 and GLL.pos("time") == 4 and ZDA.pos("year") == 3
    with pytest.raises(ValueError, match="twice"):
        Sentence("XXX", "bad", (Field("a", "int", "x"), Field("a", "int", "x")))


@pytest.mark.parametrize(
    ("sentence_", "name", "good", "bad"),
    [
        (GGA, "hdop", [("", None), ("0.9", 0.9), ("99.99", 99.99)], ["100", "1e1", "-1", "x"]),
        (GGA, "quality", [("", None), ("0", 0), ("8", 8)], ["9", "-1", "1.0", " 1"]),
        (GGA, "alt", [("-1500", -1500.0), ("545.4", 545.4)], ["-1500.1", "1_0", "nan"]),
        (RMC, "status", [("A", "A"), ("V", "V"), ("", "")], ["X", "a", "AV"]),
        (
            RMC,
            "date",
            [("230394", date(1994, 3, 23)), ("010179", date(2079, 1, 1))],
            ["320394", "23039"],
        ),
        (RMC, "time", [("123519", 45319000000), ("235960.5", 86400500000)], ["240000", "1235"]),
        (GSV, "elevation", [("-90", -90.0), ("45.5", 45.5)], ["91", "-91"]),
        (ZDA, "year", [("1980", 1980), ("2200", 2200)], ["1979", "2201", "20x6"]),
    ],
)
def test_field_parsers_check_format_and_range(
    sentence_: Sentence, name: str, good: list[tuple[str, object]], bad: list[str]
) -> None:
    parse = field_parser(sentence_.field(name))
    for text, value in good:
        assert parse(text) == value
    for text in bad:
        with pytest.raises(FieldError):
            parse(text)


def test_coordinate_parsers_take_the_hemisphere_field() -> None:
    lat = field_parser(GGA.field("lat"))
    lon = field_parser(GGA.field("lon"))
    assert lat("4807.038", "N") == pytest.approx(48 + 7.038 / 60)
    assert lat("4807.038", "S") == pytest.approx(-(48 + 7.038 / 60))
    assert lon("01131.000", "W") == pytest.approx(-(11 + 31 / 60))
    assert lat("", "") is None and lon("", "E") is None
    for args in [("4807.038", "E"), ("9100.000", "N"), ("4860.000", "N"), ("48", "N")]:
        with pytest.raises(FieldError):
            lat(*args)
    with pytest.raises(FieldError):
        lon("18000.001", "E")


def test_every_ranged_field_has_a_parser() -> None:
    for s in SENTENCES.values():
        for f in (*s.fields, *s.group, *s.extra):
            if f.type in ("time", "date", "lat", "lon") or f.lo is not None or f.letters:
                field_parser(f)
    with pytest.raises(ValueError, match="no range"):
        field_parser(GGA.field("dgps_age"))


def test_one_checksum_for_both_directions() -> None:
    for n in (0, 1, 81, 128, 129, 200, 1000):
        data = bytes((i * 37 + 11) % 256 for i in range(n))
        assert checksum(data) == _xor(data)
    assert with_checksum("GPTXT,é") == f"$GPTXT,é*{_xor(b'GPTXT,?'):02X}"  # non-ASCII: '?'
    assert with_checksum("GPGGA,,,,,,0,00,99.99,,,,,,") == "$GPGGA,,,,,,0,00,99.99,,,,,,*48"
    assert TRAILERS[0x3B] == b"*3B\r\n" and len(TRAILERS) == 256
    with pytest.raises(UnicodeEncodeError):
        sentence("GPTXT,é")
    assert STANDARD_MAX_CHARS == 82
