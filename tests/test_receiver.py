"""The one simulated receiver (sim_backend.receiver): built from every part of a scenario,
the layers run the one way, the same receiver in x6wd sim, HIL and the gap tool's baselines."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from drivers.gps_nmea import GpsDecoder
from sim_backend.effects import (
    Bias,
    Latency,
    PositionSeries,
    metres_per_degree,
    quantization_step_m,
)
from sim_backend.gnss import GnssModel, LceGrid
from sim_backend.mission import run_mission
from sim_backend.receiver import SimRandom, UartTx, build_gnss_model, build_receiver
from sim_backend.sky import SatelliteSet, read_yuma
from sim_backend.world import World, load_world, loads_world
from x6wd.core.records import GpsFix

ROOT = Path(__file__).resolve().parent.parent
SCENARIOS = ROOT / "config" / "scenarios"

FULL = """
name = "every part"
start_utc = "2020-01-01T12:00:00Z"
[origin]
lat_deg = 51.752
lon_deg = -1.2577
alt_m = 60.0
[gnss]
fidelity = "seed"
seed_uere = "re_ase_lce"
mask_deg = 10.0
rate_hz = 2.0
nmea_decimals = 4
baud = 38400
re_m = 0.3
ase_m = 0.8
lce_cell_m = 5.0
lce_east0_m = -10.0
lce_north0_m = -5.0
lce_sigma_m = [[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0]]
lce_outside_m = 0.5
[atmosphere]
env_noise_db = 3.0
[[walls]]
x0_m = -20.0
y0_m = 15.0
x1_m = 20.0
y1_m = 15.0
height_m = 12.0
[[effects]]
name = "bias"
east_m = 3.0
[[effects]]
name = "hard_iron"
bx_ut = 1.0
by_ut = 0.0
"""


def _world(text: str = FULL) -> World:
    return loads_world(text)


def test_sim_random_splits_the_seed_as_x6wd_sim_always_has() -> None:
    rand = SimRandom.from_seed(42)
    kids = np.random.SeedSequence(42).spawn(4)
    for gen, kid in zip((rand.gnss, rand.compass, rand.i2c, rand.effects), kids, strict=True):
        assert gen.random() == np.random.default_rng(kid).random()


def test_the_receiver_is_built_from_every_part_of_the_scenario() -> None:
    world = _world()
    rx = build_receiver(world, 3)
    m = rx.model
    assert (m.fidelity, m.mask_deg) == ("seed", 10.0)
    assert m.origin == (51.752, -1.2577, 60.0) and m.start_utc == world.start_utc
    assert m.atmosphere == world.atmosphere and m.walls is world.walls_model()
    p = m.params
    assert (p.seed_uere, p.re_sigma_m, p.ase_sigma_m) == ("re_ase_lce", 0.3, 0.8)
    assert isinstance(p.lce, LceGrid)
    assert np.array_equal(p.lce.sigma_m, world.lce_array())
    assert (p.lce.east0_m, p.lce.north0_m, p.lce.cell_m, p.lce.outside_m) == (-10, -5, 5, 0.5)
    assert (rx.formatter.minute_decimals, rx.rate_hz, rx.baud) == (4, 2.0, 38400)
    # only the GPS layers run in the receiver (the compass ones act on the emulation)
    assert len(rx.layers) == 1 and rx.delay_s == 0.0 and not rx.tracks
    sky = SatelliteSet.from_almanac(read_yuma(world.almanac_path, reference=world.start_utc))
    assert np.array_equal(m.sky.prns, sky.prns)


def test_closed_loop_epoch_without_layers_is_the_models_own_step() -> None:
    world = load_world(SCENARIOS / "default.toml")
    rx = build_receiver(world, 5)
    model = build_gnss_model(world, SimRandom.from_seed(5).gnss)
    lat, lon, alt = 51.75203, -1.25772, 60.34
    from sim_backend.geodesy import lla_to_enu

    pos = np.asarray(lla_to_enu(lat, lon, alt, *rx.origin), dtype=float).reshape(3)
    for k in range(5):
        want = model.step(float(k), *_lla(rx.origin, pos), (0.5, 0.2, 0.0))
        assert rx.epoch(float(k), tuple(pos), (0.5, 0.2, 0.0)) == want


def _lla(origin: tuple[float, float, float], pos: np.ndarray) -> tuple[float, float, float]:
    from sim_backend.geodesy import enu_to_lla

    lat, lon, alt = enu_to_lla(pos, *origin)
    return float(lat), float(lon), float(alt)


def _with(world: World, *layers: object) -> World:
    return replace(world, effects=tuple(e.to_params() for e in layers))  # type: ignore[attr-defined]


def test_layers_move_the_report_and_the_print_stage_runs_last() -> None:
    plain_world = load_world(SCENARIOS / "default.toml")
    pos, vel = (3.0, 4.0, 0.34), (0.0, 1.0, 0.0)
    plain = build_receiver(plain_world, 8)
    biased = build_receiver(_with(plain_world, Bias(30.0, -20.0, 1.0)), 8)
    e_per, n_per = metres_per_degree(plain_world.origin.lat_deg)
    for k in range(3):
        a, b = plain.epoch(float(k), pos, vel), biased.epoch(float(k), pos, vel)
        assert b.lon_deg - a.lon_deg == pytest.approx(30.0 / e_per, rel=1e-9)
        assert b.lat_deg - a.lat_deg == pytest.approx(-20.0 / n_per, rel=1e-9)
        assert b.alt_m - a.alt_m == pytest.approx(1.0)
        assert (b.hdop, b.satellites, b.speed_mps) == (a.hdop, a.satellites, a.speed_mps)
    # quantization listed FIRST still rounds the minutes the bias moved: printing is last
    text = (SCENARIOS / "default.toml").read_text()
    q = loads_world(
        text + '\n[[effects]]\nname = "quantization"\ndecimals = 3\n'
        '\n[[effects]]\nname = "bias"\neast_m = 7.3\nnorth_m = 2.1\n',
        base_dir=SCENARIOS,
    )
    rx = build_receiver(q, 8)
    for k in range(4):
        ep = rx.epoch(float(k), pos, vel)
        for deg in (ep.lat_deg, ep.lon_deg):
            minutes = abs(deg) * 60.0 * 1000.0
            assert abs(minutes - round(minutes)) < 1e-6


def test_an_outage_layer_gives_the_receivers_no_fix_epochs() -> None:
    world = _with(load_world(SCENARIOS / "default.toml"), _outage())
    rx = build_receiver(world, 2)
    eps = [rx.epoch(float(k), (0.0, 0.0, 0.34), (0.0, 0.0, 0.0)) for k in range(5)]
    assert not any(ep.valid for ep in eps)
    assert all(ep.quality == 0 and ep.hdop == 99.99 for ep in eps)
    assert all(not s.used for ep in eps for s in ep.satellites) and eps[0].satellites
    dec = GpsDecoder(emit_sentences=False)
    fixes = [r for ep in eps for r in dec.feed(rx.nmea(ep), 0.0) if isinstance(r, GpsFix)]
    assert len(fixes) == 5 and not any(f.valid for f in fixes)
    assert dec.counters.invalid_fields == 0


def _outage() -> object:
    from sim_backend.effects import Outages

    return Outages(mean_up_s=1e-6, mean_down_s=1e6)  # down from the start, for ever


def test_latency_solves_for_the_truth_delay_s_ago() -> None:
    world = load_world(SCENARIOS / "default.toml")
    late = build_receiver(_with(world, Latency(1.5)), 4)
    now = build_receiver(world, 4)  # the same model stream: only the truth differs
    assert late.tracks and late.delay_s == 1.5
    vel = (1.0, 2.0, 0.0)
    checked = 0
    for i in range(81):  # 20 Hz physics along a straight line, an epoch every second
        t = i / 20.0
        pos = (vel[0] * t, vel[1] * t, 0.34)
        late.observe(t, pos, vel)
        if i % 20 == 0:
            then = (vel[0] * (t - 1.5), vel[1] * (t - 1.5), 0.34)  # before 0: first velocity
            got, want = late.epoch(t, pos, vel), now.epoch(t, then, vel)
            assert (got.lat_deg, got.lon_deg) == pytest.approx((want.lat_deg, want.lon_deg),
                                                               rel=0, abs=1e-12), t  # fmt: skip
            assert got.speed_mps == want.speed_mps
            checked += 1
    assert checked == 5


def test_bytes_and_their_timing_on_the_uart() -> None:
    world = load_world(SCENARIOS / "default.toml")
    rx = build_receiver(world, 1)
    assert rx.banner().startswith(b"$GPTXT,01,01,02,u-blox ag")
    ep = rx.epoch(0.0, (0.0, 0.0, 0.34), (0.0, 0.0, 0.0))
    burst = rx.formatter.format_epoch(ep)
    lines = burst.splitlines(keepends=True)
    ep2 = build_receiver(world, 1).epoch(0.0, (0.0, 0.0, 0.34), (0.0, 0.0, 0.0))
    assert rx.sentences(ep2) == lines
    arr = rx.arrivals(burst, 10.0)
    assert [line for _t, line in arr] == lines
    n = np.cumsum([len(x) for x in lines])
    assert [t for t, _ in arr] == pytest.approx(10.0 + n * 10.0 / world.gnss.baud, abs=1e-12)
    assert rx.wire_time_s(96) == pytest.approx(96 * 10.0 / world.gnss.baud)


@pytest.mark.parametrize(("rate_hz", "baud"), [(4.0, 9600), (4.0, 38400), (1.0, 9600)])
def test_uart_queues_then_drops_whole_sentences_as_a_real_line(rate_hz: float, baud: int) -> None:
    """A NEO-5 burst is about 500 bytes; 4 Hz needs about 2,000 bytes/s. 9600 baud carries
    960 (bytes x 10 / 9600 s each): the transmit buffer fills and whole sentences are
    dropped, none torn; the first sentences of each burst get through about the full
    buffer's wire time late and nearly all GSV and GLL are dropped (docs/simulator.md, "The
    UART"); 38400 baud, or 1 Hz at 9600, carries everything."""
    world = load_world(SCENARIOS / "default.toml")
    rx = build_receiver(world, 1)
    tx = UartTx(baud)
    period_s = 1.0 / rate_hz
    sent: list[tuple[float, float, bytes]] = []  # epoch time, arrival time, sentence
    generated = generated_bytes = 0
    made: list[bytes] = []  # the kind (RMC, GSV, ...) of every sentence generated
    for k in range(int(30 * rate_hz)):
        t = k * period_s
        lines = rx.sentences(rx.epoch(t, (0.0, 0.0, 0.34), (0.0, 0.0, 0.0)))
        generated += len(lines)
        made += [line[3:6] for line in lines]
        generated_bytes += sum(map(len, lines))
        out = tx.send(lines, t)
        assert tx.queued_bytes(t) <= tx.buffer_bytes
        kept = [line for _t, line in out]
        assert kept == [x for x in lines if x in kept]  # whole sentences, in order
        sent += [(t, t_rx, line) for t_rx, line in out]
    t_end = np.array([t_rx for _t, t_rx, _ in sent])
    n = np.array([len(line) for _t, _t_rx, line in sent])
    # back to back at most: each sentence needs its own wire time after the previous one
    assert (np.diff(t_end) >= n[1:] * 10.0 / baud - 1e-9).all()
    assert tx.sent + tx.dropped == generated and tx.sent == len(sent)
    if generated_bytes > 30.0 * baud / 10.0:
        assert tx.dropped > 0
        # the line is kept busy: it carried what 30 s of the line carry, no more
        assert n.sum() == pytest.approx(30.0 * baud / 10.0, rel=0.08)
        assert n.sum() <= 30.0 * baud / 10.0 + tx.buffer_bytes
        kinds = [line[3:6] for _t, _t_rx, line in sent]
        assert kinds.count(b"RMC") > 0.9 * 30 * rate_hz  # the first of each burst gets through
        # ... about the full buffer's wire time late; the burst's tail is what is dropped
        late_s = [t_rx - t for t, t_rx, line in sent if line[3:6] == b"RMC"]
        full_s = tx.buffer_bytes * 10.0 / baud
        assert 0.5 * full_s <= float(np.median(late_s)) <= 1.1 * full_s, (late_s, full_s)
        for kind in (b"GSV", b"GLL"):
            assert kinds.count(kind) < 0.15 * made.count(kind), kind
    else:
        assert tx.dropped == 0
        # no backlog: every burst is out before the next epoch
        assert all(t_rx - t < period_s for t, t_rx, _ in sent)


