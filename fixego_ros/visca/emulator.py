"""A VISCA pan/tilt camera served on a pseudo-terminal, for tests, the simulator and ``make demo``.

Faithful where the servo and the driver can tell the difference: every byte takes its serial time
(10 bits per byte at ``baud``), replies use the camera's address, motion runs at the profile's speed
table within its range, motion commands are ACKed on a socket (two sockets) and completed when the
motion ends, and the documented errors are produced. Assumptions where the manuals are silent (and
documented here because a driver could depend on them):

- a new pan/tilt motion command needs a free socket (else ``buffer full``); it supersedes the running
  pan/tilt motion, whose socket then completes at once;
- absolute/relative targets outside the range, speed codes 0 or above the profile's maximum, and
  unknown commands answer ``z0 60 02 FF`` (syntax error / illegal parameter);
- motion has no acceleration phase; Reset is Home at full speed followed by ``reset_delay_s``;
- when powered off, commands other than power on answer ``z0 6y 41 FF`` (not executable);
- after a disconnect the camera comes back on a new pty (``link_path`` is a stable symlink to it)
  and announces itself with a network-change packet ``z0 38 FF``.

Faults (:class:`EmulatorFaults`) are real bytes on the pty: silence, lost or corrupted bytes, unsolicited
packets now or part-way through a move (a network change mid-AbsolutePosition), replies replaced by
truncated, foreign-address or error packets, a position counter reporting impossible values, and a
CAM_VersionInq answered with another model, with silence or with a syntax error (old firmware).

The true angles over time (:meth:`ViscaEmulator.pan_tilt_rad`) let the simulator render what the
camera sees. Angles follow VISCA: positive pan = right, positive tilt = up.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import math
import os
import random
import select
import shutil
import tempfile
import termios
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from fixego_ros.visca import protocol as vp
from fixego_ros.visca.driver import prompt_serial_threads
from fixego_ros.visca.profiles import CameraProfile, get_profile


@dataclass
class _Axis:
    """Piecewise-linear motion of one axis from time t0 (deg, deg/s)."""

    t0: float
    p0: float
    v: float = 0.0
    end: float | None = None       # target (stop there); None = drive until the limit
    lo: float = -math.inf
    hi: float = math.inf

    def at(self, t: float) -> float:
        p = self.p0 + self.v * max(0.0, t - self.t0)
        if self.end is not None:
            p = min(p, self.end) if self.v > 0 else max(p, self.end) if self.v < 0 else self.p0
        return min(max(p, self.lo), self.hi)

    def done_at(self) -> float:
        if self.v == 0.0:
            return self.t0
        goal = self.end if self.end is not None else (self.hi if self.v > 0 else self.lo)
        return self.t0 + abs(goal - self.p0) / abs(self.v)


class EmulatorFaults:
    """Fault injection. Plain fields are read by the serving thread on every byte/packet."""

    def __init__(self, emu: ViscaEmulator, seed: int = 0) -> None:
        self._emu = emu
        self.silent = False          # read commands but never answer (a hung or unpowered camera)
        self.drop_prob = 0.0         # each outgoing byte is lost with this probability
        self.corrupt_prob = 0.0      # each outgoing byte is XORed with a random bit
        self.rx_drop_prob = 0.0      # each incoming byte is lost
        # Pan-tiltPosInq answers this (pan, tilt) in units (signed 16-bit) instead of the true position:
        # a camera with a corrupted counter, or another model than the profile says
        self.position_override: tuple[int, int] | None = None
        # CAM_VersionInq: 'answer' (the profile's version, or ``version_override``), 'silent' (no reply) or
        # 'syntax_error' (``z0 60 02 FF``): old firmware that does not know the inquiry
        self.version_reply = 'answer'
        self.version_override: tuple[int, int, int, int] | None = None   # (vendor, model, rom, max socket)
        self.rng = random.Random(seed)
        self._replace: deque[bytes] = deque()
        self._mid_motion: deque[tuple[bytes, float]] = deque()

    def inject(self, data: bytes) -> None:
        """Send unsolicited bytes as soon as the line is free (noise, a stray reply, ...)."""
        self._emu._post(lambda t: self._emu._send(bytes(data), t, faults=False))

    def inject_mid_motion(self, data: bytes, fraction: float = 0.5) -> None:
        """Send ``data`` unsolicited ``fraction`` of the way through the next timed pan/tilt move
        (absolute, relative, home, reset), i.e. after its ACK and before its completion."""
        if not 0.0 < fraction < 1.0:
            raise ValueError(f'fraction must be in (0, 1), got {fraction!r}')
        self._mid_motion.append((bytes(data), float(fraction)))

    def replace_replies(self, *packets: bytes) -> None:
        """The next ``len(packets)`` packets the camera sends are replaced by these bytes (b'' = lost):
        truncated or garbled replies, another camera's address, error replies where an ACK was due."""
        self._replace.extend(bytes(p) for p in packets)

    def disconnect(self, duration_s: float = 0.5) -> None:
        """The device vanishes (pty closed) and reappears after ``duration_s`` at ``link_path``."""
        self._emu._post(lambda t: self._emu._disconnect(t, duration_s))


