"""Atmosphere model: delays, mapping, attenuation, received power and SNR at L1."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim_backend.atmosphere import (
    CLOUD_TYPES,
    Atmosphere,
    cloud_specific_coefficient,
    marini,
    niell_hydrostatic_mapping,
    slant_path_m,
)
from x6wd.core.config import build
from x6wd.core.errors import ConfigError


def _sky_average(values: np.ndarray, el_deg: np.ndarray) -> float:
    # Satellites are spread uniformly over the sky: weight elevations by solid angle.
    w = np.cos(np.radians(el_deg))
    return float((values * w).sum() / w.sum())


def test_iono_formula_and_typical_average() -> None:
    atmo = Atmosphere(tec_tecu=17.0)
    el = np.array([5.0, 30.0, 90.0])
    expected = 0.162 * (1 + 2.74e-6 * (96 - el) ** 3) * 17.0
    np.testing.assert_allclose(atmo.iono_delay_m(el), expected, rtol=1e-12)
    grid = np.linspace(5.0, 90.0, 2000)
    avg = _sky_average(atmo.iono_delay_m(grid), grid)
    assert 3.0 < avg < 7.0  # the seed: "about 5 m on average"
    # Linear in TEC, largest at the horizon.
    d10 = Atmosphere(tec_tecu=10.0).iono_delay_m(grid)
    d20 = Atmosphere(tec_tecu=20.0).iono_delay_m(grid)
    np.testing.assert_allclose(d20, 2 * d10)
    assert np.all(np.diff(d10) < 0)


def test_zenith_hydrostatic_delay_and_height() -> None:
    atmo = Atmosphere()
    zhd0 = float(atmo.zenith_hydrostatic_delay_m(45.0, 0.0))
    assert 2.28 < zhd0 < 2.33
    zhd2k = float(atmo.zenith_hydrostatic_delay_m(45.0, 2000.0))
    # Pressure at 2 km is ~79 % of sea level.
    assert 0.76 < zhd2k / zhd0 < 0.82
    # At zenith the slant delay is the zenith delay (mapping exactly 1 at sea level).
    assert float(atmo.tropo_delay_m(90.0, 45.0, 100.0, 0.0)) == pytest.approx(zhd0, rel=1e-9)


def test_marini_normalised_at_zenith() -> None:
    for a, b, c in ((1.2e-3, 2.9e-3, 0.063), (2.53e-5, 5.49e-3, 1.14e-3)):
        assert float(marini(np.float64(1.0), a, b, c)) == pytest.approx(1.0, abs=1e-12)


def test_niell_mapping_values() -> None:
    el = np.array([5.0, 10.0, 30.0, 90.0])
    m = niell_hydrostatic_mapping(el, 45.0, 28.0, 0.0)
    assert m[-1] == pytest.approx(1.0, abs=1e-9)
    assert 9.5 < m[0] < 10.6  # ~10 at 5 degrees
    assert 5.4 < m[1] < 5.8
    assert m[2] == pytest.approx(1.0 / math.sin(math.radians(30.0)), rel=0.01)
    # Height correction: at altitude the mapping rises slightly at low elevation.
    m_high = niell_hydrostatic_mapping(5.0, 45.0, 28.0, 2000.0)
    assert m_high > m[0]
    # Low elevation delays reach ~10 m+ (the seed: up to about 10 m at low elevations).
    d5 = Atmosphere().tropo_delay_m(5.0, 45.0, 28.0, 0.0)
    assert 20.0 < float(d5) < 25.0
    assert float(Atmosphere().tropo_delay_m(15.0, 45.0, 28.0, 0.0)) > 8.0


def test_seasonal_term_opposite_in_the_south() -> None:
    el = 5.0
    north_winter = niell_hydrostatic_mapping(el, 45.0, 28.0, 0.0)  # day 28: cos term = 1
    north_summer = niell_hydrostatic_mapping(el, 45.0, 28.0 + 365.25 / 2, 0.0)
    south_same_day = niell_hydrostatic_mapping(el, -45.0, 28.0, 0.0)
    assert north_winter != pytest.approx(north_summer, abs=1e-6)
    # The southern hemisphere is half a year out of phase.
    assert float(south_same_day) == pytest.approx(float(north_summer), abs=1e-12)
    assert np.sign(north_winter - north_summer) == -np.sign(south_same_day - north_winter)
    # No seasonal amplitude at 15 degrees and below.
    assert float(niell_hydrostatic_mapping(el, 10.0, 28.0, 0.0)) == pytest.approx(
        float(niell_hydrostatic_mapping(el, 10.0, 200.0, 0.0)), abs=1e-12
    )


def test_latitude_interpolation_is_between_rows() -> None:
    m30 = float(niell_hydrostatic_mapping(7.0, 30.0, 100.0, 0.0))
    m45 = float(niell_hydrostatic_mapping(7.0, 45.0, 100.0, 0.0))
    m37 = float(niell_hydrostatic_mapping(7.0, 37.5, 100.0, 0.0))
    assert min(m30, m45) < m37 < max(m30, m45)


def test_wet_delay_is_optional() -> None:
    dry = Atmosphere(wet_delay=False).tropo_delay_m(30.0, 45.0, 100.0, 0.0)
    wet = Atmosphere(wet_delay=True, water_vapour_gm3=10.0).tropo_delay_m(30.0, 45.0, 100.0, 0.0)
    assert 0.1 < float(wet - dry) < 0.5  # ~0.1-0.3 m zenith wet delay, x2 at 30 degrees


def test_attenuation_is_tiny_and_grows_toward_horizon() -> None:
    atmo = Atmosphere()
    zen = float(atmo.attenuation_db(90.0))
    assert 0.0 < zen < 0.1
    el = np.array([5.0, 10.0, 30.0, 60.0, 90.0])
    att = atmo.attenuation_db(el)
    assert np.all(np.diff(att) < 0)
    assert att[0] / zen == pytest.approx(10.0, rel=0.2)  # about the slant factor
    parts = atmo.attenuation_parts_db(el)
    assert parts["oxygen"][-1] > parts["water_vapour"][-1] > 0.0
    # Layers: most of the oxygen attenuation is in the troposphere.
    assert parts["oxygen:troposphere"][-1] > 0.5 * parts["oxygen"][-1]


def test_clouds_and_rain_add_attenuation() -> None:
    clear = Atmosphere()
    storm = Atmosphere(cloud="thunderstorm", rain_mmph=50.0)
    el = np.array([10.0, 90.0])
    extra = storm.attenuation_db(el) - clear.attenuation_db(el)
    assert np.all(extra > 0.0)
    assert float(extra[1]) < 0.2  # still small at L1
    parts = storm.attenuation_parts_db(90.0)
    lwc, base, top = CLOUD_TYPES["thunderstorm"]
    expected_cloud = cloud_specific_coefficient(1.57542) * lwc * (top - base) / 1e3
    assert float(parts["cloud"]) == pytest.approx(expected_cloud, rel=1e-6)
    assert float(parts["rain"]) > 0.0
    # P.840 K_l at L1 is ~2e-3 (dB/km)/(g/m^3).
    assert 1e-3 < cloud_specific_coefficient(1.57542) < 4e-3


def test_slant_path_through_a_shell() -> None:
    # Vertical: the shell thickness; low elevation: much longer but finite at 0 degrees.
    assert float(slant_path_m(90.0, 1000.0, 3000.0)) == pytest.approx(2000.0)
    low = float(slant_path_m(0.0, 0.0, 1000.0))
    assert 100e3 < low < 120e3  # sqrt(2 R h) ~ 113 km
    assert float(slant_path_m(30.0, 0.0, 1000.0)) == pytest.approx(2000.0, rel=0.01)


def test_snr_levels_and_noise() -> None:
    atmo = Atmosphere()
    snr = atmo.snr_dbhz(np.array([5.0, 45.0, 90.0]))
    # -158.5 dBW at 5 degrees against -204 + 2 + 1 dBW/Hz: about 42 dB-Hz.
    assert float(snr[0]) == pytest.approx(-158.5 - (-204.0 + 2.0 + 1.0), abs=1.0)
    assert snr[0] < snr[1] < snr[2] < 50.0
    noisy = Atmosphere(env_noise_db=40.0).snr_dbhz(np.array([5.0, 45.0, 90.0]))
    np.testing.assert_allclose(snr - noisy, 39.0)
    lossy = atmo.snr_dbhz(np.array([45.0, 45.0]), extra_loss_db=np.array([0.0, 9.0]))
    assert float(lossy[0] - lossy[1]) == pytest.approx(9.0)


def test_cutoff_removes_satellites() -> None:
    el = np.array([5.0, 20.0, 60.0, 85.0])
    quiet = Atmosphere(env_noise_db=1.0)
    assert quiet.usable(quiet.snr_dbhz(el)).all()
    industrial = Atmosphere(env_noise_db=40.0, snr_cutoff_dbhz=5.0)
    usable = industrial.usable(industrial.snr_dbhz(el))
    assert not usable.all() and usable.any()
    assert not usable[0] and usable[-1]  # low satellites go first
    # Reflection losses push a satellite under the cutoff.
    assert not quiet.usable(quiet.snr_dbhz(60.0, extra_loss_db=48.0))


def test_broadcasting_shapes() -> None:
    atmo = Atmosphere()
    el = np.full((7, 5), 30.0)
    assert atmo.iono_delay_m(el).shape == (7, 5)
    assert atmo.tropo_delay_m(el, 45.0, 10.0, 100.0).shape == (7, 5)
    assert atmo.snr_dbhz(el, np.zeros((7, 5))).shape == (7, 5)
    assert atmo.attenuation_db(el).shape == (7, 5)
    # Satellites at or below the horizon still give finite numbers (no division by zero).
    low = np.array([-3.0, 0.0, 0.2])
    assert np.isfinite(atmo.tropo_delay_m(low, 45.0, 10.0, 0.0)).all()
    assert np.isfinite(atmo.snr_dbhz(low)).all()


def test_validation_names_the_key() -> None:
    with pytest.raises(ConfigError, match=r"atmosphere\.cloud"):
        build(Atmosphere, {"cloud": "hail"}, "atmosphere.")
    with pytest.raises(ConfigError, match=r"atmosphere\.env_noise_db"):
        build(Atmosphere, {"env_noise_db": -3.0}, "atmosphere.")
    with pytest.raises(ConfigError, match=r"atmosphere\.cloud_top_m"):
        Atmosphere(cloud="fog", cloud_base_m=500.0, cloud_top_m=100.0)
    with pytest.raises(ConfigError, match=r"atmosphere\.tec_tecu"):
        Atmosphere(tec_tecu=float("nan"))
    atmo = build(Atmosphere, {"cloud": "stratus", "rain_mmph": 5}, "atmosphere.")
    assert atmo.cloud == "stratus" and atmo.rain_mmph == 5.0
