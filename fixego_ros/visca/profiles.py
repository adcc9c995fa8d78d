"""Per-model pan/tilt numbers: limits, units per degree, speed tables.

Sources: Sony EVI-D30/D31 and EVI-D100 technical manuals (pan/tilt position and speed tables, also
reprinted in the D100 manual's "D30/31 mode" section) and the EVI-D70 technical manual (position
table). The D70 speed table is not in the pages we had: its speeds are a linear approximation to the
documented maxima and marked unverified. The EVI-G20 has **no public VISCA numbers**: its profile
copies the D30 and is marked unverified; measure a real unit with ``fixego ptz calibrate``.

Model ids (``CAM_VersionInq``, ``y0 50 GG GG HH HH JJ JJ KK FF``: vendor, model, ROM, max socket), checked by
camera_node on connect: only ids a Sony manual gives. The EVI-D70 technical manual lists 040E (EVI-D70/P) and
0402 (EVI-D30/D31, also what a D70 answers in its D30/D31 mode, where it speaks D30 units); the EVI-D80/D90,
EVI-HD7V/HD3V and FCB-EV7500 manuals give their own ids (:data:`MODEL_NAMES`, for messages). The EVI-D100 manual
names the field but gives no value (a third-party table says 040D: not used), and the EVI-G20 has no public
VISCA documentation, so ``evi_d100`` and ``evi_g20`` list no model id and are not checked. The vendor id is not
checked either: Sony's manuals give 0001 (D80, D100), 0010 (HD7V) and 0020 (D70, FCB) for Sony.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

# Serial rates every profile accepts: the Sony EVI RS-232 rates (9600; 19200/38400 on the D70/D100) plus the
# two higher standard UART rates of later VISCA cameras and USB adapters (the pty emulator's fast tests use
# 115200). A profile lists any other rate its device supports in ``baud_rates``.
BAUD_RATES: tuple[int, ...] = (9600, 19200, 38400, 57600, 115200)

_POSITION_LIMIT = 0x7FFF    # positions travel as signed 16-bit values


@dataclass(frozen=True)
class CameraProfile:
    name: str
    pan_min: int            # VISCA units
    pan_max: int
    tilt_min: int
    tilt_max: int
    pan_units_per_deg: float
    tilt_units_per_deg: float
    pan_speeds_deg_s: tuple[float, ...]   # index i -> speed code i + 1
    tilt_speeds_deg_s: tuple[float, ...]
    zoom_max: int = 0x03FF
    version: tuple[int, int, int, int] = (0x0001, 0x0000, 0x0000, 0x02)  # vendor, model, rom, max socket
    verified: bool = True
    notes: str = ''
    extra: dict[str, float] = field(default_factory=dict)
    baud_rates: tuple[int, ...] = ()      # rates beyond BAUD_RATES this device supports
    # CAM_VersionInq model ids this profile's numbers are right for; empty = unknown, not checked
    model_ids: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        # a profile drives timeouts, range checks and unit conversions: a NaN or an empty speed table
        # there would turn into hangs or crashes far from the file that caused them
        for lo, hi, axis in ((self.pan_min, self.pan_max, 'pan'), (self.tilt_min, self.tilt_max, 'tilt')):
            if not all(isinstance(v, int) and not isinstance(v, bool) for v in (lo, hi)):
                raise ValueError(f'profile {self.name!r}: {axis} limits must be integers (VISCA units)')
            if not -_POSITION_LIMIT - 1 <= lo <= hi <= _POSITION_LIMIT:
                raise ValueError(f'profile {self.name!r}: {axis} range {lo}..{hi} is not a signed 16-bit interval')
        for v, what in ((self.pan_units_per_deg, 'pan_units_per_deg'), (self.tilt_units_per_deg, 'tilt_units_per_deg')):
            if not _positive(v):
                raise ValueError(f'profile {self.name!r}: {what} must be a finite number > 0, got {v!r}')
        for table, what in ((self.pan_speeds_deg_s, 'pan_speeds_deg_s'), (self.tilt_speeds_deg_s, 'tilt_speeds_deg_s')):
            if not 1 <= len(table) <= 0x18 or not all(_positive(v) for v in table):
                raise ValueError(f'profile {self.name!r}: {what} needs 1..24 finite speeds > 0 (deg/s)')
        if not isinstance(self.zoom_max, int) or not 0 <= self.zoom_max <= 0xFFFF:
            raise ValueError(f'profile {self.name!r}: zoom_max must be an integer 0..0xFFFF')
        if len(self.version) != 4 or not 1 <= int(self.version[3]) <= 7:
            raise ValueError(f'profile {self.name!r}: version must be (vendor, model, rom, max socket 1..7)')
        if not all(isinstance(b, int) and b > 0 for b in self.baud_rates):
            raise ValueError(f'profile {self.name!r}: baud_rates must be positive integers')
        if not all(isinstance(m, int) and not isinstance(m, bool) and 0 <= m <= 0xFFFF for m in self.model_ids):
            raise ValueError(f'profile {self.name!r}: model_ids must be integers 0..0xFFFF (CAM_VersionInq HHHH)')

    @property
    def max_socket(self) -> int:
        """Highest command socket the camera uses (an ACK on another socket is not ours)."""
        return int(self.version[3])

    @property
    def supported_baud_rates(self) -> tuple[int, ...]:
        return tuple(sorted(set(BAUD_RATES) | set(self.baud_rates)))

    @property
    def pan_range_deg(self) -> tuple[float, float]:
        return self.pan_deg(self.pan_min), self.pan_deg(self.pan_max)

    @property
    def tilt_range_deg(self) -> tuple[float, float]:
        return self.tilt_deg(self.tilt_min), self.tilt_deg(self.tilt_max)

    @property
    def pan_speed_max(self) -> int:
        return len(self.pan_speeds_deg_s)

    @property
    def tilt_speed_max(self) -> int:
        return len(self.tilt_speeds_deg_s)

    # unit conversions ------------------------------------------------------------------------------
    def pan_deg(self, units: int) -> float:
        return units / self.pan_units_per_deg

    def tilt_deg(self, units: int) -> float:
        return units / self.tilt_units_per_deg

    def pan_units(self, deg: float) -> int:
        return round(_finite(deg, 'pan angle') * self.pan_units_per_deg)

    def tilt_units(self, deg: float) -> int:
        return round(_finite(deg, 'tilt angle') * self.tilt_units_per_deg)

    def pan_rad(self, units: int) -> float:
        return math.radians(self.pan_deg(units))

    def tilt_rad(self, units: int) -> float:
        return math.radians(self.tilt_deg(units))

    def in_range(self, pan: int, tilt: int) -> bool:
        return self.pan_min <= pan <= self.pan_max and self.tilt_min <= tilt <= self.tilt_max

    def clamp(self, pan: int, tilt: int) -> tuple[int, int]:
        return (min(max(int(pan), self.pan_min), self.pan_max), min(max(int(tilt), self.tilt_min), self.tilt_max))

    # speeds ----------------------------------------------------------------------------------------
    @property
    def fastest_deg_s(self) -> tuple[float, float]:
        """The head's fastest pan and tilt (deg/s)."""
        return self.pan_speeds_deg_s[-1], self.tilt_speeds_deg_s[-1]

    def pan_speed_deg_s(self, code: int) -> float:
        return self.pan_speeds_deg_s[_code(code, self.pan_speed_max, 'pan') - 1]

    def tilt_speed_deg_s(self, code: int) -> float:
        return self.tilt_speeds_deg_s[_code(code, self.tilt_speed_max, 'tilt') - 1]

    def pan_code_for(self, deg_s: float) -> int:
        """Smallest speed code at least as fast as ``deg_s`` (the fastest when none is)."""
        return _code_for(self.pan_speeds_deg_s, deg_s)

    def tilt_code_for(self, deg_s: float) -> int:
        return _code_for(self.tilt_speeds_deg_s, deg_s)

    def range_text(self) -> str:
        """The position range in units and degrees, for error messages."""
        (p0, p1), (t0, t1) = self.pan_range_deg, self.tilt_range_deg
        return (f'{self.name} range pan {self.pan_min}..{self.pan_max} units ({p0:.4g}..{p1:.4g} deg), '
                f'tilt {self.tilt_min}..{self.tilt_max} units ({t0:.4g}..{t1:.4g} deg)')

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in _TUPLE_FIELDS:
            d[k] = list(getattr(self, k))
        return d


