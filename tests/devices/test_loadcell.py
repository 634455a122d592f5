"""The ELC-1 load-cell protocol and driver, byte for byte."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.devices.errors import DeviceError, DeviceTimeout
from app.devices.loadcell import AsciiLoadCell, crc8, frame, sample_body, unframe
from tests.devices.scripted import ScriptedPort


def test_crc8_check_value():
    # CRC-8/SMBUS (poly 0x07, init 0, no reflection): the catalogue check value of "123456789".
    assert crc8(b"123456789") == 0xF4
    assert crc8(b"") == 0


def test_frame_layout():
    assert frame("OK,STOP,0") == b"$OK,STOP,0*" + f"{crc8(b'OK,STOP,0'):02X}".encode() + b"\r\n"
    line = frame(sample_body(42, 420000, 1.23456, 0))
    assert line.startswith(b"$S,42,420000,+1.2346,00*") and line.endswith(b"\r\n")
    assert unframe(line.rstrip(b"\r\n")) == "S,42,420000,+1.2346,00"


def test_unframe_rejects_bad_crc_and_skips_garbage_before_dollar():
    good = frame("S,1,10000,+0.5000,00").rstrip(b"\r\n")
    assert unframe(b"\x00\xfe@@" + good) == "S,1,10000,+0.5000,00"
    bad = good.replace(b"0.5000", b"0.6000")
    assert unframe(bad) is None
    assert unframe(good[:-1]) is None
    assert unframe(b"S,1,2,3,00*00") is None


@settings(max_examples=300, deadline=None)
@given(seq=st.integers(0, 65535), t_us=st.integers(0, 2**32 - 1), force=st.floats(-50, 50),
       flags=st.integers(0, 3), pos=st.integers(0, 200), bit=st.integers(0, 7))
def test_a_single_flipped_bit_is_never_read_as_a_force(seq, t_us, force, flags, pos, bit):
    line = frame(sample_body(seq, t_us, force, flags)).rstrip(b"\r\n")
    i = pos % len(line)
    corrupted = bytearray(line)
    corrupted[i] ^= 1 << bit
    if corrupted[i] in (0x0A,):
        return  # a flipped bit that makes a line feed splits the line: two bad lines, still no force
    body = unframe(bytes(corrupted))
    # Dropped, or unchanged, or (a flip that made a new '$' with a chance CRC match) not a sample line.
    assert body is None or body == unframe(line) or not body.startswith("S,")


def _cell(script, **kw):
    port = ScriptedPort(script)
    return AsciiLoadCell(port, clock=port.clock, **kw), port


def test_identify_tare_start_stop_are_byte_exact():
    cell, port = _cell([
        (b"ID?\n", frame("ID,Acme,LC-20,SN123,2.1,20.000")),
        (b"TARE\n", frame("OK,TARE,+0.0123")),
        (b"START 250\n", frame("OK,START,250")),
        (b"STOP\n", frame("S,0,4000,+1.0000,00") + frame("OK,STOP,1")),
    ])
    info = cell.identify()
    assert (info.vendor, info.model, info.serial, info.firmware, info.full_scale_N) == \
        ("Acme", "LC-20", "SN123", "2.1", 20.0)
    assert cell.tare() == pytest.approx(0.0123)
    cell.start(250)
    assert cell.streaming and cell.rate_hz == 250
    cell.stop()
    assert not cell.streaming
    [s] = cell.read_samples()  # the sample in flight before the STOP reply is kept
    assert (s.seq, s.device_time_s, s.force_N) == (0, 0.004, 1.0)
    assert port.done()


def test_error_reply_is_a_device_error_in_plain_words():
    cell, port = _cell([(b"START 5000\n", frame("ERR,2,RATE OUT OF RANGE 1..2000"))])
    with pytest.raises(DeviceError, match="refused 'START 5000': RATE OUT OF RANGE"):
        cell.start(5000)
    assert not cell.streaming


def test_silence_times_out():
    cell, port = _cell([(b"ID?\n", b"")])
    with pytest.raises(DeviceTimeout, match="stopped answering"):
        cell.identify()


def test_corrupted_lines_are_dropped_and_counted_partial_lines_buffered():
    cell, port = _cell([(b"START 100\n", frame("OK,START,100"))])
    cell.start(100)
    lines = [frame(sample_body(i, 10000 * (i + 1), 0.1 * i, 0)) for i in range(6)]
    bad = bytearray(lines[2])
    bad[8] ^= 0x04  # corrupt a digit of the timestamp/force
    stream = lines[0] + lines[1] + bytes(bad) + b"\x13\x37noise\r\n" + lines[3] + lines[4][:9]
    port.push(stream)
    got = cell.read_samples(0.01)
    assert [s.seq for s in got] == [0, 1, 3]
    assert cell.bad_lines == 2
    assert cell.lost_samples == 1  # seq 2 was dropped
    port.push(lines[4][9:] + lines[5])
    assert [s.seq for s in cell.read_samples(0.01)] == [4, 5]
    assert [s.force_N for s in got] == [0.0, 0.1, pytest.approx(0.3)]


def test_flags_and_wraparound():
    cell, port = _cell([(b"START 1000\n", frame("OK,START,1000"))])
    cell.start(1000)
    port.push(frame(sample_body(65535, 2**32 - 1000, 20.0, 0x01)) + frame(sample_body(0, 0, -1.0, 0x02)))
    a, b = cell.read_samples(0.01)
    assert a.saturated and not a.fault and b.fault and not b.saturated
    assert b.seq == 65536 and b.device_time_s == pytest.approx(2**32 * 1e-6)
    assert cell.lost_samples == 0


def test_samples_outside_streaming_are_not_returned():
    cell, port = _cell([])
    port.push(frame(sample_body(0, 0, 1.0, 0)))
    assert cell.read_samples(0.01) == []
