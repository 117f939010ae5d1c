"""Constellation filter: a faithful port of the seed's C++ TConstellation, two forms."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from x6wd.core.errors import X6wdError
from x6wd.nav.constellation import (
    Constellation,
    ConstellationError,
    EmptyFilterError,
    filter_series,
)

DATA = Path(__file__).resolve().parent / "data" / "constellation"
NMEA_STEP_DEG = 1e-5 / 60  # one unit of the last NMEA digit (1e-5 minute)


class RefConstellation:
    """Line-by-line Python port of the C++ (Add, Filter, Average), as the oracle.

    ``intended=True`` lets the counter run past N, which brings the C++ hysteresis branch
    to life (the behaviour the library offers as ``hysteresis=True``). ``strict=True`` swaps
    the C++ ``>=`` for ``>`` (first minimum) to show that the tests can tell them apart.
    """

    def __init__(self, n: int, intended: bool = False, strict: bool = False) -> None:
        self.n = n
        self.buf = [0.0] * n
        self.counter = 0
        self.mean = 0.0
        self.intended = intended
        self.strict = strict

    def add(self, s: float) -> None:
        if self.counter < self.n:
            self.buf[self.counter] = s
            self.counter += 1
        else:
            for i in range(self.n - 1):
                self.buf[i] = self.buf[i + 1]
            self.buf[self.n - 1] = s
            if self.intended:
                self.counter += 1

    def filter(self) -> float:
        count = min(self.counter, self.n)
        buf = self.buf
        if count > 2:
            ed = []
            for h in range(count):
                for k in range(count):
                    if h != k:
                        ed.append((math.fabs(buf[h] - buf[k]), h, k))
            min_ed = 0
            for m in range(1, len(ed)):
                if self.strict:
                    if ed[min_ed][0] > ed[m][0]:
                        min_ed = m
                elif ed[min_ed][0] >= ed[m][0]:
                    min_ed = m
            p1, p2 = ed[min_ed][1], ed[min_ed][2]
            if self.counter <= self.n:  # noqa: SIM114 (kept in the C++ shape)
                self.mean = (buf[p1] + buf[p2]) / 2
            elif math.fabs(self.mean - ((buf[p1] + buf[p2]) / 2)) >= math.fabs(buf[p1] - buf[p2]):
                self.mean = (buf[p1] + buf[p2]) / 2
        elif count > 1:
            self.mean = (buf[0] + buf[1]) / 2
        elif count > 0:
            self.mean = buf[0]
        else:
            self.mean = -1
        return self.mean

    def average(self) -> float:
        count = min(self.counter, self.n)
        a = 0.0
        for i in range(count):
            a = a + self.buf[i]
        return a / count


def bits(values: list[float] | np.ndarray) -> list[int]:
    """Exact bit patterns, so -0.0 != 0.0 and any last-bit difference shows."""
    return [struct.unpack("<q", struct.pack("<d", float(v)))[0] for v in values]


def run_reference(values: list[float], n: int, **kw: bool) -> list[float]:
    ref = RefConstellation(n, **kw)
    out = []
    for v in values:
        ref.add(v)
        out.append(ref.filter())
    return out


def run_stream(values: list[float], n: int, hysteresis: bool = False) -> list[float]:
    f = Constellation(n, hysteresis=hysteresis)
    out = []
    for v in values:
        f.add(v)
        out.append(f.filter())
    return out


def nmea_positions(path: Path) -> tuple[list[float], list[float]]:
    """(lat_deg, lon_deg) of every checksum-valid GGA with a fix, parsed by hand."""
    lats, lons = [], []
    for raw in path.read_bytes().splitlines():
        line = raw.decode("ascii", "replace").strip()
        if not line.startswith("$") or "*" not in line:
            continue
        body, _, cs = line[1:].partition("*")
        x = 0
        for ch in body.encode("ascii", "replace"):
            x ^= ch
        if cs[:2].upper() != f"{x:02X}":
            continue
        f = body.split(",")
        if not f[0].endswith("GGA") or len(f) < 7 or not f[2] or f[6] in ("", "0"):
            continue
        lat = int(f[2][:2]) + float(f[2][2:]) / 60
        lon = int(f[4][:3]) + float(f[4][3:]) / 60
        lats.append(-lat if f[3] == "S" else lat)
        lons.append(-lon if f[5] == "W" else lon)
    return lats, lons


# Strategies: general floats (wide magnitudes, signs, signed zeros) and heavily tied NMEA-like
# latitudes on the 1e-5-minute lattice around 51.7 deg with a handful of distinct values.
wide_floats = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e12, max_value=1e12)
general_series = st.lists(
    st.one_of(
        wide_floats,
        st.sampled_from([0.0, -0.0, 1.0, -1.0, 5e-324, -5e-324, 1.7e308, -1.7e308, 1e308]),
    ),
    min_size=0,
    max_size=60,
)
lattice_series = st.lists(st.integers(-4, 4), min_size=0, max_size=80).map(
    lambda ks: [51.7 + k * NMEA_STEP_DEG for k in ks]
)
windows = st.integers(3, 12)


@settings(max_examples=300, deadline=None)
@given(values=general_series, n=windows)
def test_streaming_matches_cpp_reference_bit_for_bit(values: list[float], n: int) -> None:
    assert bits(run_stream(values, n)) == bits(run_reference(values, n))


@settings(max_examples=300, deadline=None)
@given(values=lattice_series, n=st.integers(3, 25))
def test_quantised_ties_match_cpp_reference(values: list[float], n: int) -> None:
    assert bits(run_stream(values, n)) == bits(run_reference(values, n))


@settings(max_examples=200, deadline=None)
@given(values=st.one_of(general_series, lattice_series), n=windows, hyst=st.booleans())
def test_series_is_bit_identical_to_streaming(values: list[float], n: int, hyst: bool) -> None:
    series = filter_series(values, n=n, hysteresis=hyst)
    assert series.dtype == np.float64 and series.shape == (len(values),)
    assert bits(series) == bits(run_stream(values, n, hysteresis=hyst))


@settings(max_examples=200, deadline=None)
@given(values=st.one_of(general_series, lattice_series), n=windows)
def test_hysteresis_matches_the_live_cpp_branch(values: list[float], n: int) -> None:
    assert bits(run_stream(values, n, hysteresis=True)) == bits(
        run_reference(values, n, intended=True)
    )


def test_last_minimum_wins_among_tied_pairs() -> None:
    # |0-1| == |3-4| == 1: the C++ '>=' scan ends on the later pair (h=3, k=2) -> 3.5;
    # a first-minimum '>' scan would stop at (0, 1) -> 0.5.
    values = [0.0, 1.0, 3.0, 4.0]
    assert run_stream(values, 20)[-1] == 3.5
    assert run_reference(values, 20, strict=True)[-1] == 0.5
    # Same h, two tied k: [1, 3, 2] has |1-2| == |3-2| == 1; the last pair in h-major order is
    # (h=2, k=1) -> (2 + 3) / 2, not (h=2, k=0) -> 1.5.
    assert run_stream([1.0, 3.0, 2.0], 20)[-1] == 2.5
    assert filter_series([1.0, 3.0, 2.0])[-1] == 2.5


def test_first_minimum_tie_break_is_detected_on_quantised_data() -> None:
    rng = np.random.default_rng(7)
    values = [51.7 + int(k) * NMEA_STEP_DEG for k in rng.integers(-3, 4, size=200)]
    faithful = run_reference(values, 20)
    first_min = run_reference(values, 20, strict=True)
    assert faithful != first_min  # the data really exercises the tie-break
    assert bits(run_stream(values, 20)) == bits(faithful)
    assert bits(filter_series(values, 20)) == bits(faithful)


def test_small_buffers_follow_the_cpp() -> None:
    f = Constellation(5)
    f.add(10.0)
    assert f.filter() == 10.0
    f.add(11.0)
    assert f.filter() == 10.5
    f.add(20.0)
    assert f.filter() == 10.5  # closest pair (11, 10)
    assert len(f) == 3 and f.max_index() == 2


def test_window_slides_and_accessors() -> None:
    f = Constellation(3)
    for v in (1.0, 2.0, 4.0, 8.0):
        f.add(v)
    assert len(f) == 3
    assert [f.buffer(i) for i in range(f.max_index() + 1)] == [2.0, 4.0, 8.0]
    assert f.average() == (2.0 + 4.0 + 8.0) / 3
    assert f.filter() == 3.0
    with pytest.raises(IndexError):
        f.buffer(3)
    with pytest.raises(IndexError):
        f.buffer(-1)
    f.clear()
    assert len(f) == 0 and f.max_index() == -1


def test_average_sums_in_cpp_order() -> None:
    rng = np.random.default_rng(3)
    values = list(51.7 + rng.normal(0, 1e-4, 50))
    f = Constellation(20)
    ref = RefConstellation(20)
    for v in values:
        f.add(v)
        ref.add(v)
        assert bits([f.average()]) == bits([ref.average()])


def test_empty_filter_is_an_error_not_a_sentinel() -> None:
    f = Constellation()
    with pytest.raises(EmptyFilterError):
        f.filter()
    with pytest.raises(EmptyFilterError):
        f.average()
    assert issubclass(EmptyFilterError, X6wdError)
    assert filter_series([]).shape == (0,)


@pytest.mark.parametrize("n", [2, 0, -5, 2.5, True, "20"])
def test_window_must_be_an_integer_of_at_least_three(n: object) -> None:
    with pytest.raises(ConstellationError, match="window n"):
        Constellation(n)  # type: ignore[arg-type]
    with pytest.raises(ConstellationError, match="window n"):
        filter_series([1.0, 2.0], n=n)  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_samples_are_rejected(bad: float) -> None:
    f = Constellation()
    f.add(1.0)
    with pytest.raises(ConstellationError, match="finite"):
        f.add(bad)
    assert len(f) == 1  # unchanged
    with pytest.raises(ConstellationError, match="sample 1"):
        filter_series([1.0, bad, 2.0])


def test_series_rejects_other_shapes() -> None:
    with pytest.raises(ConstellationError, match="one-dimensional"):
        filter_series(np.zeros((3, 3)))


def test_hysteresis_keeps_the_previous_value_inside_the_pair_spread() -> None:
    # n = 3: [0, 10, 12] -> pair (10, 12) -> 11. Slide in 12.5: window [10, 12, 12.5], pair
    # (12.5, 12) -> 12.25; |11 - 12.25| = 1.25 >= 0.5, so the output moves. Slide in 12.25:
    # window [12, 12.5, 12.25], tied pairs -> last one (12.25, 12.5) -> 12.375, but
    # |12.25 - 12.375| = 0.125 < 0.25 (the pair spread), so hysteresis keeps 12.25.
    values = [0.0, 10.0, 12.0, 12.5, 12.25]
    plain = run_stream(values, 3)
    hyst = run_stream(values, 3, hysteresis=True)
    assert plain[:4] == hyst[:4] == [0.0, 5.0, 11.0, 12.25]
    assert plain[4] == 12.375
    assert hyst[4] == 12.25
    assert list(filter_series(values, 3, hysteresis=True)) == hyst


def test_long_series_spans_several_chunks() -> None:
    rng = np.random.default_rng(11)
    values = 51.7 + np.round(rng.normal(0, 3e-5, 30_000) / NMEA_STEP_DEG) * NMEA_STEP_DEG
    assert bits(filter_series(values, 20)) == bits(run_stream(list(values), 20))


@pytest.mark.parametrize("name", ["ublox-lea-5h.log", "ublox-8.log"])
def test_real_nmea_positions(name: str) -> None:
    lats, lons = nmea_positions(DATA / name)
    assert len(lats) >= 15
    for axis in (lats, lons):
        for n in (3, 5, 20):
            expected = run_reference(axis, n)
            assert bits(run_stream(axis, n)) == bits(expected)
            assert bits(filter_series(axis, n)) == bits(expected)
        # Every output is a midpoint of two held samples, so it stays within their range.
        out = filter_series(axis, 20)
        assert min(axis) <= out.min() and out.max() <= max(axis)
