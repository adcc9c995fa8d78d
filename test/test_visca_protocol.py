"""VISCA packet grammar: documented byte examples, round trips, the splitter, and byte-identity with an
independent implementation (visca-over-ip builds the same VISCA payload inside its UDP header)."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fixego_ros.visca import protocol as vp
from fixego_ros.visca.profiles import PROFILES, CameraProfile, get_profile

positions = st.integers(min_value=-0x8000, max_value=0x7FFF)
speeds = st.integers(min_value=1, max_value=0x18)


def test_documented_examples():
    assert vp.encode_position(-880) == bytes.fromhex('0F0C0900')
    assert vp.encode_position(880) == bytes.fromhex('00030700')
    assert vp.decode_position(bytes.fromhex('0F0F090C')) == -100
    reply = bytes.fromhex('90500F0F090C0001020CFF')
    r = vp.parse_reply(reply)
    assert r.kind == vp.ReplyKind.INQUIRY and r.address == 1
    assert vp.parse_position_reply(r.data) == (-100, 300)
    assert vp.position_reply(1, -100, 300) == reply
    assert vp.address_set() == bytes.fromhex('883001FF')
    assert vp.if_clear() == bytes.fromhex('88010001FF')
    assert vp.pan_tilt_pos_inquiry(1) == bytes.fromhex('81090612FF')
    assert vp.version_inquiry(2) == bytes.fromhex('82090002FF')
    assert vp.absolute_position(1, 0x18, 0x14, -880, 300) == bytes.fromhex('810106021814' '0F0C0900' '0001020C' 'FF')
    assert vp.relative_position(3, 1, 2, -1, 1) == bytes.fromhex('830106030102' '0F0F0F0F' '00000001' 'FF')
    assert vp.pan_tilt_drive(1, vp.Direction.UP_LEFT, 5, 6) == bytes.fromhex('8101060105060101FF')
    assert vp.pan_tilt_drive(1, vp.Direction.STOP, 1, 1) == bytes.fromhex('8101060101010303FF')
    assert vp.home(1) == bytes.fromhex('81010604FF') and vp.reset(1) == bytes.fromhex('81010605FF')
    assert vp.zoom_direct(1, 0x3FF) == bytes.fromhex('810104470003 0F0F FF'.replace(' ', ''))
    assert vp.power(1, True) == bytes.fromhex('8101040002FF')


def test_replies_and_typed_errors():
    assert vp.parse_reply(bytes.fromhex('9041FF')).kind == vp.ReplyKind.ACK
    c = vp.parse_reply(bytes.fromhex('A052FF'))
    assert (c.kind, c.address, c.socket) == (vp.ReplyKind.COMPLETION, 2, 2)
    expected = {0x01: vp.MessageLengthError, 0x02: vp.ViscaSyntaxError, 0x03: vp.BufferFullError,
                0x04: vp.CommandCancelledError, 0x05: vp.NoSocketError, 0x41: vp.NotExecutableError}
    for code, cls in expected.items():
        r = vp.parse_reply(vp.error_reply(1, 1, code))
        assert r.kind == vp.ReplyKind.ERROR and r.error_code == code
        err = r.error()
        assert type(err) is cls and err.code == code and err.socket == 1
    assert vp.parse_reply(bytes.fromhex('883002FF')).kind == vp.ReplyKind.ADDRESS
    for bad in (b'\x90\xff', bytes.fromhex('9041'), bytes.fromhex('8141FF'), bytes.fromhex('907FFF')):
        with pytest.raises(vp.ViscaProtocolError):
            vp.parse_reply(bad)


def test_zero_speed_and_bad_address_rejected():
    with pytest.raises(ValueError):
        vp.absolute_position(1, 0, 1, 0, 0)
    with pytest.raises(ValueError):
        vp.pan_tilt_drive(1, vp.Direction.STOP, 1, 0)
    with pytest.raises(ValueError):
        vp.home(8)
    with pytest.raises(ValueError):
        vp.encode_position(0x8000)


@given(positions)
def test_position_round_trip(v):
    enc = vp.encode_position(v)
    assert len(enc) == 4 and all(b <= 0x0F for b in enc)
    assert vp.decode_position(enc) == v
    assert int.from_bytes(bytes((enc[0] << 4 | enc[1], enc[2] << 4 | enc[3])), 'big', signed=True) == v


def test_splitter_resynchronises():
    s = vp.PacketSplitter()
    good = vp.position_reply(1, -100, 300)
    stream = b'\x13\x37' + good[:4] + b'\xff' + b'\x00\x90' + good + vp.ack(1, 1) + b'\x12\x34' + vp.completion(1, 1)
    pkts = s.feed(stream[:7]) + s.feed(stream[7:])
    assert good in pkts and vp.ack(1, 1) in pkts and vp.completion(1, 1) in pkts
    assert s.garbage_bytes > 0
    assert s.feed(bytes(range(0x10, 0x7F)) * 3 + b'\xff') == []   # long garbage: dropped, bounded


def test_profiles():
    d30 = PROFILES['evi_d30']
    assert (d30.pan_min, d30.pan_max, d30.tilt_min, d30.tilt_max) == (-880, 880, -300, 300)
    assert d30.pan_speed_max == 0x18 and d30.tilt_speed_max == 0x14
    assert d30.pan_units(-100.0) == -880 and d30.tilt_deg(300) == pytest.approx(25.0)
    assert d30.pan_speed_deg_s(0x18) == pytest.approx(80.0) and d30.tilt_speed_deg_s(0x14) == pytest.approx(50.0)
    assert PROFILES['evi_d100'].pan_max == 0x05A0 and PROFILES['evi_d70'].pan_min == -2267
    assert not PROFILES['evi_g20'].verified and 'UNVERIFIED' in PROFILES['evi_g20'].notes
    assert d30.pan_code_for(10.0) == 3 and d30.pan_code_for(1e6) == 0x18
    with pytest.raises(ValueError):
        get_profile('evi_nope')


def test_network_change_packet():
    assert vp.network_change(1) == bytes.fromhex('9038FF')
    r = vp.parse_reply(vp.network_change(3))
    assert (r.kind, r.address) == (vp.ReplyKind.NETWORK_CHANGE, 3)


def test_profiles_refuse_values_that_would_hang_or_crash(tmp_path):
    d30 = PROFILES['evi_d30']
    for bad in ({'pan_units_per_deg': float('nan')}, {'tilt_units_per_deg': 0.0}, {'pan_speeds_deg_s': ()},
                {'tilt_speeds_deg_s': (1.0, float('inf'))}, {'pan_min': 900}, {'tilt_max': 0x8000},
                {'version': (1, 2, 3, 0)}, {'baud_rates': (0,)}, {'pan_min': -880.5}):
        with pytest.raises(ValueError):
            CameraProfile(**{**d30.__dict__, **bad})
    for angle in (float('inf'), float('-inf'), float('nan')):
        with pytest.raises(ValueError, match='finite'):
            d30.pan_units(angle)
        with pytest.raises(ValueError, match='finite'):
            d30.tilt_units(angle)
    path = tmp_path / 'p.json'                        # a calibrate-style file round-trips, extra rates included
    path.write_text(json.dumps({'profile': dict(d30.to_dict(), name='mine', baud_rates=[4800])}))
    mine = get_profile(str(path))
    assert mine.baud_rates == (4800,) and 4800 in mine.supported_baud_rates and mine.pan_max == 880


# ---------------------------------------------------------------------------- visca-over-ip identity

class _FakeUdp:
    """Stands in for visca-over-ip's UDP sockets: records what it sends, answers with a VISCA reply."""

    def __init__(self, reply: bytes) -> None:
        self.sent: list[bytes] = []
        self.reply = reply

    def sendto(self, message: bytes, location) -> None:
        self.sent.append(bytes(message))

    def recv(self, n: int) -> bytes:
        seq = self.sent[-1][4:8]
        return b'\x01\x11' + len(self.reply).to_bytes(2, 'big') + seq + self.reply


