"""Per-model pan/tilt numbers: limits, units per degree, speed tables.

Sources: Sony EVI-D30/D31 and EVI-D100 technical manuals (pan/tilt position and speed tables, also
reprinted in the D100 manual's "D30/31 mode" section) and the EVI-D70 technical manual (position
table). The D70 speed table is not in the pages we had: its speeds are a linear approximation to the
documented maxima and marked unverified. The EVI-G20 has **no public VISCA numbers**: its profile
copies the D30 and is marked unverified; measure a real unit with ``fixego ptz calibrate``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path


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
        return round(deg * self.pan_units_per_deg)

    def tilt_units(self, deg: float) -> int:
        return round(deg * self.tilt_units_per_deg)

    def pan_rad(self, units: int) -> float:
        return math.radians(self.pan_deg(units))

    def tilt_rad(self, units: int) -> float:
        return math.radians(self.tilt_deg(units))

    def in_range(self, pan: int, tilt: int) -> bool:
        return self.pan_min <= pan <= self.pan_max and self.tilt_min <= tilt <= self.tilt_max

    def clamp(self, pan: int, tilt: int) -> tuple[int, int]:
        return (min(max(int(pan), self.pan_min), self.pan_max), min(max(int(tilt), self.tilt_min), self.tilt_max))

    # speeds ----------------------------------------------------------------------------------------
    def pan_speed_deg_s(self, code: int) -> float:
        return self.pan_speeds_deg_s[_code(code, self.pan_speed_max, 'pan') - 1]

    def tilt_speed_deg_s(self, code: int) -> float:
        return self.tilt_speeds_deg_s[_code(code, self.tilt_speed_max, 'tilt') - 1]

    def pan_code_for(self, deg_s: float) -> int:
        """Smallest speed code at least as fast as ``deg_s`` (the fastest when none is)."""
        return _code_for(self.pan_speeds_deg_s, deg_s)

    def tilt_code_for(self, deg_s: float) -> int:
        return _code_for(self.tilt_speeds_deg_s, deg_s)

    def to_dict(self) -> dict:
        d = asdict(self)
        d['pan_speeds_deg_s'] = list(self.pan_speeds_deg_s)
        d['tilt_speeds_deg_s'] = list(self.tilt_speeds_deg_s)
        d['version'] = list(self.version)
        return d


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
                             _linear(50.0, 0x14), 0x03FF, (0x0001, 0x0402, 0x0100, 0x02)),
    # documented: pan +-100 deg = FA60..05A0 (+-1440), tilt +-25 deg = FE98..0168 (+-360)
    'evi_d100': CameraProfile('evi_d100', -1440, 1440, -360, 360, 14.4, 14.4, _D100_SPEEDS,
                              _D100_SPEEDS[:0x14], 0x4000, (0x0001, 0x040D, 0x0100, 0x02)),
    # documented positions: pan +-170 deg = F725..08DB, tilt -30..+90 deg = FE70..04B0 (0.075 deg/unit);
    # speeds: linear to 100 deg/s (pan, 18h) and 90 deg/s (tilt, 17h) - approximation, unverified
    'evi_d70': CameraProfile('evi_d70', -2267, 2267, -400, 1200, 2267 / 170.0, 1200 / 90.0,
                             _linear(100.0, 0x18), _linear(90.0, 0x17), 0x4000, (0x0001, 0x040E, 0x0100, 0x02),
                             notes='speed table is a linear approximation (unverified)'),
    # no public numbers: D30 values until measured with `fixego ptz calibrate`
    'evi_g20': CameraProfile('evi_g20', -880, 880, -300, 300, 8.8, 12.0, _linear(80.0, 0x18),
                             _linear(50.0, 0x14), 0x03FF, (0x0001, 0x0000, 0x0100, 0x02), verified=False,
                             notes='UNVERIFIED: copied from evi_d30; run `fixego ptz calibrate` on the device'),
}


def get_profile(name_or_path: str) -> CameraProfile:
    """A built-in profile by name, or a JSON file (e.g. the output of ``fixego ptz calibrate``)."""
    if name_or_path in PROFILES:
        return PROFILES[name_or_path]
    p = Path(name_or_path)
    if p.suffix == '.json' and p.exists():
        d = json.loads(p.read_text())
        d = d.get('profile', d)
        for k in ('pan_speeds_deg_s', 'tilt_speeds_deg_s', 'version'):
            d[k] = tuple(d[k])
        return CameraProfile(**d)
    raise ValueError(f'unknown camera profile {name_or_path!r} (built-in: {", ".join(PROFILES)}; '
                     'or a .json file written by `fixego ptz calibrate`)')
