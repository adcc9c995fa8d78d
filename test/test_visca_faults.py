"""Issue 15, VISCA fault cases: bad options, bad replies and unsolicited packets, over a real pty.

Every CLI case runs ``fixego ptz`` in a thread with a hard limit, so a hang fails the test instead of
stalling the suite. Options must be refused before anything is sent (exit 2, one stderr line); camera
faults must end in one JSON error line (exit 1) within bounded time; unsolicited packets (a network
change above all) must never complete a move early. The emulator runs at 115200 baud to keep this short.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time

import pytest

from fixego_ros.visca import protocol as vp
from fixego_ros.visca.driver import ViscaCamera, measure_limits
from fixego_ros.visca.emulator import ViscaEmulator
from fixego_ros.visca.profiles import PROFILES, CameraProfile, get_profile

D30 = PROFILES['evi_d30']
NETWORK_CHANGE = vp.network_change(1)          # 90 38 FF


@pytest.fixture
def silent_emu():
    """A camera that reads everything and never answers: any unbounded wait on it hangs."""
    with ViscaEmulator('evi_d30', baud=115200) as emu:
        emu.faults.silent = True
        yield emu


def _cli(argv: list[str], capsys, limit_s: float = 15.0) -> tuple[int, str, str, float]:
    """``fixego ARGV`` in a thread: (exit code, stdout, stderr, seconds); fails on a hang or an exception."""
    from fixego_ros.cli import main
    box: dict[str, object] = {}

    def target() -> None:
        try:
            box['rc'] = main(argv)
        except BaseException as e:      # SystemExit included: our options all parse
            box['exc'] = e

    th = threading.Thread(target=target, daemon=True)
    t0 = time.monotonic()
    th.start()
    th.join(limit_s)
    elapsed = time.monotonic() - t0
    assert not th.is_alive(), f'fixego {" ".join(argv)} still running after {limit_s} s (hang)'
    if 'exc' in box:
        raise AssertionError(f'fixego {" ".join(argv)} raised {box["exc"]!r}') from box['exc']  # type: ignore[misc]
    cap = capsys.readouterr()
    return int(box['rc']), cap.out, cap.err, elapsed  # type: ignore[call-overload]


def _json_error(out: str) -> dict:
    lines = out.splitlines()
    assert len(lines) == 1, out
    d = json.loads(lines[0])
    assert d['ok'] is False
    return d


# ------------------------------------------------------------------------------------ bad options

BAD_OPTIONS = [
    (['--timeout', 'nan', 'query'], '--timeout'),          # the reported hang
    (['--timeout', 'inf', 'query'], '--timeout'),
    (['--timeout=-inf', 'goto', '1', '1'], '--timeout'),
    (['--timeout', '0', 'query'], '--timeout'),
    (['--timeout', '-0.5', 'home'], '--timeout'),
    (['--timeout', '1e9', 'version'], '--timeout'),
    (['--baud', '0', 'query'], '--baud'),                  # the reported ZeroDivisionError
    (['--baud', '-9600', 'query'], '--baud'),
    (['--baud', '12345', 'query'], '--baud'),
    (['--baud', '99999999999999999999', 'query'], '--baud'),
    (['--address', '0', 'query'], '--address'),
    (['--address', '8', 'query'], '--address'),
    (['--address', '-1', 'reset'], '--address'),
    (['goto', 'inf', '0'], 'PAN_DEG'),                     # the reported OverflowError
    (['goto', '--', '-inf', '0'], 'PAN_DEG'),
    (['goto', 'nan', '0'], 'PAN_DEG'),
    (['goto', '0', 'nan'], 'TILT_DEG'),
    (['goto', '--', '0', '-inf'], 'TILT_DEG'),
    (['goto', '1e400', '0'], 'PAN_DEG'),                   # parses as inf
    (['goto', '1e308', '1e308'], 'PAN_DEG'),
    (['goto', '100.5', '0'], 'PAN_DEG'),                   # D30: pan +-100 deg
    (['goto', '0', '-25.5'], 'TILT_DEG'),                  # D30: tilt +-25 deg
    (['calibrate', '--settle', 'nan'], '--settle'),
    (['calibrate', '--settle', '-1'], '--settle'),
    (['calibrate', '--settle', 'inf'], '--settle'),
    (['calibrate', '--settle', '1e9'], '--settle'),
    (['calibrate', '--out', '/nonexistent-dir/x.json'], '--out'),
    (['--profile', 'evi_nope', 'query'], 'evi_nope'),
]


@pytest.mark.parametrize('args,named', BAD_OPTIONS, ids=[' '.join(a) for a, _ in BAD_OPTIONS])
def test_bad_option_is_one_stderr_line_exit_2_and_nothing_sent(silent_emu, capsys, args, named):
    rc, out, err, elapsed = _cli(['ptz', '--port', silent_emu.port, '--baud', '115200', *args], capsys)
    assert rc == 2 and out == ''
    assert len(err.splitlines()) == 1 and err.startswith('fixego ptz: ') and named in err, err
    assert 'Traceback' not in err
    assert silent_emu.stats['rx_packets'] == 0         # refused before the port was opened
    assert elapsed < 2.0


@pytest.mark.parametrize('content', [
    '{not json', '[1, 2]', '{"name": "x"}',
    json.dumps(dict(D30.to_dict(), colour='red')),
    json.dumps(dict(D30.to_dict(), pan_units_per_deg=float('nan'))),
    json.dumps(dict(D30.to_dict(), pan_speeds_deg_s=[])),
    json.dumps(dict(D30.to_dict(), tilt_min=400)),
    json.dumps(dict(D30.to_dict(), version=[1, 2, 3, 0])),
    json.dumps({'profile': dict(D30.to_dict(), pan_max=1e400)}),
], ids=['syntax', 'list', 'missing', 'unknown-field', 'nan-units', 'no-speeds', 'tilt-min-gt-max', 'no-sockets',
        'inf-limit'])
def test_unusable_profile_file_is_exit_2(silent_emu, capsys, tmp_path, content):
    path = tmp_path / 'prof.json'
    path.write_text(content)
    rc, out, err, _ = _cli(['ptz', '--port', silent_emu.port, '--profile', str(path), 'query'], capsys)
    assert rc == 2 and out == '' and len(err.splitlines()) == 1 and str(path) in err, err
    with pytest.raises(ValueError, match=r'prof\.json'):
        get_profile(str(path))


@pytest.mark.parametrize('args', [['--timeout', 'nan', 'query'], ['goto', 'inf', '0'], ['--baud', '0', 'query']])
def test_reported_cases_as_a_process(silent_emu, args):
    """The three reports exactly as a user runs them: a separate process, exit 2, one line, no traceback."""
    proc = subprocess.run([sys.executable, '-m', 'fixego_ros.cli', 'ptz', '--port', silent_emu.port, *args],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stdout == ''
    assert len(proc.stderr.splitlines()) == 1 and proc.stderr.startswith('fixego ptz: '), proc.stderr


# ------------------------------------------------------------------------------------ driver arguments

@pytest.mark.parametrize('kwargs', [
    {'timeout_s': math.nan}, {'timeout_s': math.inf}, {'timeout_s': 0.0}, {'timeout_s': -1.0}, {'timeout_s': 1e9},
    {'baud': 0}, {'baud': -9600}, {'baud': 12345}, {'baud': math.nan}, {'baud': 9600.5},
    {'address': 0}, {'address': 8}, {'address': math.inf},
    {'backoff_s': (math.nan, 1.0)}, {'backoff_s': (1.0, 0.5)},
], ids=lambda k: repr(k))
def test_driver_constructor_rejects_unusable_parameters(kwargs):
    with pytest.raises(ValueError):
        ViscaCamera('/dev/null', **kwargs)


def test_driver_accepts_profile_rates_and_documented_rates():
    assert ViscaCamera('/dev/null', baud=38400).baud == 38400
    assert ViscaCamera('/dev/null', baud=9600.0).baud == 9600
    odd = CameraProfile('odd', -10, 10, -10, 10, 1.0, 1.0, (1.0,), (1.0,), baud_rates=(4800,))
    assert ViscaCamera('/dev/null', baud=4800, profile=odd).baud == 4800
    with pytest.raises(ValueError, match='4800'):
        ViscaCamera('/dev/null', baud=4800)


def test_driver_calls_reject_nonfinite_values_before_sending(visca_rig):
    emu, cam = visca_rig
    before = emu.stats['rx_packets']
    calls = [
        lambda: cam.goto_deg(math.inf, 0.0), lambda: cam.goto_deg(0.0, math.nan),
        lambda: cam.absolute(math.nan, 0), lambda: cam.absolute(0, 0, timeout_s=math.inf),
        lambda: cam.absolute(0, 0, timeout_s=math.nan), lambda: cam.absolute(0, 0, pan_speed=math.inf),
        lambda: cam.relative(math.inf, 0), lambda: cam.relative(1, 0, timeout_s=-1.0),
        lambda: cam.drive(math.nan, 0), lambda: cam.zoom_to(math.inf),
        lambda: cam.command(vp.home(1), 'Home', completion_timeout_s=math.nan),
        lambda: cam.wait_idle(math.inf), lambda: measure_limits(cam, settle_s=math.nan),
        lambda: measure_limits(cam, timeout_s=math.inf),
    ]
    for call in calls:
        with pytest.raises(ValueError):
            call()
    time.sleep(0.05)
    assert emu.stats['rx_packets'] == before
    with pytest.raises(ValueError, match='finite'):
        D30.pan_units(math.inf)
    assert cam.position() == (0, 0)


# ------------------------------------------------------------------------------------ bounded waits

@pytest.mark.parametrize('action', [['query'], ['goto', '5', '-1'], ['home'], ['reset'], ['version'],
                                    ['calibrate', '--settle', '0.05']])
def test_silent_camera_every_action_ends_bounded(silent_emu, capsys, action):
    rc, out, err, elapsed = _cli(['ptz', '--port', silent_emu.port, '--baud', '115200', '--timeout', '0.2',
                                  *action], capsys)
    assert rc == 1 and 'ViscaTimeoutError' in _json_error(out)['error']
    assert 'Traceback' not in err and elapsed < 3.0
    assert silent_emu.stats['rx_packets'] >= 1             # it did talk to the camera


def test_garbage_flood_times_out_bounded_then_recovers(visca_rig):
    emu, cam = visca_rig
    emu.faults.inject(bytes(range(0x10, 0x7F)) * 40)       # ~4.5 kB without a terminator: ~0.4 s of line
    t0 = time.monotonic()
    with pytest.raises(vp.ViscaTimeoutError):
        cam.position()
    assert time.monotonic() - t0 < 1.0
    time.sleep(0.4)
    assert cam.position() == (0, 0)
    assert cam.stats['garbage_bytes'] > 1000


# ------------------------------------------------------------------------------------ bad replies

BAD_REPLIES = [
    (['query'], [bytes.fromhex('9050000000FF')], 'ViscaProtocolError', 'data bytes'),          # truncated
    (['query'], [bytes.fromhex('90500F0F0F1F00000000FF')], 'ViscaProtocolError', 'nibble'),    # not nibbles
    (['query'], [vp.position_reply(1, 0x7FFF, 0)], 'ViscaProtocolError', '32767'),            # 3723 deg
    (['query'], [vp.position_reply(2, 0, 0)], 'ViscaTimeoutError', 'camera address 2'),      # wrong address
    (['query'], [bytes.fromhex('123456FF')], 'ViscaTimeoutError', 'reply to Pan-tiltPosInq'),  # garbage
    (['query'], [vp.error_reply(1, 0, vp.ERR_SYNTAX)], 'ViscaSyntaxError', 'syntax'),
    (['query'], [b''], 'ViscaTimeoutError', 'Pan-tiltPosInq'),                                 # lost
    (['version'], [vp.inquiry_reply(1, b'\x00\x01')], 'ViscaProtocolError', 'expected 7'),
    (['goto', '5', '-1'], [vp.error_reply(1, 1, vp.ERR_NOT_EXECUTABLE)], 'NotExecutableError', 'not executable'),
    (['goto', '5', '-1'], [vp.error_reply(1, 0, vp.ERR_BUFFER_FULL)], 'BufferFullError', 'buffer full'),
    (['goto', '5', '-1'], [vp.ack(2, 1)], 'ViscaTimeoutError', 'ACK for AbsolutePosition'),    # wrong address
    (['home'], [bytes.fromhex('9041')], 'ViscaTimeoutError', 'ACK for Home'),                  # no terminator
    (['home'], [vp.ack(1, 0)], 'ViscaTimeoutError', 'ACK for Home'),                           # socket 0
    (['reset'], [vp.error_reply(1, 0, 0x7E)], 'ViscaReplyError', '7E'),                        # unknown code
]


@pytest.mark.parametrize('action,replies,kind,text', BAD_REPLIES,
                         ids=[f'{" ".join(a)}:{b"|".join(r).hex()}' for a, r, _, _ in BAD_REPLIES])
def test_bad_reply_is_one_json_error_within_bounded_time(visca_rig, capsys, action, replies, kind, text):
    emu, cam = visca_rig
    cam.close()
    emu.faults.replace_replies(*replies)
    rc, out, err, elapsed = _cli(['ptz', '--port', emu.port, '--baud', '115200', '--timeout', '0.2', *action],
                                 capsys)
    error = _json_error(out)['error']
    assert rc == 1 and error.startswith(kind + ':') and text in error, error
    assert 'Traceback' not in err and elapsed < 3.0


# ------------------------------------------------------------------------------------ position range

@pytest.mark.parametrize('pan,tilt', [(0x7FFF, 0), (-0x8000, 0), (881, 0), (-881, 12), (0, 301), (0, -301)])
def test_position_outside_profile_range_is_a_counted_protocol_error(visca_rig, pan, tilt):
    emu, cam = visca_rig
    emu.faults.position_override = (pan, tilt)
    errors, comm = cam.stats['protocol_errors'], cam.comm_errors
    with pytest.raises(vp.ViscaProtocolError) as info:
        cam.position()
    msg = str(info.value)
    assert f'pan {pan} units' in msg and f'tilt {tilt} units' in msg
    assert '-880..880' in msg and '-300..300' in msg                      # the range it broke
    assert cam.stats['protocol_errors'] == errors + 1 and cam.comm_errors == comm + 1
    emu.faults.position_override = None
    assert cam.position() == (0, 0)                                       # nothing stale left on the line


def test_cli_query_reports_the_out_of_range_value(visca_rig, capsys):
    emu, cam = visca_rig
    cam.close()
    emu.faults.position_override = (0x7FFF, 0)                           # pan 3723 deg on a +-100 deg head
    rc, out, _, _ = _cli(['ptz', '--port', emu.port, '--baud', '115200', 'query'], capsys)
    d = _json_error(out)
    assert rc == 1 and '32767' in d['error'] and '3724 deg' in d['error'] and 'range' in d['error']
    assert d['stats']['protocol_errors'] == 1


def test_calibrate_measures_beyond_the_profile_but_refuses_impossible_readings(capsys):
    wide_tilt = CameraProfile('wide', -44, 88, -24, 320, 8.8, 12.0, D30.pan_speeds_deg_s, D30.tilt_speeds_deg_s)
    with ViscaEmulator(wide_tilt, baud=115200) as emu:
        rc, out, _, _ = _cli(['ptz', '--port', emu.port, '--baud', '115200', 'calibrate', '--settle', '0.05'],
                             capsys)
        assert rc == 0, out
        assert json.loads(out)['limits'] == {'pan_min': -44, 'pan_max': 88, 'tilt_min': -24, 'tilt_max': 320}
        cam = ViscaCamera(emu.port, baud=115200, timeout_s=0.2).open()
        emu.faults.position_override = (0x7FFF, 0)
        with pytest.raises(vp.ViscaProtocolError, match='32767'):
            measure_limits(cam, settle_s=0.0, timeout_s=1.0)
        cam.close()


# ------------------------------------------------------------------------------------ unsolicited packets

UNSOLICITED = [
    ('network-change', NETWORK_CHANGE),
    ('network-change-cam2', vp.network_change(2)),
    ('completion-other-socket', vp.completion(1, 2)),
    ('completion-socket-0', vp.completion(1, 0)),
    ('completion-other-camera', vp.completion(2, 1)),
    ('ack-running-socket', vp.ack(1, 1)),
    ('ack-other-socket', vp.ack(1, 2)),
    ('error-idle-socket', vp.error_reply(1, 2, vp.ERR_NOT_EXECUTABLE)),
    ('error-socket-0', vp.error_reply(1, 0, vp.ERR_SYNTAX)),
    ('address-set', bytes.fromhex('883002FF')),
    ('position-reply', vp.position_reply(1, 100, 100)),
]


def _tx_times(emu: ViscaEmulator, pkt: bytes) -> list[float]:
    return [t for t, d, p in list(emu.log) if d == 'tx' and p == pkt]   # a copy: the emulator thread appends


@pytest.mark.parametrize('name,pkt', UNSOLICITED, ids=[n for n, _ in UNSOLICITED])
def test_unsolicited_packet_mid_move_does_not_complete_it(visca_rig, name, pkt):
    emu, cam = visca_rig
    emu.faults.inject_mid_motion(pkt, 0.4)
    socket = cam.absolute(264, 0, wait=True)              # 30 deg at 80 deg/s: ~0.38 s
    assert emu.pan_tilt_units() == (264, 0), 'returned before the camera finished the move'
    t_ack = _tx_times(emu, vp.ack(1, socket))[0]
    t_injected = _tx_times(emu, pkt)[-1]                   # the last: an injected ACK repeats the real one
    t_done = _tx_times(emu, vp.completion(1, socket))[-1]
    assert t_ack < t_injected < t_done                     # the packet really arrived mid-move
    assert cam.stats['unsolicited'] >= 1 and cam.busy_sockets == {}
    assert cam.stats['network_changes'] == name.startswith('network-change')
    assert cam.position() == (264, 0)


def test_cli_goto_survives_network_change_mid_move(visca_rig, capsys):
    emu, cam = visca_rig
    cam.close()
    emu.faults.inject_mid_motion(NETWORK_CHANGE, 0.5)
    rc, out, err, _ = _cli(['ptz', '--port', emu.port, '--baud', '115200', 'goto', '30', '0'], capsys)
    assert rc == 0 and err == ''
    d = json.loads(out)
    assert d['ok'] and d['pan_units'] == 264 and d['pan_deg'] == pytest.approx(30.0)
    assert any(p == NETWORK_CHANGE for _, k, p in list(emu.log) if k == 'tx')


def test_stray_completion_before_the_ack_is_not_taken(visca_rig):
    emu, cam = visca_rig
    emu.faults.inject(vp.completion(1, 0))                # 90 50 FF waiting in the input before the command
    time.sleep(0.05)
    socket = cam.absolute(264, 0, wait=True)
    assert socket in (1, 2) and emu.pan_tilt_units() == (264, 0)
    assert cam.stats['unsolicited'] == 1


def test_stray_ack_on_a_running_socket_is_not_taken(visca_rig):
    emu, cam = visca_rig
    zoom_socket = cam.zoom_to(0x3FF, wait=False)          # ~2 s of zoom holds its socket
    emu.faults.inject(vp.ack(1, zoom_socket))
    time.sleep(0.05)
    socket = cam.absolute(264, 0, wait=True)
    assert socket != zoom_socket and emu.pan_tilt_units() == (264, 0)
    assert cam.busy_sockets == {zoom_socket: 'CAM_Zoom'}
    cam.wait_idle(5.0)
    assert cam.busy_sockets == {} and cam.zoom_position() == 0x3FF


def test_ack_after_network_change_and_lost_completion_recovers(visca_rig):
    emu, cam = visca_rig
    # the zoom's completion is lost: the driver still thinks its socket is running
    emu.faults.replace_replies(vp.ack(1, 1), b'')
    assert cam.zoom_to(0x10, wait=False) == 1
    time.sleep(0.1)
    assert cam.busy_sockets == {1: 'CAM_Zoom'}
    # a network change says the camera may have restarted: an ACK on that socket is then believed
    emu.faults.inject(NETWORK_CHANGE)
    time.sleep(0.05)
    assert cam.absolute(88, 0, wait=True) == 1
    assert emu.pan_tilt_units() == (88, 0) and cam.busy_sockets == {}
    assert cam.stats['lost_completions'] == 1 and cam.stats['network_changes'] == 1


# ------------------------------------------------------------------------------ camera model (CAM_VersionInq)
def test_profiles_list_only_the_documented_model_ids():
    """Sony's manuals give 0402 (EVI-D30/D31) and 040E (EVI-D70); nothing for the D100 and G20, left unchecked.
    An emulated camera answers its profile's version, so a checked profile must list that model."""
    assert {n: p.model_ids for n, p in PROFILES.items()} == {
        'evi_d30': (0x0402,), 'evi_d70': (0x040E,), 'evi_d100': (), 'evi_g20': ()}
    for p in PROFILES.values():
        assert not p.model_ids or p.version[1] in p.model_ids
    with pytest.raises(ValueError, match='model_ids'):
        CameraProfile(**dict(D30.to_dict(), model_ids=(0x10000,)))


