"""GPS-Bee (u-blox NEO-5) protocol: sans-IO NMEA framing, field decoding and UBX frames.

Bytes in (any chunking), typed records out; no I/O here (see ``drivers.gps_io``).

Layers:

- ``NmeaFramer`` splits a byte stream into checksum-verified NMEA sentences and UBX frames.
  It resynchronises on ``$`` (and on the UBX sync ``B5 62``), requires ``*HH`` (either hex
  case), caps a sentence at 130 characters including ``$`` and the checksum (as gpsd does)
  and decodes with replacement, so line noise and binary never raise. A UBX sync is a false
  one (a byte of noise, the scan goes on after it) when its length is over 1024 bytes, its
  checksum is wrong, or a whole checksum-valid NMEA sentence with its line end lies inside
  the span it claims: so a false sync in line noise delays no sentence beyond its own line
  end (it held every byte behind it until the claimed length had arrived, up to 1 s of
  9600 baud line per 1000 bytes). A sentence complete
  up to ``*HH`` whose line ending was lost (the next ``$`` follows at once) is accepted;
  one cut off by a new ``$`` or containing another ``*`` is a framing error.
  With ``accept_unchecksummed`` (``x6wd decode`` and the gap tool's NMEA reader; gpsd's
  packet lexer checks a checksum only where a ``*`` is present), a complete line without
  ``*HH`` is a sentence too when it is well-formed: ``$``, an address of an uppercase
  letter and 2-9 uppercase letters or digits, then nothing or a comma and printable ASCII
  without ``*``, ended by CR or LF, at most 127 characters (130 with the checksum), and
  the stream has carried no line with ``*HH`` before it. A receiver or logger writes the
  checksum on every line or on none: in a stream that has carried checksums, a line
  without one is one whose end was lost (gpsd's ublox-8 log ends in an RMC cut after its
  speed's "0.", its gp-320fw cold-boot log has three cut lines; gpsd takes them, and its
  output of the RMC has no fix of it). Such a line is given its computed checksum
  (downstream it is a sentence like any other) and counted in ``unchecksummed`` as well
  as ``sentences``. A line cut off by a new ``$``, over the cap, or with a ``*`` not
  followed by two hex digits is an error as before. The robot's daemon keeps the default
  (strict): the NEO-5 always sends checksums, and on a noisy UART a line without one is
  more likely a corrupt one.
- ``GpsDecoder`` splits each sentence into its fields and converts the ones it uses with
  the parsers of the sentence table (``drivers.nmea``, shared with the simulator's NMEA
  writer), not pynmea2's conversions, which have the pitfalls listed in REFERENCE.md §4
  (0.0 for empty coordinates, raw strings on failure, TypeError on empty dates). Every used
  field is format- and range-checked; a sentence with a bad field (or any non-ASCII byte)
  is rejected whole and counted in ``invalid_fields``. pynmea2 only tells which other
  sentence types exist (``unknown_types``) and parses proprietary and odd sentences.

Epoch assembly (how a ``GpsFix`` is closed):

- GGA and RMC carry the same UTC time in one receiver cycle. A fix is emitted as soon as
  both of the same time are in, i.e. on the GGA for the NEO-5 order (RMC, VTG, GGA, GSA,
  GSV, GLL): the latency from the last GGA byte to the fix is one decode.
- A GGA whose RMC has not arrived is emitted at once, unless this stream has shown that its
  RMC follows its GGA (or it is the stream's first GGA and no RMC was seen yet); then it is
  held until that RMC arrives or until any sentence with a different time (a new epoch) or
  ``flush()`` closes the epoch.
- An RMC without a GGA of its time is emitted at once when the stream carries no GGA (none
  in the last few epochs), else when the epoch closes, as a fix without altitude; its
  ``t_s`` is the RMC's receive time, so a late fix shows its age.
- A GGA without a time (no-fix form) is emitted at once as an invalid fix; so is an RMC
  without a time when the stream carries no GGA.
- An RMC whose GGA fix is out already is not re-emitted (one fix per UTC time).
- ``mode`` follows gpsd: 1 unless the fix is valid; else the latest GSA mode (2/3) when the
  stream has GSA, else 3 when GGA gives an altitude, else 2. GSA arrives after GGA, so the
  GSA mode and PDOP/VDOP used are those of the previous cycle.
- A ``GpsSky`` is emitted when a GSV group (per talker and NMEA 4.10 signal id) completes;
  ``used`` flags and DOPs come from the GSA sentences of the current cycle; satellites of
  every talker are merged. Satellites carry gpsd's numbering (``gpsd_satellite``: PRN across
  systems, gnssid, svid), so that a GSA marks its own system's satellites used; one
  without an SNR is never used, as in gpsd.

Speed (bench/bench_nmea.py compares the whole path with ``pynmea2.parse`` alone,
bench/bench_decode.py ``x6wd decode`` with gpsd's ``gpsdecode``): runs of well-formed lines
are found by one regex match on a copy of the read whose body bytes are one letter, and
all the lines of a read are checksummed together, 4096 at a time as one XOR of their
8-byte word columns (a few lines one by one); a read's UBX frames are taken first and
checked together by bytewise running sums over their byte columns, the scan resumed at
a bad one as if it had been checked at once; the field parsers are built once per field
from the table; values that repeat from epoch to epoch (times, positions shared by GGA and RMC,
numeric and letter fields, GSA contents, GSV satellites, sentence heads and their
handlers) are decoded once and memoised, in small bounded caches keyed by the field
strings, so a cached result is exactly what decoding the same strings again gives; an
epoch's UTC is its day's midnight plus the time of day; records are built through their
slot descriptors, one call per field. Each shortcut is an exact replacement for the plain
code it stands for.
"""

from __future__ import annotations

import functools
import operator
import re
import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, fields
from datetime import UTC, date, datetime, timedelta
from itertools import chain, compress, repeat
from typing import Any, Final, cast

from drivers.nmea import (
    GGA,
    GLL,
    GSA,
    GSV,
    MPS_PER_KNOT,
    RMC,
    SENTENCES,
    ZDA,
    FieldError,
    Sentence,
    checksum,
    field_parser,
    parse_time,
)
from x6wd.core.errors import ConfigError, ParseError
from x6wd.core.geodesy import wrap360
from x6wd.core.records import GpsFix, GpsSky, SatInfo

MAX_SENTENCE_CHARS: Final = 130  # gpsd's cap, '$' to checksum inclusive
MAX_UBX_PAYLOAD: Final = 1024  # larger "frames" are false syncs in line noise
# (and so is a "frame" with a whole NMEA sentence inside it: _nmea_inside)

UBX_SYNC: Final = b"\xb5\x62"
UBX_CLASS_ACK: Final = 0x05
UBX_CLASS_CFG: Final = 0x06
UBX_ID_ACK_ACK: Final = 0x01
UBX_ID_ACK_NAK: Final = 0x00
UBX_ID_CFG_MSG: Final = 0x01
UBX_ID_CFG_RATE: Final = 0x08
UBX_CLASS_NMEA: Final = 0xF0
# u-blox NMEA message ids (class 0xF0) for CFG-MSG.
NMEA_MSG_IDS: Final[dict[str, int]] = {
    "GGA": 0x00,
    "GLL": 0x01,
    "GSA": 0x02,
    "GSV": 0x03,
    "RMC": 0x04,
    "VTG": 0x05,
    "GRS": 0x06,
    "GST": 0x07,
    "ZDA": 0x08,
}


# ---------------------------------------------------------------------------- checksums
# NMEA's is drivers.nmea.checksum, shared with the simulator's writer.


# ubx_checksum's slots: 4 bytes hold its sums for up to 4096 bytes of data, 8 beyond.
_SLOT4_MAX: Final = 4096
_B4: Final = (1 << 32) - 1
_B8: Final = (1 << 64) - 1
_FOLD_TO_SLOTS: Final = 64  # below this, one % is cheaper than another fold
_B4_SQUARED: Final = _B4 * _B4
# The folds of a 4-byte-slot X for up to 2048 slots (a UBX body is at most 1028 bytes),
# precomputed: (fold when there are more slots than, bits kept, their mask, what the rest
# is multiplied by: 1 + m (B - 1) for m slots kept).
_FOLDED_MAX: Final = 2048
_FOLDS4: Final = tuple(
    (half, 32 * half, (1 << (32 * half)) - 1, 1 + half * _B4) for half in (1024, 512, 256, 128, 64)
)


