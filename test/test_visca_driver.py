"""Driver against the emulator over a real pty: every command round-trips, every error reply surfaces
as its typed error, and injected faults (silence, garbage, corruption, disconnect) recover in bounded
time. One test runs at real 9600-baud timing; the rest at 115200 to keep the suite short."""

from __future__ import annotations

import json
import math
import sys
import threading
import time

import pytest

from fixego_ros.visca import protocol as vp
from fixego_ros.visca.driver import SWITCH_INTERVAL_S, ViscaCamera, prompt_serial_threads
from fixego_ros.visca.emulator import ViscaEmulator
from fixego_ros.visca.profiles import PROFILES, CameraProfile


def test_real_9600_timing_and_round_trips():
    emu = ViscaEmulator('evi_d30', baud=9600, start_pan_deg=-3.0, start_tilt_deg=2.0)
    try:
        cam = ViscaCamera(emu.start(), baud=9600).open()
        t0 = time.monotonic()
        r = cam.position_timed()
        rtt = time.monotonic() - t0
        assert (r.pan, r.tilt) == (PROFILES['evi_d30'].pan_units(-3.0), 24)
        assert rtt >= 16 * 10 / 9600 * 0.95          # 5 + 11 bytes at 9600 baud cannot be faster
        # sampled after the inquiry's 5 bytes were in and before the reply's 11 went out
        assert t0 + 5 * 10 / 9600 <= r.earliest <= r.latest <= time.monotonic() - 11 * 10 / 9600
        assert r.window_s == r.latest - r.earliest
        assert cam.address_set() == 1
        assert cam.version() == {'vendor': 1, 'model': 0x0402, 'rom': 0x0100, 'max_socket': 2}
        # short absolute move at speed 0x18 (80 deg/s): 5 deg -> ~60 ms of motion, completion after it
        t0 = time.monotonic()
        cam.absolute(44, -12, wait=True)
        assert time.monotonic() - t0 >= 0.05
        assert cam.position() == (44, -12)
        p, q = emu.pan_tilt_rad()
        assert p == pytest.approx(math.radians(5.0)) and q == pytest.approx(math.radians(-1.0))
        cam.relative(-88, 24, wait=True)
        assert cam.position_deg() == pytest.approx((-5.0, 1.0))
        cam.home()
        assert cam.position() == (0, 0)
        cam.close()
    finally:
        emu.stop()


def test_all_commands_round_trip(visca_rig):
    emu, cam = visca_rig
    cam.if_clear(broadcast=True)
    cam.if_clear()
    assert cam.power_state() is True
    cam.power(False)
    assert cam.power_state() is False and not emu.powered
    cam.power(True)
    assert emu.powered
    cam.zoom_to(0x100)
    assert cam.zoom_position() == 0x100 == emu.zoom
    cam.drive(3, 0)                                  # right at 10 deg/s
    time.sleep(0.15)
    cam.stop()
    pan, tilt = cam.position()
    assert pan > 5 and tilt == 0
    time.sleep(0.05)
    assert cam.position() == (pan, tilt)             # stopped means stopped
    cam.drive(-0x18, -0x14)
    time.sleep(0.1)
    cam.stop()
    assert cam.position()[1] < 0
    cam.reset()
    assert cam.position() == (0, 0)
    cam.goto_deg(2.0, -1.0)
    assert cam.position() == (PROFILES['evi_d30'].pan_units(2.0), -12)
    assert cam.busy_sockets == {}