@pytest.mark.parametrize('name', ['evi_d30', 'evi_d70'])
def test_emulated_camera_matches_its_profile(name):
    from fixego_ros.visca.driver import check_model
    with ViscaEmulator(name, baud=115200) as emu:
        cam = ViscaCamera(emu.port, baud=115200, profile=name, timeout_s=0.2).open()
        try:
            c = check_model(cam)
        finally:
            cam.close()
    assert c.outcome == 'match' and c.version['model'] == PROFILES[name].version[1], c.message
    assert f'{PROFILES[name].version[1]:#06x}' in c.message and name in c.message


def test_another_model_is_a_mismatch_naming_expected_and_found(visca_rig):
    from fixego_ros.visca.driver import check_model
    emu, cam = visca_rig
    emu.faults.version_override = (0x0020, 0x040E, 0x0100, 2)      # an EVI-D70 behind an evi_d30 profile
    c = check_model(cam)
    assert c.outcome == 'mismatch' and c.expected == (0x0402,) and c.version['model'] == 0x040E
    assert 'expects model 0x0402 (EVI-D30/D31' in c.message and 'answers model 0x040e (EVI-D70/P)' in c.message
    assert '\n' not in c.message
    assert cam.comm_errors == 0 and cam.position() == (0, 0)        # the link itself is fine


