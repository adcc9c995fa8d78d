"""VISCA over RS-232 (pyserial): one camera, synchronous calls, bounded waits, automatic reconnect.

Rules that keep the link sane at 9600 baud (~1 ms per byte):
- one command in flight per socket, and the next command is sent only after the previous one was
  ACKed (or failed); completions of earlier commands are picked up whenever bytes are read;
- every read has a deadline (nothing blocks forever); after a timeout the input is drained before the
  next command, so a late reply is never taken for the answer to a new command;
- garbage, dropped bytes and unsolicited packets are skipped by resynchronising on ``FF``; a reply that
  does not belong to the pending command (a network change ``z0 38 FF``, another camera's packet, an ACK
  on a socket that is not free, a completion or error of a socket nobody waits on, an inquiry reply of the
  wrong length) is counted as ``unsolicited`` and never taken as its ACK, completion or answer;
- a reply whose value is impossible for the profile (a position outside its range) is a protocol error,
  counted like a malformed packet, never a result;
- every timeout is checked up front (finite, > 0, bounded), so no deadline can be NaN or infinite;
- a vanished device raises :class:`ViscaDisconnectedError`; later calls reopen the port with exponential
  back-off (calls made before the next retry time fail fast instead of waiting).
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import serial

from fixego_ros.cli_options import check_float
from fixego_ros.visca import protocol as vp
from fixego_ros.visca.profiles import CameraProfile, get_profile, model_text
from fixego_ros.visca.protocol import Reply, ReplyKind

try:                              # pyserial's flush/reset call termios directly and let termios.error out
    import termios
    _TERMIOS_ERRORS: tuple[type[Exception], ...] = (termios.error,)
except ImportError:               # pragma: no cover - not POSIX
    _TERMIOS_ERRORS = ()

log = logging.getLogger(__name__)

_SERIAL_ERRORS: tuple[type[Exception], ...] = (serial.SerialException, OSError, *_TERMIOS_ERRORS)
MAX_TIMEOUT_S = 10.0    # per-reply wait: a VISCA camera answers within tens of ms; more is a typo
MAX_WAIT_S = 600.0      # any completion wait (the slowest full-range move is ~1.5 min)
MAX_SETTLE_S = 10.0     # calibrate's pause between two readings at an end stop


# ------------------------------------------------------------------------------------ validation

def check_seconds(value: float, name: str, upper: float, allow_zero: bool = False) -> float:
    """``value`` as finite seconds in (0, upper] (or [0, upper]); a NaN or infinite wait never ends. Raises
    :class:`~fixego_ros.cli_options.OptionError` (a ValueError) naming ``name``."""
    return check_float(value, name, 0.0, upper, lo_open=not allow_zero, unit='s')


def check_timeout(value: float, name: str = 'timeout_s') -> float:
    """The per-reply timeout: finite, > 0 and at most :data:`MAX_TIMEOUT_S`."""
    return check_seconds(value, name, MAX_TIMEOUT_S)


def _whole(value: float) -> int | None:
    try:
        f = float(value)
        return int(f) if f.is_integer() else None
    except (TypeError, ValueError, OverflowError):
        return None


def check_baud(value: float, profile: CameraProfile, name: str = 'baud') -> int:
    """One of the profile's serial rates (0 or an odd rate would divide by zero or never sync)."""
    rates = profile.supported_baud_rates
    b = _whole(value)
    if b is None or b not in rates:
        raise ValueError(f'{name} must be one of {", ".join(map(str, rates))} ({profile.name}), got {value!r}')
    return b


def check_address(value: float, name: str = 'address') -> int:
    a = _whole(value)
    if a is None or not 1 <= a <= 7:
        raise ValueError(f'{name} must be a camera address 1..7, got {value!r}')
    return a


def _as_int(value: float, what: str) -> int:
    """``int(value)`` with a ValueError naming ``what`` for NaN, infinity or non-numbers."""
    try:
        return int(value)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f'{what} must be a finite integer, got {value!r}') from None


SWITCH_INTERVAL_S = 5e-4    # how long a thread whose serial bytes have arrived may wait for the GIL


