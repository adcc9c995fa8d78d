"""Shipped-bag regeneration: same content on any CPU, within the stated tolerances, and real differences caught."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from fixego_ros.bags.reader import Bag
from fixego_ros.bags.shipped import FLOAT_TOL, IMAGE_MAX_FRACTION, IMAGE_MAX_LEVELS, _differences

WALK = Path(__file__).resolve().parents[1] / 'bags' / 'walk'


def _first(topic: str):
    bag = Bag(WALK)
    for m in bag.messages([topic]):
        return bag.decode(m)
    raise AssertionError(f'no {topic} in {WALK}')


def test_image_tolerance_is_the_stated_one():
    img = _first('/fixego/right/image_raw')
    assert _differences(img, img) == []
    data = np.array(img.data, copy=True)
    few = max(1, int(data.size * IMAGE_MAX_FRACTION) // 2)
    near = data.copy()
    near[:few] = np.where(near[:few] < 255 - IMAGE_MAX_LEVELS, near[:few] + IMAGE_MAX_LEVELS, near[:few] - 1)
    assert _differences(img, replace(img, data=near)) == []
    far = data.copy()
    far[0] = (int(far[0]) + 128) % 256                           # one pixel far off
    assert _differences(img, replace(img, data=far))
    many = data.copy()
    n = int(data.size * IMAGE_MAX_FRACTION * 3)
    many[:n] = np.where(many[:n] < 255, many[:n] + 1, 254)       # too many pixels, each by one level
    assert _differences(img, replace(img, data=many))
    assert _differences(img, replace(img, encoding='rgb8'))
    assert _differences(img, replace(img, width=img.width + 1))


def test_float_tolerance_is_the_stated_one():
    msg = _first('/fixego/ground_truth/pose')
    p = msg.pose.position
    ulp = replace(msg, pose=replace(msg.pose, position=replace(p, x=float(np.nextafter(p.x, 1e9)))))
    assert _differences(msg, ulp) == []
    off = replace(msg, pose=replace(msg.pose, position=replace(p, x=p.x + 100 * FLOAT_TOL * max(1.0, abs(p.x)))))
    assert _differences(msg, off)
    assert _differences(msg, replace(msg, header=replace(msg.header, frame_id='elsewhere')))


def test_the_sim_files_numbers_get_the_same_tolerance():
    """sim.yaml holds what the simulator measured (each vergence step's distance, error, std): its last bits round by
    CPU like the messages' floats (a fresh machine's `make bags-check` failed on `bags/paper` for 1e-13 m)."""
    import yaml
    text = (WALK.parent / 'paper' / 'sim.yaml').read_text()
    shipped, sim = yaml.safe_load(text), yaml.safe_load(text)
    assert _differences(sim, shipped) == []
    step = sim['vergence']['measurements'][0]
    d = step['distance_m']
    step['distance_m'] = float(np.nextafter(d, 1e9))
    assert _differences(sim, shipped) == []
    step['distance_m'] = d + 100 * FLOAT_TOL * max(1.0, abs(d))
    assert _differences(sim, shipped)
    assert _differences({'a': 1}, {'b': 1})


def test_shipped_bags_carry_checked_crcs():
    """A flipped bit in a shipped bag is found: every chunk, the data section and the summary have real CRCs."""
    from test_bag_faults import assert_real_crcs
    for name in ('paper', 'walk'):
        assert_real_crcs(next((WALK.parent / name).glob('*.mcap')))
