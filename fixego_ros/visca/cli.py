"""``fixego ptz``: talk to one VISCA camera and print one JSON object (DESIGN.md §6).

Exit codes: 0 done (``{"ok": true, ...}``); 1 the camera or the link failed (``{"ok": false, "error": ...}``
on stdout, within bounded time); 2 an option cannot be used (one ``fixego ptz: ...`` line on stderr, nothing
sent). Options are checked before the port is opened: a NaN timeout, a zero baud rate or an infinite angle
would otherwise hang or crash deep in the driver.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from fixego_ros.visca.driver import (
    MAX_SETTLE_S,
    ViscaCamera,
    check_address,
    check_baud,
    check_model,
    check_seconds,
    check_timeout,
    measure_limits,
)
from fixego_ros.visca.profiles import BAUD_RATES, PROFILES, CameraProfile, get_profile
from fixego_ros.visca.protocol import ViscaError

PROG = 'fixego ptz'


def register(subparsers) -> None:
    p = subparsers.add_parser('ptz', help='query or move one VISCA pan/tilt camera (prints JSON)',
                              description='Talk to one VISCA camera over RS-232; prints one JSON object.')
    p.add_argument('--port', required=True, help='serial device, e.g. /dev/ttyUSB0')
    p.add_argument('--baud', type=int, default=9600,
                   help=f'serial rate: {", ".join(map(str, BAUD_RATES))} or one the profile lists (default 9600)')
    p.add_argument('--address', type=int, default=1, help='camera address 1..7')
    p.add_argument('--profile', default='evi_d30',
                   help=f'camera profile ({", ".join(PROFILES)}) or a .json written by calibrate')
    p.add_argument('--timeout', type=float, default=0.5, help='per-reply timeout in seconds, in (0, 10]')
    sub = p.add_subparsers(dest='ptz_command', metavar='ACTION')
    sub.required = True
    sub.add_parser('query', help='current pan/tilt')
    g = sub.add_parser('goto', help='absolute move in degrees within the profile range (waits for completion)')
    g.add_argument('pan_deg', type=float)
    g.add_argument('tilt_deg', type=float)
    sub.add_parser('home', help='Pan-tiltDrive Home')
    sub.add_parser('reset', help='Pan-tiltDrive Reset (re-initialises the position counters)')
    sub.add_parser('version', help='CAM_VersionInq')
    c = sub.add_parser('calibrate', help='measure pan/tilt limits by driving to the end stops')
    c.add_argument('--settle', type=float, default=0.3,
                   help=f'seconds between readings at an end stop, in [0, {MAX_SETTLE_S:g}]')
    c.add_argument('--out', default=None, help='also write the measured profile as JSON here')
    p.set_defaults(func=run)


def _pose(cam: ViscaCamera) -> dict[str, float | int]:
    pan, tilt = cam.position()
    pr = cam.profile
    return {'pan_deg': round(pr.pan_deg(pan), 4), 'tilt_deg': round(pr.tilt_deg(tilt), 4),
            'pan_units': pan, 'tilt_units': tilt}


def _check_angle(value: float, lo: float, hi: float, what: str, profile: CameraProfile) -> None:
    if not math.isfinite(value):
        raise ValueError(f'{what} must be a finite angle in degrees, got {value!r}')
    if not lo <= value <= hi:
        raise ValueError(f'{what} {value:g} deg is outside the {profile.name} range {lo:.4g}..{hi:.4g} deg')


def check_args(args: argparse.Namespace) -> CameraProfile:
    """Every option, before anything is opened or sent; raises ValueError with a one-line message."""
    profile = get_profile(args.profile)
    check_timeout(args.timeout, '--timeout')
    check_baud(args.baud, profile, '--baud')
    check_address(args.address, '--address')
    if args.ptz_command == 'goto':
        _check_angle(args.pan_deg, *profile.pan_range_deg, 'PAN_DEG', profile)
        _check_angle(args.tilt_deg, *profile.tilt_range_deg, 'TILT_DEG', profile)
    if args.ptz_command == 'calibrate':
        check_seconds(args.settle, '--settle', MAX_SETTLE_S, allow_zero=True)
        if args.out is not None:
            out = Path(args.out)
            if out.is_dir() or not out.parent.is_dir():
                raise ValueError(f'--out {args.out}: not a file in an existing directory')
    return profile


def run(args: argparse.Namespace) -> int:
    out: dict[str, object]
    try:
        profile = check_args(args)
        cam = ViscaCamera(args.port, baud=args.baud, address=args.address, profile=profile,
                          timeout_s=args.timeout, reconnect=False)
    except ValueError as e:
        print(f'{PROG}: {e}', file=sys.stderr)
        return 2
    try:
        with cam:
            action = args.ptz_command
            if action == 'query':
                out = _pose(cam)
            elif action == 'goto':
                pr = cam.profile
                cam.absolute(pr.pan_units(args.pan_deg), pr.tilt_units(args.tilt_deg), wait=True)
                out = _pose(cam)
            elif action in ('home', 'reset'):
                (cam.home if action == 'home' else cam.reset)(wait=True)
                out = _pose(cam)
            elif action == 'version':
                out = cam.version()
            else:
                limits = measure_limits(cam, settle_s=args.settle)
                cam.home(wait=True)
                found = check_model(cam)      # the measured profile is for this model (if it says which)
                model_ids = [found.version['model']] if found.version else list(cam.profile.model_ids)
                measured = dict(cam.profile.to_dict(), **limits, name=cam.profile.name + '_measured',
                                verified=True, model_ids=model_ids, notes='limits measured by fixego ptz '
                                'calibrate; units per degree and speeds are still the base profile values')
                out = {'limits': limits, 'profile': measured,
                       'pan_deg_range': [cam.profile.pan_deg(limits['pan_min']),
                                         cam.profile.pan_deg(limits['pan_max'])],
                       'tilt_deg_range': [cam.profile.tilt_deg(limits['tilt_min']),
                                          cam.profile.tilt_deg(limits['tilt_max'])]}
                if args.out:
                    with open(args.out, 'w') as f:
                        json.dump(out, f, indent=2)
    except (ViscaError, ValueError, OSError) as e:
        print(json.dumps({'ok': False, 'error': f'{type(e).__name__}: {e}', 'stats': cam.stats}))
        return 1
    out = {'ok': True, **out}
    print(json.dumps(out))
    sys.stdout.flush()
    return 0