_TUPLE_FIELDS = ('pan_speeds_deg_s', 'tilt_speeds_deg_s', 'version', 'baud_rates', 'model_ids')


def _positive(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0


def _finite(v: float, what: str) -> float:
    # round(inf) raises OverflowError and round(nan) a bare ValueError: name the quantity instead
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ValueError(f'{what} must be a number, got {v!r}') from None
    if not math.isfinite(f):
        raise ValueError(f'{what} must be finite, got {v!r}')
    return f


def _code(code: int, max_code: int, axis: str) -> int:
    if not 1 <= int(code) <= max_code:
        raise ValueError(f'{axis} speed code must be 1..{max_code:#04x}, got {code}')
    return int(code)


def _code_for(table: tuple[float, ...], deg_s: float) -> int:
    for i, v in enumerate(table):
        if v >= deg_s:
            return i + 1
    return len(table)


def _linear(max_deg_s: float, codes: int) -> tuple[float, ...]:
    return tuple(round(max_deg_s * i / codes, 3) for i in range(1, codes + 1))


# EVI-D100 speed table (deg/s per code 01h..18h), from the technical manual
_D100_SPEEDS = (2.0, 2.4, 3.0, 3.7, 4.7, 6.1, 7.4, 9.1, 11.0, 14.0, 18.0, 22.0, 27.0, 34.0, 42.0, 52.0,
                65.0, 81.0, 100.0, 125.0, 155.0, 190.0, 240.0, 300.0)

PROFILES: dict[str, CameraProfile] = {
    # documented: pan +-100 deg = +-880 (FC90..0370), tilt +-25 deg = +-300 (FED4..012C);
    # pan speed 01..18h = 3.3..80 deg/s, tilt 01..14h = 2.5..50 deg/s (linear)
    'evi_d30': CameraProfile('evi_d30', -880, 880, -300, 300, 8.8, 12.0, _linear(80.0, 0x18),
                             _linear(50.0, 0x14), 0x03FF, (0x0001, 0x0402, 0x0100, 0x02), model_ids=(0x0402,)),
    # documented: pan +-100 deg = FA60..05A0 (+-1440), tilt +-25 deg = FE98..0168 (+-360)
    'evi_d100': CameraProfile('evi_d100', -1440, 1440, -360, 360, 14.4, 14.4, _D100_SPEEDS,
                              _D100_SPEEDS[:0x14], 0x4000, (0x0001, 0x040D, 0x0100, 0x02),
                              notes='model id not in the manual: not checked on connect'),
    # documented positions: pan +-170 deg = F725..08DB, tilt -30..+90 deg = FE70..04B0 (0.075 deg/unit);
    # speeds: linear to 100 deg/s (pan, 18h) and 90 deg/s (tilt, 17h) - approximation, unverified
    'evi_d70': CameraProfile('evi_d70', -2267, 2267, -400, 1200, 2267 / 170.0, 1200 / 90.0,
                             _linear(100.0, 0x18), _linear(90.0, 0x17), 0x4000, (0x0020, 0x040E, 0x0100, 0x02),
                             notes='speed table is a linear approximation (unverified)', model_ids=(0x040E,)),
    # no public numbers: D30 values until measured with `fixego ptz calibrate`
    'evi_g20': CameraProfile('evi_g20', -880, 880, -300, 300, 8.8, 12.0, _linear(80.0, 0x18),
                             _linear(50.0, 0x14), 0x03FF, (0x0001, 0x0000, 0x0100, 0x02), verified=False,
                             notes='UNVERIFIED: copied from evi_d30; run `fixego ptz calibrate` on the device'),
}

# CAM_VersionInq model ids named in Sony's technical manuals (see the module docstring), for messages
MODEL_NAMES: dict[int, str] = {
    0x0402: 'EVI-D30/D31, or a camera in D30/D31 mode', 0x040E: 'EVI-D70/P', 0x050C: 'EVI-D80', 0x050D: 'EVI-D90',
    0x0508: 'EVI-HD7V', 0x0509: 'EVI-HD3V', 0x0467: 'FCB-EV7500'}


def model_text(model: int) -> str:
    """``0x040E (EVI-D70/P)``; the name only when a manual gives it."""
    name = MODEL_NAMES.get(model)
    return f'{model:#06x}' + (f' ({name})' if name else '')


def get_profile(name_or_path: str) -> CameraProfile:
    """A built-in profile by name, or a JSON file (e.g. the output of ``fixego ptz calibrate``)."""
    if name_or_path in PROFILES:
        return PROFILES[name_or_path]
    p = Path(name_or_path)
    if p.suffix == '.json' and p.is_file():
        return _load_json(p)
    raise ValueError(f'unknown camera profile {name_or_path!r} (built-in: {", ".join(PROFILES)}; '
                     'or a .json file written by `fixego ptz calibrate`)')


def _load_json(path: Path) -> CameraProfile:
    """A profile file; every way it can be unusable is one ValueError naming the file."""
    try:
        d = json.loads(path.read_text())
        d = d.get('profile', d) if isinstance(d, dict) else d
        if not isinstance(d, dict):
            raise ValueError('expected a JSON object')
        names = {f.name for f in fields(CameraProfile)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f'unknown field(s) {", ".join(unknown)}')
        for k in _TUPLE_FIELDS:
            if k in d:
                d[k] = tuple(d[k])
        return CameraProfile(**d)
    except (OSError, ValueError, TypeError) as e:   # JSONDecodeError is a ValueError
        raise ValueError(f'camera profile {path}: {e}') from None
