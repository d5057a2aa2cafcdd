"""Scene primitives as flat arrays (numba-friendly), exact distance queries, and the builder the scenes use.

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

from surfelslam.synth.textures import TEXTURE_KINDS

PRIM_QUAD = 0
PRIM_BOX = 1
PRIM_CYLINDER = 2
PRIM_SPHERE = 3

# texture indices into the scene's bank (made from TEXTURE_KINDS, in that order)
T_WALLPAPER, T_WOOD, T_PLASTER, T_CHECKER, T_BLOBS, T_FABRIC, T_BOOKS, T_METAL, T_POSTER = range(len(TEXTURE_KINDS))


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
    ``route``: a closed walking route ``((x, y, look_offset_rad), ...)`` (world, m; the last waypoint is the
    first), the path of the ``walk`` trajectory; ``look_offset_rad`` turns the gaze from the walking direction
    (positive: to the left). Empty: the scene has no route.
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
    route: tuple[tuple[float, float, float], ...] = ()


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


class SceneBuilder:
    """Collects primitives (and furniture pieces made of them) and builds a :class:`Scene`."""

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


