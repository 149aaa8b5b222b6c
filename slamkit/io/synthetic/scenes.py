"""Declarative scenes of the synthetic world: textured rectangles plus a closed camera path.

World frame: z up, metres. A scene is plain data (``Scene``): a tuple of ``Plane`` rectangles (each with a
texture key; planes that share a key show the same pixels) and a ``CameraPath`` (position waypoints of a
closed loop, how the camera looks, the loop period and the sequence duration). Helper builders (``room``,
``box``, ``corridor_ring``) only expand rooms and boxes into rectangles; each scene function below reads as
a short description. To add a scene, write a function returning a ``Scene`` and list it in ``SCENES``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from numpy.typing import NDArray

from slamkit.errors import ConfigError

F64 = NDArray[np.float64]
Vec3 = tuple[float, float, float]

# Longest side of one textured rectangle; longer walls are split into panels (keeps every texture a
# manageable size, well under OpenCV's 32767-px warp limit, and lets textures be generated lazily).
MAX_PANEL_M = 6.0


@dataclass(frozen=True)
class Plane:
    """A textured rectangle, seen from one side.

    origin_m: (3,) world position of the texture's top-left corner (texel (0, 0) side).
    u_m: (3,) world edge vector along the texture's x axis (its length is the rectangle's width, m).
    v_m: (3,) world edge vector along the texture's y axis, perpendicular to u_m.
    texture: texture key; planes with the same key (and size) show identical pixels.
    The visible side is the one the normal ``v x u`` points to (a viewer there sees u going right, v down).
    """

    name: str
    origin_m: Vec3
    u_m: Vec3
    v_m: Vec3
    texture: str

    @property
    def normal(self) -> F64:
        """(3,) unit normal pointing to the visible side, world frame."""
        n = np.cross(np.asarray(self.v_m), np.asarray(self.u_m))
        return np.asarray(n / np.linalg.norm(n), dtype=np.float64)

    @property
    def corners_m(self) -> F64:
        """(4, 3) world corners: origin, origin+u, origin+u+v, origin+v."""
        o, u, v = np.asarray(self.origin_m), np.asarray(self.u_m), np.asarray(self.v_m)
        return np.stack([o, o + u, o + u + v, o + v]).astype(np.float64)


@dataclass(frozen=True)
class CameraPath:
    """A closed camera path: the camera passes through ``waypoints_m`` (periodic, C2) once per period.

    Orientation: if ``look_at_m`` is given (one target per waypoint, interpolated the same way), the camera
    looks at the moving target; otherwise it looks ahead along the path, at its own position
    ``look_ahead_s`` later, turned by ``yaw_offset_deg`` about the world z axis (positive = to the left).
    period_s: time of one loop; duration_s: length of the sequence (> period_s revisits the start).
    """

    waypoints_m: tuple[Vec3, ...]
    period_s: float
    duration_s: float
    look_at_m: tuple[Vec3, ...] | None = None
    look_ahead_s: float = 1.0
    yaw_offset_deg: float = 0.0


@dataclass(frozen=True)
class Scene:
    """A named world: rectangles and a camera path. ``texels_per_m`` is the default texture density."""

    name: str
    planes: tuple[Plane, ...]
    path: CameraPath
    texels_per_m: float = 256.0


# ----------------------------------------------------------------------------------------------------
# Builders: rooms and boxes -> rectangles


def quad(name: str, origin: Vec3, u: Vec3, v: Vec3, texture: str, seen_from: Vec3) -> list[Plane]:
    """Rectangle origin + [0,1] u + [0,1] v, oriented so that it is visible from point ``seen_from``,
    split along u into panels of at most MAX_PANEL_M (texture keys ``texture/i``)."""
    o, uu, vv = np.asarray(origin, float), np.asarray(u, float), np.asarray(v, float)
    if np.dot(np.cross(vv, uu), np.asarray(seen_from, float) - o) < 0:
        o, uu = o + uu, -uu  # mirror: walk u the other way so the normal faces the viewer
    n_panels = max(1, math.ceil(np.linalg.norm(uu) / MAX_PANEL_M - 1e-9))
    du = uu / n_panels
    return [
        Plane(f"{name}/{i}", _t(o + i * du), _t(du), _t(vv), f"{texture}/{i}" if n_panels > 1 else texture)
        for i in range(n_panels)
    ]


def _t(a: F64) -> Vec3:
    return (float(a[0]), float(a[1]), float(a[2]))


def room(name: str, lo: Vec3, hi: Vec3, ceiling: bool = True) -> list[Plane]:
    """The inside of the axis-aligned box [lo, hi]: floor, ceiling and four walls, all facing inwards."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    c = ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2)
    dz = (0.0, 0.0, z0 - z1)
    planes = [
        *quad(f"{name}/floor", (x0, y1, z0), (x1 - x0, 0, 0), (0, y0 - y1, 0), f"{name}/floor", c),
        *quad(f"{name}/wall_s", (x0, y0, z1), (x1 - x0, 0, 0), dz, f"{name}/wall_s", c),
        *quad(f"{name}/wall_e", (x1, y0, z1), (0, y1 - y0, 0), dz, f"{name}/wall_e", c),
        *quad(f"{name}/wall_n", (x0, y1, z1), (x1 - x0, 0, 0), dz, f"{name}/wall_n", c),
        *quad(f"{name}/wall_w", (x0, y0, z1), (0, y1 - y0, 0), dz, f"{name}/wall_w", c),
    ]
    if ceiling:
        planes += quad(f"{name}/ceiling", (x0, y0, z1), (x1 - x0, 0, 0), (0, y1 - y0, 0), f"{name}/ceiling", c)
    return planes