def test_a_profile_without_model_ids_is_not_checked():
    from fixego_ros.visca.driver import check_model
    with ViscaEmulator('evi_g20', baud=115200) as emu:
        cam = ViscaCamera(emu.port, baud=115200, profile='evi_g20', timeout_s=0.2).open()
        try:
            emu.faults.version_override = (0x0001, 0x0402, 0x0100, 2)
            c = check_model(cam)
        finally:
            cam.close()
    assert c.outcome == 'unchecked' and c.version['model'] == 0x0402 and 'lists no model id' in c.message


@pytest.mark.parametrize('fault,error', [('silent', 'ViscaTimeoutError'), ('syntax_error', 'ViscaSyntaxError')])
def test_unanswered_version_inquiry_is_bounded_and_the_link_goes_on(visca_rig, fault, error):
    """Old firmware may not know CAM_VersionInq: silence ends at the reply timeout, a syntax error at once;
    either is 'no_answer' (never an exception) and the next inquiry works."""
    from fixego_ros.visca.driver import check_model
    emu, cam = visca_rig
    emu.faults.version_reply = fault
    t0 = time.monotonic()
    c = check_model(cam)
    assert time.monotonic() - t0 < cam.timeout_s + 0.5
    assert c.outcome == 'no_answer' and c.version is None and error in c.message and 'evi_d30' in c.message
    assert cam.position() == (0, 0)