def prompt_serial_threads(interval_s: float = SWITCH_INTERVAL_S) -> None:
    """Shorten the interpreter's thread switch interval (process-wide, never lengthened) so that a thread reading
    the serial line takes its bytes when they arrive. At Python's default, 5 ms, a thread whose reply is in waits
    up to that long while another thread of the process holds the GIL (the node's image callbacks, the simulator's
    rendering): the reply reads late and its time is uncertain by the wait. Measured with a CPU-bound thread beside
    the servo loop (``python -m fixego_ros.bench.joints`` plus one such thread): late readings 96 of 355 -> 38 of
    377, prediction horizon p95 61 -> 51 ms, error max 0.174 -> 0.121 deg. Called by whoever starts such a thread
    (:class:`~fixego_ros.tracking.servo.ServoLoop`, the emulator)."""
    if sys.getswitchinterval() > interval_s:
        sys.setswitchinterval(interval_s)


@dataclass(frozen=True)
class PositionReading:
    """A Pan-tiltPosInq answer (units) and when the camera can have sampled it (monotonic s): not before the
    inquiry's last byte can have reached it (written at ``earliest`` minus its serial time), not after the reply's
    first byte left it (its last byte read at ``latest`` plus the reply's serial time). A busy host reads the
    reply late (stop 34: p95 8 ms on the demo's 2 cores, 0.3 deg at 30 deg/s), which widens the window; a camera
    answers after a short fixed delay, which is the narrowest window seen."""

    pan: int
    tilt: int
    earliest: float
    latest: float

    @property
    def window_s(self) -> float:
        return max(0.0, self.latest - self.earliest)