def _voip_camera(reply: bytes):
    camera_mod = pytest.importorskip('visca_over_ip.camera')
    cam = camera_mod.Camera.__new__(camera_mod.Camera)   # skip __init__: it binds real UDP ports
    cam._location = ('127.0.0.1', 52381)
    cam._cmd_sock = cam._inq_sock = _FakeUdp(reply)
    cam.num_missed_responses, cam.sequence_number, cam.num_retries = 0, 0, 1
    return cam, cam._cmd_sock


@settings(max_examples=150, deadline=None)
@given(pan=positions, tilt=positions, ps=speeds, ts=st.integers(min_value=1, max_value=0x14), rel=st.booleans())
def test_position_commands_byte_identical_to_visca_over_ip(pan, tilt, ps, ts, rel):
    cam, sock = _voip_camera(vp.completion(1, 1))
    cam.pantilt(ps, ts, pan, tilt, relative=rel)
    ours = (vp.relative_position if rel else vp.absolute_position)(1, ps, ts, pan, tilt)
    assert sock.sent[-1][8:] == ours


@pytest.mark.parametrize('pan,tilt', [(-880, -300), (880, 300), (-100, 300), (-1, -1), (0, 0),
                                      (0x7FFF, -0x8000), (-2267, 1200), (1, -2)])
def test_position_inquiry_byte_identical_to_visca_over_ip(pan, tilt):
    cam, sock = _voip_camera(vp.position_reply(1, pan, tilt))
    assert cam.get_pantilt_position() == (pan, tilt)         # they decode our reply encoding
    assert sock.sent[-1][8:] == vp.pan_tilt_pos_inquiry(1)   # and send our inquiry bytes
    ours = vp.absolute_position(1, 0x18, 0x14, pan, tilt)
    cam.pantilt(0x18, 0x14, pan, tilt)
    assert sock.sent[-1][8:] == ours
