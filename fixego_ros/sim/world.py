"""The simulated world: a textured room (floor, walls, ceiling, boxes) made only of rectangles.

Everything is a textured rectangle so the renderer can draw each one with a single homography
(fast, exact pinhole geometry), and the servo model can ray-cast against it analytically.

World frame: x east, y north, z up (metres). The room's floor is at z = 0.

Textures are procedural and seeded: multi-scale value noise plus random blobs, rectangles and lines
drawn at sizes from a few millimetres to tens of centimetres. The 21° cameras see ~1 m of wall at
2.5 m (~1.5 mm per pixel), so the texture must be rich at the centimetre scale for the corner
detector and KLT, and must not repeat (a periodic texture would let the tracker lock onto the wrong
period).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass
class Plane:
    """A textured rectangle ``origin + a * u + b * v`` with ``0 <= a <= width``, ``0 <= b <= height``.

    Texture pixel (x, y) (OpenCV convention, integer coordinates at texel centres) sits at
    ``origin + x * texel * u + y * texel * v``. Seen from the visible side, u points right and v down
    (so the texture is not mirrored), and ``normal = v x u`` points towards the viewer.
    """

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    width: float
    height: float
    texel: float
    texture: np.ndarray  # uint8 (H, W) grey
    name: str = ''
    group: int = -1  # -1: room surface (never occludes another room surface); >= 0: box index
    tint: np.ndarray | None = None  # low-resolution (h, w, 3) float32 colour gains, for rgb8
    _pyramid: dict[tuple[int, bool], np.ndarray] = field(default_factory=dict, repr=False)

    # Cached (read-only): a plane does not move, and the renderer asks for both on every plane of every frame
    # (np.cross alone was ~40 % of a 640x480 frame's render time).
    @functools.cached_property
    def normal(self) -> np.ndarray:
        n = np.cross(self.v, self.u)  # u = viewer's right, v = down: the visible side faces v x u
        return _frozen(n / np.linalg.norm(n))

    @functools.cached_property
    def corners(self) -> np.ndarray:
        """The four corners (4, 3) in order around the rectangle."""
        o, a, b = self.origin, self.u * self.width, self.v * self.height
        return _frozen(np.array([o, o + a, o + a + b, o + b]))

    def texture_level(self, level: int, rgb: bool) -> np.ndarray:
        """Texture at pyramid ``level`` (each level halves resolution), grey or rgb; cached."""
        key = (level, rgb)
        if key not in self._pyramid:
            if level == 0:
                img = self.texture if not rgb else _colourise(self.texture, self.tint)
            else:
                img = cv2.pyrDown(self.texture_level(level - 1, rgb))
            self._pyramid[key] = img
        return self._pyramid[key]

    def point_at(self, x: float, y: float) -> np.ndarray:
        """World point of texture pixel coordinates (x, y) at level 0."""
        return self.origin + x * self.texel * self.u + y * self.texel * self.v


def _colourise(grey: np.ndarray, tint: np.ndarray | None) -> np.ndarray:
    if tint is None:
        return np.dstack([grey] * 3)
    gains = cv2.resize(tint, (grey.shape[1], grey.shape[0]), interpolation=cv2.INTER_LINEAR)
    return np.clip(grey[:, :, None].astype(np.float32) * gains, 0, 255).astype(np.uint8)


def procedural_texture(height_px: int, width_px: int, texel: float, rng: np.random.Generator,
                       shapes_per_m2: float = 250.0) -> np.ndarray:
    """Rich, non-repetitive grey texture: multi-octave value noise + random shapes, seeded."""
    h, w = int(height_px), int(width_px)

    def octaves(spec: tuple[tuple[float, float], ...]) -> np.ndarray:
        acc = np.zeros((h, w), np.float32)
        for scale_m, amp in spec:
            cell = max(scale_m / texel, 1.0)
            gh, gw = int(np.ceil(h / cell)) + 3, int(np.ceil(w / cell)) + 3
            grid = rng.standard_normal((gh, gw)).astype(np.float32)
            up = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
            acc += amp * up[:h, :w]
        return acc

    # coarse shading under the shapes, fine grain over them (so large shapes are not flat inside)
    canvas = np.clip(128.0 + 30.0 * octaves(((0.8, 0.8), (0.2, 0.6), (0.05, 0.5))), 0, 255).astype(np.uint8)
    area = h * w * texel * texel
    n_shapes = int(shapes_per_m2 * area)
    size_m = np.exp(rng.uniform(np.log(0.006), np.log(0.18), n_shapes))
    kind = rng.integers(0, 4, n_shapes)
    cx = rng.uniform(0, w, n_shapes)
    cy = rng.uniform(0, h, n_shapes)
    grey = rng.integers(0, 256, n_shapes)
    ang = rng.uniform(0, np.pi, n_shapes)
    aspect = rng.uniform(0.3, 1.0, n_shapes)
    shift = 2
    sc = 1 << shift
    for i in range(n_shapes):
        r = max(size_m[i] / texel / 2.0, 1.0)
        c = (int(cx[i] * sc), int(cy[i] * sc))
        g = int(grey[i])
        if kind[i] == 0:
            cv2.circle(canvas, c, int(r * sc), g, -1, cv2.LINE_AA, shift)
        elif kind[i] == 1:
            box = cv2.boxPoints(((cx[i], cy[i]), (2 * r, 2 * r * aspect[i]), np.degrees(ang[i])))
            cv2.fillConvexPoly(canvas, np.round(box * sc).astype(np.int32), g, cv2.LINE_AA, shift)
        elif kind[i] == 2:
            d = np.array([np.cos(ang[i]), np.sin(ang[i])]) * r * 2
            p0 = (int((cx[i] - d[0]) * sc), int((cy[i] - d[1]) * sc))
            p1 = (int((cx[i] + d[0]) * sc), int((cy[i] + d[1]) * sc))
            cv2.line(canvas, p0, p1, g, max(1, int(r * aspect[i] * 0.3)), cv2.LINE_AA, shift)
        else:
            cv2.ellipse(canvas, ((cx[i], cy[i]), (2 * r, 2 * r * aspect[i]), np.degrees(ang[i])), g, -1,
                        cv2.LINE_AA)
    grain = octaves(((0.03, 0.5), (0.008, 0.5), (max(0.003, 2 * texel), 0.4)))
    return np.clip(canvas.astype(np.float32) + 14.0 * grain, 0, 255).astype(np.uint8)


def _tint(rng: np.random.Generator, width: float, height: float) -> np.ndarray:
    """Low-frequency colour gains (about one value per 20 cm) so rgb8 images have colour structure."""
    gh, gw = max(2, int(height / 0.2) + 1), max(2, int(width / 0.2) + 1)
    base = rng.uniform(0.6, 1.3, 3)
    return np.clip(base + 0.25 * rng.standard_normal((gh, gw, 3)), 0.3, 1.6).astype(np.float32)


def make_plane(origin, u_vec, v_vec, texel: float, rng: np.random.Generator, name: str = '',
               group: int = -1, texture: np.ndarray | None = None) -> Plane:
    """Rectangle spanned by ``u_vec`` and ``v_vec`` (their lengths are the sizes); visible side v x u."""
    origin, u_vec, v_vec = (np.asarray(x, dtype=float) for x in (origin, u_vec, v_vec))
    width, height = float(np.linalg.norm(u_vec)), float(np.linalg.norm(v_vec))
    if texture is None:
        texture = procedural_texture(round(height / texel) + 1, round(width / texel) + 1, texel, rng)
    return Plane(origin, u_vec / width, v_vec / height, width, height, texel, texture, name, group,
                 _tint(rng, width, height))


@dataclass(frozen=True)
class Box:
    """Axis-aligned box resting on the floor: centre (x, y), size (sx, sy, sz)."""

    x: float
    y: float
    sx: float
    sy: float
    sz: float


@dataclass(frozen=True)
class RoomSpec:
    """Room extent (x_min, x_max, y_min, y_max, height) and boxes; defaults fit the papers' loop."""

    x_min: float = -3.4
    x_max: float = 2.4
    y_min: float = -2.4
    y_max: float = 3.4
    height: float = 2.8
    # boxes stand near the walls, clear of every trajectory's footprint (see trajectories.py)
    boxes: tuple[Box, ...] = (
        Box(-2.8, 2.8, 0.6, 0.5, 1.1),
        Box(1.8, 2.6, 0.5, 0.7, 1.4),
        Box(1.9, -1.6, 0.6, 0.6, 0.9),
        Box(-2.9, -1.2, 0.5, 0.8, 1.6),
        Box(-0.5, 3.0, 0.8, 0.4, 0.8),
        Box(0.2, -2.0, 1.0, 0.4, 1.2),
    )


