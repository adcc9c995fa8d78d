"""VISCA packet grammar: command encoders, reply decoding, typed errors, and a resynchronising splitter.

Pure functions over ``bytes`` so the driver, the emulator and the tests share exactly one encoding.
Positions are signed 16-bit two's complement split into four nibbles, most significant first
(-880 = FC90 -> ``0F 0C 09 00``); several public libraries get negatives wrong, hence the tests
against an independent implementation (visca-over-ip).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

TERMINATOR = 0xFF
BROADCAST = 0x88
MAX_PACKET = 16  # VISCA packets are 3..16 bytes including header and terminator

# error codes carried in ``z0 6y EE FF``
ERR_LENGTH = 0x01
ERR_SYNTAX = 0x02
ERR_BUFFER_FULL = 0x03
ERR_CANCELLED = 0x04
ERR_NO_SOCKET = 0x05
ERR_NOT_EXECUTABLE = 0x41


# ----------------------------------------------------------------------------------------- errors

class ViscaError(Exception):
    """Base of every error the VISCA layer raises."""


class ViscaTimeoutError(ViscaError, TimeoutError):
    """No (complete) reply within the bounded wait."""


class ViscaDisconnectedError(ViscaError, ConnectionError):
    """The serial device vanished or cannot be opened; the driver retries with back-off."""


class ViscaProtocolError(ViscaError):
    """A reply that does not fit the grammar or the request (wrong address, bad length)."""


class ViscaReplyError(ViscaError):
    """The camera answered ``z0 6y EE FF``; subclasses name ``EE``."""

    code: int = -1
    description = 'unknown error'

    def __init__(self, socket: int = 0, code: int | None = None, packet: bytes = b'') -> None:
        if code is not None:
            self.code = code
        self.socket = socket
        self.packet = packet
        super().__init__(f'VISCA error {self.code:02X} ({self.description}) on socket {socket}'
                         + (f': {packet.hex(" ")}' if packet else ''))


class MessageLengthError(ViscaReplyError):
    code, description = ERR_LENGTH, 'message length error'


class ViscaSyntaxError(ViscaReplyError):
    code, description = ERR_SYNTAX, 'syntax error / illegal parameter'


class BufferFullError(ViscaReplyError):
    code, description = ERR_BUFFER_FULL, 'command buffer full'


class CommandCancelledError(ViscaReplyError):
    code, description = ERR_CANCELLED, 'command cancelled'


class NoSocketError(ViscaReplyError):
    code, description = ERR_NO_SOCKET, 'no socket'


class NotExecutableError(ViscaReplyError):
    code, description = ERR_NOT_EXECUTABLE, 'command not executable'


ERROR_CLASSES: dict[int, type[ViscaReplyError]] = {
    c.code: c for c in (MessageLengthError, ViscaSyntaxError, BufferFullError, CommandCancelledError,
                        NoSocketError, NotExecutableError)}


def error_for(code: int, socket: int = 0, packet: bytes = b'') -> ViscaReplyError:
    cls = ERROR_CLASSES.get(code)
    if cls is None:
        return ViscaReplyError(socket, code, packet)
    return cls(socket, packet=packet)


# -------------------------------------------------------------------------------------- encoding

def _check_address(address: int) -> int:
    if not 1 <= address <= 7:
        raise ValueError(f'camera address must be 1..7, got {address}')
    return 0x80 | address


def encode_nibbles(value: int, count: int = 4, signed: bool = True) -> bytes:
    """``value`` as ``count`` nibbles, most significant first (two's complement when signed)."""
    bits = 4 * count
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    if not lo <= value <= hi:
        raise ValueError(f'{value} does not fit in {count} nibbles ({"signed" if signed else "unsigned"})')
    v = value & ((1 << bits) - 1)
    return bytes((v >> (4 * (count - 1 - i))) & 0x0F for i in range(count))


def decode_nibbles(data: bytes, signed: bool = True) -> int:
    """Inverse of :func:`encode_nibbles`; every byte must be ``0x0n``."""
    if any(b & 0xF0 for b in data):
        raise ViscaProtocolError(f'nibble bytes must be 0x00..0x0F, got {bytes(data).hex(" ")}')
    v = 0
    for b in data:
        v = (v << 4) | b
    bits = 4 * len(data)
    if signed and v >= 1 << (bits - 1):
        v -= 1 << bits
    return v


def encode_position(value: int) -> bytes:
    """A pan or tilt position: signed 16-bit, four nibbles."""
    return encode_nibbles(int(value), 4, signed=True)


def decode_position(data: bytes) -> int:
    return decode_nibbles(data, signed=True)


def _speed(code: int, name: str) -> int:
    # cameras reject 0 (and > 0x18); profile-specific maxima are enforced by the driver
    if not 1 <= int(code) <= 0x18:
        raise ValueError(f'{name} speed code must be 0x01..0x18 (never 0), got {code}')
    return int(code)


def packet(address: int, *body: int) -> bytes:
    return bytes((_check_address(address), *body, TERMINATOR))


def address_set() -> bytes:
    return bytes((BROADCAST, 0x30, 0x01, TERMINATOR))


def if_clear(address: int | None = None) -> bytes:
    """IF_Clear, broadcast (``88 01 00 01 FF``) when ``address`` is None."""
    head = BROADCAST if address is None else _check_address(address)
    return bytes((head, 0x01, 0x00, 0x01, TERMINATOR))


def cancel(address: int, socket: int) -> bytes:
    if not 1 <= socket <= 2:
        raise ValueError(f'socket must be 1 or 2, got {socket}')
    return packet(address, 0x20 | socket)


def power(address: int, on: bool) -> bytes:
    return packet(address, 0x01, 0x04, 0x00, 0x02 if on else 0x03)


def power_inquiry(address: int) -> bytes:
    return packet(address, 0x09, 0x04, 0x00)


class Direction(Enum):
    """Pan-tiltDrive direction bytes (pan, tilt): pan 01 left / 02 right / 03 stop; tilt 01 up / 02 down."""

    UP = (0x03, 0x01)
    DOWN = (0x03, 0x02)
    LEFT = (0x01, 0x03)
    RIGHT = (0x02, 0x03)
    UP_LEFT = (0x01, 0x01)
    UP_RIGHT = (0x02, 0x01)
    DOWN_LEFT = (0x01, 0x02)
    DOWN_RIGHT = (0x02, 0x02)
    STOP = (0x03, 0x03)

    @classmethod
    def from_signs(cls, pan: int, tilt: int) -> Direction:
        """Direction for signed pan (+ right) and tilt (+ up) velocities."""
        p = 0x02 if pan > 0 else 0x01 if pan < 0 else 0x03
        t = 0x01 if tilt > 0 else 0x02 if tilt < 0 else 0x03
        return cls((p, t))


def pan_tilt_drive(address: int, direction: Direction, pan_speed: int, tilt_speed: int) -> bytes:
    """Continuous drive; speeds are sent even for a stopped axis and must never be 0."""
    p, t = direction.value
    return packet(address, 0x01, 0x06, 0x01, _speed(pan_speed, 'pan'), _speed(tilt_speed, 'tilt'), p, t)


def absolute_position(address: int, pan_speed: int, tilt_speed: int, pan: int, tilt: int) -> bytes:
    """``8x 01 06 02 VV WW 0Y0Y0Y0Y 0Z0Z0Z0Z FF``."""
    return packet(address, 0x01, 0x06, 0x02, _speed(pan_speed, 'pan'), _speed(tilt_speed, 'tilt'),
                  *encode_position(pan), *encode_position(tilt))


def relative_position(address: int, pan_speed: int, tilt_speed: int, pan: int, tilt: int) -> bytes:
    """``8x 01 06 03 VV WW 0Y0Y0Y0Y 0Z0Z0Z0Z FF``."""
    return packet(address, 0x01, 0x06, 0x03, _speed(pan_speed, 'pan'), _speed(tilt_speed, 'tilt'),
                  *encode_position(pan), *encode_position(tilt))


def home(address: int) -> bytes:
    return packet(address, 0x01, 0x06, 0x04)


def reset(address: int) -> bytes:
    return packet(address, 0x01, 0x06, 0x05)


def pan_tilt_pos_inquiry(address: int) -> bytes:
    return packet(address, 0x09, 0x06, 0x12)


def zoom_direct(address: int, position: int) -> bytes:
    return packet(address, 0x01, 0x04, 0x47, *encode_nibbles(int(position), 4, signed=False))


def zoom_pos_inquiry(address: int) -> bytes:
    return packet(address, 0x09, 0x04, 0x47)


def version_inquiry(address: int) -> bytes:
    return packet(address, 0x09, 0x00, 0x02)


# -------------------------------------------------------------------------------------- replies

class ReplyKind(Enum):
    ACK = 'ack'
    COMPLETION = 'completion'      # z0 5y FF (y = socket; y = 0 for IF_Clear)
    INQUIRY = 'inquiry'            # z0 50 data... FF
    ERROR = 'error'                # z0 6y EE FF
    ADDRESS = 'address'            # 88 30 0w FF (AddressSet coming back round the chain)
    IF_CLEAR = 'if_clear'          # 88 01 00 01 FF (broadcast IF_Clear coming back)
    NETWORK_CHANGE = 'network_change'  # z0 38 FF


@dataclass(frozen=True)
class Reply:
    kind: ReplyKind
    address: int          # camera address 1..7 (0 for broadcast replies)
    socket: int = 0
    data: bytes = b''     # inquiry payload (without z0 50 and FF), or AddressSet's next address
    error_code: int = 0
    raw: bytes = b''

    def error(self) -> ViscaReplyError:
        return error_for(self.error_code, self.socket, self.raw)


def reply_header(address: int) -> int:
    """Header byte of replies from camera ``address``: ``(address + 8) << 4``."""
    _check_address(address)
    return (address + 8) << 4


def parse_reply(pkt: bytes) -> Reply:
    """Decode one controller-side packet (ending in FF); raises :class:`ViscaProtocolError`."""
    pkt = bytes(pkt)
    if len(pkt) < 3 or pkt[-1] != TERMINATOR or len(pkt) > MAX_PACKET:
        raise ViscaProtocolError(f'not a VISCA packet: {pkt.hex(" ")}')
    h = pkt[0]
    if h == BROADCAST:
        if len(pkt) == 4 and pkt[1] == 0x30:
            return Reply(ReplyKind.ADDRESS, 0, data=pkt[2:3], raw=pkt)
        if pkt == if_clear(None):
            return Reply(ReplyKind.IF_CLEAR, 0, raw=pkt)
        raise ViscaProtocolError(f'unexpected broadcast packet: {pkt.hex(" ")}')
    if h & 0x0F or not 0x90 <= h <= 0xF0:
        raise ViscaProtocolError(f'bad reply header {h:02X}: {pkt.hex(" ")}')
    address = (h >> 4) - 8
    kind, y = pkt[1] >> 4, pkt[1] & 0x0F
    if pkt[1] == 0x38 and len(pkt) == 3:
        return Reply(ReplyKind.NETWORK_CHANGE, address, raw=pkt)
    if kind == 4 and len(pkt) == 3:
        return Reply(ReplyKind.ACK, address, y, raw=pkt)
    if kind == 5 and len(pkt) == 3:
        return Reply(ReplyKind.COMPLETION, address, y, raw=pkt)
    if kind == 5 and y == 0 and len(pkt) > 3:
        return Reply(ReplyKind.INQUIRY, address, 0, data=pkt[2:-1], raw=pkt)
    if kind == 6 and len(pkt) == 4:
        return Reply(ReplyKind.ERROR, address, y, error_code=pkt[2], raw=pkt)
    raise ViscaProtocolError(f'unrecognised reply: {pkt.hex(" ")}')


def parse_position_reply(data: bytes) -> tuple[int, int]:
    """(pan, tilt) units from the payload of ``y0 50 0w0w0w0w 0z0z0z0z FF``."""
    if len(data) != 8:
        raise ViscaProtocolError(f'position reply needs 8 data bytes, got {len(data)}: {data.hex(" ")}')
    return decode_position(data[:4]), decode_position(data[4:])


def position_reply(address: int, pan: int, tilt: int) -> bytes:
    """What a camera sends for Pan-tiltPosInq (used by the emulator and tests)."""
    return bytes((reply_header(address), 0x50, *encode_position(pan), *encode_position(tilt), TERMINATOR))


def ack(address: int, socket: int) -> bytes:
    return bytes((reply_header(address), 0x40 | socket, TERMINATOR))


def completion(address: int, socket: int) -> bytes:
    return bytes((reply_header(address), 0x50 | socket, TERMINATOR))


def error_reply(address: int, socket: int, code: int) -> bytes:
    return bytes((reply_header(address), 0x60 | socket, code, TERMINATOR))


def inquiry_reply(address: int, data: bytes) -> bytes:
    return bytes((reply_header(address), 0x50, *data, TERMINATOR))


def network_change(address: int) -> bytes:
    """``z0 38 FF``: unsolicited, sent by a camera when the daisy chain changes (e.g. after power-up)."""
    return bytes((reply_header(address), 0x38, TERMINATOR))


# ------------------------------------------------------------------------------------- splitting

class PacketSplitter:
    """Cuts a byte stream into packets at FF, dropping garbage so one bad byte costs one packet.

    A packet must start with a header byte (bit 7 set, not FF); bytes before the last header byte of a
    chunk are garbage (they are counted). Chunks longer than 16 bytes are discarded whole. This is how
    the link resynchronises after noise, dropped bytes or unsolicited data.
    """

    def __init__(self, max_len: int = MAX_PACKET, min_len: int = 3) -> None:
        # the emulator passes larger bounds so it can answer 'length error' itself
        self.max_len, self.min_len = max_len, min_len
        self._buf = bytearray()
        self.garbage_bytes = 0
        self.bad_packets = 0

    def feed(self, data: bytes) -> list[bytes]:
        out: list[bytes] = []
        for b in data:
            if b != TERMINATOR:
                self._buf.append(b)
                if len(self._buf) > 4 * self.max_len:   # never grow without bound on an FF-less stream
                    self.garbage_bytes += len(self._buf) - self.max_len
                    del self._buf[:-self.max_len]
                continue
            chunk = bytes(self._buf) + b'\xff'
            self._buf.clear()
            pkt = self._trim(chunk)
            if pkt is not None:
                out.append(pkt)
        return out

    def _trim(self, chunk: bytes) -> bytes | None:
        # the last header-like byte (81..88 command, 90..F0 reply) starts the packet; position and
        # status data bytes are all < 0x80, so they never look like a header
        starts = [i for i, b in enumerate(chunk[:-1]) if 0x81 <= b <= 0x88 or (b >= 0x90 and not b & 0x0F)]
        if not starts:
            self.garbage_bytes += len(chunk)
            self.bad_packets += 1
            return None
        i = starts[-1] if chunk[0] != BROADCAST else 0
        if i:
            self.garbage_bytes += i
        pkt = chunk[i:]
        if len(pkt) < self.min_len or len(pkt) > self.max_len:
            self.garbage_bytes += len(pkt)
            self.bad_packets += 1
            return None
        return pkt

    def reset(self) -> None:
        self._buf.clear()