def test_error_replies_are_typed(visca_rig):
    _, cam = visca_rig
    with pytest.raises(vp.ViscaSyntaxError):
        cam.absolute(881, 0, check_range=False)       # beyond the D30's +-880
    with pytest.raises(ValueError):
        cam.absolute(881, 0)                          # the driver refuses before sending
    with pytest.raises(vp.ViscaSyntaxError):
        cam.command(vp.packet(1, 0x01, 0x06, 0x02, 0, 1, *vp.encode_position(0), *vp.encode_position(0)))
    with pytest.raises(vp.ViscaSyntaxError):
        cam.command(vp.packet(1, 0x01, 0x7E, 0x55))   # unknown command
    with pytest.raises(vp.MessageLengthError):
        cam.command(bytes((0x81,) + (0x01,) * 16 + (0xFF,)))
    # buffer full: a zoom and a pan/tilt motion hold both sockets; another pan/tilt needs a third
    cam.zoom_to(0x3FF, wait=False)
    cam.absolute(800, 0, pan_speed=1, wait=False)
    with pytest.raises(vp.BufferFullError):
        cam.absolute(0, 0, wait=False)
    # cancel the running motion: its socket reports 'cancelled'; cancelling an idle socket: no socket
    motion_socket = next(s for s, n in cam.busy_sockets.items() if n == 'AbsolutePosition')
    cam.cancel(motion_socket)
    with pytest.raises(vp.NoSocketError):
        cam.cancel(motion_socket)
    cam.if_clear()
    cam.power(False)
    with pytest.raises(vp.NotExecutableError):
        cam.home()
    cam.power(True)
    cam.home()
    assert cam.stats['reply_errors'] >= 7


def test_silence_times_out_bounded_then_recovers(visca_rig):
    emu, cam = visca_rig
    emu.faults.silent = True
    t0 = time.monotonic()
    with pytest.raises(vp.ViscaTimeoutError):
        cam.position()
    with pytest.raises(vp.ViscaTimeoutError):
        cam.home()
    assert time.monotonic() - t0 < 2.0
    emu.faults.silent = False
    assert cam.position() == (0, 0)
    assert cam.stats['timeouts'] == 2


def test_garbage_and_unsolicited_bytes_are_skipped(visca_rig):
    emu, cam = visca_rig
    cam.goto_deg(1.0, 1.0)
    for junk in (b'\x12\x34\xff', b'\x90\x38\xff', b'\x00\x07', b'\xa0\x51\xff', b'\x90\x41\xff' * 0 + b'\x55'):
        emu.faults.inject(junk)
        assert cam.position() == (9, 12)
    assert cam.stats['garbage_bytes'] > 0 and cam.stats['unsolicited'] >= 2


def test_corrupt_and_dropped_bytes_never_hang(visca_rig):
    emu, cam = visca_rig
    emu.faults.drop_prob = 0.02            # ~35 % of 11-byte replies damaged one way or another
    emu.faults.corrupt_prob = 0.02
    t0 = time.monotonic()
    ok = failed = 0
    for i in range(40):
        try:
            pos = cam.position()
            # a corrupted nibble can still decode; a wrong value must be rare, a hang never
            ok += pos == (0, 0)
        except vp.ViscaError:
            failed += 1
        if i % 10 == 0:
            try:
                cam.absolute(0, 0, wait=True, timeout_s=0.5)
            except vp.ViscaError:
                failed += 1
    assert time.monotonic() - t0 < 20.0
    assert ok >= 15 and failed >= 1
    emu.faults.drop_prob = emu.faults.corrupt_prob = 0.0
    deadline = time.monotonic() + 2.0
    while True:                                   # back to a clean link within bounded time
        try:
            assert cam.position() == (0, 0)
            break
        except vp.ViscaError:
            assert time.monotonic() < deadline


def test_disconnect_mid_command_and_reconnect(visca_rig):
    emu, cam = visca_rig
    cam.close()
    cam = ViscaCamera(emu.link_path, baud=115200, timeout_s=0.2, backoff_s=(0.02, 0.2)).open()
    errors: list[BaseException] = []

    def slow_move():
        try:
            cam.absolute(880, 0, pan_speed=1, wait=True)     # ~30 s at 3.3 deg/s: cut off mid-way
        except BaseException as e:
            errors.append(e)

    th = threading.Thread(target=slow_move)
    th.start()
    time.sleep(0.2)
    emu.faults.disconnect(0.4)
    th.join(timeout=5.0)
    assert not th.is_alive()
    assert errors and isinstance(errors[0], vp.ViscaDisconnectedError)
    t0 = time.monotonic()
    while True:
        try:
            pan, _ = cam.position()
            break
        except vp.ViscaDisconnectedError:
            assert time.monotonic() - t0 < 5.0, 'did not reconnect'
            time.sleep(0.02)
    assert 0 < pan < 880                                     # stopped where the power went
    assert cam.stats['disconnects'] >= 1 and cam.stats['reconnects'] >= 1
    cam.home()
    assert cam.position() == (0, 0)
    cam.close()