def box(name: str, centre_xy: tuple[float, float], size: Vec3, z0: float = 0.0) -> list[Plane]:
    """An axis-aligned box standing on z = z0 (furniture): top and four sides, facing outwards."""
    (cx, cy), (sx, sy, sz) = centre_xy, size
    x0, x1, y0, y1, z1 = cx - sx / 2, cx + sx / 2, cy - sy / 2, cy + sy / 2, z0 + sz
    dz = (0.0, 0.0, z0 - z1)
    far = 1e3  # a point far outside on each side, to orient each face outwards
    return [
        *quad(f"{name}/top", (x0, y1, z1), (sx, 0, 0), (0, -sy, 0), f"{name}/top", (cx, cy, z1 + far)),
        *quad(f"{name}/s", (x0, y0, z1), (sx, 0, 0), dz, f"{name}/s", (cx, y0 - far, z0)),
        *quad(f"{name}/n", (x0, y1, z1), (sx, 0, 0), dz, f"{name}/n", (cx, y1 + far, z0)),
        *quad(f"{name}/e", (x1, y0, z1), (0, sy, 0), dz, f"{name}/e", (x1 + far, cy, z0)),
        *quad(f"{name}/w", (x0, y0, z1), (0, sy, 0), dz, f"{name}/w", (x0 - far, cy, z0)),
    ]


def corridor_ring(name: str, half_outer: tuple[float, float], width: float, height: float) -> list[Plane]:
    """A closed rectangular corridor around a central block: outer walls facing in, the block's walls
    facing out, and floor/ceiling strips. half_outer: (hx, hy) half-sizes of the outer rectangle, m."""
    hx, hy = half_outer
    ix, iy = hx - width, hy - width
    planes = [p for p in room(f"{name}/outer", (-hx, -hy, 0), (hx, hy, height), ceiling=False) if "floor" not in p.name]
    # The block's top is never seen (it is as high as the ceiling).
    planes += [p for p in box(f"{name}/block", (0.0, 0.0), (2 * ix, 2 * iy, height)) if "/top" not in p.name]
    up, down = (0.0, 0.0, 1e3), (0.0, 0.0, -1e3)
    strips = [  # (x0, y0, x1, y1) of the floor/ceiling strips: two long (south, north), two short (west, east)
        (-hx, -hy, hx, -iy),
        (-hx, iy, hx, hy),
        (-hx, -iy, -ix, iy),
        (ix, -iy, hx, iy),
    ]
    for k, (x0, y0, x1, y1) in enumerate(strips):
        for part, z, seen in (("floor", 0.0, up), ("ceiling", height, down)):
            planes += quad(
                f"{name}/{part}{k}", (x0, y1, z), (x1 - x0, 0, 0), (0, y0 - y1, 0), f"{name}/{part}{k}", seen
            )
    return planes


