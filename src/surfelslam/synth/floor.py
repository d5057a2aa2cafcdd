"""``floor``: rooms of different sizes on both sides of a corridor, joined by doorways, with a walking route.

World frame (m, z up): the corridor runs along x, ``0 <= y <= CORRIDOR_WIDTH_M``, from ``x = -END_ZONE_M`` to
``length + END_ZONE_M``. South rooms (y < 0) and north rooms (y > the corridor width) sit side by side along it,
behind walls ``WALL_M`` thick; each has one doorway (a gap with a wooden frame) into the corridor. Room sizes, door
positions, furniture kits and wall textures (plain plaster or patterned) depend on the builder's seed.

Each room is furnished in its own frame (:class:`_RoomFrame`): x along the door wall, y into the room from it, so
a kit fits either side. Furniture stays within ``BAND_M`` of the walls (or on an island in the middle of large
rooms) and away from the doorway, which leaves a lap ``LOOP_INSET_M`` from the walls free for the walking route
(``ViewHint.route``): east along the corridor entering each south room (a lap round it, looking out at its walls),
a turn at the east end, west entering each north room, a turn at the west end, glancing into the rooms it passes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from surfelslam.synth.builder import (
    T_BLOBS,
    T_BOOKS,
    T_CHECKER,
    T_FABRIC,
    T_METAL,
    T_PLASTER,
    T_POSTER,
    T_WALLPAPER,
    T_WOOD,
    SceneBuilder,
    ViewHint,
    yaw,
)

CORRIDOR_WIDTH_M = 2.4  # wide enough for a walking turn (radius ~0.6 m) 0.6 m from the walls
CEILING_M = 2.7  # room and corridor height
WALL_M = 0.12  # wall thickness between corridor and rooms and between rooms
END_ZONE_M = 2.6  # corridor beyond the last rooms at each end: room to turn round
DOOR_HALF_W_M, DOOR_H_M = 0.5, 2.1  # clear doorway: 1.0 m wide (0.5 m each side of a walker), 2.1 m high
FRAME_W_M, FRAME_PROUD_M = 0.08, 0.02  # door frame width, and how far it stands out of the wall
THRESHOLD_M = 0.01  # door threshold height: above both floors, so that it never ties with them
N_SOUTH = 4  # rooms south of the corridor; the north side gets 3 or 4 (seeded)
ROOM_W_M, ROOM_D_M = (3.8, 6.0), (4.0, 6.0)  # room width (along the corridor) and depth ranges
BAND_M = 0.65  # furniture stands within this distance of a wall (or on the island)
LOOP_INSET_M, LOOP_FRONT_M = 1.05, 1.0  # the lap round a room: this far from side/back walls and the door wall
ISLAND_CLEAR_M = 0.75  # an island (table) keeps this far inside the lap
TURN_M = (2.6, 1.0, 0.55)  # end turn: starts this far from the end wall, comes within 1.0 m, +-0.55 m across
ROOM_LOOK_RAD = -0.87  # in a room the gaze turns 50 deg right of the walking direction (out at the walls)
GLANCE_RAD = 1.0  # passing a doorway on the left, the gaze turns 57 deg to look into the room
GLANCE_HALF_M = 1.0  # ... over this distance either side of the doorway
PATTERNED_WALLS = (T_WALLPAPER, T_POSTER, T_CHECKER, T_BLOBS)


@dataclass(frozen=True)
class _RoomFrame:
    """A room's frame: world xy = ``origin + R(yaw_deg) @ local xy``; local y points into the room."""

    origin: tuple[float, float]
    yaw_deg: float
    width_m: float
    depth_m: float
    door_x_m: float

    def p(self, lx: float, ly: float, z: float) -> tuple[float, float, float]:
        c, s = np.cos(np.radians(self.yaw_deg)), np.sin(np.radians(self.yaw_deg))
        return (self.origin[0] + c * lx - s * ly, self.origin[1] + s * lx + c * ly, z)

    def R(self, deg: float = 0.0) -> np.ndarray:
        return yaw(self.yaw_deg + deg)

    def normal(self, lnx: float, lny: float) -> tuple[float, float, float]:
        x, y, _ = self.p(lnx, lny, 0.0)
        return (x - self.origin[0], y - self.origin[1], 0.0)