def test_ptz_cli_against_emulator(tmp_path, capsys):
    from fixego_ros.cli import main
    small = CameraProfile('tiny', -44, 88, -24, 36, 8.8, 12.0, PROFILES['evi_d30'].pan_speeds_deg_s,
                          PROFILES['evi_d30'].tilt_speeds_deg_s)
    with ViscaEmulator(small, baud=115200) as emu:
        base = ['ptz', '--port', emu.port, '--baud', '115200', '--profile', 'evi_d30']
        assert main([*base, 'goto', '5', '-1']) == 0
        out = json.loads(capsys.readouterr().out)
        assert out['pan_units'] == 44 and out['tilt_units'] == -12 and out['pan_deg'] == pytest.approx(5.0)
        assert main([*base, 'query']) == 0
        assert json.loads(capsys.readouterr().out)['tilt_deg'] == pytest.approx(-1.0)
        assert main([*base, 'version']) == 0
        assert json.loads(capsys.readouterr().out)['max_socket'] == 2
        assert main([*base, 'home']) == 0
        assert json.loads(capsys.readouterr().out)['pan_units'] == 0
        prof = tmp_path / 'measured.json'
        emu.faults.version_override = (0x0001, 0x0402, 0x0100, 2)
        assert main([*base, 'calibrate', '--settle', '0.1', '--out', str(prof)]) == 0
        limits = json.loads(capsys.readouterr().out)['limits']
        assert limits == {'pan_min': -44, 'pan_max': 88, 'tilt_min': -24, 'tilt_max': 36}
        assert json.loads(prof.read_text())['profile']['model_ids'] == [0x0402]   # the measured device's model
        assert main(['ptz', '--port', emu.port, '--baud', '115200', '--profile', str(prof),
                     'goto', '9', '2']) == 0          # the measured profile is usable as --profile
        assert json.loads(capsys.readouterr().out)['pan_units'] == 79
        assert main([*base, 'goto', '50', '0']) == 1     # outside the device range: error JSON, exit 1
        assert json.loads(capsys.readouterr().out)['ok'] is False
    assert main(['ptz', '--port', '/nonexistent/tty', 'query']) == 1
    assert 'ViscaDisconnectedError' in json.loads(capsys.readouterr().out)['error']


def test_an_event_the_emulator_reaches_late_happens_when_it_is_handled():
    """The emulator's thread shares the CPU (and the GIL) with whatever hosts it. An event it reaches late - an
    inquiry to answer, a motion to start - happens then, as on a busy camera: dated back to when it was due, a
    late reply would look sampled earlier than the host can tell, and a motion would rewrite what the renderer
    already showed."""
    emu = ViscaEmulator('evi_d30', baud=9600)
    try:
        emu.start()
        got: list[float] = []
        t_post = time.monotonic()
        emu._post(lambda now: emu._schedule(now - 1.0, got.append))      # due a second ago
        deadline = time.monotonic() + 2.0
        while not got and time.monotonic() < deadline:
            time.sleep(0.005)
        assert got and t_post <= got[0] <= time.monotonic()
    finally:
        emu.stop()


def test_serial_threads_take_the_gil_promptly():
    """Starting the emulator (or a servo loop) shortens the interpreter's thread switch interval, so a thread whose
    serial bytes have arrived is not kept waiting ~5 ms by another thread of the process; a shorter one set by the
    application is kept."""
    old = sys.getswitchinterval()
    try:
        sys.setswitchinterval(0.005)
        emu = ViscaEmulator('evi_d30')
        emu.start()
        emu.stop()
        assert sys.getswitchinterval() <= SWITCH_INTERVAL_S * 1.001
        sys.setswitchinterval(1e-4)
        prompt_serial_threads()
        assert sys.getswitchinterval() == pytest.approx(1e-4, rel=1e-3)
    finally:
        sys.setswitchinterval(old)