def rounded_rectangle(half: tuple[float, float], corner_m: float, spacing_m: float, z: float) -> tuple[Vec3, ...]:
    """Waypoints counter-clockwise around the rectangle [-hx, hx] x [-hy, hy] at height z, about
    ``spacing_m`` apart; each side stops ``corner_m`` short of the corners so the spline rounds them.
    The first waypoint is on the south side, ``corner_m`` east of the south-west corner."""
    hx, hy = half
    corners = np.array([(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)])
    pts: list[Vec3] = []
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        d = (b - a) / np.linalg.norm(b - a)
        p0, p1 = a + corner_m * d, b - corner_m * d
        n = max(1, math.ceil(np.linalg.norm(p1 - p0) / spacing_m))
        pts += [(float(q[0]), float(q[1]), z) for q in (p0 + (p1 - p0) * k / n for k in range(n + 1))]
    return tuple(pts)


# ----------------------------------------------------------------------------------------------------
# The scenes


def room_scene() -> Scene:
    """A furnished 8 x 6 x 3 m room; the camera circles it once (24 s) looking at the walls and furniture,
    then goes on for 4 s over the start again (a loop closure)."""
    planes = [
        *room("room", (-4.0, -3.0, 0.0), (4.0, 3.0, 3.0)),
        *box("table", (0.0, 0.0), (1.4, 0.8, 0.75)),
        *box("shelf", (3.55, 0.5), (0.5, 1.6, 1.9)),
        *box("cabinet", (-3.4, -2.2), (0.8, 0.6, 1.1)),
        *box("crate_a", (-1.2, 2.5), (0.7, 0.6, 0.6)),
        *box("crate_b", (1.9, -2.5), (0.6, 0.6, 0.9)),
    ]
    # An ellipse (radii 2.2 x 1.3 m) at eye height, gently bobbing, starting at the south side.
    n = 16
    angles = [-math.pi / 2 + 2 * math.pi * k / n for k in range(n)]
    way = tuple((2.2 * math.cos(a), 1.3 * math.sin(a), 1.45 + 0.15 * math.sin(3 * a)) for a in angles)
    # Look at the walls ahead-outwards (60 degrees ahead of the radial direction), swinging the target
    # slowly in and out (0.4 rad, twice per loop) so walls, corners and furniture come in view at various
    # distances; the camera turns once per loop (~0.26 rad/s on average).
    look = tuple(
        (4.5 * math.cos(b), 3.5 * math.sin(b), 1.1) for b in (a + math.pi / 3 + 0.4 * math.sin(2 * a) for a in angles)
    )
    return Scene("room", tuple(planes), CameraPath(way, period_s=24.0, duration_s=28.0, look_at_m=look))


def planar_scene() -> Scene:
    """A 10 x 8 x 4 m room. The camera starts 2.5 m in front of the north wall, facing it and sliding
    sideways for ~1.5 s (only that plane in view: the homography case of the two-view initializer), then
    tours the room and comes back."""
    planes = [*room("hall", (-5.0, -4.0, 0.0), (5.0, 4.0, 4.0)), *box("desk", (0.0, -1.5), (1.6, 0.8, 0.8))]
    eye = 2.0
    way: list[Vec3] = [(-0.9, 1.5, eye), (-0.3, 1.5, eye), (0.3, 1.5, eye), (0.9, 1.5, eye)]
    look: list[Vec3] = [(x, 4.0, eye) for x, _, _ in way]
    # Then a loop around the room (look-at targets on the walls) back to the start, with a midpoint
    # between tour waypoints so the speed stays within ~2x of the sideways start.
    tour = [
        (2.4, 1.0, 1.8),
        (3.0, -0.5, 1.6),
        (2.4, -2.4, 1.6),
        (0.0, -3.0, 1.7),
        (-2.4, -2.4, 1.7),
        (-3.0, -0.5, 1.8),
        (-2.2, 1.1, 1.9),
    ]
    tour_look = [
        (5.0, 2.5, 1.8),
        (5.0, -2.0, 1.5),
        (2.0, -4.0, 1.5),
        (-2.0, -4.0, 1.6),
        (-5.0, -2.0, 1.6),
        (-5.0, 2.0, 1.8),
        (-2.5, 4.0, 2.0),
    ]
    way += _with_midpoints([way[-1], *tour])[1:]
    look += _with_midpoints([look[-1], *tour_look])[1:]
    path = CameraPath(tuple(way), period_s=26.0, duration_s=29.0, look_at_m=tuple(look))
    return Scene("planar", tuple(planes), path)


