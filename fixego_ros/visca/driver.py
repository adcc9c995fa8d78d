"""VISCA over RS-232 (pyserial): one camera, synchronous calls, bounded waits, automatic reconnect.

Rules that keep the link sane at 9600 baud (~1 ms per byte):
- one command in flight per socket, and the next command is sent only after the previous one was
  ACKed (or failed); completions of earlier commands are picked up whenever bytes are read;
- every read has a deadline (nothing blocks forever); after a timeout the input is drained before the
  next command, so a late reply is never taken for the answer to a new command;
- garbage, dropped bytes and unsolicited packets are skipped by resynchronising on ``FF``;
- a vanished device raises :class:`ViscaDisconnectedError`; later calls reopen the port with exponential
  back-off (calls made before the next retry time fail fast instead of waiting).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import serial

from fixego_ros.visca import protocol as vp
from fixego_ros.visca.profiles import CameraProfile, get_profile
from fixego_ros.visca.protocol import Reply, ReplyKind


class ViscaCamera:
    """One VISCA camera on a serial port. Thread-safe (calls are serialised by a lock)."""

    def __init__(self, port: str, baud: int = 9600, address: int = 1, profile: str | CameraProfile = 'evi_d30',
                 timeout_s: float = 0.3, reconnect: bool = True, backoff_s: tuple[float, float] = (0.05, 2.0),
                 serial_factory: Callable[..., Any] | None = None) -> None:
        self.port = port
        self.baud = int(baud)
        self.address = int(address)
        self.profile = profile if isinstance(profile, CameraProfile) else get_profile(profile)
        self.timeout_s = float(timeout_s)
        self.reconnect = reconnect
        self.backoff_min, self.backoff_max = backoff_s
        self.byte_time = 10.0 / self.baud
        self._factory = serial_factory or serial.Serial
        self._ser: Any = None
        self._lock = threading.RLock()
        self._splitter = vp.PacketSplitter()
        self._pending: list[bytes] = []
        self._busy: dict[int, str] = {}          # socket -> command name awaiting completion
        self._async_errors: dict[int, vp.ViscaReplyError] = {}
        self._dirty = False
        self._backoff = self.backoff_min
        self._next_retry = 0.0
        self._ever_open = False
        self.state = 'closed'
        self.last_error = ''
        self.stats: dict[str, int] = {k: 0 for k in (
            'commands', 'inquiries', 'timeouts', 'reply_errors', 'protocol_errors', 'garbage_bytes',
            'disconnects', 'reconnects', 'open_failures', 'unsolicited')}

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
        except (serial.SerialException, OSError, ValueError) as e:
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
        try:
            self._ser.write(pkt)
            self._ser.flush()
        except (serial.SerialException, OSError) as e:
            raise self._lost(e) from None

    def _read_packet(self, deadline: float) -> bytes | None:
        """Next complete packet before ``deadline`` (monotonic), else None."""
        while True:
            if self._pending:
                return self._pending.pop(0)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            try:
                self._ser.timeout = min(remaining, 0.05)
                data = self._ser.read(max(1, self._ser.in_waiting))
            except (serial.SerialException, OSError, TypeError, AttributeError) as e:
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
        """Parse; book-keep asynchronous completions/errors; return the reply if a caller may want it."""
        try:
            r = vp.parse_reply(pkt)
        except vp.ViscaProtocolError:
            self.stats['protocol_errors'] += 1
            return None
        if r.kind in (ReplyKind.ADDRESS, ReplyKind.IF_CLEAR):
            return r
        if r.address != self.address:
            self.stats['unsolicited'] += 1
            return None
        if r.kind == ReplyKind.NETWORK_CHANGE:
            self.stats['unsolicited'] += 1
            self._busy.clear()
            return None
        if r.kind == ReplyKind.COMPLETION and r.socket in self._busy:
            del self._busy[r.socket]
            return r
        if r.kind == ReplyKind.ERROR and r.socket in self._busy:
            self._busy.pop(r.socket, None)
            self._async_errors[r.socket] = r.error()
            self.stats['reply_errors'] += 1
            return r
        return r

    # ------------------------------------------------------------------------------ transactions
    def _timeout(self, what: str) -> vp.ViscaTimeoutError:
        self.stats['timeouts'] += 1
        self._dirty = True
        self.last_error = f'timeout waiting for {what}'
        return vp.ViscaTimeoutError(f'{self.port}: no {what} within the timeout')

    def _exchange(self, pkt: bytes, what: str, reply_bytes: int, accept: Callable[[Reply], bool]) -> Reply:
        """Write ``pkt`` and return the first reply ``accept`` takes, within the timeout plus the
        serial time of ``reply_bytes``; other packets are book-kept by :meth:`_classify`."""
        self._write(pkt)
        deadline = time.monotonic() + self.timeout_s + reply_bytes * self.byte_time
        while True:
            raw = self._read_packet(deadline)
            if raw is None:
                raise self._timeout(what)
            r = self._classify(raw)
            if r is not None and accept(r):
                return r

    def command(self, pkt: bytes, name: str = 'command', wait: bool = True,
                completion_timeout_s: float | None = None) -> int:
        """Send a command, wait for its ACK (and completion when ``wait``); returns the socket.

        Raises a :class:`~fixego_ros.visca.protocol.ViscaReplyError` subclass for error replies,
        :class:`ViscaTimeoutError` or :class:`ViscaDisconnectedError`.
        """
        with self._lock:
            self.stats['commands'] += 1
            self._write(pkt)
            deadline = time.monotonic() + self.timeout_s + (len(pkt) + 4) * self.byte_time
            socket = None
            while socket is None:
                raw = self._read_packet(deadline)
                if raw is None:
                    raise self._timeout(f'ACK for {name}')
                r = self._classify(raw)
                if r is None:
                    continue
                if r.kind == ReplyKind.ACK:
                    socket = r.socket
                elif r.kind == ReplyKind.ERROR and r.socket not in self._async_errors:
                    self.stats['reply_errors'] += 1
                    raise r.error()
                elif r.kind == ReplyKind.COMPLETION and r.socket == 0:
                    return 0                   # IF_Clear (addressed) answers z0 50 FF without an ACK
            self._async_errors.pop(socket, None)
            self._busy[socket] = name
            if wait:
                self._wait_socket(socket, name, completion_timeout_s or 5.0)
            return socket

    def _wait_socket(self, socket: int, name: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while socket in self._busy:
            raw = self._read_packet(deadline)
            if raw is None:
                self._busy.pop(socket, None)
                raise self._timeout(f'completion of {name}')
            self._classify(raw)
        err = self._async_errors.pop(socket, None)
        if err is not None:
            raise err

    def inquiry(self, pkt: bytes, name: str = 'inquiry') -> tuple[bytes, float]:
        """Send an inquiry; returns (payload, monotonic time the last reply byte arrived)."""
        with self._lock:
            self.stats['inquiries'] += 1
            self._write(pkt)
            deadline = time.monotonic() + self.timeout_s + (len(pkt) + 16) * self.byte_time
            while True:
                raw = self._read_packet(deadline)
                if raw is None:
                    raise self._timeout(f'reply to {name}')
                t = time.monotonic()
                r = self._classify(raw)
                if r is None:
                    continue
                if r.kind == ReplyKind.INQUIRY:
                    return r.data, t
                if r.kind == ReplyKind.ERROR and r.socket == 0:
                    self.stats['reply_errors'] += 1
                    raise r.error()

    def wait_idle(self, timeout_s: float = 5.0) -> None:
        """Wait until every command we sent has completed (or raise its error)."""
        with self._lock:
            for s, name in list(self._busy.items()):
                self._wait_socket(s, name, timeout_s)

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
            self._async_errors.clear()

    def cancel(self, socket: int) -> None:
        """Cancel the command on ``socket``; raises NoSocketError when nothing runs there."""
        with self._lock:
            r = self._exchange(vp.cancel(self.address, socket), 'Cancel reply', 8,
                               lambda r: r.kind == ReplyKind.ERROR and r.socket == socket)
            self._async_errors.pop(socket, None)
            if r.error_code != vp.ERR_CANCELLED:
                raise r.error()

    def power(self, on: bool) -> None:
        self.command(vp.power(self.address, on), 'CAM_Power', completion_timeout_s=10.0)

    def power_state(self) -> bool:
        data, _ = self.inquiry(vp.power_inquiry(self.address), 'CAM_PowerInq')
        return data[:1] == b'\x02'

    def _codes(self, pan_speed: int | None, tilt_speed: int | None) -> tuple[int, int]:
        pr = self.profile
        ps = pr.pan_speed_max if pan_speed is None else int(pan_speed)
        ts = pr.tilt_speed_max if tilt_speed is None else int(tilt_speed)
        return min(max(ps, 1), pr.pan_speed_max), min(max(ts, 1), pr.tilt_speed_max)

    def drive(self, pan_speed: int, tilt_speed: int) -> None:
        """Continuous drive with signed speed codes (+pan right, +tilt up, 0 stops that axis)."""
        pr = self.profile
        direction = vp.Direction.from_signs(pan_speed, tilt_speed)
        ps = min(max(abs(int(pan_speed)), 1), pr.pan_speed_max)      # never send a zero speed
        ts = min(max(abs(int(tilt_speed)), 1), pr.tilt_speed_max)
        self.command(vp.pan_tilt_drive(self.address, direction, ps, ts), 'Pan-tiltDrive', wait=True,
                     completion_timeout_s=1.0)

    def stop(self) -> None:
        self.drive(0, 0)

    def _motion_timeout(self, d_pan_units: float, d_tilt_units: float, ps: int, ts: int) -> float:
        pr = self.profile
        tp = abs(d_pan_units) / pr.pan_units_per_deg / pr.pan_speed_deg_s(ps)
        tt = abs(d_tilt_units) / pr.tilt_units_per_deg / pr.tilt_speed_deg_s(ts)
        return 1.5 * max(tp, tt) + 1.0 + 40 * self.byte_time

    def absolute(self, pan: int, tilt: int, pan_speed: int | None = None, tilt_speed: int | None = None,
                 wait: bool = True, check_range: bool = True, timeout_s: float | None = None) -> int:
        """AbsolutePosition in VISCA units; returns the socket. Out-of-range raises ValueError unless
        ``check_range=False`` (then the camera's own error is raised)."""
        pan, tilt = int(pan), int(tilt)
        if check_range and not self.profile.in_range(pan, tilt):
            raise ValueError(f'position ({pan}, {tilt}) outside {self.profile.name} range '
                             f'pan {self.profile.pan_min}..{self.profile.pan_max}, '
                             f'tilt {self.profile.tilt_min}..{self.profile.tilt_max}')
        ps, ts = self._codes(pan_speed, tilt_speed)
        if timeout_s is None:
            span = (self.profile.pan_max - self.profile.pan_min, self.profile.tilt_max - self.profile.tilt_min)
            timeout_s = self._motion_timeout(*span, ps, ts)
        return self.command(vp.absolute_position(self.address, ps, ts, pan, tilt), 'AbsolutePosition',
                            wait=wait, completion_timeout_s=timeout_s)

    def relative(self, d_pan: int, d_tilt: int, pan_speed: int | None = None, tilt_speed: int | None = None,
                 wait: bool = True, timeout_s: float | None = None) -> int:
        ps, ts = self._codes(pan_speed, tilt_speed)
        timeout_s = timeout_s or self._motion_timeout(d_pan, d_tilt, ps, ts)
        return self.command(vp.relative_position(self.address, ps, ts, int(d_pan), int(d_tilt)),
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
                            completion_timeout_s=2.0 * self._motion_timeout(
                                pr.pan_max - pr.pan_min, pr.tilt_max - pr.tilt_min,
                                pr.pan_speed_max, pr.tilt_speed_max) + 5.0)

    def position_timed(self) -> tuple[int, int, float]:
        """(pan units, tilt units, monotonic time the camera sampled them).

        The camera answers as soon as the inquiry is in; the 11-byte reply then takes its serial time,
        so the sample time is the arrival of the last byte minus the reply's transmission time.
        """
        data, t = self.inquiry(vp.pan_tilt_pos_inquiry(self.address), 'Pan-tiltPosInq')
        pan, tilt = vp.parse_position_reply(data)
        return pan, tilt, t - 11 * self.byte_time

    def position(self) -> tuple[int, int]:
        pan, tilt, _ = self.position_timed()
        return pan, tilt

    def position_deg(self) -> tuple[float, float]:
        pan, tilt = self.position()
        return self.profile.pan_deg(pan), self.profile.tilt_deg(tilt)

    def position_rad(self) -> tuple[float, float]:
        p, t = self.position_deg()
        return math.radians(p), math.radians(t)

    def zoom_to(self, position: int, wait: bool = True) -> int:
        return self.command(vp.zoom_direct(self.address, int(position)), 'CAM_Zoom', wait=wait,
                            completion_timeout_s=10.0)

    def zoom_position(self) -> int:
        data, _ = self.inquiry(vp.zoom_pos_inquiry(self.address), 'CAM_ZoomPosInq')
        return vp.decode_nibbles(data[:4], signed=False)

    def version(self) -> dict[str, int]:
        data, _ = self.inquiry(vp.version_inquiry(self.address), 'CAM_VersionInq')
        if len(data) < 7:
            raise vp.ViscaProtocolError(f'version reply too short: {data.hex(" ")}')
        return {'vendor': data[0] << 8 | data[1], 'model': data[2] << 8 | data[3],
                'rom': data[4] << 8 | data[5], 'max_socket': data[6]}


def measure_limits(cam: ViscaCamera, settle_s: float = 0.3, timeout_s: float = 30.0) -> dict[str, int]:
    """Drive to each end stop at full speed and read the position where it stops (for ``calibrate``).

    An axis has reached its stop when two PosInq readings ``settle_s`` apart agree.
    """
    result: dict[str, int] = {}
    pr = cam.profile
    for key, (pan_sign, tilt_sign), idx in (('pan_min', (-1, 0), 0), ('pan_max', (1, 0), 0),
                                            ('tilt_min', (0, -1), 1), ('tilt_max', (0, 1), 1)):
        cam.drive(pan_sign * pr.pan_speed_max, tilt_sign * pr.tilt_speed_max)
        deadline = time.monotonic() + timeout_s
        last = cam.position()[idx]
        while True:
            time.sleep(settle_s)
            now = cam.position()[idx]
            if now == last:
                break
            if time.monotonic() > deadline:
                cam.stop()
                raise vp.ViscaTimeoutError(f'{key}: axis still moving after {timeout_s} s')
            last = now
        cam.stop()
        result[key] = now
    return result