class World:
    """A list of textured planes plus analytic ray casting (for fixation selection and occlusion)."""

    def __init__(self, planes: list[Plane]) -> None:
        self.planes = planes
        self._O = np.array([p.origin for p in planes])
        self._U = np.array([p.u for p in planes])
        self._V = np.array([p.v for p in planes])
        self._N = np.array([p.normal for p in planes])
        self._W = np.array([p.width for p in planes])
        self._H = np.array([p.height for p in planes])

    def raycast(self, origin: np.ndarray, direction: np.ndarray) -> tuple[float, int]:
        """Distance along ``direction`` (any length; distance in its units) to the first plane hit, index.

        Returns ``(inf, -1)`` when nothing is hit. Both faces of a plane block a ray (boxes are solid).
        """
        origin = np.asarray(origin, dtype=float)
        d = np.asarray(direction, dtype=float)
        denom = self._N @ d
        with np.errstate(divide='ignore', invalid='ignore'):    # a plane parallel to the ray: inf/nan, not hit
            lam = np.einsum('ij,ij->i', self._O - origin, self._N) / denom
            hit = origin + lam[:, None] * d
            a = np.einsum('ij,ij->i', hit - self._O, self._U)
            b = np.einsum('ij,ij->i', hit - self._O, self._V)
            ok = (np.abs(denom) > 1e-12) & (lam > 1e-9) & (a >= 0) & (a <= self._W) & (b >= 0) & (b <= self._H)
        if not np.any(ok):
            return float('inf'), -1
        lam = np.where(ok, lam, np.inf)
        i = int(np.argmin(lam))
        return float(lam[i]), i

    def visible(self, eye: np.ndarray, point: np.ndarray, tol: float = 0.01) -> bool:
        """True when nothing lies between ``eye`` and ``point`` (a point on a surface)."""
        d = np.asarray(point, dtype=float) - eye
        dist = float(np.linalg.norm(d))
        lam, _ = self.raycast(eye, d / dist)
        return lam >= dist - tol

    def memory_bytes(self) -> int:
        return int(sum(p.texture.nbytes for p in self.planes))