def _template(world: World, n: int) -> PositionSeries:
    z = np.zeros(n)
    return PositionSeries(
        np.arange(n, dtype=float), z, z, z, np.ones(n, dtype=bool),
        world.origin.lat_deg, world.origin.lon_deg,
    )  # fmt: skip


def test_gap_errors_carry_the_scenarios_lce_grid() -> None:
    base = FULL.split("[[walls]]")[0]
    quiet = _world(base.replace("lce_outside_m = 0.5", "lce_outside_m = 0.0"))
    loud = _world(base.replace("lce_outside_m = 0.5", "lce_outside_m = 25.0"))
    tpl = _template(quiet, 400)  # at the origin: the map's cell (row 1, column 2), 7 m
    far = tpl.with_(true_east_m=np.full(400, 500.0), true_north_m=np.zeros(400))  # off the map
    rms = {}
    for name, world in (("quiet", quiet), ("loud", loud)):
        e = build_receiver(world, 11).errors(far)
        rms[name] = math.sqrt(float(np.mean(e.east_m**2 + e.north_m**2)))
    assert rms["loud"] > 5 * rms["quiet"]
    # in the map's 7 m cell the errors grow as the seed-003 form says
    inside = build_receiver(quiet, 11).errors(tpl)
    assert math.sqrt(float(np.mean(inside.east_m**2 + inside.north_m**2))) > 2 * rms["quiet"]


