"""Synthetic indoor scenes as flat arrays of primitives (numba-friendly), with exact distance queries.

World frame: metres, z up, the floor at z = 0. Each primitive ``p`` has a pose (rotation ``R[p]`` whose
columns are the local axes in world coordinates, centre ``center[p]``) and half-sizes ``size[p]``. In its
local frame:

* ``PRIM_QUAD``      rectangle ``|x| <= size.x, |y| <= size.y`` in the plane ``z = 0`` (normal local +z);
* ``PRIM_BOX``       solid box ``|x| <= size.x, |y| <= size.y, |z| <= size.z``;
* ``PRIM_CYLINDER``  capped solid cylinder of radius ``size.x`` around local z, ``|z| <= size.z``;
* ``PRIM_SPHERE``    solid sphere of radius ``size.x``.

Walls, floor and ceiling are quads whose local +z points into the room.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.synth.textures import TextureConfig, make_texture_bank

PRIM_QUAD = 0
PRIM_BOX = 1
PRIM_CYLINDER = 2
PRIM_SPHERE = 3

SCENES = ["room", "office", "plane", "corridor"]

_TEX = ("wallpaper", "wood", "plaster", "checker", "blobs", "fabric", "books", "metal", "poster")
T_WALLPAPER, T_WOOD, T_PLASTER, T_CHECKER, T_BLOBS, T_FABRIC, T_BOOKS, T_METAL, T_POSTER = range(len(_TEX))


@dataclass(frozen=True)
class ViewHint:
    """Where trajectories may go in a scene (all world frame, metres).

    ``kind`` is ``"room"`` (the camera may turn all the way round), ``"wall"`` (it keeps facing one
    surface) or ``"corridor"`` (it walks along ``facing``, looking ahead).
    ``centre``: middle of the free space the camera moves in. ``orbit_radius_m``: radius of the
    slow orbit (positive: the eye is behind the centre and looks across the room; negative: the eye is
    ahead of the centre and looks out at the nearer walls). ``loop_radii_m``: (x, y) semi-axes of the
    walking loop. ``eye_height_m``: mean camera height. ``look_distance_m``: how far ahead the look-at
    target is; ``look_height_m``: its height. ``facing`` (``"wall"`` only): unit direction camera -> wall.
    """

    kind: str
    centre: tuple[float, float, float]
    orbit_radius_m: float
    loop_radii_m: tuple[float, float]
    eye_height_m: float
    look_distance_m: float
    look_height_m: float
    facing: tuple[float, float, float] = (1.0, 0.0, 0.0)
    ceiling_facing: tuple[float, float, float] = (0.0, -1.0, 0.0)  # "upward": towards a wall bare up to the ceiling


@dataclass
class Scene:
    """A scene: primitive arrays (see module docstring), textures and a point light.

    Attributes:
        name: scene name.
        prim_type: ``(P,)`` int32 primitive kind (``PRIM_*``).
        prim_R: ``(P, 3, 3)`` float64 world-from-local rotations.
        prim_center: ``(P, 3)`` float64 centres (world, m).
        prim_size: ``(P, 3)`` float64 half-sizes (m); radius in ``[:, 0]`` for cylinders and spheres.
        prim_tex: ``(P,)`` int32 texture index into ``textures``.
        prim_uv_offset_m: ``(P, 2)`` float64 texture offset (m) so equal textures look different.
        prim_names: ``P`` labels (for debugging and tests).
        textures: ``(T, S, S, 3)`` uint8 RGB.
        texel_m: texture resolution (metres per texel).
        light_pos_world: ``(3,)`` point light position (m).
        ambient: ambient shading factor; ``diffuse``: Lambertian factor (albedo x (ambient + diffuse cos)).
        view: trajectory hint.
    """

    name: str
    prim_type: np.ndarray
    prim_R: np.ndarray
    prim_center: np.ndarray
    prim_size: np.ndarray
    prim_tex: np.ndarray
    prim_uv_offset_m: np.ndarray
    prim_names: list[str]
    textures: np.ndarray = field(repr=False)
    texel_m: float
    light_pos_world: np.ndarray
    ambient: float
    diffuse: float
    view: ViewHint

    @property
    def n_primitives(self) -> int:
        return len(self.prim_type)

    def primitive_distances(self, points_world: np.ndarray) -> np.ndarray:
        """Signed distance of each point to each primitive, ``(N, 3)`` -> ``(N, P)`` float64.

        Solids are negative inside. Quads (zero thickness) are signed by their side: positive on the
        local +z side (the room side for walls).
        """
        pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        out = np.empty((len(pts), self.n_primitives))
        for p in range(self.n_primitives):  # loop over primitives (tens), vectorised over points
            q = (pts - self.prim_center[p]) @ self.prim_R[p]
            s = self.prim_size[p]
            kind = self.prim_type[p]
            if kind == PRIM_QUAD:
                dx = np.maximum(np.abs(q[:, 0]) - s[0], 0.0)
                dy = np.maximum(np.abs(q[:, 1]) - s[1], 0.0)
                d = np.sqrt(dx * dx + dy * dy + q[:, 2] ** 2)
                out[:, p] = np.where(q[:, 2] >= 0, d, -d)
            elif kind == PRIM_BOX:
                e = np.abs(q) - s
                outside = np.linalg.norm(np.maximum(e, 0.0), axis=1)
                inside = np.minimum(e.max(axis=1), 0.0)
                out[:, p] = outside + inside
            elif kind == PRIM_CYLINDER:
                dr = np.hypot(q[:, 0], q[:, 1]) - s[0]
                dz = np.abs(q[:, 2]) - s[2]
                out[:, p] = np.minimum(np.maximum(dr, dz), 0.0) + np.hypot(
                    np.maximum(dr, 0.0), np.maximum(dz, 0.0)
                )
            else:
                out[:, p] = np.linalg.norm(q, axis=1) - s[0]
        return out

    def signed_distance(self, points_world: np.ndarray) -> np.ndarray:
        """``(N, 3)`` -> ``(N,)`` float64: the per-primitive signed distance of smallest magnitude.

        Negative inside furniture and behind walls (on the non-room side of a wall quad).
        """
        d = self.primitive_distances(points_world)
        i = np.argmin(np.abs(d), axis=1)
        return d[np.arange(len(d)), i]

    def distance_to_surface(self, points_world: np.ndarray) -> np.ndarray:
        """``(N, 3)`` -> ``(N,)`` float64 unsigned distance (m) to the nearest surface of the scene."""
        return np.abs(self.primitive_distances(points_world)).min(axis=1)


def frame_from_normal(normal, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Rotation whose local z is ``normal`` and local y is as close as possible to ``up``."""
    z = np.asarray(normal, np.float64)
    z = z / np.linalg.norm(z)
    up = np.asarray(up, np.float64)
    if abs(float(np.dot(up, z))) > 0.99:
        up = np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


