"""The synthetic indoor scenes (:data:`SCENES`), built from the primitives of :mod:`surfelslam.synth.builder`.

World frame: metres, z up, the floor at z = 0. Walls, floor and ceiling are quads whose local +z points into the
room. ``floor`` (several rooms along a corridor) is built in :mod:`surfelslam.synth.floor`.
"""

from __future__ import annotations

import numpy as np

from surfelslam.errors import ConfigError
from surfelslam.synth.builder import (
    PRIM_BOX,
    PRIM_CYLINDER,
    PRIM_QUAD,
    PRIM_SPHERE,
    T_BLOBS,
    T_BOOKS,
    T_CHECKER,
    T_FABRIC,
    T_METAL,
    T_PLASTER,
    T_POSTER,
    T_WALLPAPER,
    T_WOOD,
    Scene,
    SceneBuilder,
    ViewHint,
    frame_from_normal,
    yaw,
)
from surfelslam.synth.floor import build_floor
from surfelslam.synth.textures import TEXTURE_KINDS, TextureConfig, make_texture_bank

__all__ = ["PRIM_BOX", "PRIM_CYLINDER", "PRIM_QUAD", "PRIM_SPHERE", "SCENES", "Scene", "ViewHint", "make_scene"]

SCENES = ["room", "office", "plane", "corridor", "floor"]

def _room(b: SceneBuilder) -> ViewHint:
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


def _office(b: SceneBuilder) -> ViewHint:
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


def _plane(b: SceneBuilder) -> ViewHint:
    """One textured wall (4 x 3 m) at x = 0 facing +x: the degenerate case for ICP."""
    b.quad((0.0, 0.0, 1.5), (1, 0, 0), 2.0, 1.5, T_BLOBS, "wall")
    return ViewHint("wall", (1.5, 0.0, 1.5), 0.15, (0.25, 0.15), 1.5, 1.5, 1.5, facing=(-1.0, 0.0, 0.0))


def _corridor(b: SceneBuilder) -> ViewHint:
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


_BUILDERS = {"room": _room, "office": _office, "plane": _plane, "corridor": _corridor, "floor": build_floor}


def make_scene(name: str, seed: int = 0, texture_cfg: TextureConfig = TextureConfig()) -> Scene:
    """Build scene ``name`` (one of :data:`SCENES`); textures and small details depend on ``seed``."""
    if name not in _BUILDERS:
        raise ConfigError(f"unknown scene {name!r}; known scenes: {', '.join(SCENES)}")
    b = SceneBuilder(np.random.default_rng([seed, 104729]))
    view = _BUILDERS[name](b)
    textures = make_texture_bank(TEXTURE_KINDS, seed, texture_cfg)
    lx = view.centre
    light = (lx[0] - 0.4, lx[1] + 0.3, 2.5) if view.kind in ("room", "corridor") else (2.0, 0.5, 2.5)
    return b.build(name, textures, texture_cfg.texel_m, light, view)