def test_gap_errors_are_what_x6wd_sim_prints_for_the_same_seed(tmp_path: Path) -> None:
    # The static survey: x6wd sim's NMEA and the gap baseline's errors, same scenario and seed.
    world = load_world(SCENARIOS / "open_field.toml")
    run_mission(world, tmp_path, seed=3, duration_s=40.0)
    dec = GpsDecoder(emit_sentences=False)
    fixes = [r for r in dec.feed((tmp_path / "gps.nmea").read_bytes(), 0.0)
             if isinstance(r, GpsFix)]  # fmt: skip
    o = world.origin
    e_per, n_per = metres_per_degree(o.lat_deg)
    assert len(fixes) == 41 and all(f.valid for f in fixes)
    sim_e = np.array([(f.lon_deg - o.lon_deg) * e_per for f in fixes])  # type: ignore[operator]
    sim_n = np.array([(f.lat_deg - o.lat_deg) * n_per for f in fixes])  # type: ignore[operator]
    base = build_receiver(world, 3).errors(_template(world, 41))
    step_e, step_n = quantization_step_m(world.gnss.nmea_decimals, o.lat_deg)
    # the same draws: equal to the printed lattice (the antenna's 0.34 m may flip a digit)
    assert np.max(np.abs(base.east_m - sim_e)) <= 1.01 * step_e
    assert np.max(np.abs(base.north_m - sim_n)) <= 1.01 * step_n
    assert np.median(np.abs(base.east_m - sim_e)) < 0.01 * step_e
    assert base.valid.all() and np.all(base.nsats >= 4)