def ubx_checksum(data: bytes) -> bytes:
    """8-bit Fletcher checksum (CK_A, CK_B) over class, id, length and payload.

    CK_A is the sum of the bytes d_k mod 256, CK_B the sum of the running sums, i.e. of
    (n - k) d_k (k from 0). Both come from one big integer instead of a Python loop per
    byte (a UBX stream is mostly payload, so this loop was most of its decoding): with
    each byte in its own w-byte slot, X = sum of d_k B^k for B = 2^(8w), and as
    B^m = 1 + m (B - 1) mod (B - 1)^2 for every m, X mod (B - 1)^2 = S + (B - 1) K with S
    the sum of d_k and K the sum of k d_k. X is first folded (its slots from m on, H, are
    added back as H (1 + m (B - 1)): the same residue, half the size), then one divmod by
    B - 1 of the residue gives S and K exactly (both are below B - 1 for these lengths).
    """
    n = len(data)
    if n <= _FOLDED_MAX:  # every UBX frame this framer takes: the folds are fixed
        spread = bytearray(4 * n)
        spread[::4] = data
        x = int.from_bytes(spread, "little")
        for above, low_bits, low_mask, high_times in _FOLDS4:
            if n > above:
                x = (x & low_mask) + (x >> low_bits) * high_times
        k_sum, total = divmod(x % _B4_SQUARED, _B4)
        return bytes((total & 0xFF, (n * total - k_sum) & 0xFF))
    width, base_1 = (4, _B4) if n <= _SLOT4_MAX else (8, _B8)
    slot_bits = 8 * width
    spread = bytearray(width * n)
    spread[::width] = data
    x = int.from_bytes(spread, "little")
    while (n_bits := x.bit_length()) > _FOLD_TO_SLOTS * slot_bits:
        low_bits = n_bits // (2 * slot_bits) * slot_bits
        x = (x & ((1 << low_bits) - 1)) + (x >> low_bits) * (1 + low_bits // slot_bits * base_1)
    k_sum, total = divmod(x % (base_1 * base_1), base_1)
    return bytes((total & 0xFF, (n * total - k_sum) & 0xFF))


# ---------------------------------------------------------------------------- frames


@dataclass(frozen=True, slots=True)
class NmeaFrame:
    """One checksum-valid NMEA sentence, ``$`` to ``*HH`` inclusive, no line ending."""

    text: str


@dataclass(frozen=True, slots=True)
class UbxFrame:
    """One checksum-valid UBX frame: message class, message id and payload bytes."""

    msg_class: int
    msg_id: int
    payload: bytes

    def to_bytes(self) -> bytes:
        """The frame on the wire (sync, header, payload, checksum)."""
        return ubx_frame(self.msg_class, self.msg_id, self.payload)


Frame = NmeaFrame | UbxFrame
# UbxFrame's fields set through their slot descriptors (a frozen dataclass's __init__ sets
# each through object.__setattr__, a lookup by name): the same object, built faster.
_SET_UBX: Final = tuple(vars(UbxFrame)[name].__set__ for name in ("msg_class", "msg_id", "payload"))
assert tuple(f.name for f in fields(UbxFrame)) == ("msg_class", "msg_id", "payload")


@dataclass(slots=True)
class FramerCounters:
    """What the framer saw. ``sentences`` counts checksum-valid NMEA sentences."""

    sentences: int = 0
    checksum_failures: int = 0
    framing_errors: int = 0  # too long, truncated by a new '$', no '*HH' at the line end
    ubx_frames: int = 0
    skipped_bytes: int = 0  # bytes outside any frame (line noise, comments), CR/LF excluded
    # Of ``sentences``, lines taken without '*HH' (NmeaFramer's accept_unchecksummed).
    unchecksummed: int = 0


# One scan finds the next sentence start or UBX sync. A sentence runs from '$' up to CR, LF,
# the next '$' or a 0xB5 (never in NMEA text; it may start an interleaved UBX frame).
# The first alternative is the common case, a whole well-formed sentence with its ending.
_SCAN: Final = re.compile(
    rb"\$([^$\r\n\xb5*]{1,126})\*([0-9A-Fa-f]{2})[ \t]*(?:\r\n|\r|\n|(?=[$\xb5]))"
    rb"|\$[^$\r\n\xb5]*|\xb5\x62"
)
_HEX: Final = frozenset(b"0123456789abcdefABCDEF")
# A complete line without '*HH' that NmeaFramer(accept_unchecksummed=True) takes: an
# address ("GPGGA", "PFEC", "STI"), then nothing or a comma and printable ASCII without
# '*' (the line end and trailing blanks already cut off).
_UNCHECKSUMMED: Final = re.compile(rb"\$[A-Z][A-Z0-9]{2,9}(?:,[\x20-\x29\x2b-\x7e]*)?")
# Where a sentence's unterminated segment ends: a line end, or the start of another frame.
_FRAME_END: Final = re.compile(rb"[$\r\n\xb5]")

# The fast path: a run of strictly well-formed lines ("$body*HH" and CR LF or LF, at most
# 128 bytes), which is what a healthy receiver or log sends, then possibly the start of the
# next sentence up to the end of the data (possessive: the body's class excludes the '*'
# that follows it, and the tail is optional, so giving back never helps). Each line is
# exactly what the first alternative of _SCAN matches, and the tail what its second one
# matches (up to the end, not too long, so held), so the two paths frame identically;
# anything else goes through _SCAN.
_RUN: Final = re.compile(
    rb"((?:\$[^$\r\n\xb5*]{1,124}+\*[0-9A-Fa-f]{2}\r?\n)*+)(\$[^$\r\n\xb5]{0,%d}\Z)?"
    % (MAX_SENTENCE_CHARS - 1)
)

# One such line alone (the whole of a read).
_LINE: Final = re.compile(rb"\$[^$\r\n\xb5*]{1,124}\*[0-9A-Fa-f]{2}\r?\n")

# XOR of a whole line "$body*HH" for each "HH" whose checksum matches: the stated checksum
# (the XOR of body) ^ '$' ^ '*' ^ the two hex digits. Folding the whole line then needs no
# slice to cut the body out.
_LINE_XOR: Final[dict[bytes, int]] = {
    bytes((hi, lo)): int(bytes((hi, lo)), 16) ^ 0x24 ^ 0x2A ^ hi ^ lo for hi in _HEX for lo in _HEX
}


# Runs of many lines are checksummed in batches (_line_sums): every line of a _RUN match is at
# most 128 bytes ("$", 124, "*HH").
_BATCH_LINES: Final = 4096  # bounds a batch's block to 512 KiB
_BATCH_MIN: Final = 16  # fewer lines: one checksum() each
# _LINE_XOR split by digit: _LINE_XOR[hi + lo] == _HI_XOR[hi] ^ _LO_XOR[lo], as byte tables
# (bytes.translate) for the checksum digits of a whole batch at once.
_HI_XOR: Final = bytes(
    (int(chr(c), 16) << 4) ^ 0x24 ^ 0x2A ^ c if c in _HEX else 0 for c in range(256)
)
_LO_XOR: Final = bytes(int(chr(c), 16) ^ c if c in _HEX else 0 for c in range(256))
assert all(_LINE_XOR[k] == _HI_XOR[k[0]] ^ _LO_XOR[k[1]] for k in _LINE_XOR)
_HEX_DIGITS: Final = bytes(sorted(_HEX))
_Run = tuple[int, list[bytes] | list[str]]  # a run's place in the frames, its lines (_run)
_ASCII: Final = operator.methodcaller("encode", "ascii")
_ZERO_IS_OK: Final = bytes([1] + [0] * 255)  # a line's sum XOR what it must be: 1 if equal

# _RUN on a copy of the data with every byte a body may hold (anything but "$", "*", CR,
# LF and 0xB5) written as "b": the body is then one repeated literal, which the regex
# engine takes about five times faster than the class. The checksum digits are "bb" too,
# so a run found this way is _RUN's once its digits are known to be hex (_line_sums).
_BODY_AS_B: Final = bytes(c if c in b"$*\r\n\xb5" else 0x62 for c in range(256))
_RUN_B: Final = re.compile(
    rb"((?:\$b{1,124}+\*bb\r?\n)*+)(\$[b*]{0,%d}\Z)?" % (MAX_SENTENCE_CHARS - 1)
)


def _line_sums(lines: list[bytes] | list[str]) -> tuple[bytes, bytes, bool]:
    """(``checksum(line)`` of every line, the value each must have: ``_LINE_XOR`` of its
    last two characters, whether those are all hex digits), for lines of at most 128
    bytes, computed all at once.

    The lines are right-aligned with zeros (zeros change no XOR) in slots as wide as the
    longest line rounded up to 8 bytes, and the block is read column by column of 8-byte
    words: column ``i`` (one strided view) holds the ``i``-th word of every slot, and the
    XOR of all columns, each read as one integer, holds every line's XOR folded to 8 bytes,
    which three shifts fold into the low byte of each slot. That is one big-int XOR per
    column (at most 16), however many lines. Right-aligned, the checksum digits are the
    last two byte columns. The lines may be ASCII ``str`` (all of them) instead.
    """
    width = (max(map(len, lines)) + 7) & ~7
    if type(lines[0]) is str:  # ASCII text: its bytes are its characters
        texts = cast("list[str]", lines)
        block = "".join(map(str.rjust, texts, repeat(width), repeat("\0"))).encode("ascii")
    else:
        raw = cast("list[bytes]", lines)
        block = b"".join(map(bytes.rjust, raw, repeat(width), repeat(b"\0")))
    words = memoryview(block).cast("Q")
    step = width // 8
    x = 0
    for i in range(step):
        x ^= int.from_bytes(words[i::step], "little")
    x ^= x >> 32
    x ^= x >> 16
    x ^= x >> 8
    n = len(lines)
    hi = block[width - 2 :: width]
    lo = block[width - 1 :: width]
    expected = int.from_bytes(hi.translate(_HI_XOR), "little") ^ int.from_bytes(
        lo.translate(_LO_XOR), "little"
    )
    all_hex = not (hi + lo).translate(None, _HEX_DIGITS)
    return x.to_bytes(8 * n, "little")[::8], expected.to_bytes(n, "little"), all_hex


class NmeaFramer:
    """Sans-IO framer: ``feed(bytes) -> list[Frame]``; never raises on any input."""

    def __init__(self, *, accept_unchecksummed: bool = False) -> None:
        """``accept_unchecksummed``: take a well-formed complete line without ``*HH`` as a
        sentence (module docstring); off for the robot's receiver."""
        self._buf = bytearray()
        self.accept_unchecksummed = accept_unchecksummed
        # The rest of an over-long sentence that was counted (one framing error) and dropped
        # before its end arrived is dropped too, uncounted, up to where that sentence would
        # end: the counters then do not depend on how the stream was cut into reads.
        self._dropping = False
        self.counters = FramerCounters()

    def reset(self) -> None:
        """Drop any partial frame (e.g. after the port was reopened)."""
        self._buf.clear()
        self._dropping = False

    @property
    def pending_bytes(self) -> int:
        """Bytes held while waiting for the rest of a frame."""
        return len(self._buf)

    def end(self) -> None:
        """The stream ended: the bytes held for a frame that never ended (a last line without
        its line end) are counted as skipped, as gpsd drops them, and dropped (before, they
        vanished uncounted: 163 sentences of a 164-line log, nothing said)."""
        if not self._dropping:
            tail = bytes(self._buf)
            self.counters.skipped_bytes += len(tail) - tail.count(b"\n") - tail.count(b"\r")
        self.reset()

    def feed(self, data: bytes) -> list[Frame]:
        """Append ``data`` and return every frame it completes, in stream order."""
        return [NmeaFrame(f) if type(f) is str else f for f in self.scan(data)]  # type: ignore[misc]

    def scan(self, data: bytes) -> list[str | UbxFrame]:
        """Like ``feed`` but sentences come as plain ``str`` (the decoder's fast path)."""
        if self._dropping:
            m = _FRAME_END.search(data)
            if m is None:
                return []
            self._dropping = False
            data = data[m.start() :]
        buf = self._buf
        if not buf and _LINE.fullmatch(data) is not None:
            # Exactly one well-formed line and nothing held (a simulated or line-buffered
            # receiver, one sentence per read): what the _RUN path makes of it, without
            # the buffer.
            line = data.rstrip(b"\r\n")
            if checksum(line) == _LINE_XOR[line[-2:]]:
                self.counters.sentences += 1
                return [line.decode("ascii", "replace")]
            self.counters.checksum_failures += 1
            return []
        c = FramerCounters()
        # One pass over the data as bytes (slices of it are bytes), after what is held; the
        # counters of a pass are added when it is taken. _RUN_B finds the runs unless a
        # run's checksum digits are not all hex, then _RUN does (a second pass).
        if buf:
            buf += data
            snapshot = bytes(buf)
        else:
            snapshot = bytes(data)  # (bytes is not copied)
        result = self._pass(snapshot, c, fast=True)
        if result is None:
            c = FramerCounters()
            result = self._pass(snapshot, c, fast=False)
            assert result is not None
        out, pos, dropping = result
        total = self.counters
        total.sentences += c.sentences
        total.checksum_failures += c.checksum_failures
        total.framing_errors += c.framing_errors
        total.ubx_frames += c.ubx_frames
        total.skipped_bytes += c.skipped_bytes
        total.unchecksummed += c.unchecksummed
        if dropping:
            self._dropping = True
        if pos < len(snapshot):
            self._buf = bytearray(snapshot[pos:])  # held for the next read
        elif buf:
            buf.clear()
        return out

    def _pass(
        self, buf: bytes, c: FramerCounters, *, fast: bool
    ) -> tuple[list[str | UbxFrame], int, bool] | None:
        """Frame ``buf``: (frames, bytes consumed, whether the rest of an over-long sentence
        is to be dropped), counted in ``c``; None when ``fast`` and a run's checksum digits
        are not all hex (``_RUN_B`` then framed what ``_RUN`` does not)."""
        out: list[str | UbxFrame] = []
        # Runs of lines, checksummed together at the end: (index in out, their lines).
        runs: list[_Run] = []
        n = len(buf)
        pos = 0
        dropping = False
        search = _SCAN.search
        if fast:
            run_match = _RUN_B.match
            target = buf.translate(_BODY_AS_B)
            take_ubx = _guess_ubx
        else:
            run_match = _RUN.match
            target = buf
            take_ubx = _ubx
        # UBX frames taken before their checksums are known (fast): (sync, frame length,
        # len(out), len(runs), counters) before each; checked together after the scan,
        # which resumes at the first bad one as if it had been checked at once
        # (_first_bad_ubx).
        guessed: list[_Guess] = []
        checked = 0
        while True:
            while True:
                run = run_match(target, pos)
                assert run is not None  # the pattern matches the empty string
                end = run.end(1)
                if end > pos:
                    self._run(buf[pos:end], out, runs)
                    pos = end
                if run.start(2) >= 0:  # a sentence in progress: wait for the rest
                    pos = run.start(2)
                    break
                if pos == n:
                    break
                m = search(buf, pos)
                if m is None:
                    # Keep a lone trailing 0xB5: it may be the first half of a UBX sync.
                    keep = n - 1 if n > pos and buf[n - 1] == 0xB5 else n
                    _skip(buf, pos, keep, c)
                    pos = keep
                    break
                start, end = m.span()
                if start > pos and not (
                    start - pos == 2 and buf[pos] == 0x0D and buf[pos + 1] == 0x0A
                ):
                    _skip(buf, pos, start, c)
                body = m.group(1)
                if body is not None:
                    pos = end
                    if checksum(body) != int(m.group(2), 16):
                        c.checksum_failures += 1
                    else:
                        c.sentences += 1
                        out.append(buf[start : start + len(body) + 4].decode("ascii", "replace"))
                    continue
                if buf[start] == 0xB5:
                    consumed, frame = take_ubx(buf, start, n, c, guessed, out, runs)
                    # A UBX stream sends frames back to back: the next sync right after a frame
                    # is where the scan would find the next match, so take it here.
                    while frame is not None:
                        out.append(frame)
                        start += consumed
                        if buf[start : start + 2] != UBX_SYNC:
                            break
                        consumed, frame = take_ubx(buf, start, n, c, guessed, out, runs)
                    if consumed == 0:  # incomplete: wait for more
                        pos = start
                        break
                    pos = start + consumed if frame is None else start
                    continue
                seg = m.group()
                ln = len(seg)
                if end == n:  # no terminator yet
                    if ln > MAX_SENTENCE_CHARS:
                        c.framing_errors += 1
                        pos = n
                        dropping = True
                    else:
                        pos = start
                    break
                term = buf[end]
                if term == 0x0A or term == 0x0D:
                    pos = end + 1
                    seg = seg.rstrip(b" \t")
                    ln = len(seg)
                    if self.accept_unchecksummed and seg.find(b"*") == -1:
                        # A whole line without '*HH' (no '*' at all): a sentence if it is
                        # well-formed, fits the cap with its checksum added and the stream
                        # has carried no checksummed line before it.
                        if (
                            ln > MAX_SENTENCE_CHARS - 3
                            or _UNCHECKSUMMED.fullmatch(seg) is None
                            or self._carried_checksums(out, c)
                        ):
                            c.framing_errors += 1
                            continue
                        c.sentences += 1
                        c.unchecksummed += 1
                        out.append(f"{seg.decode('ascii')}*{checksum(seg[1:]):02X}")
                        continue
                else:
                    pos = end
                    if ln < 4 or seg[-3] != 0x2A:
                        # A new frame began before this one ended: collision or truncation
                        # ("$$" is a doubled start, not a lost sentence).
                        if ln > 1:
                            c.framing_errors += 1
                        else:
                            c.skipped_bytes += 1
                        continue
                    # Complete up to "*HH", only its line ending was lost: taken as is.
                if (
                    ln > MAX_SENTENCE_CHARS
                    or ln < 4
                    or seg[-3] != 0x2A  # '*'
                    or seg[-2] not in _HEX
                    or seg[-1] not in _HEX
                    or seg.find(b"*", 1, ln - 3) != -1  # spliced remains of another sentence
                ):
                    c.framing_errors += 1
                    continue
                if checksum(seg[1:-3]) != int(seg[-2:], 16):
                    c.checksum_failures += 1
                    continue
                c.sentences += 1
                out.append(seg.decode("ascii", "replace"))
            if checked == len(guessed):
                break
            bad = _first_bad_ubx(buf, guessed, checked)
            if bad is None:
                break
            # As if that frame had been checked when it was found: a false sync, one byte.
            # The scan goes on from there checking each frame at once (a stream with many
            # bad frames would be scanned again after each).
            at, _, n_out, n_runs, counts = guessed[bad]
            del guessed[bad:], out[n_out:], runs[n_runs:]
            _set_counters(c, counts)
            c.skipped_bytes += 1
            pos = at + 1
            dropping = False
            checked = bad
            take_ubx = _ubx
        if runs and not _check_runs(runs, out, c):
            return None
        return out, pos, dropping

    def _carried_checksums(self, out: list[str | UbxFrame], c: FramerCounters) -> bool:
        """Whether the stream carried a line with ``*HH`` (valid or not) before the point
        ``_pass`` has reached with ``out`` and ``c``: earlier passes' counters, this pass's
        checksum failures and the lines in ``out`` (every frame there is a UBX frame, an
        unchecksummed line or a line with ``*HH``, the run lines not yet checked)."""
        t = self.counters
        return bool(
            t.sentences - t.unchecksummed + t.checksum_failures
            or c.checksum_failures
            or len(out) - c.ubx_frames - c.unchecksummed
        )

    @staticmethod
    def _run(run: bytes, out: list[str | UbxFrame], runs: list[_Run]) -> None:
        """Append the lines of a run (``_RUN``'s group 1) to ``out`` as text, and note them
        in ``runs`` for their checksums (``_check_runs``): the text lines themselves when
        the run is ASCII (their bytes are their characters), else its byte lines."""
        # CR occurs here only as part of a CR LF. One decode for the whole run; a replaced
        # byte stays one character, so the str lines pair up with the byte lines.
        text = run.decode("ascii", "replace")
        if run.count(b"\r") == run.count(b"\n"):  # every line ends in CR LF
            texts = text.split("\r\n")
        else:
            texts = text.replace("\r", "").split("\n")
        texts.pop()  # the empty tail after the last line end
        if run.isascii():
            runs.append((len(out), texts))
        else:
            lines = run.replace(b"\r", b"").split(b"\n")
            lines.pop()
            runs.append((len(out), lines))
        out += texts


def _check_runs(runs: list[_Run], out: list[str | UbxFrame], c: FramerCounters) -> bool:
    """Checksum the lines of ``runs`` (``_run``) all together: drop the bad ones from
    ``out`` and count them; False (nothing changed) if a line's checksum digits are not
    all hex."""
    if any(type(part[0]) is bytes for _, part in runs):  # a run not ASCII: all as bytes
        runs = [
            (i, part if type(part[0]) is bytes else list(map(_ASCII, part))) for i, part in runs
        ]
    lines: list[Any] = list(chain.from_iterable(part for _, part in runs))
    n = len(lines)
    if n < _BATCH_MIN:
        if type(lines[0]) is str:
            lines = list(map(_ASCII, lines))
        try:
            ok = bytes(checksum(line) == _LINE_XOR[line[-2:]] for line in lines)
        except KeyError:  # not hex
            return False
        if all(ok):
            c.sentences += n
            return True
    else:
        sums = bytearray()
        expected = bytearray()
        for i in range(0, n, _BATCH_LINES):
            s, e, all_hex = _line_sums(lines[i : i + _BATCH_LINES])
            if not all_hex:
                return False
            sums += s
            expected += e
        if sums == expected:
            c.sentences += n
            return True
        # 1 where a line's sum differs from what it must be
        diff = int.from_bytes(sums, "little") ^ int.from_bytes(expected, "little")
        ok = diff.to_bytes(n, "little").translate(_ZERO_IS_OK)
    # A line's place in out: its number among the lines + its run's offset.
    offsets: list[int] = []
    for start, part in runs:
        offsets += repeat(start - len(offsets), len(part))
    bad = []
    i = ok.find(0)
    while i >= 0:
        bad.append(i)
        i = ok.find(0, i + 1)
    for i in reversed(bad):
        del out[offsets[i] + i]
    c.sentences += n - len(bad)
    c.checksum_failures += len(bad)
    return True


def _skip(buf: bytes, a: int, b: int, c: FramerCounters) -> None:
    """Count the bytes ``buf[a:b]`` outside any frame (CR and LF excluded)."""
    if b - a == 2 and buf[a] == 0x0D and buf[a + 1] == 0x0A:
        return
    if b > a:
        chunk = buf[a:b]
        c.skipped_bytes += b - a - chunk.count(b"\n") - chunk.count(b"\r")


_Guess = tuple[int, int, int, int, tuple[int, ...]]  # see NmeaFramer._pass

# A complete NMEA sentence with its line ending, as it may show inside the span a UBX sync
# claims (_nmea_inside).
_SENTENCE_IN_SPAN: Final = re.compile(rb"\$([^$\r\n\xb5*]{1,126})\*([0-9A-Fa-f]{2})\r?\n")


def _nmea_inside(buf: bytes, a: int, b: int) -> bool:
    """Whether ``buf[a:b]`` holds a whole checksum-valid NMEA sentence, ``$`` to its line
    feed: then the UBX sync before it was a false one in line noise (a receiver never puts
    NMEA inside a UBX frame). Without this test a false sync claiming up to 1024 bytes held
    every sentence behind it until that many bytes had arrived (3 s at 9600 baud: fixes
    delivered seconds late, stamped with their late receive time); with it no sentence
    waits for more than its own bytes. A frame is judged on the bytes in its span that have
    arrived, so a whole frame and one arriving piecemeal are judged alike."""
    search = _SENTENCE_IN_SPAN.search
    m = search(buf, a, b)
    while m is not None:
        if checksum(m.group(1)) == int(m.group(2), 16):
            return True
        m = search(buf, m.end(), b)
    return False


def _ubx(
    buf: bytes,
    at: int,
    n: int,
    c: FramerCounters,
    guessed: list[_Guess] | None = None,
    out: list[str | UbxFrame] | None = None,
    runs: list[_Run] | None = None,
) -> tuple[int, UbxFrame | None]:
    """(bytes consumed, frame or None) at the UBX sync ``at``; 0 consumed means wait for
    more data. (``guessed``, ``out`` and ``runs`` are ``_guess_ubx``'s.)"""
    if n - at < 6:
        return 0, None
    length = buf[at + 4] | (buf[at + 5] << 8)
    if length > MAX_UBX_PAYLOAD:
        c.skipped_bytes += 1
        return 1, None
    total = 8 + length
    if _nmea_inside(buf, at + 2, min(n, at + total)):
        c.skipped_bytes += 1  # a false sync: rescan from the next byte
        return 1, None
    if n - at < total:
        return 0, None
    if ubx_checksum(buf[at + 2 : at + 6 + length]) != buf[at + 6 + length : at + total]:
        c.skipped_bytes += 1
        return 1, None  # false sync: rescan from the next byte
    c.ubx_frames += 1
    return total, _ubx_frame(buf, at, length)


def _guess_ubx(
    buf: bytes,
    at: int,
    n: int,
    c: FramerCounters,
    guessed: list[_Guess],
    out: list[str | UbxFrame],
    runs: list[_Run],
) -> tuple[int, UbxFrame | None]:
    """``_ubx`` taking a whole frame before its checksum is known: noted in ``guessed``
    with where the scan stood, for ``_first_bad_ubx``."""
    if n - at < 6:
        return 0, None
    length = buf[at + 4] | (buf[at + 5] << 8)
    if length > MAX_UBX_PAYLOAD:
        c.skipped_bytes += 1
        return 1, None
    total = 8 + length
    if _nmea_inside(buf, at + 2, min(n, at + total)):
        c.skipped_bytes += 1  # a false sync: rescan from the next byte
        return 1, None
    if n - at < total:
        return 0, None
    guessed.append((at, total, len(out), len(runs), _counts(c)))
    c.ubx_frames += 1
    return total, _ubx_frame(buf, at, length)


def _ubx_frame(buf: bytes, at: int, length: int) -> UbxFrame:
    """The UbxFrame at sync ``at``: ``UbxFrame(class, id, payload)`` (see _SET_UBX)."""
    frame = object.__new__(UbxFrame)
    set_class, set_id, set_payload = _SET_UBX
    set_class(frame, buf[at + 2])
    set_id(frame, buf[at + 3])
    set_payload(frame, buf[at + 6 : at + 6 + length])
    return frame


_COUNTERS: Final = (
    "sentences",
    "checksum_failures",
    "framing_errors",
    "ubx_frames",
    "skipped_bytes",
    "unchecksummed",
)
assert tuple(f.name for f in fields(FramerCounters)) == _COUNTERS, "update _counts"


def _counts(c: FramerCounters) -> tuple[int, ...]:
    """The counters' values (a frame at a time: written out, no loop)."""
    return (
        c.sentences,
        c.checksum_failures,
        c.framing_errors,
        c.ubx_frames,
        c.skipped_bytes,
        c.unchecksummed,
    )


def _set_counters(c: FramerCounters, counts: tuple[int, ...]) -> None:
    (
        c.sentences,
        c.checksum_failures,
        c.framing_errors,
        c.ubx_frames,
        c.skipped_bytes,
        c.unchecksummed,
    ) = counts


_FIRST: Final = operator.itemgetter(0)
_SECOND: Final = operator.itemgetter(1)
_UBX_BATCH_MIN: Final = 16  # fewer frames: ubx_checksum each
_SMALL_UBX: Final = 64  # bodies up to this long are checked in a batch of their own


def _first_bad_ubx(buf: bytes, guessed: list[_Guess], start: int) -> int | None:
    """The index of the first frame of ``guessed[start:]`` whose checksum is wrong, None
    if all are right."""
    part = guessed[start:]
    ats = list(map(_FIRST, part))
    ends = list(map(operator.add, ats, map(_SECOND, part)))  # each frame's end
    sums_at = list(map(operator.sub, ends, repeat(2)))
    bodies = list(map(buf.__getitem__, map(slice, map((2).__add__, ats), sums_at)))
    sums = list(map(buf.__getitem__, map(slice, sums_at, ends)))
    if len(bodies) < _UBX_BATCH_MIN:
        found = list(map(ubx_checksum, bodies))
    else:  # the small ones (NAV-CLOCK and the like) in a block of their own
        small = list(map((_SMALL_UBX).__ge__, map(len, bodies)))
        large = list(map(operator.not_, small))
        if list(compress(sums, small)) == _fletcher_lanes(list(compress(bodies, small))) and (
            list(compress(sums, large)) == _fletcher_lanes(list(compress(bodies, large)))
        ):
            return None
        found = list(map(ubx_checksum, bodies))
    if found == sums:
        return None
    return start + next(i for i, (f, e) in enumerate(zip(found, sums, strict=True)) if f != e)


_LOW7: Final = 0x7F
_HIGH1: Final = 0x80


def _fletcher_lanes(bodies: list[bytes]) -> list[bytes]:
    """``ubx_checksum`` of each body, all at once: the bodies are the rows of a block
    (right-aligned with zeros to the longest, W bytes: zeros before a body leave both of
    its sums at 0) and each byte column, read as one integer with a byte per body, is added
    to the running sum A and A to B, bytewise mod 256 (SWAR: the low 7 bits of each byte
    added, the top bit by XOR, so no carry crosses a byte). About 12 big-int operations per
    column, however many bodies."""
    if not bodies:
        return []
    width = max(map(len, bodies))
    block = b"".join(map(bytes.rjust, bodies, repeat(width), repeat(b"\0")))
    n = len(bodies)
    low = int.from_bytes(bytes([_LOW7]) * n, "little")
    high = int.from_bytes(bytes([_HIGH1]) * n, "little")
    a = b = 0
    for k in range(width):
        d = int.from_bytes(block[k::width], "little")
        a = ((a & low) + (d & low)) ^ ((a ^ d) & high)
        b = ((b & low) + (a & low)) ^ ((b ^ a) & high)
    return list(map(bytes, zip(a.to_bytes(n, "little"), b.to_bytes(n, "little"), strict=True)))


# ---------------------------------------------------------------------------- UBX messages


def ubx_frame(msg_class: int, msg_id: int, payload: bytes = b"") -> bytes:
    """A complete UBX frame: ``B5 62 class id len(LE16) payload CK_A CK_B``."""
    if not (0 <= msg_class <= 0xFF and 0 <= msg_id <= 0xFF):
        raise ConfigError(f"UBX class/id must be bytes, got {msg_class!r}/{msg_id!r}")
    if len(payload) > 0xFFFF:
        raise ConfigError(f"UBX payload too long: {len(payload)} bytes (max 65535)")
    body = struct.pack("<BBH", msg_class, msg_id, len(payload)) + bytes(payload)
    return UBX_SYNC + body + ubx_checksum(body)


def cfg_rate(meas_ms: int, nav_rate: int = 1, time_ref: int = 1) -> bytes:
    """UBX CFG-RATE: measurement period in ms (NEO-5: 250..65535, i.e. up to 4 Hz).

    ``time_ref`` 0 aligns to UTC, 1 to GPS time (the receiver's default).
    """
    if not 250 <= meas_ms <= 0xFFFF:
        raise ConfigError(f"CFG-RATE meas_ms must be 250..65535 ms, got {meas_ms!r}")
    if not 1 <= nav_rate <= 0xFFFF:
        raise ConfigError(f"CFG-RATE nav_rate must be 1..65535, got {nav_rate!r}")
    if time_ref not in (0, 1):
        raise ConfigError(f"CFG-RATE time_ref must be 0 (UTC) or 1 (GPS), got {time_ref!r}")
    return ubx_frame(
        UBX_CLASS_CFG, UBX_ID_CFG_RATE, struct.pack("<HHH", meas_ms, nav_rate, time_ref)
    )


def cfg_msg(message: str | tuple[int, int], rate: int | tuple[int, ...]) -> bytes:
    """UBX CFG-MSG: output rate of a message, in navigation epochs (0 disables it).

    ``message`` is an NMEA type name (``"GSV"``) or a ``(class, id)`` pair; ``rate`` an int
    (the port this is sent on) or 6 ints (one per port: I2C, UART1, UART2, USB, SPI, res.).
    """
    if isinstance(message, str):
        key = message.upper()
        if key not in NMEA_MSG_IDS:
            raise ConfigError(
                f"CFG-MSG: unknown NMEA message {message!r}; valid: {', '.join(NMEA_MSG_IDS)}"
            )
        msg_class, msg_id = UBX_CLASS_NMEA, NMEA_MSG_IDS[key]
    else:
        msg_class, msg_id = message
    rates = (rate,) if isinstance(rate, int) else tuple(rate)
    if len(rates) not in (1, 6) or not all(isinstance(r, int) and 0 <= r <= 255 for r in rates):
        raise ConfigError(f"CFG-MSG rate must be one or six ints in 0..255, got {rate!r}")
    return ubx_frame(UBX_CLASS_CFG, UBX_ID_CFG_MSG, bytes((msg_class, msg_id, *rates)))


@dataclass(frozen=True, slots=True)
class UbxAck:
    """ACK-ACK (``acked`` True) or ACK-NAK for the message ``(msg_class, msg_id)``."""

    acked: bool
    msg_class: int
    msg_id: int


def parse_ack(frame: UbxFrame) -> UbxAck | None:
    """The ACK/NAK carried by ``frame``, or None if it is another message.

    Raises ParseError for an ACK-class frame whose payload is not 2 bytes.
    """
    if frame.msg_class != UBX_CLASS_ACK or frame.msg_id not in (UBX_ID_ACK_ACK, UBX_ID_ACK_NAK):
        return None
    if len(frame.payload) != 2:
        raise ParseError(f"UBX ACK payload must be 2 bytes, got {len(frame.payload)}")
    return UbxAck(frame.msg_id == UBX_ID_ACK_ACK, frame.payload[0], frame.payload[1])


# ---------------------------------------------------------------------------- field parsing

# Field positions and parsers come from the sentence table (drivers.nmea), built once here:
# a sentence is decoded by one split on commas and one call per field read. A field that
# fails its format or range check raises FieldError (a ValueError); the sentence is dropped.


def _at(sentence: Sentence, name: str) -> tuple[int, Callable[..., Any]]:
    """Position of field ``name`` in ``sentence`` and its parser."""
    return sentence.pos(name), field_parser(sentence.field(name))


_GGA_TIME, _gga_time = _at(GGA, "time")
_GGA_LAT, _gga_lat = _at(GGA, "lat")
_GGA_LON, _gga_lon = _at(GGA, "lon")
_GGA_QUAL, _gga_quality = _at(GGA, "quality")
_GGA_SATS, _gga_sats = _at(GGA, "sats_used")
_GGA_HDOP, _gga_hdop = _at(GGA, "hdop")
_GGA_ALT, _gga_alt = _at(GGA, "alt")
_GGA_SEP, _gga_sep = _at(GGA, "geoid_sep")
_RMC_TIME, _rmc_time = _at(RMC, "time")
_RMC_STATUS, _rmc_status = _at(RMC, "status")
_RMC_LAT, _rmc_lat = _at(RMC, "lat")
_RMC_LON, _rmc_lon = _at(RMC, "lon")
_RMC_SPEED, _rmc_speed = _at(RMC, "speed")
_RMC_COURSE, _rmc_course = _at(RMC, "course")
_RMC_DATE, _rmc_date = _at(RMC, "date")
_GSA_MODE, _gsa_mode = _at(GSA, "fix_type")
_GSA_SV1 = GSA.pos("prn")
_GSA_PRN_LO = int(GSA.field("prn").lo or 0)
_GSA_PRN_HI = int(GSA.field("prn").hi or 0)
_GSA_PDOP, _gsa_dop = _at(GSA, "pdop")  # HDOP and VDOP follow, with the same range
_GSV_NUM = GSV.pos("messages")
_GSV_SEQ = GSV.pos("message")
_GSV_INVIEW, _gsv_in_view = _at(GSV, "in_view")
_GSV_SAT1, _gsv_prn = _at(GSV, "prn")
_gsv_el = field_parser(GSV.field("elevation"))
_gsv_az = field_parser(GSV.field("azimuth"))
_gsv_snr = field_parser(GSV.field("snr"))
_GSV_PRN_MAX = int(GSV.field("prn").hi or 0)
_GSV_EL_MAX = float(GSV.field("elevation").hi or 0)
_GSV_AZ_MAX = float(GSV.field("azimuth").hi or 0)
_GSV_SNR_MAX = float(GSV.field("snr").hi or 0)
_GLL_TIME, _gll_time = _at(GLL, "time")
_GLL_LAT, _gll_lat = _at(GLL, "lat")
_GLL_LON, _gll_lon = _at(GLL, "lon")
_GLL_STATUS = GLL.pos("status")
_GLL_MODE = GLL.pos("mode")
assert _GLL_STATUS == _GLL_TIME + 1 and _GLL_MODE == _GLL_TIME + 2
_ZDA_TIME, _zda_time = _at(ZDA, "time")
assert _gga_time is _rmc_time is _gll_time is _zda_time is parse_time  # see _time_of_day
_ZDA_DAY, _zda_day = _at(ZDA, "day")
_zda_month = field_parser(ZDA.field("month"))
_zda_year = field_parser(ZDA.field("year"))
assert ZDA.pos("month") == _ZDA_DAY + 1 and ZDA.pos("year") == _ZDA_DAY + 2

# A time of day's usual texts ("hhmmss", "hhmmss.ss", "hhmmss.sss") from tables: the
# microseconds of the minute "hhmm" (00:00-23:59), of the second "ss" (00-60: a leap
# second) and of the fraction. Every key is digits in range, so a text made of keys is one
# parse_time accepts, with the same value; any other text goes through parse_time.
_MINUTE_US: Final = {
    f"{h:02d}{m:02d}": (h * 60 + m) * 60_000_000 for h in range(24) for m in range(60)
}
_SECOND_US: Final = {f"{sec:02d}": sec * 1_000_000 for sec in range(61)}
_FRACTION_US: Final = {f".{c:02d}": c * 10_000 for c in range(100)} | {
    f".{c:03d}": c * 1_000 for c in range(1000)
}


@functools.lru_cache(maxsize=64)  # a time repeats in every sentence of its epoch
def _time_of_day(s: str) -> int | None:
    """``parse_time(s)`` (microseconds of the day, None if empty, FieldError if bad): three
    table reads for the usual forms, a new epoch's time being parsed once per epoch."""
    try:
        us = _MINUTE_US[s[:4]] + _SECOND_US[s[4:6]]
        return us + _FRACTION_US[s[6:]] if len(s) > 6 else us
    except KeyError:
        return parse_time(s)


_gga_time = _rmc_time = _gll_time = _zda_time = _time_of_day
assert GGA.pos("lat_hemi") == _GGA_LAT + 1 and GGA.pos("lon_hemi") == _GGA_LON + 1
assert RMC.pos("lat_hemi") == _RMC_LAT + 1 and RMC.pos("lon_hemi") == _RMC_LON + 1
assert GSA.pos("hdop") == _GSA_PDOP + 1 and GSA.pos("vdop") == _GSA_PDOP + 2
assert len(GSV.group) == 4  # _gsv_sats reads a satellite as four fields
assert _GSV_SAT1 == _GSV_INVIEW + 1  # the head is the three fields before the satellites


def _pynmea2() -> Any:
    """pynmea2, imported on first need: only sentences outside the table use it, so a NEO-5
    stream never does (and `x6wd decode` starts faster)."""
    import pynmea2

    return pynmea2


@functools.cache
def _known_types() -> frozenset[str]:
    """The sentence types pynmea2 knows (NMEA 0183 and common extensions): a talker sentence
    of one of these types that this decoder does not read still counts as decoded, any other
    as an unknown type. It knows every type of the table (tests/test_nmea_table.py)."""
    return frozenset(_pynmea2().TalkerSentence.sentence_types)


# Talker and sentence type per sentence head ("GPGGA," = text[1:7]), or None where
# pynmea2.parse must decide (proprietary, query, unknown or odd heads). Bounded, as line
# noise can make any head.
_Head = tuple[str, str] | None
_HEADS: Final[dict[str, _Head]] = {}
_HEADS_MAX: Final = 512


def _head(key: str) -> _Head:
    """The ``_HEADS`` entry for ``key`` = ``text[1:7]`` (computed and stored on a miss)."""
    head: _Head = None
    if key[5:6] == "," and key[0] != "P" and key[:5].isalnum():
        kind = key[2:5]
        if kind in SENTENCES or kind in _known_types():
            head = (key[:2], kind)
    if len(_HEADS) >= _HEADS_MAX:
        _HEADS.clear()
    _HEADS[key] = head
    return head


@dataclass(slots=True)
class _Gga:
    t_s: float
    tod_us: int | None
    lat_deg: float | None
    lon_deg: float | None
    quality: int
    sats: int | None
    hdop: float | None
    alt_m: float | None
    sep_m: float | None


@dataclass(slots=True)
class _Rmc:
    t_s: float
    tod_us: int | None
    valid: bool
    lat_deg: float | None
    lon_deg: float | None
    speed_mps: float | None
    course_deg: float | None
    day: date | None


# ---------------------------------------------------------------------------- satellite numbers
# gpsd numbers every satellite in one range (driver_nmea0183.c, nmeaid_to_prn): NMEA numbers
# 1-32 of GPS, BeiDou and Galileo collide, so a BeiDou 13 must become 413 before a GSA's
# "used" can be matched to it. The system comes from the talker (GSV, GSA) or from an NMEA
# 4.10 GSA's system id; GP and GN (and unknown talkers) leave it to the number's range.

# NMEA 4.10 system ids (GSA's last field) and the talkers that name one.
NMEA_GPS: Final = 1
NMEA_GLONASS: Final = 2
NMEA_GALILEO: Final = 3
NMEA_BEIDOU: Final = 4
NMEA_QZSS: Final = 5
_SYSTEM_OF_TALKER: Final = {
    "GL": NMEA_GLONASS,
    "GA": NMEA_GALILEO,
    "GB": NMEA_BEIDOU,
    "BD": NMEA_BEIDOU,
    "GQ": NMEA_QZSS,
    "QZ": NMEA_QZSS,
}
# gpsd's gnssid values (u-blox's numbering, gps.h struct satellite_t).
GNSSID_GPS: Final = 0
GNSSID_SBAS: Final = 1
GNSSID_GALILEO: Final = 2
GNSSID_BEIDOU: Final = 3
GNSSID_IMES: Final = 4
GNSSID_QZSS: Final = 5
GNSSID_GLONASS: Final = 6
# By number alone: (first, last NMEA number, gnssid, svid = number - offset, PRN = number + shift).
_RANGES: Final = (
    (1, 32, GNSSID_GPS, 0, 0),
    (33, 64, GNSSID_SBAS, -87, 0),  # NMEA 33-64 are SBAS PRNs 120-151
    (65, 96, GNSSID_GLONASS, 64, 0),
    (120, 158, GNSSID_SBAS, 0, 0),
    (173, 182, GNSSID_IMES, 172, 0),
    (193, 199, GNSSID_QZSS, 192, 0),
    (201, 237, GNSSID_BEIDOU, 200, 200),  # some SiRF: BeiDou 201-237, gpsd's 401-437
    (301, 356, GNSSID_GALILEO, 300, 0),
    (401, 437, GNSSID_BEIDOU, 400, 0),
)
# A named system: (gnssid, PRN base, NMEA number offsets tried in order: svid = n - offset
# for the first offset that leaves 1..99, for the vendor variants gpsd accepts).
_SYSTEMS: Final = {
    NMEA_GLONASS: (GNSSID_GLONASS, 64, (0, 64)),
    NMEA_GALILEO: (GNSSID_GALILEO, 300, (0, 100, 300)),
    NMEA_BEIDOU: (GNSSID_BEIDOU, 400, (0, 200, 400)),
    NMEA_QZSS: (GNSSID_QZSS, 192, (0, 192)),
}

_SYSTEM_IDS: Final = frozenset(str(k) for k in (NMEA_GPS, *_SYSTEMS))

SatId = tuple[int, int | None, int | None]
"""gpsd's PRN, gnssid and svid of a satellite (gnssid and svid None: no known range)."""


@functools.lru_cache(maxsize=1024)
def gpsd_satellite(system: int, number: int) -> SatId:
    """gpsd's PRN, gnssid and svid of NMEA satellite ``number`` of ``system`` (an NMEA 4.10
    system id, 0 or GPS: by the number's range, as gpsd reads GP and GN talkers). A number
    in no range keeps its value, without gnssid and svid."""
    named = _SYSTEMS.get(system)
    if named is not None:
        gnssid, base, offsets = named
        for offset in offsets:
            if 1 <= number - offset <= (32 if gnssid == GNSSID_GLONASS else 99):
                return base + number - offset, gnssid, number - offset
        return number, None, None
    for first, last, gnssid, offset, shift in _RANGES:
        if first <= number <= last:
            return number + shift, gnssid, number - offset
    return number, None, None


def talker_system(talker: str) -> int:
    """The NMEA 4.10 system id a talker names (GL, GA, GB/BD, GQ/QZ), else 0."""
    return _SYSTEM_OF_TALKER.get(talker, 0)


# gpsd's fix status (gps.h STATUS_*: 0 no fix, 1 fix, 2 DGPS, 3 RTK fixed, 4 RTK float,
# 5 dead reckoning, 7 surveyed/time, 8 simulated) for each GGA quality 0..8 (gpsd's
# processGGA: 3, PPS, is a plain fix; 7, manual input, its "time" status).
_FIX_STATUS: Final = (0, 1, 2, 1, 3, 4, 5, 7, 8)
STATUS_DGPS: Final = 2
"""The lowest status gpsd's TPV shows (0 and 1 it leaves out, as its regressions do)."""


def fix_status(quality: int) -> int:
    """gpsd's TPV ``status`` for a fix of GGA ``quality`` (1, a plain fix, if unknown)."""
    return _FIX_STATUS[quality] if type(quality) is int and 0 <= quality <= 8 else 1


_GsaValues = tuple[int | None, frozenset[int], float | None, float | None, float | None]


@functools.lru_cache(maxsize=64)
def _parse_gsa(talker: str, f: tuple[str, ...], system_id: str = "") -> _GsaValues:
    """GSA fields ``fix_type`` .. ``vdop`` of ``talker`` and the NMEA 4.10 ``system_id``
    field after them ("" if absent) -> fix mode, gpsd PRNs used (``gpsd_satellite``), PDOP,
    HDOP, VDOP.

    Memoised: a receiver repeats its GSA for as long as the constellation holds.
    """
    mode = _gsa_mode(f[0])
    prns = [s for s in f[_GSA_SV1 - _GSA_MODE : _GSA_PDOP - _GSA_MODE] if s]
    if prns and not ("".join(prns).isdigit() and "".join(prns).isascii()):
        raise FieldError("GSA PRN")
    numbers = frozenset(int(s) for s in prns)
    if len(numbers) and (min(numbers) < _GSA_PRN_LO or max(numbers) > _GSA_PRN_HI):
        raise FieldError("GSA PRN range")
    # A GN talker's GSA names its system in NMEA 4.10 (one GSA per system): without it,
    # a BeiDou GSA's 13 would mark GPS 13 used. An unknown id leaves it to the talker.
    system = talker_system(talker)
    if system_id in _SYSTEM_IDS:  # another value (or several extra fields): not one
        system = int(system_id)
    used = frozenset(gpsd_satellite(system, n)[0] for n in numbers)
    dops = f[_GSA_PDOP - _GSA_MODE :]
    return mode, used, _gsa_dop(dops[0]), _gsa_dop(dops[1]), _gsa_dop(dops[2])


@functools.lru_cache(maxsize=64)
def _gsv_head(num: str, seq: str, in_view: str) -> tuple[int, int]:
    """GSV message count and number (checked); the satellites-in-view count is checked only."""
    head = num + seq
    if len(head) != 2 or not head.isdigit() or not head.isascii():  # one digit each
        raise FieldError("GSV sequence")
    total = int(num)
    n = int(seq)
    _gsv_in_view(in_view)
    if not 1 <= n <= total:
        raise FieldError("GSV sequence")
    return total, n


# One GSV satellite: the PRN a GSA marks it used by, and its SatInfo as not used / used in
# the fix (GSA decides which at emission; both are built once, so a sky report allocates
# no SatInfo in steady state). That PRN is 0 (never used) without an SNR: gpsd marks no
# satellite used that it does not hear, as a receiver listing one signal of a satellite
# in its GSA cannot say which of the satellite's GSV signal groups it used.
_Sat = tuple[int, SatInfo, SatInfo]
# Per system (talker_system), a satellite's text "PRN,elevation,azimuth,SNR" -> _Sat: the
# same text is another satellite in another system. Bounded: noise makes new keys.
_SATS: Final[dict[int, dict[str, _Sat]]] = {}
_SATS_MAX: Final = 4096
# A GSV's satellites are its fields from the fourth on, four each: one match per satellite
# (its text; the comma after it consumed). A partial group at the end does not match: no
# three commas follow any of its positions. Possessive: a field ends at a comma, so giving
# characters back never helps (and costs time: on the NEO-5 hour's GSVs 0.60 us a sentence
# against 0.71 us with plain greedy repeats).
_GSV_GROUP: Final = re.compile(r"([^,]*+,[^,]*+,[^,]*+,[^,]*+)(?:,|\Z)")


def clear_memos() -> None:
    """Forget the decoder's memos (satellites, GSA fields): the next sentences are decoded
    afresh. They never change a result; this is for tests and memory accounting."""
    _SATS.clear()
    _parse_gsa.cache_clear()
    gpsd_satellite.cache_clear()


def gsv_groups(text: str) -> list[str]:
    """The satellites' texts (``"PRN,elevation,azimuth,SNR"``) of a GSV sentence from the
    text of its fields from the first satellite's on (``text``): groups of four fields. One
    field after whole groups is NMEA 4.10's signal id (``gsv_signal``), not a satellite; a
    satellite cut short (two or three fields left) by the end of a sentence of fewer than
    four counts, with empty fields."""
    groups: list[str] = _GSV_GROUP.findall(text)
    n_fields = text.count(",") + 1
    if n_fields % 4 > 1 and n_fields < 16:
        tail = text.split(",")[4 * len(groups) :]
        groups.append(",".join(tail + [""] * (4 - len(tail))))
    return groups


def gsv_signal(text: str) -> str:
    """The NMEA 4.10 signal id of a GSV from the text of its fields from the first
    satellite's on (``text``): the field after whole groups of four, "" if there is none;
    FieldError if it is not a hexadecimal digit string (NMEA 4.11 ids run 1-F)."""
    if text.count(",") % 4:  # not 4k + 1 fields
        return ""
    signal = text[text.rfind(",") + 1 :]
    if signal.strip(SIGNAL_DIGITS):  # (strip leaves a character only if one is not a digit)
        raise FieldError("GSV signal id")
    return signal


SIGNAL_DIGITS: Final = "0123456789ABCDEF"
"""The characters of a GSV signal id (hexadecimal, upper case)."""


def gsv_satellite(group: str, system: int = 0) -> _Sat | None:
    """The satellite of one group of ``gsv_groups`` of a GSV of ``system``
    (``talker_system``; None without a PRN: not a satellite); FieldError if a field is out
    of range. Memoised by the group's text."""
    sat = _SATS.get(system, {}).get(group)
    if sat is None:
        fields = group.split(",")
        if not fields[0]:
            return None
        sat = _gsv_sat(group, fields, system)
    return sat


def _gsv_sats(text: str, system: int = 0) -> list[_Sat]:
    """The satellites of a GSV sentence of ``system`` (``gsv_groups``; a group without a
    PRN is skipped). A satellite's fields mostly repeat from earlier epochs (elevation and
    azimuth move slowly, SNR jitters over a few values): each group is decoded once and
    memoised by its text, so a sentence whose groups are all known is one lookup each."""
    groups = gsv_groups(text)
    memo = _SATS.get(system)
    if memo is not None:
        found = list(map(memo.get, groups))
        if None not in found:
            return found  # type: ignore[return-value]
    return [sat for sat in (gsv_satellite(g, system) for g in groups) if sat is not None]


def _gsv_sat(key: str, fields: list[str], system: int = 0) -> _Sat:
    """Decode and range-check one satellite (PRN not empty) of a GSV sentence of ``system``:
    its four ``fields``, memoised under their text ``key``."""
    number, el, az, snr = _gsv_values(fields)
    prn, gnssid, svid = gpsd_satellite(system, number)
    free = SatInfo(prn, el, az, snr, False, gnssid, svid)
    sat = (prn if snr else 0, free, SatInfo(prn, el, az, snr, True, gnssid, svid))
    memo = _SATS.setdefault(system, {})
    if len(memo) >= _SATS_MAX:
        memo.clear()
    memo[key] = sat
    return sat


_SatValues = tuple[int, float | None, float | None, float | None]


def gsv_values(group: str) -> _SatValues | None:
    """PRN, elevation (deg), azimuth (deg) and SNR (dB-Hz) of one group of ``gsv_groups``
    (None without a PRN: not a satellite), as ``gsv_satellite`` decodes and checks them,
    without building its records or using its memo (``x6wd decode`` keeps its own)."""
    fields = group.split(",")
    return _gsv_values(fields) if fields[0] else None


def _gsv_values(fields: list[str]) -> _SatValues:
    """PRN, elevation, azimuth and SNR of a satellite's four ``fields`` (PRN not empty),
    range-checked (FieldError)."""
    p, e, a, r = fields
    if e and a and r and (p + e + a + r).isdigit():
        # Fast path for the usual all-integer group (the sentence is ASCII, see _decode).
        prn, el, az, snr = int(p), float(e), float(a), float(r)
        if prn > _GSV_PRN_MAX or el > _GSV_EL_MAX or az > _GSV_AZ_MAX or snr > _GSV_SNR_MAX:
            raise FieldError(p)
        return prn, el, az, snr
    prn_ = _gsv_prn(p)
    assert prn_ is not None
    return prn_, _gsv_el(e), _gsv_az(a), _gsv_snr(r)


# ---------------------------------------------------------------------------- decoder


@dataclass(frozen=True, slots=True)
class NmeaSentence:
    """One checksum-valid raw sentence (``$`` to ``*HH``) and the time it was received (s)."""

    t_s: float
    text: str


GpsOutput = GpsFix | GpsSky | NmeaSentence
"""What the decoder emits: a fix, a sky report, or a raw sentence (when asked for them)."""

# Records are built through their slot descriptors: a frozen dataclass's __init__ stores
# each field through object.__setattr__ (a lookup by name each time), which made building
# fixes and sky reports a visible part of decoding. Same objects, about twice as fast.
_SET_SENTENCE_T_S: Final = vars(NmeaSentence)["t_s"].__set__
_SET_SENTENCE_TEXT: Final = vars(NmeaSentence)["text"].__set__
_FIX_FIELDS: Final = (
    "t_s", "utc", "lat_deg", "lon_deg", "alt_m", "quality", "sats_used", "hdop", "speed_mps",
    "course_deg", "valid", "mode", "pdop", "vdop", "geoid_sep_m",
)  # fmt: skip
_SKY_FIELDS: Final = ("t_s", "satellites", "pdop", "hdop", "vdop", "utc")
assert tuple(f.name for f in fields(GpsFix)) == _FIX_FIELDS, "GpsFix changed: update _emit"
assert tuple(f.name for f in fields(GpsSky)) == _SKY_FIELDS, "GpsSky changed: update _emit_sky"
_FIX_SETTERS: Final = tuple(vars(GpsFix)[name].__set__ for name in _FIX_FIELDS)
_SKY_SETTERS: Final = tuple(vars(GpsSky)[name].__set__ for name in _SKY_FIELDS)


@dataclass(slots=True)
class DecoderCounters:
    """Decoder statistics.

    Every checksum-valid sentence (``sentences``) ends in exactly one of ``decoded``,
    ``unknown_types`` (pynmea2 has no class for it) or ``invalid_fields`` (format or range
    failure, sentence rejected whole). ``unchecksummed`` counts the sentences among them
    that came without ``*HH`` (``NmeaFramer``'s ``accept_unchecksummed``; always 0 on the
    robot's strict decoder).
    """

    sentences: int = 0
    decoded: int = 0
    checksum_failures: int = 0
    framing_errors: int = 0
    unchecksummed: int = 0  # of sentences, lines without '*HH' (accept_unchecksummed)
    unknown_types: int = 0
    invalid_fields: int = 0
    ubx_frames: int = 0
    skipped_bytes: int = 0
    fixes: int = 0
    skies: int = 0

    def as_dict(self) -> dict[str, int]:
        """Plain dict, field order preserved."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


_GGA_MEMORY_EPOCHS: Final = 3  # RMC cycles without GGA before a stream counts as RMC-only
_Handler = Callable[[str, list[str], float, list[GpsOutput]], None]
_Route = tuple[str, _Handler | None, int, int]


class GpsDecoder:
    """Sans-IO NMEA decoder: bytes (or framed sentences) + receive time -> records.

    ``feed`` returns, in stream order, an ``NmeaSentence`` for every checksum-valid sentence
    (when ``emit_sentences``) followed by any ``GpsFix``/``GpsSky`` it completes. UBX frames
    are counted and kept for ``take_ubx()``. Never raises on stream content.
    """

    gll_fixes: bool = True
    """An epoch whose only position is a valid GLL makes a fix, as in gpsd (a subclass that
    reads GLL-only logs its own way turns it off)."""

    def __init__(
        self,
        *,
        emit_sentences: bool = True,
        ubx_queue: int = 64,
        accept_unchecksummed: bool = False,
    ) -> None:
        self.framer = NmeaFramer(accept_unchecksummed=accept_unchecksummed)
        self.emit_sentences = emit_sentences
        self._counters = DecoderCounters()
        self._ubx: deque[UbxFrame] = deque(maxlen=ubx_queue)
        self._date: date | None = None
        self._date_tod_us: int | None = None  # time of day the date belongs to
        self._gga: _Gga | None = None  # held, waiting for its RMC
        self._rmc: _Rmc | None = None  # not yet emitted
        # a valid GLL of the epoch in progress (t_s, time of day, lat, lon): its fix when the
        # epoch closes without a GGA or RMC (gpsd reports GLL-only epochs too)
        self._gll: tuple[float, int, float | None, float | None] | None = None
        self._last_fix_tod: int | None = None
        self._last_fix_had_gga = False
        self._ggas_seen = 0
        self._rmcs_seen = 0
        self._rmc_after_gga = False
        self._epochs_without_gga = 0
        self._gsa_mode: int | None = None
        self._pdop: float | None = None
        self._hdop_gsa: float | None = None
        self._vdop: float | None = None
        self._used: frozenset[int] = frozenset()
        self._gsa_fresh = False  # a GSA arrived since the last time-bearing sentence
        self._gsv_talker = ""
        self._gsv_next = 0
        self._gsv_sats: list[_Sat] = []
        # talker -> (epoch index of its last complete GSV group, satellites)
        self._sky: dict[str, tuple[int, list[_Sat]]] = {}
        self._epoch_idx = 0
        self._tod_us: int | None = None
        self._utc_key: tuple[int, date, int] | None = None
        self._utc_value: datetime | None = None
        self._midnight_day: date | None = None
        self._midnight = datetime(1970, 1, 1, tzinfo=UTC)
        # Field handlers by sentence type, with the number of fields each reads (shorter
        # sentences are padded with empty fields) and the most splits its fields need
        # (-1: every field); other known types need none. A handler reads only its first
        # fields, so the split stops there (the rest of the text is one unread element).
        self._handlers: dict[str, tuple[_Handler, int, int]] = {
            # GSV: its three head fields, then the text of its satellites (_gsv_sats).
            "GSV": (self._gsv_fields, _GSV_SAT1, _GSV_SAT1),
            "GGA": (self._gga_fields, _GGA_SEP + 1, _GGA_SEP + 1),
            "RMC": (self._rmc_fields, _RMC_DATE + 1, _RMC_DATE + 1),
            # GSA: its fields to VDOP, then the rest (NMEA 4.10's system id, if any).
            "GSA": (self._gsa_fields, _GSA_PDOP + 3, _GSA_PDOP + 3),
            # GLL: to its time at least (a fix from its status and mode, when they are there)
            "GLL": (self._gll_fields, _GLL_TIME + 1, _GLL_MODE + 1),
            "ZDA": (self._zda_fields, _ZDA_DAY + 3, _ZDA_DAY + 3),
        }
        # Sentence head (text[1:7], "GPGGA,") -> (talker, handler or None, fields it reads,
        # splits),
        # or None where pynmea2.parse must decide: _HEADS joined with _handlers, per decoder.
        self._routes: dict[str, _Route | None] = {}

    @property
    def counters(self) -> DecoderCounters:
        """Current counters (framer figures merged in)."""
        c = self._counters
        f = self.framer.counters
        c.checksum_failures = f.checksum_failures
        c.framing_errors = f.framing_errors
        c.ubx_frames = f.ubx_frames
        c.skipped_bytes = f.skipped_bytes
        c.unchecksummed = f.unchecksummed
        return c

    def take_ubx(self) -> list[UbxFrame]:
        """UBX frames received since the last call (oldest first; at most ``ubx_queue``)."""
        out = list(self._ubx)
        self._ubx.clear()
        return out

    def assume_date(self, day: date, tod_us: int) -> None:
        """Date epochs with ``day`` (whose UTC time of day is ``tod_us``, microseconds) until
        a sentence brings a date. For a log reader that has found the log's first date
        further on: epochs before it are then dated from it, within 12 h either side (the
        rule by which a date is carried over midnight), instead of having no UTC."""
        self._date = day
        self._date_tod_us = tod_us

    def assume_utc(self, utc: datetime) -> None:
        """:meth:`assume_date` from a dated epoch's UTC (the first a log reader found)."""
        tod_us = (utc.hour * 3600 + utc.minute * 60 + utc.second) * 1_000_000
        self.assume_date(utc.date(), tod_us + utc.microsecond)

    def reset(self) -> None:
        """Forget partial frames and the epoch in progress (after a reconnect)."""
        self.framer.reset()
        self._gga = None
        self._rmc = None
        self._gll = None
        self._gsv_next = 0
        self._gsv_sats = []

    def feed(self, data: bytes, t_s: float) -> list[GpsOutput]:
        """Decode ``data`` received at ``t_s`` (s, host monotonic clock)."""
        out: list[GpsOutput] = []
        self._decode(self.framer.scan(data), t_s, out)
        return out

    def feed_sentence(self, text: str, t_s: float) -> list[GpsOutput]:
        """Decode one already-framed sentence (``$...*HH``, line ending optional).

        The checksum and length are still verified and counted like framed bytes.
        """
        out: list[GpsOutput] = []
        line = text.strip()
        f = self.framer.counters
        if (
            len(line) > MAX_SENTENCE_CHARS
            or len(line) < 4
            or line[0] != "$"
            or line[-3] != "*"
            or "$" in line[1:]
            or "*" in line[1:-3]
        ):
            f.framing_errors += 1
            return out
        try:
            expected = int(line[-2:], 16)
        except ValueError:
            f.framing_errors += 1
            return out
        if checksum(line[1:-3].encode("ascii", "replace")) != expected or not line[-2:].isalnum():
            f.checksum_failures += 1
            return out
        f.sentences += 1
        self._decode([line], t_s, out)
        return out

    def flush(self, t_s: float | None = None) -> list[GpsOutput]:
        """Close the epoch in progress (end of stream): emit a held GGA or pending RMC; a
        last line without its line end is counted as skipped bytes (:meth:`NmeaFramer.end`)."""
        out: list[GpsOutput] = []
        self.framer.end()
        self._close_epoch(out)
        return out

    # -- internals

    def _decode(self, frames: list[str | UbxFrame], t_s: float, out: list[GpsOutput]) -> None:
        """Decode checksum-valid sentences, queue UBX frames; in stream order.

        This is every sentence's path, so it is one loop over locals: call and attribute
        overheads are a large part of a sentence's cost. Each sentence counts once in
        ``sentences`` and once in ``decoded``, ``unknown_types`` or ``invalid_fields``.
        """
        c = self._counters
        emit = self.emit_sentences
        routes = self._routes
        new_object = object.__new__
        set_t_s = _SET_SENTENCE_T_S
        set_text = _SET_SENTENCE_TEXT
        n_sentences = n_decoded = 0
        try:
            for text in frames:
                if type(text) is not str:
                    self._ubx.append(text)  # type: ignore[arg-type]
                    continue
                n_sentences += 1
                if emit:  # NmeaSentence(t_s, text), see _SET_SENTENCE_T_S
                    record = new_object(NmeaSentence)
                    set_t_s(record, t_s)
                    set_text(record, text)
                    out.append(record)
                if not text.isascii():  # NMEA is ASCII; replaced bytes mean corruption
                    c.invalid_fields += 1
                    continue
                key = text[1:7]
                try:
                    route = routes[key]
                except KeyError:
                    route = self._route(key)
                if route is not None:
                    talker, handler, fields_needed, splits = route
                    if handler is None:  # a known type whose fields are not read
                        n_decoded += 1
                        continue
                    d = text[7:-3].split(",", splits)
                else:
                    pynmea2 = _pynmea2()
                    try:
                        msg = pynmea2.parse(text[:-3] if text[-3:-2] == "*" else text)
                    except pynmea2.SentenceTypeError:
                        c.unknown_types += 1
                        continue
                    except Exception:  # pynmea2's proprietary parsers raise anything
                        c.invalid_fields += 1
                        continue
                    attrs = msg.__dict__
                    talker = attrs.get("talker", "")
                    d = msg.data
                    entry = self._handlers.get(attrs.get("sentence_type", ""))
                    if entry is None:
                        n_decoded += 1
                        continue
                    handler, fields_needed, splits = entry
                    if splits >= 0:
                        d = ",".join(d).split(",", splits)
                if len(d) < fields_needed:  # pynmea2 reads missing fields as empty
                    d += [""] * (fields_needed - len(d))
                try:
                    handler(talker, d, t_s, out)
                except (IndexError, ValueError):  # FieldError is a ValueError
                    c.invalid_fields += 1
                    continue
                n_decoded += 1
        finally:
            c.sentences += n_sentences
            c.decoded += n_decoded

    def _route(self, key: str) -> _Route | None:
        """The ``_routes`` entry for sentence head ``key`` (computed and stored on a miss)."""
        try:
            head = _HEADS[key]
        except KeyError:
            head = _head(key)
        route: _Route | None = None
        if head is not None:
            talker, kind = head
            handler, fields_needed, splits = self._handlers.get(kind, (None, 0, -1))
            route = (talker, handler, fields_needed, splits)
        if len(self._routes) >= _HEADS_MAX:
            self._routes.clear()
        self._routes[key] = route
        return route

    def _gga_fields(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        gga = _Gga(
            t_s,
            _gga_time(d[_GGA_TIME]),
            _gga_lat(d[_GGA_LAT], d[_GGA_LAT + 1]),
            _gga_lon(d[_GGA_LON], d[_GGA_LON + 1]),
            _gga_quality(d[_GGA_QUAL]) or 0,
            _gga_sats(d[_GGA_SATS]),
            _gga_hdop(d[_GGA_HDOP]),
            _gga_alt(d[_GGA_ALT]),
            _gga_sep(d[_GGA_SEP]),
        )
        self._on_gga(gga, out)

    def _rmc_fields(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        status = _rmc_status(d[_RMC_STATUS])
        speed_kn = _rmc_speed(d[_RMC_SPEED])
        course = _rmc_course(d[_RMC_COURSE])
        rmc = _Rmc(
            t_s,
            _rmc_time(d[_RMC_TIME]),
            status == "A",
            _rmc_lat(d[_RMC_LAT], d[_RMC_LAT + 1]),
            _rmc_lon(d[_RMC_LON], d[_RMC_LON + 1]),
            None if speed_kn is None else speed_kn * MPS_PER_KNOT,
            None if course is None else wrap360(course),
            _rmc_date(d[_RMC_DATE]),
        )
        self._on_rmc(rmc, out)

    def _gsa_fields(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        self._on_gsa(talker, d)

    def _gll_fields(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        tod = _gll_time(d[_GLL_TIME])
        if tod != self._tod_us:  # (_on_time's test, inlined: GLL repeats its epoch's time)
            self._on_time(tod, out)
        if (
            tod is not None
            and len(d) > _GLL_STATUS
            and d[_GLL_STATUS] == "A"
            and (len(d) <= _GLL_MODE or d[_GLL_MODE][:1] != "N")
        ):
            lat = _gll_lat(d[_GLL_LAT], d[_GLL_LAT + 1])
            self._gll = (t_s, tod, lat, _gll_lon(d[_GLL_LON], d[_GLL_LON + 1]))

    def _zda_fields(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        self._on_zda(d, out)

    def _on_time(self, tod: int | None, out: list[GpsOutput]) -> None:
        """A time-bearing sentence: a different time closes the epoch in progress."""
        if tod is None:
            return
        if tod != self._tod_us:
            self._close_epoch(out)
            self._tod_us = tod
            self._gsa_fresh = False
            self._epoch_idx += 1

    def _close_epoch(self, out: list[GpsOutput]) -> None:
        gga = self._gga
        rmc = self._rmc
        gll = self._gll
        self._gga = None
        self._rmc = None
        self._gll = None
        if gga is not None:
            self._emit(gga, rmc if rmc is not None and rmc.tod_us == gga.tod_us else None, out)
        elif rmc is not None and rmc.tod_us != self._last_fix_tod:
            self._emit(None, rmc, out)
        elif gll is not None and gll[1] != self._last_fix_tod and self.gll_fixes:
            # an epoch whose only position is a valid GLL: a fix without speed or course
            t_s, tod, lat, lon = gll
            self._emit(None, _Rmc(t_s, tod, True, lat, lon, None, None, None), out)

    def _on_gga(self, gga: _Gga, out: list[GpsOutput]) -> None:
        self._epochs_without_gga = 0
        self._ggas_seen += 1
        if gga.tod_us is None:
            self._emit(gga, None, out)
            return
        if gga.tod_us != self._tod_us:
            self._on_time(gga.tod_us, out)
        rmc = self._rmc
        if rmc is not None and rmc.tod_us == gga.tod_us:
            self._rmc = None
            self._rmc_after_gga = False
            self._emit(gga, rmc, out)
        elif self._rmc_after_gga or (self._rmcs_seen == 0 and self._ggas_seen == 1):
            # Order unknown on the first GGA of a stream: wait one sentence for its RMC.
            self._gga = gga
        else:
            self._emit(gga, None, out)

    def _on_rmc(self, rmc: _Rmc, out: list[GpsOutput]) -> None:
        self._rmcs_seen += 1
        if rmc.tod_us is None:
            if self._epochs_without_gga > _GGA_MEMORY_EPOCHS:
                self._emit(None, rmc, out)
            return
        if rmc.tod_us != self._tod_us:
            self._epochs_without_gga += 1
        self._on_time(rmc.tod_us, out)  # an epoch of another time closes with its own date
        if rmc.day is not None:
            self._date = rmc.day
            self._date_tod_us = rmc.tod_us
        gga = self._gga
        if gga is not None and gga.tod_us == rmc.tod_us:
            self._gga = None
            self._rmc_after_gga = True
            self._emit(gga, rmc, out)
        elif self._last_fix_tod == rmc.tod_us and self._last_fix_had_gga:
            # Its GGA came first and was already emitted: hold GGAs from now on.
            self._rmc_after_gga = True
        elif self._epochs_without_gga > _GGA_MEMORY_EPOCHS:
            self._emit(None, rmc, out)
        else:
            self._rmc = rmc

    def _on_gsa(self, talker: str, d: list[str]) -> None:
        # (the rest of the text after VDOP: one field, the system id, or anything else)
        system_id = d[_GSA_PDOP + 3] if len(d) > _GSA_PDOP + 3 else ""
        self._set_gsa(_parse_gsa(talker, tuple(d[_GSA_MODE : _GSA_PDOP + 3]), system_id))

    def _set_gsa(self, gsa: _GsaValues) -> None:
        """Take a GSA's fix mode, PRNs used and DOPs (``_parse_gsa``)."""
        mode, used, pdop, hdop, vdop = gsa
        if self._gsa_fresh:  # several GSAs per cycle (one per constellation)
            self._used |= used
        else:
            self._used = used
            self._gsa_fresh = True
        self._gsa_mode = mode
        self._pdop, self._hdop_gsa, self._vdop = pdop, hdop, vdop

    def _gsv_fields(self, talker: str, d: list[str], t_s: float, out: list[GpsOutput]) -> None:
        # d: the three head fields and the text of the rest (split at most _GSV_SAT1 times)
        total, seq = _gsv_head(d[_GSV_NUM], d[_GSV_SEQ], d[_GSV_INVIEW])
        if len(d) > _GSV_SAT1:
            text = d[_GSV_SAT1]
            sats = self._sats_of(talker, text)
            # One group per talker and signal: NMEA 4.10 receivers send a GPS group per
            # signal (L1, L5, ...); each must not replace the other.
            talker += gsv_signal(text)
        else:
            sats = []
        if seq == 1:
            self._gsv_talker = talker
            self._gsv_sats = sats
        elif seq == self._gsv_next and talker == self._gsv_talker:
            self._gsv_sats.extend(sats)
        else:  # a lost part: drop the group
            self._gsv_next = 0
            return
        self._gsv_next = seq + 1
        if seq == total:
            self._gsv_next = 0
            self._sky[talker] = (self._epoch_idx, self._gsv_sats)
            self._gsv_sats = []
            self._emit_sky(t_s, out)

    def _sats_of(self, talker: str, text: str) -> list[_Sat]:
        """The satellites of a GSV sentence's satellite fields ``text`` from ``talker`` as
        the sky keeps them (``x6wd decode`` keeps them as their report texts instead)."""
        return _gsv_sats(text, talker_system(talker))

    def _on_zda(self, d: list[str], out: list[GpsOutput]) -> None:
        tod = _zda_time(d[_ZDA_TIME])
        day = _zda_day(d[_ZDA_DAY])
        month = _zda_month(d[_ZDA_DAY + 1])
        year = _zda_year(d[_ZDA_DAY + 2])
        if tod is not None and day and month and year:
            try:
                self._date = date(year, month, day)
            except ValueError:
                raise FieldError("ZDA date") from None
            self._date_tod_us = tod
        self._on_time(tod, out)

    def _utc(self, tod: int | None) -> datetime | None:
        if tod is None or self._date is None or self._date_tod_us is None:
            return None
        key = (tod, self._date, self._date_tod_us)
        if key == self._utc_key:  # fix and sky of one epoch share it
            return self._utc_value
        self._utc_key = key
        self._utc_value = self._utc_compute(tod, self._date, self._date_tod_us)
        return self._utc_value

    def _utc_compute(self, tod: int, day: date, date_tod_us: int) -> datetime:
        # A time far before the date's own time of day means midnight passed since.
        if tod < date_tod_us - 43_200_000_000:
            day = day + timedelta(days=1)
        elif tod > date_tod_us + 43_200_000_000:
            day = day - timedelta(days=1)
        if tod >= 86_400_000_000:  # 23:59:60, a leap second: datetime cannot hold it
            return datetime(day.year, day.month, day.day, 23, 59, 59, 999_999, tzinfo=UTC)
        # The day's midnight plus the time of day (0 <= tod < 24 h: the same day, exactly
        # the datetime of its hours, minutes, seconds and microseconds), kept for the day.
        if day != self._midnight_day:
            self._midnight_day = day
            self._midnight = datetime(day.year, day.month, day.day, tzinfo=UTC)
        return self._midnight + timedelta(microseconds=tod)

    def _fix_head(
        self, gga: _Gga | None, rmc: _Rmc | None
    ) -> tuple[float, int | None, bool, int, float | None, float | None]:
        """(t_s, time of day, valid, mode, lat, lon) of the fix made of ``gga`` and/or
        ``rmc``, noted as the last fix and counted (``_emit``; a subclass may write the fix
        its own way)."""
        if gga is not None:
            valid = gga.quality > 0 and (rmc is None or rmc.valid)
            tod = gga.tod_us
            t_s = gga.t_s if rmc is None else max(gga.t_s, rmc.t_s)
            lat, lon = gga.lat_deg, gga.lon_deg
        else:
            assert rmc is not None
            valid = rmc.valid
            tod = rmc.tod_us
            t_s = rmc.t_s
            lat, lon = rmc.lat_deg, rmc.lon_deg
        if lat is None or lon is None:
            valid = False
        if not valid:
            mode = 1
        elif self._gsa_mode in (2, 3):
            mode = self._gsa_mode
        elif gga is not None and gga.alt_m is not None:
            mode = 3
        else:
            mode = 2
        if tod is not None:
            self._last_fix_tod = tod
            self._last_fix_had_gga = gga is not None
        self._counters.fixes += 1
        return t_s, tod, valid, mode, lat, lon

    def _emit(self, gga: _Gga | None, rmc: _Rmc | None, out: list[GpsOutput]) -> None:
        t_s, tod, valid, mode, lat, lon = self._fix_head(gga, rmc)
        # One call per field, in _FIX_FIELDS order (unrolled: a loop over the setters costs
        # more than the setters themselves).
        (set_t_s, set_utc, set_lat, set_lon, set_alt, set_quality, set_sats, set_hdop,
         set_speed, set_course, set_valid, set_mode, set_pdop, set_vdop, set_sep,
         ) = _FIX_SETTERS  # fmt: skip
        fix = object.__new__(GpsFix)
        set_t_s(fix, t_s)
        set_utc(fix, self._utc(tod))
        set_lat(fix, lat)
        set_lon(fix, lon)
        if gga is None:
            set_alt(fix, None)
            set_quality(fix, 0)
            set_sats(fix, None)
            set_hdop(fix, self._hdop_gsa)
            set_sep(fix, None)
        else:
            set_alt(fix, gga.alt_m)
            set_quality(fix, gga.quality)
            set_sats(fix, gga.sats)
            set_hdop(fix, gga.hdop)
            set_sep(fix, gga.sep_m)
        if rmc is None:
            set_speed(fix, None)
            set_course(fix, None)
        else:
            set_speed(fix, rmc.speed_mps)
            set_course(fix, rmc.course_deg)
        set_valid(fix, valid)
        set_mode(fix, mode)
        set_pdop(fix, self._pdop)
        set_vdop(fix, self._vdop)
        out.append(fix)

    def _emit_sky(self, t_s: float, out: list[GpsOutput]) -> None:
        used = self._used
        sats: list[SatInfo] = []
        # A constellation that stopped reporting drops out after one missed epoch.
        oldest = self._epoch_idx - 1
        for epoch_idx, group in self._sky.values():
            if epoch_idx >= oldest:
                sats += [in_use if prn in used else free for prn, free, in_use in group]
        self._counters.skies += 1
        set_t_s, set_sats, set_pdop, set_hdop, set_vdop, set_utc = _SKY_SETTERS  # _SKY_FIELDS
        sky = object.__new__(GpsSky)
        set_t_s(sky, t_s)
        set_sats(sky, tuple(sats))
        set_pdop(sky, self._pdop)
        set_hdop(sky, self._hdop_gsa)
        set_vdop(sky, self._vdop)
        set_utc(sky, self._utc(self._tod_us))
        out.append(sky)


__all__ = [
    "MAX_SENTENCE_CHARS",
    "NMEA_MSG_IDS",
    "DecoderCounters",
    "Frame",
    "FramerCounters",
    "GpsDecoder",
    "GpsOutput",
    "NmeaFrame",
    "NmeaFramer",
    "NmeaSentence",
    "UbxAck",
    "UbxFrame",
    "cfg_msg",
    "cfg_rate",
    "fix_status",
    "gpsd_satellite",
    "parse_ack",
    "ubx_checksum",
    "ubx_frame",
]
