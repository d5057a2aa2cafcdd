"""Ray casting of primitive scenes (quads, boxes, cylinders, spheres) for the synthetic generator.

Rays are cast in each primitive's local frame (see :mod:`surfelslam.synth.scenes`). Camera rays use the
direction ``d_cam = ((u - cx) / fx, (v - cy) / fy, 1)`` (not normalised), so the ray parameter ``t`` of a
hit IS its z-depth in metres. ``raycast_ref`` is the plain-numpy reference of the intersection, over a
batch of arbitrary rays, with the same parametrisation (``t`` in units of the given direction's length).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

PRIM_QUAD = 0
PRIM_BOX = 1
PRIM_CYLINDER = 2
PRIM_SPHERE = 3

_PARALLEL_EPS = 1e-12  # |direction component| below this counts as parallel to a plane
# texture offset per box face axis (m) so that the faces of a box do not show the same patch
_FACE_UV_SHIFT_M = 1.37


@njit(cache=True)
def _hit_quad(ox, oy, oz, dx, dy, dz, sx, sy, t_min, t_best):
    if abs(dz) < _PARALLEL_EPS:
        return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    t = -oz / dz
    if t <= t_min or t >= t_best:
        return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    px = ox + t * dx
    py = oy + t * dy
    if abs(px) > sx or abs(py) > sy:
        return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return t, 0.0, 0.0, 1.0, px, py


@njit(cache=True)
def _hit_box(ox, oy, oz, dx, dy, dz, sx, sy, sz, t_min, t_best):
    t_near = -np.inf
    t_far = np.inf
    ax_near = 0
    ax_far = 0
    for k in range(3):
        if k == 0:
            o, d, s = ox, dx, sx
        elif k == 1:
            o, d, s = oy, dy, sy
        else:
            o, d, s = oz, dz, sz
        if abs(d) < _PARALLEL_EPS:
            if abs(o) > s:
                return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
            continue
        t1 = (-s - o) / d
        t2 = (s - o) / d
        if t1 > t2:
            t1, t2 = t2, t1
        if t1 > t_near:
            t_near = t1
            ax_near = k
        if t2 < t_far:
            t_far = t2
            ax_far = k
    if t_near > t_far:
        return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    if t_near > t_min:
        t = t_near
        ax = ax_near
    elif t_far > t_min:
        t = t_far
        ax = ax_far
    else:
        return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    if t >= t_best:
        return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    px = ox + t * dx
    py = oy + t * dy
    pz = oz + t * dz
    shift = _FACE_UV_SHIFT_M * ax
    if ax == 0:
        return t, 1.0 if px > 0 else -1.0, 0.0, 0.0, py + shift, pz
    if ax == 1:
        return t, 0.0, 1.0 if py > 0 else -1.0, 0.0, px + shift, pz
    return t, 0.0, 0.0, 1.0 if pz > 0 else -1.0, px + shift, py


@njit(cache=True)
def _hit_cylinder(ox, oy, oz, dx, dy, dz, r, h, t_min, t_best):
    best = t_best
    nx = 0.0
    ny = 0.0
    nz = 0.0
    uu = 0.0
    vv = 0.0
    found = False
    a = dx * dx + dy * dy
    if a > _PARALLEL_EPS:
        b = ox * dx + oy * dy
        c = ox * ox + oy * oy - r * r
        disc = b * b - a * c
        if disc >= 0.0:
            sq = math.sqrt(disc)
            for sgn in (-1.0, 1.0):
                t = (-b + sgn * sq) / a
                if t > t_min and t < best:
                    pz = oz + t * dz
                    if abs(pz) <= h:
                        px = ox + t * dx
                        py = oy + t * dy
                        best = t
                        nx = px / r
                        ny = py / r
                        nz = 0.0
                        uu = r * math.atan2(py, px)
                        vv = pz
                        found = True
                        break
    if abs(dz) > _PARALLEL_EPS:
        for sgn in (-1.0, 1.0):
            t = (sgn * h - oz) / dz
            if t > t_min and t < best:
                px = ox + t * dx
                py = oy + t * dy
                if px * px + py * py <= r * r:
                    best = t
                    nx = 0.0
                    ny = 0.0
                    nz = sgn
                    uu = px
                    vv = py
                    found = True
    if not found:
        return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return best, nx, ny, nz, uu, vv


@njit(cache=True)
def _hit_sphere(ox, oy, oz, dx, dy, dz, r, t_min, t_best):
    a = dx * dx + dy * dy + dz * dz
    b = ox * dx + oy * dy + oz * dz
    c = ox * ox + oy * oy + oz * oz - r * r
    disc = b * b - a * c
    if disc < 0.0:
        return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    sq = math.sqrt(disc)
    t = (-b - sq) / a
    if t <= t_min:
        t = (-b + sq) / a
    if t <= t_min or t >= t_best:
        return -1.0, 0.0, 0.0, 0.0, 0.0, 0.0
    px = ox + t * dx
    py = oy + t * dy
    pz = oz + t * dz
    return t, px / r, py / r, pz / r, r * math.atan2(py, px), r * math.asin(min(1.0, max(-1.0, pz / r)))


@njit(cache=True)
def _hit(kind, ox, oy, oz, dx, dy, dz, sx, sy, sz, t_min, t_best):
    if kind == PRIM_QUAD:
        return _hit_quad(ox, oy, oz, dx, dy, dz, sx, sy, t_min, t_best)
    if kind == PRIM_BOX:
        return _hit_box(ox, oy, oz, dx, dy, dz, sx, sy, sz, t_min, t_best)
    if kind == PRIM_CYLINDER:
        return _hit_cylinder(ox, oy, oz, dx, dy, dz, sx, sz, t_min, t_best)
    return _hit_sphere(ox, oy, oz, dx, dy, dz, sx, t_min, t_best)


@njit(cache=True)
def _sample_texture(textures, tex, u_m, v_m, texel_m):
    """Bilinear, wrapped texture lookup at ``(u_m, v_m)`` metres -> (r, g, b) floats.

    The texture side S must be a power of two (wrapping is a bit mask).
    """
    mask = textures.shape[1] - 1
    fu = u_m / texel_m
    fv = v_m / texel_m
    iu = math.floor(fu)
    iv = math.floor(fv)
    au = fu - iu
    av = fv - iv
    u0 = int(iu) & mask
    v0 = int(iv) & mask
    u1 = (u0 + 1) & mask
    v1 = (v0 + 1) & mask
    w00 = (1.0 - au) * (1.0 - av)
    w01 = au * (1.0 - av)
    w10 = (1.0 - au) * av
    w11 = au * av
    t = textures[tex]
    a = t[v0, u0]
    b = t[v0, u1]
    c = t[v1, u0]
    d = t[v1, u1]
    r = w00 * a[0] + w01 * b[0] + w10 * c[0] + w11 * d[0]
    g = w00 * a[1] + w01 * b[1] + w10 * c[1] + w11 * d[1]
    bl = w00 * a[2] + w01 * b[2] + w10 * c[2] + w11 * d[2]
    return r, g, bl


@njit(cache=True)
def render_kernel(
    R_world_cam, t_world_cam, fx, fy, cx, cy,
    prim_type, prim_R, prim_M, prim_o, prim_size, prim_bbox, prim_tex, prim_uv_offset_m,
    textures, texel_m, light_pos_world, ambient, diffuse, t_min_m,
    rgb_out, depth_out, normal_out, id_out,
):
    """Cast one ray per pixel; write colour, z-depth, camera-frame normal and primitive id.

    Args:
        R_world_cam, t_world_cam: ``(3, 3)``, ``(3,)`` camera pose.
        prim_M: ``(P, 3, 3)`` ``R_p^T R_world_cam`` (camera direction -> primitive-local direction).
        prim_o: ``(P, 3)`` camera centre in each primitive's local frame.
        prim_bbox: ``(P, 4)`` float64 conservative pixel bounds ``umin, umax, vmin, vmax`` of each primitive.
        t_min_m: near clipping depth (m).
        rgb_out ``(H, W, 3)`` uint8, depth_out ``(H, W)`` float32 (0 = no hit), normal_out ``(H, W, 3)``
        float32 (facing the camera), id_out ``(H, W)`` int32 (-1 = no hit).
    Serial: rendering costs less than writing the frames' PNGs, which the writer does on other threads, and a
    ``parallel=True`` kernel takes twice as long to compile.
    """
    H, W = depth_out.shape
    P = prim_type.shape[0]
    cand = np.empty(P, np.int64)
    for v in range(H):
        y = (v - cy) / fy
        # primitives whose pixel bounds cover this row (checked once per row, not per pixel)
        n_cand = 0
        for p in range(P):
            if prim_bbox[p, 2] <= v <= prim_bbox[p, 3] and prim_bbox[p, 1] >= 0 and prim_bbox[p, 0] <= W - 1:
                cand[n_cand] = p
                n_cand += 1
        for u in range(W):
            x = (u - cx) / fx
            best_t = np.inf
            best_p = -1
            bnx = 0.0
            bny = 0.0
            bnz = 0.0
            buu = 0.0
            bvv = 0.0
            for c in range(n_cand):
                p = cand[c]
                if u < prim_bbox[p, 0] or u > prim_bbox[p, 1]:
                    continue
                dx = prim_M[p, 0, 0] * x + prim_M[p, 0, 1] * y + prim_M[p, 0, 2]
                dy = prim_M[p, 1, 0] * x + prim_M[p, 1, 1] * y + prim_M[p, 1, 2]
                dz = prim_M[p, 2, 0] * x + prim_M[p, 2, 1] * y + prim_M[p, 2, 2]
                t, nx, ny, nz, uu, vv = _hit(
                    prim_type[p], prim_o[p, 0], prim_o[p, 1], prim_o[p, 2], dx, dy, dz,
                    prim_size[p, 0], prim_size[p, 1], prim_size[p, 2], t_min_m, best_t,
                )
                if t > 0.0:
                    best_t = t
                    best_p = p
                    bnx = nx
                    bny = ny
                    bnz = nz
                    buu = uu
                    bvv = vv
            if best_p < 0:
                depth_out[v, u] = 0.0
                id_out[v, u] = -1
                for k in range(3):
                    normal_out[v, u, k] = 0.0
                    rgb_out[v, u, k] = 0
                continue
            p = best_p
            # normal: local -> world -> camera, oriented toward the camera
            nwx = prim_R[p, 0, 0] * bnx + prim_R[p, 0, 1] * bny + prim_R[p, 0, 2] * bnz
            nwy = prim_R[p, 1, 0] * bnx + prim_R[p, 1, 1] * bny + prim_R[p, 1, 2] * bnz
            nwz = prim_R[p, 2, 0] * bnx + prim_R[p, 2, 1] * bny + prim_R[p, 2, 2] * bnz
            ncx = R_world_cam[0, 0] * nwx + R_world_cam[1, 0] * nwy + R_world_cam[2, 0] * nwz
            ncy = R_world_cam[0, 1] * nwx + R_world_cam[1, 1] * nwy + R_world_cam[2, 1] * nwz
            ncz = R_world_cam[0, 2] * nwx + R_world_cam[1, 2] * nwy + R_world_cam[2, 2] * nwz
            if ncx * x + ncy * y + ncz > 0.0:
                ncx = -ncx
                ncy = -ncy
                ncz = -ncz
                nwx = -nwx
                nwy = -nwy
                nwz = -nwz
            depth_out[v, u] = best_t
            id_out[v, u] = p
            normal_out[v, u, 0] = ncx
            normal_out[v, u, 1] = ncy
            normal_out[v, u, 2] = ncz
            # shading: albedo x (ambient + diffuse * max(0, n . l)) with a point light
            pwx = t_world_cam[0] + best_t * (R_world_cam[0, 0] * x + R_world_cam[0, 1] * y + R_world_cam[0, 2])
            pwy = t_world_cam[1] + best_t * (R_world_cam[1, 0] * x + R_world_cam[1, 1] * y + R_world_cam[1, 2])
            pwz = t_world_cam[2] + best_t * (R_world_cam[2, 0] * x + R_world_cam[2, 1] * y + R_world_cam[2, 2])
            lx = light_pos_world[0] - pwx
            ly = light_pos_world[1] - pwy
            lz = light_pos_world[2] - pwz
            ln = math.sqrt(lx * lx + ly * ly + lz * lz)
            cos_l = (nwx * lx + nwy * ly + nwz * lz) / max(ln, 1e-9)
            shade = ambient + diffuse * max(cos_l, 0.0)
            r, g, b = _sample_texture(
                textures, prim_tex[p], buu + prim_uv_offset_m[p, 0], bvv + prim_uv_offset_m[p, 1], texel_m
            )
            rgb_out[v, u, 0] = np.uint8(min(255.0, r * shade + 0.5))
            rgb_out[v, u, 1] = np.uint8(min(255.0, g * shade + 0.5))
            rgb_out[v, u, 2] = np.uint8(min(255.0, b * shade + 0.5))


def raycast_ref(
    origins_world: np.ndarray,
    dirs_world: np.ndarray,
    prim_type: np.ndarray,
    prim_R: np.ndarray,
    prim_center: np.ndarray,
    prim_size: np.ndarray,
    t_min: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Numpy reference: nearest hit of each ray ``o + t d`` (``t > t_min``) with the primitives.

    Args:
        origins_world, dirs_world: ``(N, 3)`` rays (directions need not be unit; ``t`` is in their units).
        prim_*: scene arrays (see :class:`surfelslam.synth.scenes.Scene`).
    Returns:
        ``t (N,)`` (inf = miss), ``prim_id (N,)`` int32 (-1 = miss), ``normal_world (N, 3)`` unit normals
        oriented against the ray (zero on a miss).
    """
    o = np.asarray(origins_world, np.float64)
    d = np.asarray(dirs_world, np.float64)
    n = len(o)
    best_t = np.full(n, np.inf)
    best_id = np.full(n, -1, np.int32)
    best_nl = np.zeros((n, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        for p in range(len(prim_type)):
            ol = (o - prim_center[p]) @ prim_R[p]
            dl = d @ prim_R[p]
            s = prim_size[p]
            cand_t: list[np.ndarray] = []
            cand_n: list[np.ndarray] = []
            if prim_type[p] == PRIM_QUAD:
                t = -ol[:, 2] / dl[:, 2]
                q = ol + t[:, None] * dl
                ok = (np.abs(dl[:, 2]) >= _PARALLEL_EPS) & (np.abs(q[:, 0]) <= s[0]) & (np.abs(q[:, 1]) <= s[1])
                cand_t.append(np.where(ok, t, np.nan))
                cand_n.append(np.tile([0.0, 0.0, 1.0], (n, 1)))
            elif prim_type[p] == PRIM_BOX:
                for k in range(3):  # each of the 6 faces as a bounded plane
                    for sgn in (-1.0, 1.0):
                        t = (sgn * s[k] - ol[:, k]) / dl[:, k]
                        q = ol + t[:, None] * dl
                        a, b = (k + 1) % 3, (k + 2) % 3
                        tol = 1e-9
                        ok = (np.abs(q[:, a]) <= s[a] + tol) & (np.abs(q[:, b]) <= s[b] + tol)
                        ok &= np.abs(dl[:, k]) >= _PARALLEL_EPS
                        cand_t.append(np.where(ok, t, np.nan))
                        nrm = np.zeros((n, 3))
                        nrm[:, k] = sgn
                        cand_n.append(nrm)
            elif prim_type[p] == PRIM_CYLINDER:
                r, h = s[0], s[2]
                a = dl[:, 0] ** 2 + dl[:, 1] ** 2
                b = ol[:, 0] * dl[:, 0] + ol[:, 1] * dl[:, 1]
                c = ol[:, 0] ** 2 + ol[:, 1] ** 2 - r * r
                disc = b * b - a * c
                for sgn in (-1.0, 1.0):
                    t = (-b + sgn * np.sqrt(disc)) / a
                    q = ol + t[:, None] * dl
                    ok = (disc >= 0) & (a > _PARALLEL_EPS) & (np.abs(q[:, 2]) <= h)
                    cand_t.append(np.where(ok, t, np.nan))
                    cand_n.append(np.column_stack([q[:, 0] / r, q[:, 1] / r, np.zeros(n)]))
                for sgn in (-1.0, 1.0):
                    t = (sgn * h - ol[:, 2]) / dl[:, 2]
                    q = ol + t[:, None] * dl
                    ok = (np.abs(dl[:, 2]) > _PARALLEL_EPS) & (q[:, 0] ** 2 + q[:, 1] ** 2 <= r * r)
                    cand_t.append(np.where(ok, t, np.nan))
                    cand_n.append(np.tile([0.0, 0.0, sgn], (n, 1)))
            else:
                r = s[0]
                a = np.sum(dl * dl, axis=1)
                b = np.sum(ol * dl, axis=1)
                c = np.sum(ol * ol, axis=1) - r * r
                disc = b * b - a * c
                for sgn in (-1.0, 1.0):
                    t = (-b + sgn * np.sqrt(disc)) / a
                    q = ol + t[:, None] * dl
                    cand_t.append(np.where(disc >= 0, t, np.nan))
                    cand_n.append(q / r)
            for t, nl in zip(cand_t, cand_n, strict=True):
                better = np.isfinite(t) & (t > t_min) & (t < best_t)
                best_t = np.where(better, t, best_t)
                best_id = np.where(better, np.int32(p), best_id)
                best_nl = np.where(better[:, None], nl @ prim_R[p].T, best_nl)
    flip = np.sum(best_nl * d, axis=1) > 0
    best_nl[flip] *= -1.0
    return best_t, best_id, best_nl
