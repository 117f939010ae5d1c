"""The simulated NEO-5's side of UBX configuration: what the host writes to its UART.

Hardware in the loop (:mod:`sim_backend.hil`) reads the bytes the daemon writes to the GPS
pty and hands them to a :class:`UbxConfigPort`, which answers as a NEO-5 does for the
messages ``[gps] configure_receiver`` sends (``drivers.gps_io.neo5_setup``):

- CFG-RATE (6 bytes: measurement period ms, navigation rate, time reference): ACK-ACK and
  the new rate (the receiver's epochs move to it) when the period gives 1..4 Hz (the
  simulated receiver's range; a real NEO-5 also runs slower than 1 Hz) and the navigation
  rate is 1, else ACK-NAK. An empty payload (a poll): the current CFG-RATE, then ACK-ACK.
- CFG-MSG (3 bytes: class, id, rate on this port; or 8: a rate per port, UART 1's taken):
  ACK-ACK; for an NMEA message (class 0xF0) the rate becomes how often the sentence is
  printed (every ``rate`` epochs, 0 never: :meth:`UbxConfigPort.keeps`).
- any other CFG message: ACK-NAK. The simulation implements nothing else, and a NAK tells
  the host so, rather than an ACK for a setting that changes nothing. Other classes (polls
  of NAV messages ...) are ignored; NMEA the host sends too.

Sans-IO: bytes in, answer frames out.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from drivers.gps_nmea import (
    NMEA_MSG_IDS,
    UBX_CLASS_ACK,
    UBX_CLASS_CFG,
    UBX_CLASS_NMEA,
    UBX_ID_ACK_ACK,
    UBX_ID_ACK_NAK,
    UBX_ID_CFG_MSG,
    UBX_ID_CFG_RATE,
    NmeaFramer,
    UbxFrame,
    ubx_frame,
)

SIM_RATES_HZ = (1.0, 4.0)
"""The navigation rates the simulated receiver runs at (its NMEA writer's range)."""
_NMEA_NAMES = {v: k for k, v in NMEA_MSG_IDS.items()}


@dataclass(frozen=True)
class Answer:
    """What one host frame caused: the bytes to send back and a new rate (Hz) or None."""

    reply: bytes
    rate_hz: float | None = None


class UbxConfigPort:
    """The receiver's UBX input: :meth:`feed` the host's bytes, send back each
    :attr:`Answer.reply`, apply each :attr:`Answer.rate_hz`. :attr:`msg_rates`: the NMEA
    sentence types set by CFG-MSG, every how many epochs (absent: every epoch)."""

    def __init__(self, rate_hz: float) -> None:
        self.rate_hz = rate_hz
        self.msg_rates: dict[str, int] = {}
        self.frames_in = 0  # UBX frames the host sent
        self._framer = NmeaFramer()

    def reset(self) -> None:
        """Drop a partial frame (the port was reopened)."""
        self._framer.reset()

    def feed(self, data: bytes) -> list[Answer]:
        """The answers to the frames ``data`` completes, in order."""
        out = []
        for frame in self._framer.feed(data):
            if isinstance(frame, UbxFrame):
                self.frames_in += 1
                answer = self._answer(frame)
                if answer is not None:
                    out.append(answer)
        return out

    def keeps(self, sentence_type: str, epoch: int) -> bool:
        """Whether epoch ``epoch``'s burst prints ``sentence_type`` ("GGA", "GSV" ...)."""
        every = self.msg_rates.get(sentence_type, 1)
        return every > 0 and epoch % every == 0

    def _answer(self, frame: UbxFrame) -> Answer | None:
        if frame.msg_class != UBX_CLASS_CFG:
            return None
        key = bytes((frame.msg_class, frame.msg_id))
        ack = ubx_frame(UBX_CLASS_ACK, UBX_ID_ACK_ACK, key)
        nak = Answer(ubx_frame(UBX_CLASS_ACK, UBX_ID_ACK_NAK, key))
        p = frame.payload
        if frame.msg_id == UBX_ID_CFG_RATE:
            if not p:  # a poll: the setting, then its ACK
                meas_ms = round(1000.0 / self.rate_hz)
                now = ubx_frame(UBX_CLASS_CFG, UBX_ID_CFG_RATE, struct.pack("<HHH", meas_ms, 1, 1))
                return Answer(now + ack)
            if len(p) != 6:
                return nak
            meas_ms, nav_rate, time_ref = struct.unpack("<HHH", p)
            if meas_ms == 0 or nav_rate != 1 or time_ref > 1:
                return nak
            hz = 1000.0 / meas_ms
            lo, hi = SIM_RATES_HZ
            if not lo <= hz <= hi:
                return nak
            self.rate_hz = hz
            return Answer(ack, hz)
        if frame.msg_id == UBX_ID_CFG_MSG:
            if len(p) not in (3, 8):
                return nak  # (a 2-byte poll of a message's rates is not simulated)
            rate = p[2] if len(p) == 3 else p[3]  # this port's, or UART 1's of the six
            if p[0] == UBX_CLASS_NMEA and p[1] in _NMEA_NAMES:
                self.msg_rates[_NMEA_NAMES[p[1]]] = rate
            return Answer(ack)
        return nak