class ViscaCamera:
    """One VISCA camera on a serial port. Thread-safe (calls are serialised by a lock)."""

    def __init__(self, port: str, baud: int = 9600, address: int = 1, profile: str | CameraProfile = 'evi_d30',
                 timeout_s: float = 0.3, reconnect: bool = True, backoff_s: tuple[float, float] = (0.05, 2.0),
                 serial_factory: Callable[..., Any] | None = None) -> None:
        self.port = port
        self.profile = profile if isinstance(profile, CameraProfile) else get_profile(profile)
        self.baud = check_baud(baud, self.profile)
        self.address = check_address(address)
        self.timeout_s = check_timeout(timeout_s)
        self.reconnect = reconnect
        self.backoff_min = check_seconds(backoff_s[0], 'backoff_s[0]', 60.0)
        self.backoff_max = check_seconds(backoff_s[1], 'backoff_s[1]', 60.0)
        if self.backoff_max < self.backoff_min:
            raise ValueError(f'backoff_s must be (min, max) with min <= max, got {backoff_s!r}')
        self.byte_time = 10.0 / self.baud
        self._factory = serial_factory or serial.Serial
        self._ser: Any = None
        self._lock = threading.RLock()
        self._splitter = vp.PacketSplitter()
        self._pending: list[bytes] = []
        self._busy: dict[int, str] = {}          # socket -> command name awaiting completion
        self._maybe_free: set[int] = set()       # busy when a network change came: the camera may have reset
        self._ignored: list[str] = []            # unsolicited packets of the current transaction (for errors)
        self._async_errors: dict[int, vp.ViscaReplyError] = {}
        self._dirty = False
        self._backoff = self.backoff_min
        self._next_retry = 0.0
        self._ever_open = False
        self.state = 'closed'
        self.last_error = ''
        self.last_write = 0.0
        self.last_arrival = 0.0
        self.stats: dict[str, int] = {k: 0 for k in (
            'commands', 'inquiries', 'timeouts', 'reply_errors', 'protocol_errors', 'garbage_bytes',
            'disconnects', 'reconnects', 'open_failures', 'unsolicited', 'network_changes', 'lost_completions')}

    # ------------------------------------------------------------------------------ connection
    def open(self) -> ViscaCamera:
        with self._lock:
            self._ensure_open(force=True)
        return self

    def close(self) -> None:
        with self._lock:
            self._close()
            self.state = 'closed'

    def __enter__(self) -> ViscaCamera:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        return self._ser is not None

    @property
    def comm_errors(self) -> int:
        s = self.stats
        return s['timeouts'] + s['protocol_errors'] + s['disconnects'] + s['open_failures']

    def _close(self) -> None:
        if self._ser is not None:
            with contextlib.suppress(Exception):   # closing a vanished device may fail in many ways
                self._ser.close()
        self._ser = None

    def _ensure_open(self, force: bool = False) -> None:
        if self._ser is not None:
            return
        now = time.monotonic()
        if self._ever_open and not self.reconnect and not force:
            raise vp.ViscaDisconnectedError(f'{self.port}: disconnected (reconnect disabled)')
        if not force and now < self._next_retry:
            raise vp.ViscaDisconnectedError(f'{self.port}: disconnected, next retry in {self._next_retry - now:.2f} s'
                                       f' ({self.last_error})')
        try:
            ser = self._factory(self.port, baudrate=self.baud, bytesize=8, parity='N', stopbits=1,
                                timeout=0.05, write_timeout=1.0)
            ser.reset_input_buffer()
        except (*_SERIAL_ERRORS, ValueError) as e:
            self.stats['open_failures'] += 1
            self.last_error = f'open failed: {e}'
            self._next_retry = now + self._backoff
            self._backoff = min(self._backoff * 2.0, self.backoff_max)
            self.state = 'disconnected'
            raise vp.ViscaDisconnectedError(f'{self.port}: cannot open ({e})') from None
        self._ser = ser
        if self._ever_open:
            self.stats['reconnects'] += 1
        self._ever_open = True
        self._backoff = self.backoff_min
        self._splitter.reset()
        self._pending.clear()
        self._busy.clear()
        self._maybe_free.clear()
        self._dirty = False
        self.state = 'connected'

    def _lost(self, e: Exception) -> vp.ViscaDisconnectedError:
        self.stats['disconnects'] += 1
        self.last_error = f'device lost: {e}'
        self._close()
        self.state = 'disconnected'
        self._next_retry = time.monotonic() + self._backoff
        self._backoff = min(self._backoff * 2.0, self.backoff_max)
        self._busy.clear()
        return vp.ViscaDisconnectedError(f'{self.port}: {e}')

    # ------------------------------------------------------------------------------ byte level
    def _write(self, pkt: bytes) -> None:
        self._ensure_open()
        if self._dirty:
            self._drain()
        self._ignored = []
        try:
            self.last_write = time.monotonic()      # the packet's first byte cannot leave before this
            self.last_arrival = self.last_write + len(pkt) * self.byte_time    # nor its last reach the camera
            self._ser.write(pkt)
            self._ser.flush()
        except _SERIAL_ERRORS as e:
            raise self._lost(e) from None

    def _read_packet(self, deadline: float) -> bytes | None:
        """Next complete packet before ``deadline`` (monotonic), else None."""
        while True:
            if self._pending:
                return self._pending.pop(0)
            remaining = deadline - time.monotonic()
            if not remaining > 0:                 # also ends a NaN deadline instead of waiting forever
                return None
            try:
                self._ser.timeout = min(remaining, 0.05)
                data = self._ser.read(max(1, self._ser.in_waiting))
            except (*_SERIAL_ERRORS, TypeError, AttributeError) as e:
                raise self._lost(e) from None
            if data:
                before = self._splitter.garbage_bytes
                self._pending.extend(self._splitter.feed(data))
                self.stats['garbage_bytes'] += self._splitter.garbage_bytes - before

    def _drain(self, quiet_s: float | None = None, max_s: float = 0.3) -> None:
        """Read (and book-keep) whatever is still coming until the line is quiet."""
        quiet = quiet_s if quiet_s is not None else max(0.02, 20 * self.byte_time)
        end = time.monotonic() + max_s
        self._dirty = False
        while time.monotonic() < end:
            pkt = self._read_packet(min(end, time.monotonic() + quiet))
            if pkt is None:
                break
            self._classify(pkt)

    def _classify(self, pkt: bytes) -> Reply | None:
        """Parse and book-keep; None when the packet is fully handled here, else the reply for the caller.

        Handled here: malformed packets, other cameras' packets, network changes, and the completion or
        error of a socket we wait on (wherever it arrives). The caller accepts what belongs to its own
        transaction and passes the rest to :meth:`_unsolicited`.
        """
        try:
            r = vp.parse_reply(pkt)
        except vp.ViscaProtocolError:
            self.stats['protocol_errors'] += 1
            self._note(f'malformed {pkt.hex(" ")}')
            return None
        if r.kind in (ReplyKind.ADDRESS, ReplyKind.IF_CLEAR):
            return r
        if r.kind == ReplyKind.NETWORK_CHANGE:
            # the chain changed; it says nothing about our commands, which keep running (or, if our camera
            # restarted, never complete: their waits end at their deadlines). If it was our camera, the
            # sockets we think busy may be free again.
            self.stats['network_changes'] += 1
            if r.address == self.address:
                self._maybe_free |= set(self._busy)
            self._unsolicited(r, f'network change from camera address {r.address}')
            log.info('%s: VISCA network change from address %d; pending: %s', self.port, r.address,
                     self._busy or 'none')
            return None
        if r.address != self.address:
            self._unsolicited(r, f'from camera address {r.address}')
            return None
        if r.kind in (ReplyKind.COMPLETION, ReplyKind.ERROR) and r.socket in self._busy:
            del self._busy[r.socket]
            self._maybe_free.discard(r.socket)
            if r.kind == ReplyKind.ERROR:
                self._async_errors[r.socket] = r.error()
                self.stats['reply_errors'] += 1
            return None
        return r

    def _note(self, text: str) -> None:
        self._ignored = [*self._ignored[-3:], text]

    def _unsolicited(self, r: Reply, why: str) -> None:
        """A reply that belongs to no pending transaction: count it, remember it for the error message."""
        self.stats['unsolicited'] += 1
        self._note(f'{why}: {r.raw.hex(" ")}')
        log.debug('%s: ignored unsolicited %s (%s)', self.port, r.raw.hex(' '), why)

    def _take_ack(self, socket: int) -> bool:
        """Whether an ACK on ``socket`` can be the ACK of the command just sent.

        Not on a socket still running an earlier command (a corrupted completion reads as an ACK after
        one bit flip), unless our camera announced a network change since: it may have restarted and
        forgotten that command. A completion lost otherwise costs one ACK timeout; the camera's next
        completion on that socket then clears the record.
        """
        if not 1 <= socket <= self.profile.max_socket:
            return False
        if socket not in self._busy:
            return True
        if socket in self._maybe_free:
            self._busy.pop(socket)
            self._maybe_free.discard(socket)
            self.stats['lost_completions'] += 1
            return True
        return False

    # ------------------------------------------------------------------------------ transactions
    def _timeout(self, what: str, waited_s: float) -> vp.ViscaTimeoutError:
        self.stats['timeouts'] += 1
        self._dirty = True
        ignored = f' (ignored: {"; ".join(self._ignored)})' if self._ignored else ''
        self.last_error = f'timeout waiting for {what}{ignored}'
        return vp.ViscaTimeoutError(f'{self.port}: no {what} within {waited_s:.3g} s{ignored}')

    def _bad_reply(self, message: str) -> vp.ViscaProtocolError:
        """A reply that parsed but cannot be true: counted with the malformed ones, and the line drained."""
        self.stats['protocol_errors'] += 1
        self._dirty = True
        self.last_error = message
        return vp.ViscaProtocolError(f'{self.port}: {message}')

    def _exchange(self, pkt: bytes, what: str, reply_bytes: int, accept: Callable[[Reply], bool]) -> Reply:
        """Write ``pkt`` and return the first reply ``accept`` takes, within the timeout plus the
        serial time of ``reply_bytes``; other packets are book-kept or counted as unsolicited."""
        self._write(pkt)
        wait_s = self.timeout_s + reply_bytes * self.byte_time
        deadline = time.monotonic() + wait_s
        while True:
            raw = self._read_packet(deadline)
            if raw is None:
                raise self._timeout(what, wait_s)
            r = self._classify(raw)
            if r is None:
                continue
            if accept(r):
                return r
            self._unsolicited(r, f'while waiting for {what}')

    def command(self, pkt: bytes, name: str = 'command', wait: bool = True,
                completion_timeout_s: float | None = None) -> int:
        """Send a command, wait for its ACK (and completion when ``wait``); returns the socket.

        Raises a :class:`~fixego_ros.visca.protocol.ViscaReplyError` subclass for error replies,
        :class:`ViscaTimeoutError` or :class:`ViscaDisconnectedError`; ValueError for a bad timeout.
        """
        wait_s = check_seconds(completion_timeout_s or 5.0, 'completion_timeout_s', MAX_WAIT_S)
        is_if_clear = bytes(pkt) == vp.if_clear(self.address)
        with self._lock:
            self.stats['commands'] += 1
            self._write(pkt)
            ack_s = self.timeout_s + (len(pkt) + 4) * self.byte_time
            deadline = time.monotonic() + ack_s
            socket = None
            while socket is None:
                raw = self._read_packet(deadline)
                if raw is None:
                    raise self._timeout(f'ACK for {name}', ack_s)
                r = self._classify(raw)
                if r is None:
                    continue
                if r.kind == ReplyKind.ACK and self._take_ack(r.socket):
                    socket = r.socket
                elif r.kind == ReplyKind.ERROR:      # errors of sockets we wait on were book-kept above
                    self.stats['reply_errors'] += 1
                    raise r.error()
                elif r.kind == ReplyKind.COMPLETION and r.socket == 0 and is_if_clear:
                    return 0                   # IF_Clear (addressed) answers z0 50 FF without an ACK
                else:
                    self._unsolicited(r, f'while waiting for the ACK of {name}')
            self._async_errors.pop(socket, None)
            self._busy[socket] = name
            self._maybe_free.discard(socket)
            if wait:
                self._wait_socket(socket, name, time.monotonic() + wait_s)
            return socket

    def _wait_socket(self, socket: int, name: str, deadline: float) -> None:
        """Until ``socket`` completes (or fails) or ``deadline``; only its own completion ends the wait."""
        start = time.monotonic()
        while socket in self._busy:
            raw = self._read_packet(deadline)
            if raw is None:
                self._busy.pop(socket, None)
                self._maybe_free.discard(socket)
                raise self._timeout(f'completion of {name}', max(0.0, deadline - start))
            r = self._classify(raw)
            if r is not None:
                self._unsolicited(r, f'while {name} runs')
        err = self._async_errors.pop(socket, None)
        if err is not None:
            raise err

    def inquiry(self, pkt: bytes, name: str = 'inquiry', data_len: int | None = None) -> tuple[bytes, float]:
        """Send an inquiry; returns (payload, monotonic time the last reply byte arrived).

        With ``data_len``, an inquiry reply of another length is not taken for ours (it may be a stale
        reply to another inquiry); if no reply of the right length comes, it is reported as malformed.
        """
        with self._lock:
            self.stats['inquiries'] += 1
            self._write(pkt)
            wait_s = self.timeout_s + (len(pkt) + 16) * self.byte_time
            deadline = time.monotonic() + wait_s
            wrong: Reply | None = None
            while True:
                raw = self._read_packet(deadline)
                if raw is None:
                    if wrong is not None:
                        raise self._bad_reply(f'reply to {name} has {len(wrong.data)} data bytes, expected '
                                              f'{data_len}: {wrong.raw.hex(" ")}')
                    raise self._timeout(f'reply to {name}', wait_s)
                t = time.monotonic()
                r = self._classify(raw)
                if r is None:
                    continue
                if r.kind == ReplyKind.INQUIRY and (data_len is None or len(r.data) == data_len):
                    if wrong is not None:
                        self._unsolicited(wrong, f'wrong length for {name}')
                    return r.data, t
                if r.kind == ReplyKind.INQUIRY and wrong is None:
                    wrong = r
                elif r.kind == ReplyKind.ERROR and r.socket == 0:
                    self.stats['reply_errors'] += 1
                    raise r.error()
                else:
                    self._unsolicited(r, f'while waiting for the reply to {name}')

    def wait_idle(self, timeout_s: float = 5.0) -> None:
        """Wait until every command we sent has completed (or raise its error)."""
        deadline = time.monotonic() + check_seconds(timeout_s, 'timeout_s', MAX_WAIT_S)
        with self._lock:
            for s, name in list(self._busy.items()):
                self._wait_socket(s, name, deadline)

    @property
    def busy_sockets(self) -> dict[int, str]:
        return dict(self._busy)

    # ------------------------------------------------------------------------------ commands
    def address_set(self) -> int:
        """AddressSet broadcast; returns how many cameras answered on the chain."""
        with self._lock:
            r = self._exchange(vp.address_set(), 'AddressSet reply', 8, lambda r: r.kind == ReplyKind.ADDRESS)
            return r.data[0] - 1

    def if_clear(self, broadcast: bool = False) -> None:
        with self._lock:
            if broadcast:
                self._exchange(vp.if_clear(None), 'IF_Clear reply', 10, lambda r: r.kind == ReplyKind.IF_CLEAR)
            else:
                self.command(vp.if_clear(self.address), 'IF_Clear', wait=False)
            self._busy.clear()
            self._maybe_free.clear()
            self._async_errors.clear()

    def cancel(self, socket: int) -> None:
        """Cancel the command on ``socket``; raises NoSocketError when nothing runs there."""
        with self._lock:
            pkt = vp.cancel(self.address, socket)
            self._async_errors.pop(socket, None)       # a stale error of that socket is not the answer
            self._write(pkt)
            wait_s = self.timeout_s + 8 * self.byte_time
            deadline = time.monotonic() + wait_s
            while True:
                raw = self._read_packet(deadline)
                if raw is None:
                    raise self._timeout('Cancel reply', wait_s)
                r = self._classify(raw)
                err = self._async_errors.pop(socket, None)   # the socket was busy: book-kept by _classify
                if err is None and r is not None and r.kind == ReplyKind.ERROR and r.socket == socket:
                    self.stats['reply_errors'] += 1
                    err = r.error()
                if err is not None:
                    if err.code != vp.ERR_CANCELLED:
                        raise err
                    return
                if r is not None:
                    self._unsolicited(r, 'while waiting for the Cancel reply')

    def power(self, on: bool) -> None:
        self.command(vp.power(self.address, on), 'CAM_Power', completion_timeout_s=10.0)

    def power_state(self) -> bool:
        with self._lock:
            data, _ = self.inquiry(vp.power_inquiry(self.address), 'CAM_PowerInq', data_len=1)
            if data not in (b'\x02', b'\x03'):
                raise self._bad_reply(f'CAM_PowerInq reply {data.hex(" ")} is neither 02 (on) nor 03 (off)')
            return data == b'\x02'

    def _codes(self, pan_speed: int | None, tilt_speed: int | None) -> tuple[int, int]:
        pr = self.profile
        ps = pr.pan_speed_max if pan_speed is None else _as_int(pan_speed, 'pan speed')
        ts = pr.tilt_speed_max if tilt_speed is None else _as_int(tilt_speed, 'tilt speed')
        return min(max(ps, 1), pr.pan_speed_max), min(max(ts, 1), pr.tilt_speed_max)

    def drive(self, pan_speed: int, tilt_speed: int) -> None:
        """Continuous drive with signed speed codes (+pan right, +tilt up, 0 stops that axis)."""
        pr = self.profile
        pan_speed, tilt_speed = _as_int(pan_speed, 'pan speed'), _as_int(tilt_speed, 'tilt speed')
        direction = vp.Direction.from_signs(pan_speed, tilt_speed)
        ps = min(max(abs(pan_speed), 1), pr.pan_speed_max)      # never send a zero speed
        ts = min(max(abs(tilt_speed), 1), pr.tilt_speed_max)
        self.command(vp.pan_tilt_drive(self.address, direction, ps, ts), 'Pan-tiltDrive', wait=True,
                     completion_timeout_s=1.0)

    def stop(self) -> None:
        self.drive(0, 0)

    def _motion_timeout(self, d_pan_units: float, d_tilt_units: float, ps: int, ts: int) -> float:
        pr = self.profile
        tp = abs(d_pan_units) / pr.pan_units_per_deg / pr.pan_speed_deg_s(ps)
        tt = abs(d_tilt_units) / pr.tilt_units_per_deg / pr.tilt_speed_deg_s(ts)
        return min(1.5 * max(tp, tt) + 1.0 + 40 * self.byte_time, MAX_WAIT_S)

    def absolute(self, pan: int, tilt: int, pan_speed: int | None = None, tilt_speed: int | None = None,
                 wait: bool = True, check_range: bool = True, timeout_s: float | None = None) -> int:
        """AbsolutePosition in VISCA units; returns the socket. Out-of-range raises ValueError unless
        ``check_range=False`` (then the camera's own error is raised)."""
        pan, tilt = _as_int(pan, 'pan position'), _as_int(tilt, 'tilt position')
        if check_range and not self.profile.in_range(pan, tilt):
            raise ValueError(f'position ({pan}, {tilt}) outside {self.profile.range_text()}')
        ps, ts = self._codes(pan_speed, tilt_speed)
        if timeout_s is None:
            span = (self.profile.pan_max - self.profile.pan_min, self.profile.tilt_max - self.profile.tilt_min)
            timeout_s = self._motion_timeout(*span, ps, ts)
        else:
            timeout_s = check_seconds(timeout_s, 'timeout_s', MAX_WAIT_S)
        return self.command(vp.absolute_position(self.address, ps, ts, pan, tilt), 'AbsolutePosition',
                            wait=wait, completion_timeout_s=timeout_s)

    def relative(self, d_pan: int, d_tilt: int, pan_speed: int | None = None, tilt_speed: int | None = None,
                 wait: bool = True, timeout_s: float | None = None) -> int:
        d_pan, d_tilt = _as_int(d_pan, 'pan step'), _as_int(d_tilt, 'tilt step')
        ps, ts = self._codes(pan_speed, tilt_speed)
        timeout_s = (check_seconds(timeout_s, 'timeout_s', MAX_WAIT_S) if timeout_s
                     else self._motion_timeout(d_pan, d_tilt, ps, ts))
        return self.command(vp.relative_position(self.address, ps, ts, d_pan, d_tilt),
                            'RelativePosition', wait=wait, completion_timeout_s=timeout_s)

    def goto_deg(self, pan_deg: float, tilt_deg: float, wait: bool = True) -> int:
        pr = self.profile
        return self.absolute(pr.pan_units(pan_deg), pr.tilt_units(tilt_deg), wait=wait)

    def home(self, wait: bool = True) -> int:
        pr = self.profile
        return self.command(vp.home(self.address), 'Home', wait=wait,
                            completion_timeout_s=self._motion_timeout(pr.pan_max - pr.pan_min,
                                                                      pr.tilt_max - pr.tilt_min,
                                                                      pr.pan_speed_max, pr.tilt_speed_max))

    def reset(self, wait: bool = True) -> int:
        pr = self.profile
        return self.command(vp.reset(self.address), 'Reset', wait=wait,
                            completion_timeout_s=min(2.0 * self._motion_timeout(
                                pr.pan_max - pr.pan_min, pr.tilt_max - pr.tilt_min,
                                pr.pan_speed_max, pr.tilt_speed_max) + 5.0, MAX_WAIT_S))

    def position_timed(self, check_range: bool = True) -> PositionReading:
        """The pan/tilt units and the window of monotonic time in which the camera sampled them
        (:class:`PositionReading`): from the inquiry's write plus its serial time to the reply's arrival minus
        its serial time. A reading outside the profile's range raises :class:`ViscaProtocolError` (a corrupted or
        foreign reply); ``check_range=False`` (calibration) only refuses angles no pan/tilt head can have.
        """
        with self._lock:
            pkt = vp.pan_tilt_pos_inquiry(self.address)
            data, t = self.inquiry(pkt, 'Pan-tiltPosInq', data_len=8)
            try:
                pan, tilt = vp.parse_position_reply(data)
            except vp.ViscaProtocolError as e:
                raise self._bad_reply(f'Pan-tiltPosInq: {e}') from None
            pr = self.profile
            if check_range:
                ok, allowed = pr.in_range(pan, tilt), pr.range_text()
            else:
                ok = abs(pr.pan_deg(pan)) <= 360.0 and abs(pr.tilt_deg(tilt)) <= 180.0
                allowed = 'what any pan/tilt head can reach (|pan| <= 360 deg, |tilt| <= 180 deg)'
            if not ok:
                raise self._bad_reply(f'Pan-tiltPosInq reply pan {pan} units ({pr.pan_deg(pan):.4g} deg), tilt '
                                      f'{tilt} units ({pr.tilt_deg(tilt):.4g} deg) is outside {allowed}: '
                                      f'data {data.hex(" ")}')
            latest = t - 11 * self.byte_time
            return PositionReading(pan, tilt, min(self.last_arrival, latest), latest)

    def position(self, check_range: bool = True) -> tuple[int, int]:
        r = self.position_timed(check_range)
        return r.pan, r.tilt

    def position_deg(self) -> tuple[float, float]:
        pan, tilt = self.position()
        return self.profile.pan_deg(pan), self.profile.tilt_deg(tilt)

    def position_rad(self) -> tuple[float, float]:
        p, t = self.position_deg()
        return math.radians(p), math.radians(t)

    def zoom_to(self, position: int, wait: bool = True) -> int:
        return self.command(vp.zoom_direct(self.address, _as_int(position, 'zoom position')), 'CAM_Zoom',
                            wait=wait, completion_timeout_s=10.0)

    def zoom_position(self) -> int:
        with self._lock:
            data, _ = self.inquiry(vp.zoom_pos_inquiry(self.address), 'CAM_ZoomPosInq', data_len=4)
            try:
                zoom = vp.decode_nibbles(data, signed=False)
            except vp.ViscaProtocolError as e:
                raise self._bad_reply(f'CAM_ZoomPosInq: {e}') from None
            if zoom > self.profile.zoom_max:
                raise self._bad_reply(f'CAM_ZoomPosInq reply {zoom:#06x} is above {self.profile.name} '
                                      f'zoom_max {self.profile.zoom_max:#06x}')
            return zoom

    def version(self) -> dict[str, int]:
        data, _ = self.inquiry(vp.version_inquiry(self.address), 'CAM_VersionInq', data_len=7)
        return {'vendor': data[0] << 8 | data[1], 'model': data[2] << 8 | data[3],
                'rom': data[4] << 8 | data[5], 'max_socket': data[6]}