def _room_planes(spec: RoomSpec, texel: float, rng: np.random.Generator) -> list[Plane]:
    x0, x1, y0, y1, h = spec.x_min, spec.x_max, spec.y_min, spec.y_max, spec.height
    ft = texel * 2.0  # floor/ceiling are only seen obliquely: coarser texture is enough
    planes = [
        # walls seen from inside: u = viewer's right, v = down (visible normal v x u points into the room)
        make_plane([x0, y1, h], [x1 - x0, 0, 0], [0, 0, -h], texel, rng, 'wall_north'),
        make_plane([x1, y1, h], [0, y0 - y1, 0], [0, 0, -h], texel, rng, 'wall_east'),
        make_plane([x1, y0, h], [x0 - x1, 0, 0], [0, 0, -h], texel, rng, 'wall_south'),
        make_plane([x0, y0, h], [0, y1 - y0, 0], [0, 0, -h], texel, rng, 'wall_west'),
        make_plane([x0, y1, 0], [x1 - x0, 0, 0], [0, y0 - y1, 0], ft, rng, 'floor'),
        make_plane([x0, y0, h], [x1 - x0, 0, 0], [0, y1 - y0, 0], ft, rng, 'ceiling'),
    ]
    return planes


def _box_planes(box: Box, index: int, texel: float, rng: np.random.Generator) -> list[Plane]:
    x0, x1 = box.x - box.sx / 2, box.x + box.sx / 2
    y0, y1 = box.y - box.sy / 2, box.y + box.sy / 2
    z = box.sz
    faces = [  # outward normals (v x u points out of the box)
        ([x0, y0, z], [x1 - x0, 0, 0], [0, 0, -z], 'south'),
        ([x1, y0, z], [0, y1 - y0, 0], [0, 0, -z], 'east'),
        ([x1, y1, z], [x0 - x1, 0, 0], [0, 0, -z], 'north'),
        ([x0, y1, z], [0, y0 - y1, 0], [0, 0, -z], 'west'),
        ([x0, y1, z], [x1 - x0, 0, 0], [0, y0 - y1, 0], 'top'),
    ]
    return [make_plane(o, u, v, texel, rng, f'box{index}_{n}', index) for o, u, v, n in faces]


# texture resolution in m: finer than TEXEL_RANGE[0] the room's textures take gigabytes (4x per halving);
# coarser than TEXEL_RANGE[1] a wall is a few texels and soon no corner is left to fixate on
TEXEL_RANGE = (0.001, 1.0)


def check_texel(texel: float) -> float:
    """``texel`` as a float in :data:`TEXEL_RANGE`, or ValueError (NaN or 1e-9 would exhaust memory)."""
    try:
        t = float(texel)
    except (TypeError, ValueError):
        t = math.nan
    if not (math.isfinite(t) and TEXEL_RANGE[0] <= t <= TEXEL_RANGE[1]):
        raise ValueError(f'texel must be a finite size in [{TEXEL_RANGE[0]:g}, {TEXEL_RANGE[1]:g}] m, got {texel!r}')
    return t


@functools.lru_cache(maxsize=4)
def make_room(seed: int = 0, texel: float = 0.002, spec: RoomSpec = RoomSpec()) -> World:
    """The default room; cached per (seed, texel, spec) because building textures takes ~1 s. ``texel`` must be
    in :data:`TEXEL_RANGE` (ValueError otherwise)."""
    texel = check_texel(texel)
    rng = np.random.default_rng([int(seed), 0x5EED])
    planes = _room_planes(spec, texel, rng)
    for i, b in enumerate(spec.boxes):
        planes += _box_planes(b, i, texel, rng)
    return World(planes)
