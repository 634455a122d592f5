"""GrblStage against scripted bytes: each request's exact bytes and GRBL's exact replies."""

from __future__ import annotations

import pytest

from app.devices.errors import DeviceTimeout, GrblAlarm, GrblError, ProtocolError
from app.devices.grbl import GRBL_ALARMS, GRBL_ERRORS, GrblStage, parse_status
from tests.devices.scripted import ScriptedPort

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"
SETTINGS = b"$20=1\r\n$110=1200.000\r\n$120=50.000\r\n$122=40.000\r\n$132=45.000\r\nok\r\n"
IDLE0 = b"<Idle|MPos:0.000,0.000,0.000|Bf:15,128|FS:0,0>\r\n"


def connected(script_after=(), clock=None, **kw):
    port = ScriptedPort([(b"\x18", BANNER), (b"$$\n", SETTINGS), (b"?", IDLE0), *script_after], clock=clock)
    stage = GrblStage(port, **kw, clock=port.clock)
    stage.connect()
    return stage, port


def test_connect_sends_soft_reset_then_reads_settings_and_status():
    stage, port = connected()
    assert bytes(port.sent) == b"\x18$$\n?"
    assert stage.version == "1.1h"
    assert stage.settings[122] == 40.0
    assert stage.acceleration_mm_s2 == 40.0  # Z acceleration, $122
    assert stage.travel_range_mm == (0.0, 45.0)  # machine [-45, 0] seen as travel into the specimen
    assert stage.last_status.state == "Idle" and stage.last_status.travel_mm == 0.0
    assert port.done()


def test_connect_without_banner_says_what_is_wrong():
    port = ScriptedPort([(b"\x18", b"")])
    stage = GrblStage(port, clock=port.clock, banner_timeout_s=0.5)
    with pytest.raises(DeviceTimeout, match="no GRBL banner.*soft reset"):
        stage.connect()


def test_banner_after_garbage_and_alarm_lock_message():
    port = ScriptedPort([(b"\x18", b"\x00\xff\r\n" + BANNER + b"[MSG:'$H'|'$X' to unlock]\r\n"),
                         (b"$$\n", SETTINGS),
                         (b"?", b"<Alarm|MPos:0.000,0.000,-1.000|FS:0,0>\r\n"),
                         (b"$X\n", b"[MSG:Caution: Unlocked]\r\nok\r\n")])
    stage = GrblStage(port, clock=port.clock)
    st = stage.connect()
    assert st.alarm and st.travel_mm == 1.0
    stage.unlock()
    assert stage.messages == ["MSG:'$H'|'$X' to unlock", "MSG:Caution: Unlocked"]
    assert port.done()


@pytest.mark.parametrize("call, request_bytes", [
    (lambda s: s.jog_by(1.5, 0.5), b"$J=G91 G21 Z-1.500 F30.0\n"),
    (lambda s: s.jog_to(2.25, 1.0), b"$J=G53 G21 Z-2.250 F60.0\n"),
    (lambda s: s.start_move(3.0, 2.0), b"$J=G53 G21 Z-3.000 F120.0\n"),
    (lambda s: s.linear_move(4.0, 0.25), b"G90 G1 Z-4.000 F15.0\n"),
    (lambda s: s.linear_move(-0.5, 0.25, relative=True), b"G91 G1 Z0.500 F15.0\n"),
    (lambda s: s.build_info(), b"$I\n"),
])
def test_commands_are_byte_exact(call, request_bytes):
    stage, port = connected([(request_bytes, b"ok\r\n")])
    call(stage)
    assert port.done()


def test_axis_and_sign_are_settings():
    stage, port = connected([(b"$J=G53 G21 X3.000 F60.0\n", b"ok\r\n"),
                             (b"?", b"<Jog|MPos:1.000,0.000,0.000|FS:60,0>\r\n")], axis="X", into_specimen=1)
    stage.jog_to(3.0, 1.0)
    st = stage.query_status()
    assert st.travel_mm == 1.0 and st.state == "Jog" and st.speed_mm_s == 1.0


@pytest.mark.parametrize("method, byte", [("feed_hold", b"!"), ("cycle_resume", b"~"), ("jog_cancel", b"\x85"),
                                          ("request_status", b"?")])
def test_realtime_bytes_have_no_line_end(method, byte):
    stage, port = connected([(byte, b"")])
    getattr(stage, method)()
    assert bytes(port.sent).endswith(byte) and port.done()


def test_error_reply_becomes_grbl_error_with_meaning():
    stage, port = connected([(b"$J=G53 G21 Z-99.000 F60.0\n", b"error:15\r\n")])
    with pytest.raises(GrblError) as info:
        stage.jog_to(99.0, 1.0)
    assert info.value.code == 15
    assert "Jog travel exceeds max travel" in str(info.value)
    assert "$J=G53 G21 Z-99.000 F60.0" in str(info.value)