@dataclass(frozen=True)
class ModelCheck:
    """What :func:`check_model` found: ``outcome`` is 'match', 'mismatch', 'unchecked' (the profile lists no
    model id) or 'no_answer' (silence, an error reply or a malformed one); ``message`` is one log line.
    ``final`` is False for a no-answer that may pass (silence, garbled bytes, a lost port, e.g. just after a
    reconnect); an error reply (old firmware refusing the inquiry) is final."""

    outcome: str
    message: str
    version: dict[str, int] | None = None
    expected: tuple[int, ...] = ()
    final: bool = True


def check_model(cam: ViscaCamera) -> ModelCheck:
    """Ask the camera's model (CAM_VersionInq, one bounded inquiry) and compare it with the profile's
    ``model_ids``. A wrong profile gives wrong units per degree, ranges and speeds, so every joint angle would
    be scaled wrong without any serial error; this is the one place that can tell. Never raises a VISCA error:
    old firmware may not know the inquiry (silence or a syntax error), which is reported, not fatal."""
    pr = cam.profile
    expected = tuple(pr.model_ids)
    try:
        v = cam.version()
    except vp.ViscaError as e:
        return ModelCheck('no_answer', f'{cam.port}: no usable answer to CAM_VersionInq ({type(e).__name__}: {e}); '
                                       f'camera model not checked against profile {pr.name}', None, expected,
                          final=isinstance(e, vp.ViscaReplyError))
    found = (f'model {model_text(v["model"])}, vendor {v["vendor"]:#06x}, ROM {v["rom"]:#06x}, '
             f'{v["max_socket"]} sockets')
    if not expected:
        return ModelCheck('unchecked', f'{cam.port}: camera answers {found}; profile {pr.name} lists no model id, '
                                       'so it is not checked', v, expected)
    if v['model'] in expected:
        return ModelCheck('match', f'{cam.port}: camera {found}: matches profile {pr.name}', v, expected)
    want = ' or '.join(model_text(m) for m in expected)
    return ModelCheck('mismatch', f'{cam.port}: camera model mismatch: profile {pr.name} expects model {want}, the '
                                  f'camera answers {found}; its units per degree, ranges and speeds may differ '
                                  '(set the profile parameter to the camera\'s)', v, expected)