def test_the_gnss_model_is_built_only_here() -> None:
    # nothing else in the project constructs a GnssModel from a scenario
    hits = []
    for pkg in ("sim_backend", "x6wd"):
        for path in (ROOT / pkg).rglob("*.py"):
            if path.name in ("receiver.py", "gnss.py"):
                continue
            if "GnssModel(" in path.read_text():
                hits.append(str(path.relative_to(ROOT)))
    assert hits == []
    assert GnssModel  # the class itself stays public for the benchmarks and tests


@pytest.mark.parametrize("seed", range(6))
def test_the_uart_table_is_send_sentence_by_sentence(seed: int) -> None:
    """``UartTx.send_table`` (a chunk's sentence sizes at once) against ``send_bursts`` (the
    sentences one by one): the same arrival times to the bit, the same drops and state, for
    lines that keep up (the vectorised path), lines that fall behind or drop, a banner still
    on the wire, empty epochs and uneven rates, over consecutive chunks."""
    rng = np.random.default_rng(seed)
    for trial in range(40):
        baud = int(rng.choice([4800, 9600, 38400, 115200]))
        rate = float(rng.choice([1.0, 2.0, 4.0, 0.5, 1 / 3]))
        n_e = int(rng.integers(1, 50))
        t = np.arange(n_e) / rate + float(rng.choice([0.0, 1000.0, 65530.0, 1e6]))
        sizes = rng.integers(30, 80, size=(n_e, 9))
        sizes[rng.random((n_e, 9)) < 0.3] = 0
        if trial % 7 == 0:
            sizes[rng.integers(0, n_e)] = 0  # an epoch without sentences
        if trial % 5 == 0:
            sizes[rng.random((n_e, 9)) < 0.05] = 2000  # longer than the buffer
        buffer_bytes = int(rng.choice([1024, 200, 5000]))
        one, table = UartTx(baud, buffer_bytes), UartTx(baud, buffer_bytes)
        one.free_at_s = table.free_at_s = float(rng.choice([-math.inf, t[0] + 0.3, t[0] - 0.1]))
        for rows in np.array_split(np.arange(n_e), 3):
            bursts = [
                b"".join(b"x" * (int(m) - 2) + b"\r\n" for m in row if m > 0) for row in sizes[rows]
            ]
            want = [(t_rx, len(line)) for t_rx, line in one.send_bursts(bursts, t[rows].tolist())]
            arrive, sent = table.send_table(sizes[rows], t[rows])
            got = [(float(a), int(m)) for a, m in zip(arrive[sent], sizes[rows][sent], strict=True)]
            assert got == want
            assert (table.free_at_s, table.dropped, table.sent) == (
                one.free_at_s, one.dropped, one.sent,
            )  # fmt: skip