def _wall(b: SceneBuilder, p0, p1, normal, doors_s, tex: int, name: str) -> None:
    """A wall from ``p0`` to ``p1`` (world xy) facing ``normal``, with doorways centred ``doors_s`` m from ``p0``."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.linalg.norm(p1 - p0))
    along = (p1 - p0) / length
    edge = DOOR_HALF_W_M + FRAME_W_M / 2  # wall pieces end inside the frame's jambs
    cuts = [0.0]
    for s in sorted(doors_s):
        cuts += [s - edge, s + edge]
        c = p0 + s * along
        z0 = DOOR_H_M + FRAME_W_M / 2
        b.quad((c[0], c[1], 0.5 * (z0 + CEILING_M)), normal, edge, 0.5 * (CEILING_M - z0), tex, f"{name}_lintel")
    cuts.append(length)
    for a, e in zip(cuts[::2], cuts[1::2], strict=True):
        c = p0 + 0.5 * (a + e) * along
        b.quad((c[0], c[1], CEILING_M / 2), normal, 0.5 * (e - a), CEILING_M / 2, tex, name)


def _door_frame(b: SceneBuilder, centre_xy, along_deg: float, name: str) -> None:
    """Jambs, head and threshold of a doorway centred at ``centre_xy`` (the wall's mid-plane), along ``along_deg``."""
    R = yaw(along_deg)
    half_t = WALL_M / 2 + FRAME_PROUD_M
    for sgn in (-1.0, 1.0):
        off = R @ np.array([sgn * (DOOR_HALF_W_M + FRAME_W_M / 2), 0.0, 0.0])
        b.box((centre_xy[0] + off[0], centre_xy[1] + off[1], DOOR_H_M / 2), (FRAME_W_M / 2, half_t, DOOR_H_M / 2),
              T_WOOD, f"{name}_jamb", R)
    b.box((centre_xy[0], centre_xy[1], DOOR_H_M + FRAME_W_M / 2),
          (DOOR_HALF_W_M + FRAME_W_M, half_t, FRAME_W_M / 2), T_WOOD, f"{name}_head", R)
    # a threshold 1 cm high bridges the floors of the corridor and the room under the doorway
    b.box((centre_xy[0], centre_xy[1], 0.0), (DOOR_HALF_W_M + FRAME_W_M / 2, half_t, THRESHOLD_M), T_WOOD,
          f"{name}_threshold", R)


def _room_shell(b: SceneBuilder, rf: _RoomFrame, wall_tex: int, name: str) -> None:
    w, d = rf.width_m, rf.depth_m
    centre = rf.p(w / 2, d / 2, 0.0)
    hx, hy = (w / 2, d / 2) if abs(np.sin(np.radians(rf.yaw_deg))) < 0.5 else (d / 2, w / 2)
    b.quad(centre, (0, 0, 1), hx, hy, T_WOOD, f"{name}_floor", up=(0, 1, 0))
    b.quad(centre[:2] + (CEILING_M,), (0, 0, -1), hx, hy, T_PLASTER, f"{name}_ceiling", up=(0, 1, 0))
    for (a, e), n in [(((0, 0), (0, d)), (1, 0)), (((w, 0), (w, d)), (-1, 0)), (((0, d), (w, d)), (0, -1))]:
        _wall(b, rf.p(*a, 0.0)[:2], rf.p(*e, 0.0)[:2], rf.normal(*n), [], wall_tex, f"{name}_wall")
    _wall(b, rf.p(0, 0, 0.0)[:2], rf.p(w, 0, 0.0)[:2], rf.normal(0, 1), [rf.door_x_m], wall_tex, f"{name}_door_wall")


def _island(rf: _RoomFrame) -> tuple[float, float] | None:
    """Half-sizes of the island a room's lap leaves room for in its middle, or None."""
    hx = 0.5 * (rf.width_m - 2 * LOOP_INSET_M) - ISLAND_CLEAR_M
    hy = 0.5 * (rf.depth_m - LOOP_INSET_M - LOOP_FRONT_M) - ISLAND_CLEAR_M
    return (hx, hy) if min(hx, hy) >= 0.3 else None


def _island_centre(rf: _RoomFrame) -> tuple[float, float]:
    return rf.width_m / 2, 0.5 * (LOOP_FRONT_M + rf.depth_m - LOOP_INSET_M)


def _plant(b: SceneBuilder, rf: _RoomFrame, lx: float, ly: float, name: str) -> None:
    b.cylinder(rf.p(lx, ly, 0.22), 0.18, 0.22, T_CHECKER, f"{name}_pot")
    b.sphere(rf.p(lx, ly, 0.44 + 0.28), 0.3, T_BLOBS, f"{name}_plant")


def _living(b: SceneBuilder, rf: _RoomFrame, name: str) -> None:
    w, d = rf.width_m, rf.depth_m
    hs = min(1.0, w / 2 - 0.8)
    b.box(rf.p(w / 2, d - 0.4, 0.22), (hs, 0.25, 0.22), T_FABRIC, f"{name}_sofa_seat", rf.R())
    b.box(rf.p(w / 2, d - 0.08, 0.45), (hs, 0.07, 0.45), T_FABRIC, f"{name}_sofa_back", rf.R())
    b.shelf(*rf.p(w - 0.2, d / 2, 0.0)[:2], 0.6, 0.18, 1.9, 4, rf.R(-90.0), T_WOOD, f"{name}_shelf")
    b.box(rf.p(w / 2 + 0.3, d - 0.02, 1.6), (0.4, 0.02, 0.3), T_POSTER, f"{name}_picture", rf.R())
    b.box(rf.p(0.25, d / 2, 0.3), (0.4, 0.22, 0.3), T_WOOD, f"{name}_tv_unit", rf.R(90.0))
    _plant(b, rf, 0.4, d - 0.4, name)
    isl = _island(rf)
    if isl is not None:
        cx, cy = _island_centre(rf)
        b.table(*rf.p(cx, cy, 0.0)[:2], min(isl[0], 0.6), min(isl[1], 0.35), 0.45, rf.R(8.0), T_WOOD, f"{name}_ctable")
        b.box(rf.p(cx, cy, 0.004), (isl[0], isl[1], 0.004), T_CHECKER, f"{name}_rug", rf.R())
        b.sphere(rf.p(cx - 0.2, cy, 0.45 + 0.1), 0.1, T_BLOBS, f"{name}_ball")


def _office(b: SceneBuilder, rf: _RoomFrame, name: str) -> None:
    w, d = rf.width_m, rf.depth_m
    for i, cx in enumerate([w / 2] if w < 5.0 else [w / 3, 2 * w / 3]):
        b.table(*rf.p(cx, d - 0.35, 0.0)[:2], 0.6, 0.28, 0.74, rf.R(), T_WOOD, f"{name}_desk{i}")
        b.box(rf.p(cx, d - 0.2, 0.74 + 0.22), (0.28, 0.02, 0.17), T_POSTER, f"{name}_monitor{i}", rf.R())
        b.box(rf.p(cx + 0.4, d - 0.3, 0.74 + 0.1), (0.1, 0.12, 0.1), T_BOOKS, f"{name}_books{i}", rf.R())
    for j in range(2):
        b.box(rf.p(0.25, 1.2 + 0.5 * j, 0.55), (0.22, 0.23, 0.55), T_METAL, f"{name}_cabinet{j}", rf.R())
    b.sphere(rf.p(0.25, 1.2, 1.1 + 0.12), 0.12, T_BLOBS, f"{name}_globe")
    b.box(rf.p(w - 0.03, d / 2, 1.4), (0.03, 0.8, 0.5), T_POSTER, f"{name}_whiteboard", rf.R())
    b.cylinder(rf.p(w - 0.3, 0.4, 0.55), 0.16, 0.55, T_METAL, f"{name}_cooler")
    _plant(b, rf, w - 0.4, d - 0.4, name)


def _library(b: SceneBuilder, rf: _RoomFrame, name: str) -> None:
    w, d = rf.width_m, rf.depth_m
    b.shelf(*rf.p(w / 2, d - 0.2, 0.0)[:2], min(1.0, w / 2 - 0.5), 0.18, 2.0, 5, rf.R(), T_WOOD, f"{name}_shelf_b")
    b.shelf(*rf.p(0.2, d / 2, 0.0)[:2], 0.7, 0.18, 1.8, 4, rf.R(90.0), T_WOOD, f"{name}_shelf_s")
    b.box(rf.p(w - 0.35, d - 0.9, 0.22), (0.3, 0.3, 0.22), T_FABRIC, f"{name}_armchair", rf.R(-15.0))
    b.cylinder(rf.p(w - 0.3, 0.5, 0.8), 0.025, 0.8, T_METAL, f"{name}_lamp_pole")
    b.cylinder(rf.p(w - 0.3, 0.5, 1.75), 0.2, 0.15, T_FABRIC, f"{name}_lamp_shade")
    isl = _island(rf)
    if isl is not None:
        cx, cy = _island_centre(rf)
        b.table(*rf.p(cx, cy, 0.0)[:2], isl[0], min(isl[1], 0.5), 0.74, rf.R(), T_WOOD, f"{name}_table")
        b.box(rf.p(cx + 0.2, cy, 0.74 + 0.03), (0.15, 0.1, 0.03), T_BOOKS, f"{name}_open_book", rf.R(20.0))


def _kitchen(b: SceneBuilder, rf: _RoomFrame, name: str) -> None:
    w, d = rf.width_m, rf.depth_m
    hc = w / 2 - 0.5
    b.box(rf.p(w / 2, d - 0.3, 0.43), (hc, 0.3, 0.43), T_BLOBS, f"{name}_counter", rf.R())
    b.box(rf.p(w / 2, d - 0.3, 0.89), (hc + 0.02, 0.31, 0.03), T_WOOD, f"{name}_worktop", rf.R())
    b.box(rf.p(w / 2, d - 0.18, 1.85), (hc, 0.18, 0.35), T_BLOBS, f"{name}_wall_units", rf.R())
    b.cylinder(rf.p(w / 2 - 0.5, d - 0.3, 0.92 + 0.1), 0.06, 0.1, T_METAL, f"{name}_kettle")
    b.box(rf.p(w - 0.35, d / 2 - 0.5, 0.9), (0.3, 0.33, 0.9), T_METAL, f"{name}_fridge", rf.R())
    b.box(rf.p(0.02, d / 2, 1.5), (0.02, 0.5, 0.35), T_POSTER, f"{name}_calendar", rf.R())
    isl = _island(rf)
    if isl is not None:
        cx, cy = _island_centre(rf)
        b.table(*rf.p(cx, cy, 0.0)[:2], min(isl[0], 0.7), min(isl[1], 0.45), 0.76, rf.R(-10.0), T_WOOD,
                f"{name}_table")
        for k in range(3):
            b.sphere(rf.p(cx - 0.15 + 0.13 * k, cy + 0.05 * k, 0.76 + 0.05), 0.05, T_BLOBS, f"{name}_fruit")


def _meeting(b: SceneBuilder, rf: _RoomFrame, name: str) -> None:
    w, d = rf.width_m, rf.depth_m
    b.box(rf.p(w / 2, d - 0.25, 0.45), (min(1.2, w / 2 - 0.6), 0.22, 0.45), T_WOOD, f"{name}_sideboard", rf.R())
    b.box(rf.p(w / 2, d - 0.02, 1.6), (0.7, 0.02, 0.4), T_POSTER, f"{name}_screen", rf.R())
    b.box(rf.p(0.02, d / 2, 1.5), (0.02, 0.45, 0.3), T_CHECKER, f"{name}_picture", rf.R())
    b.box(rf.p(w - 0.3, d / 2, 0.7), (0.25, 0.2, 0.7), T_BLOBS, f"{name}_column", rf.R(30.0))
    _plant(b, rf, 0.4, d - 0.4, name)
    isl = _island(rf)
    if isl is not None:
        cx, cy = _island_centre(rf)
        b.table(*rf.p(cx, cy, 0.0)[:2], isl[0], isl[1], 0.74, rf.R(), T_WOOD, f"{name}_table")
        b.cylinder(rf.p(cx, cy, 0.74 + 0.06), 0.05, 0.06, T_METAL, f"{name}_jug")
    else:
        b.cylinder(rf.p(w - 0.35, 0.45, 0.36), 0.3, 0.36, T_WOOD, f"{name}_round_table")


_KITS = (_living, _office, _library, _kitchen, _meeting)


def _widths(rng: np.random.Generator, n: int, total_m: float | None) -> list[float]:
    """``n`` room widths in ``ROOM_W_M``; with ``total_m``, scaled so that they and the walls between fill it."""
    w = rng.uniform(*ROOM_W_M, n)
    if total_m is not None:
        w *= (total_m - (n - 1) * WALL_M) / w.sum()
    return [float(v) for v in w]


def _plan_rooms(rng: np.random.Generator) -> tuple[list[_RoomFrame], list[_RoomFrame], float]:
    """South and north room frames and the corridor length they line (m)."""
    south_w = _widths(rng, N_SOUTH, None)
    length = sum(south_w) + (N_SOUTH - 1) * WALL_M
    north_w = _widths(rng, int(rng.integers(3, N_SOUTH + 1)), length)
    sides = []
    for widths, south in ((south_w, True), (north_w, False)):
        rooms, x0 = [], 0.0
        for w in widths:
            d = float(rng.uniform(*ROOM_D_M))
            door = float(rng.uniform(LOOP_INSET_M + 0.1, w - LOOP_INSET_M - 0.1))
            # south rooms are turned 180 deg so that their local y points away from the corridor (-y)
            origin = (x0 + w, -WALL_M) if south else (x0, CORRIDOR_WIDTH_M + WALL_M)
            rooms.append(_RoomFrame(origin, 180.0 if south else 0.0, w, d, door))
            x0 += w + WALL_M
        sides.append(rooms)
    return sides[0], sides[1], length


def _door_world_x(rf: _RoomFrame) -> float:
    return rf.p(rf.door_x_m, 0.0, 0.0)[0]


def _room_visit(rf: _RoomFrame, corridor_y: float) -> list[tuple[float, float, float]]:
    """Waypoints from the corridor through the doorway, a lap round the room (looking out), and back out."""
    w, d = rf.width_m, rf.depth_m
    lap = [(rf.door_x_m, LOOP_FRONT_M, 0.0), (w - LOOP_INSET_M, LOOP_FRONT_M, ROOM_LOOK_RAD),
           (w - LOOP_INSET_M, d - LOOP_INSET_M, ROOM_LOOK_RAD), (LOOP_INSET_M, d - LOOP_INSET_M, ROOM_LOOK_RAD),
           (LOOP_INSET_M, LOOP_FRONT_M, ROOM_LOOK_RAD), (rf.door_x_m, LOOP_FRONT_M, 0.0)]
    xd = _door_world_x(rf)
    return [(xd, corridor_y, 0.0)] + [rf.p(x, y, 0.0)[:2] + (o,) for x, y, o in lap] + [(xd, corridor_y, 0.0)]


def _leg(enter: list[_RoomFrame], glance: list[_RoomFrame], eastward: bool) -> list[tuple[float, float, float]]:
    """The corridor waypoints of one way: visits of ``enter`` and glances into ``glance`` in walking order."""
    yc = CORRIDOR_WIDTH_M / 2
    entered = [_door_world_x(rf) for rf in enter]
    events = [(x, rf, True) for x, rf in zip(entered, enter, strict=True)]
    for rf in glance:
        x = _door_world_x(rf)
        if min(abs(x - e) for e in entered) > 2.0 * GLANCE_HALF_M:
            events.append((x, rf, False))
    events.sort(key=lambda e: e[0], reverse=not eastward)
    step = GLANCE_HALF_M if eastward else -GLANCE_HALF_M
    out: list[tuple[float, float, float]] = []
    for x, rf, inside in events:
        if inside:
            out += _room_visit(rf, yc)
        else:
            out += [(x - step, yc, 0.0), (x, yc, GLANCE_RAD), (x + step, yc, 0.0)]
    return out


def _route(south: list[_RoomFrame], north: list[_RoomFrame], length: float) -> tuple:
    """The closed walking route (see the module docstring)."""
    yc = CORRIDOR_WIDTH_M / 2
    x_w, x_e = -END_ZONE_M, length + END_ZONE_M
    start, near, across = TURN_M
    route = [(x_w + start, yc, 0.0)] + _leg(south, north, True)
    route += [(x_e - start, yc, 0.0), (x_e - near - across, yc - across, 0.0), (x_e - near, yc, 0.0),
              (x_e - near - across, yc + across, 0.0), (x_e - start, yc, 0.0)]
    route += _leg(north, south, False)
    route += [(x_w + start, yc, 0.0), (x_w + near + across, yc + across, 0.0), (x_w + near, yc, 0.0),
              (x_w + near + across, yc - across, 0.0), (x_w + start, yc, 0.0)]
    return tuple((float(x), float(y), float(o)) for x, y, o in route)


def build_floor(b: SceneBuilder) -> ViewHint:
    """Build the floor into ``b``; the view hint centres the other styles in the corridor and carries the route."""
    rng = b.rng
    south, north, length = _plan_rooms(rng)
    x_w, x_e, W = -END_ZONE_M, length + END_ZONE_M, CORRIDOR_WIDTH_M
    mid = ((x_w + x_e) / 2, W / 2)
    b.quad((*mid, 0.0), (0, 0, 1), (x_e - x_w) / 2, W / 2, T_CHECKER, "corridor_floor", up=(0, 1, 0))
    b.quad((*mid, CEILING_M), (0, 0, -1), (x_e - x_w) / 2, W / 2, T_PLASTER, "corridor_ceiling", up=(0, 1, 0))
    _wall(b, (x_w, 0.0), (x_w, W), (1, 0, 0), [], T_POSTER, "corridor_end_w")
    _wall(b, (x_e, 0.0), (x_e, W), (-1, 0, 0), [], T_POSTER, "corridor_end_e")
    _wall(b, (x_w, 0.0), (x_e, 0.0), (0, 1, 0), [_door_world_x(r) - x_w for r in south], T_PLASTER, "corridor_s")
    _wall(b, (x_w, W), (x_e, W), (0, -1, 0), [_door_world_x(r) - x_w for r in north], T_PLASTER, "corridor_n")
    for i, x in enumerate(np.arange(x_w + 2.0, x_e - 1.0, 5.0)):
        b.box((x, W / 2, CEILING_M - 0.03), (0.6, 0.15, 0.03), T_METAL, f"corridor_light{i}")
    kits = rng.permutation(len(_KITS))
    for i, rf in enumerate(south + north):
        name = f"room{i}"
        wall_tex = T_PLASTER if i % 2 == 0 else PATTERNED_WALLS[int(rng.integers(len(PATTERNED_WALLS)))]
        _room_shell(b, rf, wall_tex, name)
        y_mid = -WALL_M / 2 if rf.yaw_deg else W + WALL_M / 2
        _door_frame(b, (_door_world_x(rf), y_mid), 0.0, f"{name}_door")
        _KITS[int(kits[i % len(_KITS)])](b, rf, name)
    b.box((x_e - 0.02, W / 2, 1.5), (0.02, 0.5, 0.35), T_BLOBS, "corridor_sign")
    return ViewHint("corridor", (*mid, 1.4), (x_e - x_w) / 2 - END_ZONE_M, (0.2, 0.1), 1.5, 2.5, 1.3,
                    facing=(1.0, 0.0, 0.0), route=_route(south, north, length))