def _with_midpoints(points: list[Vec3]) -> list[Vec3]:
    """points with the midpoint of each consecutive pair inserted between them (open polyline)."""
    out = [points[0]]
    for a, b in itertools.pairwise(points):
        out += [_t((np.asarray(a) + np.asarray(b)) / 2), b]
    return out


def long_loop_scene() -> Scene:
    """A corridor ring around a 19 x 9 m block (outer 24 x 14 m, 2.6 m wide, 3 m high) with crates along its
    outer walls; the camera walks its ~66 m centre line once (70 s) looking 45 deg to the right of its path,
    then 10 s more past the start: scale drift builds up over a long loop before it closes. It starts on the
    straight south side by a group of crates, where a monocular map can be initialised."""
    planes = corridor_ring("ring", (12.0, 7.0), 2.6, 3.0)
    # crates along the outer walls: depth structure, so the two-view geometry is not one plane
    # (x, y, depth from the wall, height): a storage area by the start on the south wall, then single crates
    crates = [
        (1.2, -7.0, 0.9, 1.6),
        (2.4, -7.0, 0.5, 0.9),
        (3.5, -7.0, 1.1, 1.2),
        (4.7, -7.0, 0.6, 2.0),
        (5.9, -7.0, 0.8, 1.0),
        (-8.0, -7.0, 0.7, 0.8),
        (-3.5, -7.0, 0.7, 1.4),
        (12.0, -3.5, 0.7, 1.1),
        (12.0, 3.0, 0.7, 0.8),
        (7.0, 7.0, 0.7, 1.4),
        (0.5, 7.0, 0.7, 1.1),
        (-6.0, 7.0, 0.7, 0.8),
        (-12.0, 2.5, 0.7, 1.4),
        (-12.0, -3.0, 0.7, 1.1),
    ]
    for i, (x, y, depth, height) in enumerate(crates):
        if abs(abs(y) - 7.0) < 1e-9:  # against the south or north wall
            planes += box(f"crate{i}", (x, y - np.sign(y) * depth / 2), (1.0, depth, height))
        else:  # against the east or west wall
            planes += box(f"crate{i}", (x - np.sign(x) * depth / 2, y), (depth, 1.0, height))
    way = rounded_rectangle((10.7, 5.7), corner_m=1.1, spacing_m=1.5, z=1.5)
    # start halfway along the long south side, on a straight stretch: a monocular map cannot be initialised
    # while the camera turns (rotation brings no parallax)
    south = sum(1 for w in way if abs(w[1] + 5.7) < 1e-9)
    way = way[south // 2 :] + way[: south // 2]
    path = CameraPath(way, period_s=70.0, duration_s=80.0, look_ahead_s=1.2, yaw_offset_deg=-45.0)
    return Scene("long_loop", tuple(planes), path, texels_per_m=224.0)


def twins_scene() -> Scene:
    """A corridor ring (outer 18 x 12 m) whose outer wall shows the same 6 m stretch of texture twice: in
    the middle of the south side and, mirrored by the ring's symmetry, in the middle of the north side.
    The camera looks obliquely at the outer wall, so it sees the two twin places from the same relative
    pose: a place recognizer will find them alike although they are 12 m apart (a false loop), while the
    real loop closes when the camera passes its start again."""
    # The outer south and north walls are split into 3 panels of 6 m; the middle ones are the twins.
    return _corridor_ring_with_twins("twins", ("ring/outer/wall_s/1", "ring/outer/wall_n/1"))


def twins_translated_scene() -> Scene:
    """The ``twins`` corridor ring and camera path, but the twin places are related by a TRANSLATION: the outer
    south wall (18 m, three 6 m panels) shows the same texture on its west panel (x in [-9, -3] m) and its east
    panel (x in [3, 9] m), 12 m apart along the same straight stretch, seen from the same relative pose with the
    same orientation. A false loop between them would imply almost no rotation (a rotation prior cannot reject
    it): only geometry and consistency can.

    What makes the two places different is STRUCTURE in front of the twin panels: crates of their own textures
    stand against each twin, in different places (five by each twin, a tall one where the other place has a low one), so each view shows
    the twin texture partly hidden by boxes the other place does not have. Without them (the first version of
    this scene) the twin filled the view exactly as at its twin place, a revisit no check on the views can tell
    from the true one (ORB-SLAM3's counts were all passed: 91 refined matches at 5 px, 3 covisibles agreeing),
    and the camera saw a single plane for 17 s, so the map started late (frame 523) by the east twin and the
    true revisit came after the sequence's end. The west crates also give the start its depth structure, so the
    map starts by the west twin (the path's first waypoint faces it) and the east twin is met ~20 s later, as a
    false hypothesis; the real loop closes when the camera passes its start again (~80 s)."""
    # (x along the wall, depth from the wall, height, width), m; the crates' fronts stay >= 0.6 m from the path
    crates = [
        (-8.2, 0.7, 1.3, 0.9),
        (-7.0, 0.5, 1.9, 1.0),
        (-5.8, 0.7, 1.1, 1.0),
        (-4.6, 0.6, 1.6, 1.0),
        (-3.6, 0.7, 0.9, 0.8),
        (3.9, 0.4, 2.1, 1.0),
        (5.0, 0.5, 0.8, 0.9),
        (6.2, 0.4, 2.0, 1.1),
        (7.4, 0.5, 0.9, 0.9),
        (8.4, 0.4, 1.8, 0.8),
    ]
    extra: list[Plane] = []
    for i, (x, depth, height, width) in enumerate(crates):
        extra += box(f"crate{i}", (x, -6.0 + depth / 2), (width, depth, height))
    return _corridor_ring_with_twins(
        "twins_translated", ("ring/outer/wall_s/0", "ring/outer/wall_s/2"), extra_planes=tuple(extra)
    )


def _corridor_ring_with_twins(
    name: str, twin_panels: tuple[str, str], extra_planes: tuple[Plane, ...] = ()
) -> Scene:
    """The twin scenes' corridor ring (outer 18 x 12 m, 2.6 m wide, 3 m high) with the two named panels showing the
    same texture, ``extra_planes`` (furniture) added, and their camera path (one lap in 80 s, looking 40 degrees to
    the right of the way ahead)."""
    planes = tuple(
        Plane(p.name, p.origin_m, p.u_m, p.v_m, "twin_wall") if p.name in twin_panels else p
        for p in corridor_ring("ring", (9.0, 6.0), 2.6, 3.0)
    ) + tuple(extra_planes)
    way = rounded_rectangle((7.7, 4.7), corner_m=1.1, spacing_m=1.5, z=1.5)
    path = CameraPath(way, period_s=80.0, duration_s=86.0, look_ahead_s=1.2, yaw_offset_deg=-40.0)
    return Scene(name, planes, path)


#: scene name -> builder. Read-only; add a scene by adding an entry.
SCENES: MappingProxyType[str, Callable[[], Scene]] = MappingProxyType(
    {
        "room": room_scene,
        "planar": planar_scene,
        "long_loop": long_loop_scene,
        "twins": twins_scene,
        "twins_translated": twins_translated_scene,
    }
)


def build_scene(name: str) -> Scene:
    """The scene called ``name``; ConfigError naming ``dataset.scene`` and the choices otherwise."""
    builder = SCENES.get(name)
    if builder is None:
        raise ConfigError(f"dataset.scene: unknown synthetic scene {name!r}; expected one of {sorted(SCENES)}")
    return builder()