def test_errors_of_a_long_template_run_in_even_chunks_that_join_seamlessly(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The gap tool's simulated logs: a 1 h 10 Hz template in one call took ~240 MB more than
    # in chunks. Chunks continue the processes' state, so the joins do not show; a template
    # within one chunk is one call, as it always was.
    import sim_backend.receiver as receiver
    from sim_backend.effects import PositionSeries

    world = load_world(SCENARIOS / "open_field.toml")
    n = 2_400
    t = np.arange(n) * 0.5
    template = PositionSeries(t, np.zeros(n), np.zeros(n), np.zeros(n), np.ones(n, dtype=bool),
                              world.origin.lat_deg, world.origin.lon_deg)  # fmt: skip
    whole = build_receiver(world, 4).errors(template)
    assert len(whole.t_s) == n and whole.sat_set is not None and len(whole.sat_set) == n
    monkeypatch.setattr(receiver, "ERRORS_CHUNK_EPOCHS", 700)  # 4 calls of 600
    calls: list[int] = []
    rx = build_receiver(world, 4)
    batch = rx.batch
    monkeypatch.setattr(rx, "batch", lambda t, p, v: calls.append(len(t)) or batch(t, p, v))
    parts = rx.errors(template)
    assert calls == [600] * 4
    assert np.array_equal(parts.t_s, whole.t_s) and len(parts.sat_set) == n
    assert np.all(parts.valid) and np.all(whole.valid)
    for e in (parts, whole):  # same law: the slow error's spread, the step size
        assert 0.3 < np.std(e.east_m) < 8.0
    steps = np.hypot(np.diff(parts.east_m), np.diff(parts.north_m))
    joins = steps[np.arange(599, n - 1, 600)]
    assert np.max(joins) < np.percentile(steps, 99.9) + 0.05  # no jump where chunks meet
    assert np.median(steps) == pytest.approx(
        np.median(np.hypot(np.diff(whole.east_m), np.diff(whole.north_m))), rel=0.3
    )