class ViscaEmulator:
    """A VISCA camera on a pty; see the module docstring for the behaviour."""

    def __init__(self, profile: str | CameraProfile = 'evi_d30', address: int = 1, baud: int = 9600,
                 start_pan_deg: float = 0.0, start_tilt_deg: float = 0.0, reset_delay_s: float = 0.3,
                 zoom_full_range_s: float = 2.0, seed: int = 0) -> None:
        self.profile = profile if isinstance(profile, CameraProfile) else get_profile(profile)
        self.address = address
        self.baud = baud
        self.byte_time = 10.0 / baud
        self.reset_delay_s = reset_delay_s
        self.zoom_full_range_s = zoom_full_range_s
        self.faults = EmulatorFaults(self, seed)
        pr = self.profile
        self._pan_lim = (pr.pan_deg(pr.pan_min), pr.pan_deg(pr.pan_max))
        self._tilt_lim = (pr.tilt_deg(pr.tilt_min), pr.tilt_deg(pr.tilt_max))
        t = time.monotonic()
        self._pan = _Axis(t, float(start_pan_deg), lo=self._pan_lim[0], hi=self._pan_lim[1])
        self._tilt = _Axis(t, float(start_tilt_deg), lo=self._tilt_lim[0], hi=self._tilt_lim[1])
        self._history: deque[tuple[float, _Axis, _Axis]] = deque([(-math.inf, self._pan, self._tilt)],
                                                                  maxlen=256)
        self._zoom = 0
        self._power = True
        self._sockets: dict[int, str] = {}   # busy socket -> 'pantilt' | 'zoom' | 'power'
        self._motion_gen = 0
        self._motion_socket: int | None = None
        self._lock = threading.RLock()
        self._events: list[tuple[float, int, Callable[[float], None]]] = []
        self._seq = itertools.count()
        self._posted: deque[Callable[[float], None]] = deque()
        self._rx_clock = 0.0
        self._tx_clock = 0.0
        self._splitter = vp.PacketSplitter(max_len=64, min_len=2)
        self._master: int | None = None
        self._slave: int | None = None
        self._wake_r, self._wake_w = -1, -1
        self._thread: threading.Thread | None = None
        self._running = False
        self._tmpdir: str | None = None
        self.port: str | None = None         # current slave path (changes after a disconnect)
        self.link_path: str | None = None    # stable symlink to the current slave
        self.stats = {'rx_packets': 0, 'tx_packets': 0, 'errors_sent': 0, 'disconnects': 0}
        self.log: deque[tuple[float, str, bytes]] = deque(maxlen=500)  # (t, 'rx'|'tx', packet)

    # ------------------------------------------------------------------------------ public API
    def start(self) -> str:
        """Open the pty and serve it on a daemon thread; returns the slave path."""
        if self._running:
            assert self.port is not None
            return self.port
        self._tmpdir = tempfile.mkdtemp(prefix='fixego-visca-')
        self.link_path = os.path.join(self._tmpdir, 'tty')
        self._open_pty()
        self._wake_r, self._wake_w = os.pipe()
        prompt_serial_threads()     # its byte timing is the device's: rendering in the same process must not delay it
        self._running = True
        self._thread = threading.Thread(target=self._serve, name=f'visca-emu-{self.address}', daemon=True)
        self._thread.start()
        assert self.port is not None
        return self.port

    def stop(self) -> None:
        """Idempotent: stop the thread and close the pty."""
        if not self._running and self._thread is None:
            return
        self._running = False
        if self._wake_w >= 0:
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b'x')
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_pty()
        for fd in (self._wake_r, self._wake_w):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._wake_r = self._wake_w = -1
        if self._tmpdir:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def __enter__(self) -> ViscaEmulator:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def pan_tilt_deg(self, t: float | None = None) -> tuple[float, float]:
        """True mechanical angles (deg) at monotonic time ``t`` (default now); thread-safe."""
        t = time.monotonic() if t is None else t
        with self._lock:
            for t_start, pan, tilt in reversed(self._history):
                if t >= t_start:
                    return pan.at(t), tilt.at(t)
            _, pan, tilt = self._history[0]
            return pan.at(t), tilt.at(t)

    def pan_tilt_rad(self, t: float | None = None) -> tuple[float, float]:
        """True mechanical angles (rad) at monotonic time ``t`` (default now); thread-safe."""
        p, q = self.pan_tilt_deg(t)
        return math.radians(p), math.radians(q)

    def pan_tilt_units(self, t: float | None = None) -> tuple[int, int]:
        p, q = self.pan_tilt_deg(t)
        return self.profile.pan_units(p), self.profile.tilt_units(q)

    @property
    def zoom(self) -> int:
        return self._zoom

    @property
    def powered(self) -> bool:
        return self._power

    def busy_sockets(self) -> dict[int, str]:
        with self._lock:
            return dict(self._sockets)

    # ------------------------------------------------------------------------------ pty handling
    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)              # no echo / line discipline before the host configures it
        attrs = termios.tcgetattr(slave)
        attrs[2] |= termios.CLOCAL
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.port = os.ttyname(slave)
        assert self.link_path is not None
        tmp = self.link_path + '.new'
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        os.symlink(self.port, tmp)
        os.replace(tmp, self.link_path)

    def _close_pty(self) -> None:
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None

    def _disconnect(self, t: float, duration_s: float) -> None:
        self.stats['disconnects'] += 1
        self._close_pty()
        self._splitter.reset()
        with self._lock:
            self._sockets.clear()
            self._motion_socket = None
            self._motion_gen += 1
            self._set_motion(t, 0.0, None, 0.0, None)   # power loss: stop where it is
        self._events = [e for e in self._events if getattr(e[2], 'keep', False)]
        heapq.heapify(self._events)
        self._schedule(t + max(0.0, duration_s), self._reconnect)

    def _reconnect(self, t: float) -> None:
        if self._master is None and self._running:
            self._open_pty()
            self._rx_clock = self._tx_clock = t
            self._send(vp.network_change(self.address), t)

    # ------------------------------------------------------------------------------ event loop
    def _post(self, fn: Callable[[float], None]) -> None:
        self._posted.append(fn)
        if self._wake_w >= 0:
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b'x')

    def _schedule(self, t: float, fn: Callable[[float], None]) -> None:
        heapq.heappush(self._events, (t, next(self._seq), fn))

    def _serve(self) -> None:
        while self._running:
            now = time.monotonic()
            while self._posted:
                self._posted.popleft()(now)
            while self._events and self._events[0][0] <= now:
                t, _, fn = heapq.heappop(self._events)
                try:
                    # An event this thread reaches late (it shares a CPU, and a GIL, with whatever hosts it) happens
                    # when it is handled, as on a camera whose processor is busy: an inquiry samples the head then
                    # and its reply leaves after that, a motion starts then. Dating it back to when it was due would
                    # make a late reply look sampled later than it was, and rewrite a motion the renderer has
                    # already shown.
                    fn(max(t, time.monotonic()))
                except Exception as e:
                    self.stats['internal_errors'] = self.stats.get('internal_errors', 0) + 1
                    self.last_internal_error = repr(e)
            timeout = 0.05
            if self._events:
                timeout = min(timeout, max(0.0, self._events[0][0] - time.monotonic()))
            fds = [self._wake_r] + ([self._master] if self._master is not None else [])
            try:
                readable, _, _ = select.select(fds, [], [], timeout)
            except (OSError, ValueError):
                continue
            if self._wake_r in readable:
                with contextlib.suppress(OSError):
                    os.read(self._wake_r, 256)
            if self._master is not None and self._master in readable:
                try:
                    data = os.read(self._master, 4096)
                except BlockingIOError:
                    continue
                except OSError:       # no slave open (EIO): nothing to read
                    time.sleep(0.01)
                    continue
                self._receive(data, time.monotonic())

    def _receive(self, data: bytes, now: float) -> None:
        t = max(self._rx_clock, now)
        for b in data:
            t += self.byte_time
            if self.faults.rx_drop_prob and self.faults.rng.random() < self.faults.rx_drop_prob:
                continue
            for pkt in self._splitter.feed(bytes((b,))):
                self._schedule(t, lambda tt, p=pkt: self._handle(p, tt))
        self._rx_clock = t

    def _send(self, pkt: bytes, t: float, faults: bool = True) -> None:
        """Queue ``pkt`` to be written when its last byte would have left the UART."""
        if faults and self.faults.silent:
            return
        if faults and self.faults._replace:
            pkt = self.faults._replace.popleft()
            if not pkt:
                return
        out = bytearray()
        for b in pkt:
            if faults and self.faults.drop_prob and self.faults.rng.random() < self.faults.drop_prob:
                continue
            if faults and self.faults.corrupt_prob and self.faults.rng.random() < self.faults.corrupt_prob:
                b ^= 1 << self.faults.rng.randrange(8)
            out.append(b)
        self._tx_clock = max(self._tx_clock, t) + len(pkt) * self.byte_time
        self._schedule(self._tx_clock, lambda tt, d=bytes(out), p=pkt: self._write(d, p, tt))

    def _write(self, data: bytes, pkt: bytes, t: float) -> None:
        if self._master is None or not data:
            return
        # logged before the write: the driver may read the bytes and a test look at the log before the
        # line after os.write runs
        self.log.append((t, 'tx', pkt))
        try:
            os.write(self._master, data)
            self.stats['tx_packets'] += 1
        except OSError:
            pass

    # ------------------------------------------------------------------------------ commands
    def _reply_error(self, socket: int, code: int, t: float) -> None:
        self.stats['errors_sent'] += 1
        self._send(vp.error_reply(self.address, socket, code), t)

    def _free_socket(self) -> int | None:
        for s in (1, 2):
            if s not in self._sockets:
                return s
        return None

    def _handle(self, pkt: bytes, t: float) -> None:
        self.stats['rx_packets'] += 1
        self.log.append((t, 'rx', pkt))
        if self.faults.silent:
            return
        head = pkt[0]
        if head == vp.BROADCAST:
            self._handle_broadcast(pkt, t)
            return
        if head != 0x80 | self.address:
            return                              # for another camera on the chain
        if len(pkt) < 3 or len(pkt) > vp.MAX_PACKET:
            self._reply_error(0, vp.ERR_LENGTH, t)
            return
        body = pkt[1:-1]
        with self._lock:
            try:
                self._dispatch(body, t)
            except (_SyntaxError, vp.ViscaProtocolError):
                self._reply_error(0, vp.ERR_SYNTAX, t)

    def _handle_broadcast(self, pkt: bytes, t: float) -> None:
        if len(pkt) == 4 and pkt[1] == 0x30 and 1 <= pkt[2] <= 7:
            self.address = pkt[2]
            self._send(bytes((vp.BROADCAST, 0x30, pkt[2] + 1, 0xFF)), t)
        elif pkt == vp.if_clear(None):
            with self._lock:
                self._clear(t)
            self._send(pkt, t)

    def _clear(self, t: float) -> None:
        """IF_Clear: empty the command buffers; a continuous drive stops."""
        self._sockets.clear()
        self._motion_socket = None
        self._motion_gen += 1
        self._set_motion(t, 0.0, None, 0.0, None)

    def _dispatch(self, body: bytes, t: float) -> None:
        a = self.address
        if len(body) == 1 and body[0] >> 4 == 2:                       # Cancel 2y
            y = body[0] & 0x0F
            if y in self._sockets:
                kind = self._sockets.pop(y)
                if kind == 'pantilt' and self._motion_socket == y:
                    self._motion_socket = None
                    self._motion_gen += 1
                    self._set_motion(t, 0.0, None, 0.0, None)
                self._reply_error(y, vp.ERR_CANCELLED, t)
            else:
                self._reply_error(y, vp.ERR_NO_SOCKET, t)
            return
        if body == b'\x01\x00\x01':                                     # IF_Clear (addressed)
            self._clear(t)
            self._send(vp.completion(a, 0), t)
            return
        if body[:1] == b'\x09':
            self._inquiry(body[1:], t)
            return
        if body[:1] != b'\x01' or len(body) < 3:
            raise _SyntaxError
        cat, cmd, args = body[1], body[2], body[3:]
        if (cat, cmd) == (0x04, 0x00):                                  # CAM_Power
            if args not in (b'\x02', b'\x03'):
                raise _SyntaxError
            self._power_cmd(args == b'\x02', t)
            return
        if cat == 0x06 and cmd in (0x01, 0x02, 0x03, 0x04, 0x05):
            self._pan_tilt_cmd(cmd, args, t)
            return
        if (cat, cmd) == (0x04, 0x47) and len(args) == 4:              # CAM_Zoom direct
            self._zoom_cmd(args, t)
            return
        raise _SyntaxError

    def _inquiry(self, q: bytes, t: float) -> None:
        a, pr = self.address, self.profile
        if q == b'\x06\x12':
            pan, tilt = self.faults.position_override or self.pan_tilt_units(t)
            self._send(vp.position_reply(a, pan, tilt), t)
        elif q == b'\x04\x47':
            self._send(vp.inquiry_reply(a, vp.encode_nibbles(self._zoom, 4, signed=False)), t)
        elif q == b'\x00\x02':
            if self.faults.version_reply == 'silent':
                return
            if self.faults.version_reply == 'syntax_error':
                raise _SyntaxError
            vendor, model, rom, sockets = self.faults.version_override or pr.version
            data = bytes(((vendor >> 8) & 0x7F, vendor & 0x7F, (model >> 8) & 0x7F, model & 0x7F,
                          (rom >> 8) & 0x7F, rom & 0x7F, sockets & 0x7F))
            self._send(vp.inquiry_reply(a, data), t)
        elif q == b'\x04\x00':
            self._send(vp.inquiry_reply(a, b'\x02' if self._power else b'\x03'), t)
        else:
            raise _SyntaxError

    def _accept(self, kind: str, t: float) -> int | None:
        """Take a socket and ACK, or answer buffer full / not executable; returns the socket."""
        s = self._free_socket()
        if s is None:
            self._reply_error(0, vp.ERR_BUFFER_FULL, t)
            return None
        if not self._power and kind != 'power':
            self._reply_error(s, vp.ERR_NOT_EXECUTABLE, t)
            return None
        self._sockets[s] = kind
        self._send(vp.ack(self.address, s), t)
        return s

    def _complete(self, s: int, t: float, kind: str, gen: int | None = None) -> None:
        if self._sockets.get(s) != kind:
            return
        if gen is not None and gen != self._motion_gen:
            return
        del self._sockets[s]
        if kind == 'pantilt' and self._motion_socket == s:
            self._motion_socket = None
        self._send(vp.completion(self.address, s), t)

    def _power_cmd(self, on: bool, t: float) -> None:
        s = self._accept('power', t)
        if s is None:
            return
        self._power = on
        if not on:
            self._set_motion(t, 0.0, None, 0.0, None)
        self._schedule(t + 0.05, lambda tt: self._with_lock(self._complete, s, tt, 'power'))

    def _with_lock(self, fn: Callable[..., None], *args: object) -> None:
        with self._lock:
            fn(*args)

    def _speeds(self, vv: int, ww: int) -> tuple[float, float]:
        pr = self.profile
        if not 1 <= vv <= pr.pan_speed_max or not 1 <= ww <= pr.tilt_speed_max:
            raise _SyntaxError
        return pr.pan_speed_deg_s(vv), pr.tilt_speed_deg_s(ww)

    def _pan_tilt_cmd(self, cmd: int, args: bytes, t: float) -> None:
        pr = self.profile
        # validate everything before taking a socket: an illegal parameter never gets an ACK
        if cmd == 0x01:
            if len(args) != 4:
                raise _SyntaxError
            vp_, vt = self._speeds(args[0], args[1])
            dp, dt = args[2], args[3]
            if dp not in (1, 2, 3) or dt not in (1, 2, 3):
                raise _SyntaxError
            pan_v = {1: -vp_, 2: vp_, 3: 0.0}[dp]
            tilt_v = {1: vt, 2: -vt, 3: 0.0}[dt]
            s = self._accept('pantilt', t)
            if s is None:
                return
            self._supersede(t)
            self._set_motion(t, pan_v, None, tilt_v, None)
            self._complete(s, t, 'pantilt')        # a drive command completes when the drive starts
            return
        if cmd in (0x02, 0x03):
            if len(args) != 10:
                raise _SyntaxError
            vp_, vt = self._speeds(args[0], args[1])
            try:
                pan_u, tilt_u = vp.decode_position(args[2:6]), vp.decode_position(args[6:10])
            except vp.ViscaProtocolError:
                raise _SyntaxError from None
            if cmd == 0x03:
                cur_p, cur_t = self.pan_tilt_units(t)
                pan_u, tilt_u = cur_p + pan_u, cur_t + tilt_u
            if not pr.in_range(pan_u, tilt_u):
                raise _SyntaxError
            target = (pr.pan_deg(pan_u), pr.tilt_deg(tilt_u))
            extra = 0.0
        else:
            if args:
                raise _SyntaxError
            vp_, vt = pr.pan_speeds_deg_s[-1], pr.tilt_speeds_deg_s[-1]
            target = (0.0, 0.0)
            extra = self.reset_delay_s if cmd == 0x05 else 0.0
        s = self._accept('pantilt', t)
        if s is None:
            return
        self._supersede(t)
        p_now, q_now = self.pan_tilt_deg(t)
        pan_v = math.copysign(vp_, target[0] - p_now) if target[0] != p_now else 0.0
        tilt_v = math.copysign(vt, target[1] - q_now) if target[1] != q_now else 0.0
        done = self._set_motion(t, pan_v, target[0], tilt_v, target[1], start_delay=extra)
        self._motion_socket = s
        gen = self._motion_gen
        self._schedule(done, lambda tt: self._with_lock(self._complete, s, tt, 'pantilt', gen))
        if done > t and self.faults._mid_motion:
            data, fraction = self.faults._mid_motion.popleft()
            self._schedule(t + fraction * (done - t), lambda tt, d=data: self._send(d, tt, faults=False))

    def _supersede(self, t: float) -> None:
        old = self._motion_socket
        self._motion_gen += 1
        if old is not None and self._sockets.get(old) == 'pantilt':
            self._complete(old, t, 'pantilt')
        self._motion_socket = None

    def _set_motion(self, t: float, pan_v: float, pan_end: float | None, tilt_v: float,
                    tilt_end: float | None, start_delay: float = 0.0) -> float:
        """Start new axis segments at ``t``; returns when both reach their targets."""
        p, q = self.pan_tilt_deg(t)
        t0 = t + start_delay
        self._pan = _Axis(t0, p, pan_v, pan_end, *self._pan_lim)
        self._tilt = _Axis(t0, q, tilt_v, tilt_end, *self._tilt_lim)
        if start_delay:
            self._history.append((t, _Axis(t, p, lo=self._pan_lim[0], hi=self._pan_lim[1]),
                                  _Axis(t, q, lo=self._tilt_lim[0], hi=self._tilt_lim[1])))
        self._history.append((t0, self._pan, self._tilt))
        return max(self._pan.done_at() if pan_end is not None else t0,
                   self._tilt.done_at() if tilt_end is not None else t0)

    def _zoom_cmd(self, args: bytes, t: float) -> None:
        pos = vp.decode_nibbles(args, signed=False)
        if pos > self.profile.zoom_max:
            raise _SyntaxError
        old = [s for s, k in self._sockets.items() if k == 'zoom']
        s = self._accept('zoom', t)
        if s is None:
            return
        for o in old:
            self._complete(o, t, 'zoom')
        dur = abs(pos - self._zoom) / max(1, self.profile.zoom_max) * self.zoom_full_range_s
        self._zoom = pos

        def done(tt: float, s: int = s) -> None:
            with self._lock:
                if self._sockets.get(s) == 'zoom':
                    del self._sockets[s]
                    self._send(vp.completion(self.address, s), tt)
        self._schedule(t + dur, done)


class _SyntaxError(Exception):
    """Internal: answer ``z0 60 02 FF``."""