def test_alarm_line_becomes_grbl_alarm_with_meaning():
    stage, port = connected([(b"?", b"ALARM:1\r\n<Alarm|MPos:0.000,0.000,-3.000|FS:0,0>\r\n")])
    stage.request_status()
    with pytest.raises(GrblAlarm) as info:
        stage.poll(0.1)
    assert info.value.code == 1 and "Hard limit" in str(info.value)
    assert stage.last_status.alarm  # the status that came with it was kept


def test_every_code_has_a_meaning():
    assert set(GRBL_ERRORS) >= set(range(1, 18)) | set(range(20, 39))
    assert set(GRBL_ALARMS) == set(range(1, 10))
    assert "unknown GRBL error code 99" in str(GrblError(99))


def test_no_reply_times_out_in_plain_words():
    stage, port = connected([(b"G90 G1 Z-1.000 F60.0\n", b"")])
    with pytest.raises(DeviceTimeout, match="stopped answering"):
        stage.linear_move(1.0, 1.0)


def test_finish_hold_resets_a_completed_hold_and_keeps_position():
    stage, port = connected([
        (b"?", b"<Hold:1|MPos:0.000,0.000,-2.000|FS:30,0>\r\n"),
        (b"?", b"<Hold:0|MPos:0.000,0.000,-2.010|FS:0,0>\r\n"),
        (b"\x18", BANNER),
        (b"?", b"<Idle|MPos:0.000,0.000,-2.010|FS:0,0>\r\n"),
    ])
    st = stage.finish_hold()
    assert st.state == "Idle" and st.travel_mm == pytest.approx(2.01)
    assert port.done()


def test_emergency_stop_sends_hold_and_jog_cancel_at_once():
    stage, port = connected([(b"!\x85", b""), (b"?", b"<Jog|MPos:0.000,0.000,-2.000|FS:30,0>\r\n"),
                             (b"?", b"<Idle|MPos:0.000,0.000,-2.010|FS:0,0>\r\n")])
    st = stage.emergency_stop()
    assert st.state == "Idle" and port.done()


def test_partial_lines_and_noise_are_tolerated():
    stage, port = connected([(b"?", b"<Run|MPos:0.000,0.00")])
    stage.request_status()
    assert stage.poll(0.01) == []
    port.push(b"0,-1.500|FS:60,0>\r\n\x07#garbage\r\nok\r\n")
    new = stage.poll(0.01)
    assert [s.travel_mm for s in new] == [1.5]
    assert stage.ignored_lines == 1


@pytest.mark.parametrize("text, state, sub, mpos, wpos, feed", [
    ("<Idle|MPos:1.000,2.000,-3.500|FS:0,0>", "Idle", None, (1, 2, -3.5), None, 0),
    ("<Jog|WPos:0.000,0.000,-1.250|Bf:14,127|FS:120,0|WCO:0.000,0.000,-0.500>", "Jog", None, None,
     (0, 0, -1.25), 120),
    ("<Hold:1|MPos:0.000,0.000,-2.000|Bf:15,128|FS:45.5,0|Ov:100,100,100>", "Hold", 1, (0, 0, -2), None, 45.5),
    ("<Run|MPos:0.000,0.000,-2.000|F:500>", "Run", None, (0, 0, -2), None, 500),
    ("<Alarm|MPos:0.000,0.000,0.000|FS:0,0|Pn:Z>", "Alarm", None, (0, 0, 0), None, 0),
])
def test_status_reports_parse(text, state, sub, mpos, wpos, feed):
    r = parse_status(text)
    assert (r.state, r.substate, r.mpos, r.wpos, r.feed_mm_min) == (state, sub, mpos, wpos, feed)


def test_wpos_reports_use_the_last_wco():
    stage, port = connected([
        (b"?", b"<Idle|WPos:0.000,0.000,-1.000|FS:0,0|WCO:0.000,0.000,-0.500>\r\n"),
        (b"?", b"<Idle|WPos:0.000,0.000,-2.000|FS:0,0>\r\n"),
    ])
    assert stage.query_status().travel_mm == pytest.approx(1.5)
    assert stage.query_status().travel_mm == pytest.approx(2.5)
    assert stage.last_report.wco is None  # WCO only comes now and then; the driver remembers it


def test_malformed_status_is_a_protocol_error():
    with pytest.raises(ProtocolError):
        parse_status("<Idle|FS:0,0>")
    with pytest.raises(ProtocolError):
        parse_status("<Idle|MPos:1.0,x,3|FS:0,0>")