def measure_limits(cam: ViscaCamera, settle_s: float = 0.3, timeout_s: float = 30.0) -> dict[str, int]:
    """Drive to each end stop at full speed and read the position where it stops (for ``calibrate``).

    An axis has reached its stop when two PosInq readings ``settle_s`` apart agree. The readings are not
    checked against the profile's range (measuring the real one is the point), only for plausibility.
    """
    settle_s = check_seconds(settle_s, 'settle_s', MAX_SETTLE_S, allow_zero=True)
    timeout_s = check_seconds(timeout_s, 'timeout_s', MAX_WAIT_S)
    result: dict[str, int] = {}
    pr = cam.profile
    for key, (pan_sign, tilt_sign), idx in (('pan_min', (-1, 0), 0), ('pan_max', (1, 0), 0),
                                            ('tilt_min', (0, -1), 1), ('tilt_max', (0, 1), 1)):
        cam.drive(pan_sign * pr.pan_speed_max, tilt_sign * pr.tilt_speed_max)
        try:
            deadline = time.monotonic() + timeout_s
            last = cam.position(check_range=False)[idx]
            while True:
                time.sleep(settle_s)
                now = cam.position(check_range=False)[idx]
                if now == last:
                    break
                if time.monotonic() > deadline:
                    raise vp.ViscaTimeoutError(f'{key}: axis still moving after {timeout_s} s')
                last = now
        finally:
            with contextlib.suppress(vp.ViscaError):    # never leave the head driving; the first error wins
                cam.stop()
        result[key] = now
    return result