def yaw(deg: float) -> np.ndarray:
    """Rotation about world z by ``deg`` degrees."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class _Builder:
    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.rows: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, int, str]] = []

    def add(self, kind: int, R, center, size, tex: int, name: str) -> None:
        self.rows.append((kind, np.asarray(R, float), np.asarray(center, float), np.asarray(size, float), tex, name))

    def quad(self, center, normal, half_w, half_h, tex, name, up=(0.0, 0.0, 1.0)) -> None:
        self.add(PRIM_QUAD, frame_from_normal(normal, up), center, (half_w, half_h, 0.0), tex, name)

    def box(self, center, half, tex, name, R=None) -> None:
        self.add(PRIM_BOX, np.eye(3) if R is None else R, center, half, tex, name)

    def cylinder(self, center, radius, half_h, tex, name, R=None) -> None:
        self.add(PRIM_CYLINDER, np.eye(3) if R is None else R, center, (radius, radius, half_h), tex, name)

    def sphere(self, center, radius, tex, name) -> None:
        self.add(PRIM_SPHERE, np.eye(3), center, (radius, radius, radius), tex, name)

    def room_shell(self, lx, ly, lz, wall_tex=(T_WALLPAPER,) * 4, floor_tex=T_WOOD, ceil_tex=T_PLASTER) -> None:
        self.quad((lx / 2, ly / 2, 0.0), (0, 0, 1), lx / 2, ly / 2, floor_tex, "floor", up=(0, 1, 0))
        self.quad((lx / 2, ly / 2, lz), (0, 0, -1), lx / 2, ly / 2, ceil_tex, "ceiling", up=(0, 1, 0))
        self.quad((0.0, ly / 2, lz / 2), (1, 0, 0), ly / 2, lz / 2, wall_tex[0], "wall_x0")
        self.quad((lx, ly / 2, lz / 2), (-1, 0, 0), ly / 2, lz / 2, wall_tex[1], "wall_x1")
        self.quad((lx / 2, 0.0, lz / 2), (0, 1, 0), lx / 2, lz / 2, wall_tex[2], "wall_y0")
        self.quad((lx / 2, ly, lz / 2), (0, -1, 0), lx / 2, lz / 2, wall_tex[3], "wall_y1")

    def table(self, cx, cy, hx, hy, height, R, tex, name, leg_r=0.025) -> None:
        top_half = 0.02
        self.box((cx, cy, height - top_half), (hx, hy, top_half), tex, f"{name}_top", R)
        leg_h = (height - 2 * top_half) / 2
        for sx in (-1, 1):
            for sy in (-1, 1):
                off = R @ np.array([sx * (hx - 0.06), sy * (hy - 0.06), 0.0])
                self.cylinder((cx + off[0], cy + off[1], leg_h), leg_r, leg_h, T_METAL, f"{name}_leg")

    def shelf(self, cx, cy, hx, hy, height, n_levels, R, tex, name) -> None:
        """An open shelf unit (two sides, back, boards) filled with books of varied height."""
        t = 0.015
        for sx in (-1, 1):
            off = R @ np.array([sx * (hx - t), 0.0, 0.0])
            self.box((cx + off[0], cy + off[1], height / 2), (t, hy, height / 2), tex, f"{name}_side", R)
        off = R @ np.array([0.0, hy - t, 0.0])
        self.box((cx + off[0], cy + off[1], height / 2), (hx, t, height / 2), tex, f"{name}_back", R)
        for k in range(n_levels + 1):
            z = 0.05 + k * (height - 0.07) / n_levels
            self.box((cx, cy, z), (hx - 2 * t, hy - t, t), tex, f"{name}_board", R)
            if k == n_levels:
                break
            # a row of books on this board: a few boxes with random width and height
            u = -hx + 2 * t + 0.02
            while True:
                w = float(self.rng.uniform(0.08, 0.25))
                if u + w > hx - 2 * t - 0.02:
                    break
                hgt = float(self.rng.uniform(0.12, 0.75 * (height - 0.07) / n_levels))
                depth = float(self.rng.uniform(0.6, 0.85)) * (hy - t)
                c = R @ np.array([u + w / 2, (hy - t) - depth, 0.0])
                self.box(
                    (cx + c[0], cy + c[1], z + t + hgt / 2), (w / 2, depth, hgt / 2), T_BOOKS, f"{name}_books", R
                )
                u += w + float(self.rng.uniform(0.0, 0.08))

    def build(self, name, textures, texel_m, light, view, ambient=0.35, diffuse=0.75) -> Scene:
        n = len(self.rows)
        off = self.rng.uniform(0.0, textures.shape[1] * texel_m, size=(n, 2))
        return Scene(
            name=name,
            prim_type=np.array([r[0] for r in self.rows], np.int32),
            prim_R=np.stack([r[1] for r in self.rows]),
            prim_center=np.stack([r[2] for r in self.rows]),
            prim_size=np.stack([r[3] for r in self.rows]),
            prim_tex=np.array([r[4] for r in self.rows], np.int32),
            prim_uv_offset_m=off,
            prim_names=[r[5] for r in self.rows],
            textures=textures,
            texel_m=texel_m,
            light_pos_world=np.asarray(light, np.float64),
            ambient=ambient,
            diffuse=diffuse,
            view=view,
        )


def _room(b: _Builder) -> ViewHint:
    """Living room 5 x 4 x 2.7 m: sofa, coffee table, shelf, TV unit, rotated cabinet, lamp, plants, balls."""
    lx, ly, lz = 5.0, 4.0, 2.7
    b.room_shell(lx, ly, lz, wall_tex=(T_WALLPAPER, T_POSTER, T_PLASTER, T_WALLPAPER))
    # sofa along wall y = ly
    b.box((2.4, 3.55, 0.22), (1.0, 0.38, 0.22), T_FABRIC, "sofa_seat")
    b.box((2.4, 3.87, 0.5), (1.0, 0.12, 0.5), T_FABRIC, "sofa_back")
    for sx in (-1, 1):
        b.box((2.4 + sx * 1.1, 3.55, 0.32), (0.1, 0.42, 0.32), T_FABRIC, "sofa_arm")
    b.cylinder((1.9, 3.35, 0.5), 0.09, 0.25, T_CHECKER, "cushion", R=frame_from_normal((1, 0, 0)))
    # coffee table + objects
    b.table(2.5, 2.1, 0.6, 0.32, 0.45, yaw(8.0), T_WOOD, "coffee_table")
    b.sphere((2.2, 2.0, 0.45 + 0.11), 0.11, T_BLOBS, "ball_on_table")
    b.cylinder((2.8, 2.2, 0.45 + 0.09), 0.05, 0.09, T_METAL, "mug")
    b.box((2.6, 1.95, 0.45 + 0.03), (0.15, 0.1, 0.03), T_POSTER, "book_on_table", R=yaw(-25.0))
    # rug (thin box on the floor)
    b.box((2.5, 2.1, 0.004), (1.2, 0.8, 0.004), T_CHECKER, "rug", R=yaw(8.0))
    # shelf on wall x = lx (back against the wall): local +y points to the wall
    b.shelf(lx - 0.2, 1.6, 0.6, 0.18, 1.9, 4, yaw(-90.0), T_WOOD, "shelf")
    # TV unit along wall y = 0
    b.box((2.5, 0.25, 0.28), (0.9, 0.22, 0.28), T_WOOD, "tv_unit")
    b.box((2.5, 0.12, 0.95), (0.6, 0.03, 0.36), T_POSTER, "tv")
    b.box((1.8, 0.3, 0.62), (0.08, 0.08, 0.06), T_METAL, "speaker")
    # rotated cabinet in the corner (non-axis-aligned planes)
    b.box((0.55, 0.55, 0.45), (0.32, 0.25, 0.45), T_BLOBS, "corner_cabinet", R=yaw(40.0))
    b.sphere((0.55, 0.55, 0.9 + 0.14), 0.14, T_FABRIC, "vase")
    # floor lamp and plant by the sofa
    b.cylinder((0.45, 3.55, 0.8), 0.025, 0.8, T_METAL, "lamp_pole")
    b.cylinder((0.45, 3.55, 1.6 + 0.15), 0.2, 0.15, T_FABRIC, "lamp_shade")
    b.cylinder((4.55, 3.55, 0.25), 0.2, 0.25, T_CHECKER, "plant_pot")
    b.sphere((4.55, 3.55, 0.5 + 0.3), 0.32, T_BLOBS, "plant")
    # a picture frame leaning on wall x = 0 (tilted plane) and pictures on the walls
    lean = np.radians(12.0)
    b.quad((0.14, 2.0, 0.55), (np.cos(lean), 0.0, np.sin(lean)), 0.45, 0.55, T_POSTER, "leaning_frame")
    b.box((0.02, 1.2, 1.6), (0.02, 0.35, 0.25), T_CHECKER, "picture_x0")
    b.box((3.8, ly - 0.02, 1.7), (0.4, 0.02, 0.3), T_POSTER, "picture_y1")
    b.box((1.2, ly - 0.02, 1.5), (0.25, 0.02, 0.35), T_BLOBS, "picture_y1b")
    # armchair (rotated) near the x = 0 wall
    R = yaw(-30.0)
    b.box((1.0, 2.5, 0.22), (0.38, 0.38, 0.22), T_FABRIC, "armchair_seat", R)
    c = R @ np.array([-0.32, 0.0, 0.0])
    b.box((1.0 + c[0], 2.5 + c[1], 0.5), (0.08, 0.38, 0.5), T_FABRIC, "armchair_back", R)
    # a ball on the floor
    b.sphere((3.9, 1.0, 0.13), 0.13, T_CHECKER, "floor_ball")
    return ViewHint("room", (2.5, 2.0, 1.4), 0.9, (0.9, 0.6), 1.45, 2.0, 0.7)


def _office(b: _Builder) -> ViewHint:
    """Office 6 x 5 x 2.8 m: two rotated desks with monitors, cabinets, shelf, whiteboard, column, plant."""
    lx, ly, lz = 6.0, 5.0, 2.8
    b.room_shell(lx, ly, lz, wall_tex=(T_PLASTER, T_WALLPAPER, T_POSTER, T_PLASTER), floor_tex=T_CHECKER)
    for i, (cx, cy, ang) in enumerate([(1.4, 1.2, 15.0), (4.5, 1.3, -20.0)]):
        R = yaw(ang)
        b.table(cx, cy, 0.75, 0.4, 0.74, R, T_WOOD, f"desk{i}")
        m = R @ np.array([0.0, -0.2, 0.0])
        b.box((cx + m[0], cy + m[1], 0.74 + 0.25), (0.3, 0.02, 0.18), T_POSTER, f"monitor{i}", R)
        b.box((cx + m[0], cy + m[1], 0.74 + 0.04), (0.1, 0.08, 0.04), T_METAL, f"monitor_foot{i}", R)
        k = R @ np.array([0.25, 0.15, 0.0])
        b.box((cx + k[0], cy + k[1], 0.74 + 0.1), (0.1, 0.12, 0.1), T_BOOKS, f"desk_books{i}", R)
        # chair: seat + back + base cylinder
        ch = R @ np.array([0.0, 0.75, 0.0])
        Rc = R @ yaw(10.0)
        b.cylinder((cx + ch[0], cy + ch[1], 0.22), 0.04, 0.22, T_METAL, f"chair_post{i}")
        b.box((cx + ch[0], cy + ch[1], 0.47), (0.24, 0.24, 0.03), T_FABRIC, f"chair_seat{i}", Rc)
        cb = Rc @ np.array([0.0, 0.24, 0.0])
        b.box((cx + ch[0] + cb[0], cy + ch[1] + cb[1], 0.8), (0.22, 0.03, 0.28), T_FABRIC, f"chair_back{i}", Rc)
    # filing cabinets along wall x = 0
    for j in range(2):
        b.box((0.25, 3.0 + j * 0.5, 0.55), (0.23, 0.22, 0.55), T_METAL, f"cabinet{j}")
    b.sphere((0.25, 3.0, 1.1 + 0.12), 0.12, T_BLOBS, "globe")
    # shelf against wall y = ly
    b.shelf(3.2, ly - 0.2, 0.9, 0.18, 2.0, 5, np.eye(3), T_WOOD, "shelf")
    # whiteboard on wall x = lx (slightly tilted out), posters
    b.box((lx - 0.03, 2.6, 1.4), (0.03, 0.9, 0.55), T_POSTER, "whiteboard", R=None)
    b.box((2.0, 0.02, 1.6), (0.5, 0.02, 0.35), T_BLOBS, "poster_y0")
    # structural column and a water cooler, plant
    b.box((4.9, 4.0, lz / 2), (0.2, 0.2, lz / 2), T_PLASTER, "column", R=yaw(30.0))
    b.cylinder((5.6, 0.4, 0.55), 0.16, 0.55, T_METAL, "water_cooler")
    b.cylinder((5.6, 0.4, 1.1 + 0.2), 0.13, 0.2, T_CHECKER, "water_bottle")
    b.cylinder((0.5, 0.5, 0.22), 0.2, 0.22, T_WOOD, "plant_pot")
    b.sphere((0.5, 0.5, 0.44 + 0.35), 0.38, T_BLOBS, "plant")
    # a low rotated box (printer stand) and a wedge-like leaning panel
    b.box((1.0, 4.4, 0.35), (0.35, 0.25, 0.35), T_BLOBS, "printer_stand", R=yaw(-35.0))
    b.box((1.0, 4.4, 0.7 + 0.12), (0.22, 0.18, 0.12), T_METAL, "printer", R=yaw(-35.0))
    n = np.array([-np.cos(np.radians(15)), 0.0, np.sin(np.radians(15))])
    b.quad((lx - 0.15, 4.3, 0.55), n, 0.4, 0.55, T_CHECKER, "leaning_board")
    return ViewHint("room", (3.0, 2.6, 1.4), -1.0, (1.1, 0.7), 1.5, 2.4, 0.7, ceiling_facing=(-1.0, 0.0, 0.0))


def _plane(b: _Builder) -> ViewHint:
    """One textured wall (4 x 3 m) at x = 0 facing +x: the degenerate case for ICP."""
    b.quad((0.0, 0.0, 1.5), (1, 0, 0), 2.0, 1.5, T_BLOBS, "wall")
    return ViewHint("wall", (1.5, 0.0, 1.5), 0.15, (0.25, 0.15), 1.5, 1.5, 1.5, facing=(-1.0, 0.0, 0.0))


def _corridor(b: _Builder) -> ViewHint:
    """A corridor 16 x 1.8 x 2.5 m along x: two long plain walls, floor and ceiling, with a door frame every 4 m
    and a few fittings. Away from the end walls the geometry leaves translation along the corridor nearly free:
    the near-degenerate case where ICP slides and only the fittings (and texture) hold the pose."""
    lx, ly, lz = 16.0, 1.8, 2.5
    b.room_shell(lx, ly, lz, wall_tex=(T_POSTER, T_POSTER, T_PLASTER, T_PLASTER), floor_tex=T_CHECKER)
    for i, x in enumerate(np.arange(2.0, lx - 1.0, 4.0)):
        side = (0.02, ly - 0.02)[i % 2]
        b.box((x, side, 1.0), (0.45, 0.02, 1.0), T_WOOD, f"door{i}")
        b.box((x + 1.3, (ly - 0.03, 0.03)[i % 2], 1.5), (0.2, 0.03, 0.15), T_BLOBS, f"sign{i}")
    for i, x in enumerate(np.arange(3.0, lx - 1.0, 5.0)):
        b.box((x, ly / 2, lz - 0.03), (0.6, 0.15, 0.03), T_METAL, f"light{i}")
    return ViewHint("corridor", (lx / 2, ly / 2, 1.4), 4.5, (0.2, 0.1), 1.5, 2.5, 1.3, facing=(1.0, 0.0, 0.0))


_BUILDERS = {"room": _room, "office": _office, "plane": _plane, "corridor": _corridor}


def make_scene(name: str, seed: int = 0, texture_cfg: TextureConfig = TextureConfig()) -> Scene:
    """Build scene ``name`` (one of :data:`SCENES`); textures and small details depend on ``seed``."""
    if name not in _BUILDERS:
        raise ConfigError(f"unknown scene {name!r}; known scenes: {', '.join(SCENES)}")
    b = _Builder(np.random.default_rng([seed, 104729]))
    view = _BUILDERS[name](b)
    textures = make_texture_bank(_TEX, seed, texture_cfg)
    lx = view.centre
    light = (lx[0] - 0.4, lx[1] + 0.3, 2.5) if view.kind in ("room", "corridor") else (2.0, 0.5, 2.5)
    return b.build(name, textures, texture_cfg.texel_m, light, view)
