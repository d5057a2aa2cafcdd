"""Point-based fusion kernels: association, merge, addition, removal rules.

Determinism: association only reads the map; each map surfel projects into exactly one input pixel
(:func:`bucket_by_pixel`), so it is the candidate of at most one input pixel and the merge writes never
conflict (rows run in parallel, results do not depend on the schedule). New surfels are appended in
raster order by a serial kernel. Each kernel has a numpy reference ``<name>_ref``.

Association status per input pixel (``assoc`` int32 ``(H, W)``): ``>= 0`` the surfel row to merge into,
``ASSOC_INVALID`` no usable measurement, ``ASSOC_COVERED`` no candidate in the pixel's own bucket but a
matching surfel in a neighbouring pixel's bucket (neither merged nor added), ``ASSOC_NEW`` add a surfel.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from surfelslam.kernels.render import candidates_in_camera_ref
from surfelslam.kernels.threads import dual_njit

ASSOC_INVALID = -1
ASSOC_COVERED = -2
ASSOC_NEW = -3


@njit(cache=True, nogil=True)
def _match(i, qx, qy, qz, mx, my, mz, pos, nrm, dist2, cos_angle):
    """Squared distance of surfel ``i`` to the measurement if it passes both tests, else -1."""
    dx = pos[i, 0] - qx
    dy = pos[i, 1] - qy
    dz = pos[i, 2] - qz
    d2 = dx * dx + dy * dy + dz * dz
    if d2 >= dist2:
        return -1.0
    if nrm[i, 0] * mx + nrm[i, 1] * my + nrm[i, 2] * mz <= cos_angle:
        return -1.0
    return d2


@njit(cache=True, nogil=True)
def bucket_by_pixel(cand, m, pos, nrm, R, t, fx, fy, cx, cy, H, W, near, far, cull_back, pix_scratch,
                    start_out, order_out):
    """Group candidate surfels by the input pixel their centre projects to (stable counting sort).

    Args:
        cand: int32 ``(>= m,)`` surfel rows (culled candidates); pos, nrm: float32 ``(N, 3)`` world frame.
        R, t: float64 world-to-camera rotation ``(3, 3)`` and translation ``(3,)``.
        near, far: depth range (metres); cull_back: drop surfels whose normal faces away from the camera.
        pix_scratch: int32 ``(>= m,)`` scratch; start_out: int32 ``(H*W + 1,)``; order_out: int32 ``(>= m,)``.

    Afterwards the surfels projecting into pixel ``p = v * W + u`` are
    ``order_out[start_out[p]:start_out[p + 1]]`` (candidate order). This is the index map of Keller et al.
    with unlimited supersampling: every surfel lands in exactly one pixel, so each is the candidate of at
    most one input pixel. Returns the number of bucketed surfels.
    """
    npix = H * W
    for p in range(npix + 1):
        start_out[p] = 0
    for k in range(m):
        i = cand[k]
        px = R[0, 0] * pos[i, 0] + R[0, 1] * pos[i, 1] + R[0, 2] * pos[i, 2] + t[0]
        py = R[1, 0] * pos[i, 0] + R[1, 1] * pos[i, 1] + R[1, 2] * pos[i, 2] + t[1]
        pz = R[2, 0] * pos[i, 0] + R[2, 1] * pos[i, 1] + R[2, 2] * pos[i, 2] + t[2]
        pix_scratch[k] = -1
        if pz < near or pz > far:
            continue
        if cull_back:
            nx = R[0, 0] * nrm[i, 0] + R[0, 1] * nrm[i, 1] + R[0, 2] * nrm[i, 2]
            ny = R[1, 0] * nrm[i, 0] + R[1, 1] * nrm[i, 1] + R[1, 2] * nrm[i, 2]
            nz = R[2, 0] * nrm[i, 0] + R[2, 1] * nrm[i, 1] + R[2, 2] * nrm[i, 2]
            if nx * px + ny * py + nz * pz >= 0.0:
                continue
        u = int(math.floor(fx * px / pz + cx + 0.5))
        v = int(math.floor(fy * py / pz + cy + 0.5))
        if u < 0 or v < 0 or u >= W or v >= H:
            continue
        p = v * W + u
        pix_scratch[k] = p
        start_out[p + 1] += 1
    for p in range(npix):
        start_out[p + 1] += start_out[p]
    n = start_out[npix]
    # scatter with a cursor: start_out[p] is advanced, then shifted back
    for k in range(m):
        p = pix_scratch[k]
        if p >= 0:
            order_out[start_out[p]] = cand[k]
            start_out[p] += 1
    for p in range(npix, 0, -1):
        start_out[p] = start_out[p - 1]
    start_out[0] = 0
    return n


def bucket_by_pixel_ref(cand, m, pos, nrm, R, t, fx, fy, cx, cy, H, W, near, far, cull_back):
    """Numpy reference of :func:`bucket_by_pixel`; returns ``(start (H*W+1,), order (n,))``."""
    idx, px, py, pz, ok = candidates_in_camera_ref(cand, m, pos, nrm, R, t, near, far, cull_back)
    pzs = np.where(ok, pz, 1.0)
    u = np.floor(fx * px / pzs + cx + 0.5).astype(np.int64)
    v = np.floor(fy * py / pzs + cy + 0.5).astype(np.int64)
    ok &= (u >= 0) & (v >= 0) & (u < W) & (v < H)
    k = np.flatnonzero(ok)
    pix = v[k] * W + u[k]
    srt = np.argsort(pix, kind="stable")
    counts = np.bincount(pix, minlength=H * W)
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    return start, idx[k[srt]].astype(np.int32)


@dual_njit()
def associate(vertex, normal, bstart, border, pos, nrm, conf, R, t, dist_m, cos_angle, min_depth, max_depth,
              cover_radius_px, assoc_out):
    """Pick, for every input pixel, the map surfel it updates.

    Args:
        vertex, normal: float32 ``(H, W, 3)`` camera-frame measurement (normal 0 or depth 0 = invalid).
        bstart, border: the surfels projecting into each pixel at the frame's pose
            (see :func:`bucket_by_pixel`).
        pos, nrm, conf: map arrays (world frame).
        R, t: float64 camera-to-world rotation ``(3, 3)`` and translation ``(3,)``.
        dist_m: max |p - q| (metres); cos_angle: min cosine between normals.
        min_depth, max_depth: measurements outside this depth range are not fused.
        cover_radius_px: neighbour pixels searched when the pixel's own surfels have no match (0 = none).
        assoc_out: int32 ``(H, W)`` status (see module doc).

    Among the pixel's surfels that pass |p - q| < dist_m and the normal test, the one with the highest
    confidence wins; ties: smaller distance, then smaller row.
    """
    H, W = assoc_out.shape
    dist2 = dist_m * dist_m
    for v in prange(H):
        for u in range(W):
            z = vertex[v, u, 2]
            n0 = normal[v, u, 0]
            n1 = normal[v, u, 1]
            n2 = normal[v, u, 2]
            if not (z >= min_depth and z <= max_depth) or (n0 * n0 + n1 * n1 + n2 * n2) < 0.25:
                assoc_out[v, u] = ASSOC_INVALID
                continue
            x = vertex[v, u, 0]
            y = vertex[v, u, 1]
            qx = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
            qy = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
            qz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
            mx = R[0, 0] * n0 + R[0, 1] * n1 + R[0, 2] * n2
            my = R[1, 0] * n0 + R[1, 1] * n1 + R[1, 2] * n2
            mz = R[2, 0] * n0 + R[2, 1] * n1 + R[2, 2] * n2
            best = -1
            best_c = -1.0
            best_d = 0.0
            p = v * W + u
            for k in range(bstart[p], bstart[p + 1]):
                i = border[k]
                d2 = _match(i, qx, qy, qz, mx, my, mz, pos, nrm, dist2, cos_angle)
                if d2 < 0:
                    continue
                c = conf[i]
                if best < 0 or c > best_c or (c == best_c and (d2 < best_d or (d2 == best_d and i < best))):
                    best = i
                    best_c = c
                    best_d = d2
            if best >= 0:
                assoc_out[v, u] = best
                continue
            status = ASSOC_NEW
            r = cover_radius_px
            for vv in range(max(v - r, 0), min(v + r + 1, H)):
                if status == ASSOC_COVERED:
                    break
                for uu in range(max(u - r, 0), min(u + r + 1, W)):
                    if vv == v and uu == u:
                        continue
                    pp = vv * W + uu
                    for k in range(bstart[pp], bstart[pp + 1]):
                        if _match(border[k], qx, qy, qz, mx, my, mz, pos, nrm, dist2, cos_angle) >= 0:
                            status = ASSOC_COVERED
                            break
                    if status == ASSOC_COVERED:
                        break
            assoc_out[v, u] = status


def associate_ref(vertex, normal, bstart, border, pos, nrm, conf, R, t, dist_m, cos_angle, min_depth, max_depth,
                  cover_radius_px):
    """Numpy reference of :func:`associate`; returns ``assoc`` int32 ``(H, W)``."""
    H, W = vertex.shape[:2]
    z = vertex[..., 2].astype(np.float64).ravel()
    n = normal.astype(np.float64).reshape(-1, 3)
    valid = (z >= min_depth) & (z <= max_depth) & ((n**2).sum(-1) >= 0.25)
    q = vertex.reshape(-1, 3).astype(np.float64) @ R.T + t
    mn = n @ R.T
    counts = np.diff(bstart)
    pair_pix = np.repeat(np.arange(H * W), counts)  # (pixel, surfel) pairs of the buckets
    pair_row = border[: bstart[-1]].astype(np.int64)

    def passes(target_pix, rows):
        d2 = ((pos[rows].astype(np.float64) - q[target_pix]) ** 2).sum(-1)
        dot = (nrm[rows].astype(np.float64) * mn[target_pix]).sum(-1)
        return (d2 < dist_m**2) & (dot > cos_angle), d2

    ok, d2 = passes(pair_pix, pair_row)
    sel = np.flatnonzero(ok)
    srt = np.lexsort((pair_row[sel], d2[sel], -conf[pair_row[sel]].astype(np.float64), pair_pix[sel]))
    sp = pair_pix[sel][srt]
    first = np.ones(len(sp), bool)
    first[1:] = sp[1:] != sp[:-1]
    assoc = np.full(H * W, ASSOC_NEW, np.int64)
    assoc[sp[first]] = pair_row[sel][srt][first]
    has = np.zeros(H * W, bool)
    has[sp] = True
    covered = np.zeros(H * W, bool)
    r = cover_radius_px
    pv, pu = np.divmod(pair_pix, W)
    for dv in range(-r, r + 1):
        for du in range(-r, r + 1):
            if dv == 0 and du == 0:
                continue
            tv, tu = pv - dv, pu - du  # the pixel that sees this bucket as its neighbour (dv, du)
            inside = (tv >= 0) & (tv < H) & (tu >= 0) & (tu < W)
            tp = (tv * W + tu)[inside]
            nb_ok, _ = passes(tp, pair_row[inside])
            covered[tp[nb_ok]] = True
    assoc = np.where(~has & covered, ASSOC_COVERED, assoc)
    return np.where(valid, assoc, ASSOC_INVALID).astype(np.int32).reshape(H, W)


@njit(cache=True, nogil=True)
def _is_duplicate(i, b, pos, nrm, rad, dist2, cos_angle, front_m):
    """Whether surfel ``i`` duplicates ``b``: :func:`flag_duplicates`' normal, near-copy and layer-in-front tests (the
    caller tests the confidence)."""
    if nrm[i, 0] * nrm[b, 0] + nrm[i, 1] * nrm[b, 1] + nrm[i, 2] * nrm[b, 2] <= cos_angle:
        return False
    dx = pos[i, 0] - pos[b, 0]
    dy = pos[i, 1] - pos[b, 1]
    dz = pos[i, 2] - pos[b, 2]
    d2 = dx * dx + dy * dy + dz * dz
    if d2 < dist2:
        return True
    off = dx * nrm[b, 0] + dy * nrm[b, 1] + dz * nrm[b, 2]  # towards the camera: b's normal faces it
    reach = np.float64(rad[i]) + np.float64(rad[b])
    return 0.0 < off < front_m and d2 - off * off < reach * reach


@njit(cache=True, nogil=True)
def flag_duplicates(assoc, bstart, border, pos, nrm, rad, conf, dist_m, cos_angle, front_m, dead):
    """Flag as dead the duplicates of each pixel's chosen surfel (a fused map stays at one surfel per pixel).

    For every pixel with a chosen surfel ``b = assoc[v, u] >= 0``, each other surfel ``i`` of the pixel's
    bucket (see :func:`bucket_by_pixel`) with ``n_i . n_b > cos_angle``, ``conf[i] <= conf[b]`` and either
    ``|p_i - p_b| < dist_m`` (a near-copy) or an offset along ``n_b`` towards the camera in ``(0, front_m)`` with a
    sideways distance below ``rad[i] + rad[b]`` (a layer in front of the measured surface, over it: the pixel's ray
    went through it) describes the same piece of surface: it is flagged (``dead[i] = 1``). Each surfel lies in one
    bucket only, so the result does not depend on the pixel order. Returns the number flagged.
    """
    H, W = assoc.shape
    dist2 = dist_m * dist_m
    k = 0
    for v in range(H):
        for u in range(W):
            b = assoc[v, u]
            if b < 0:
                continue
            p = v * W + u
            if bstart[p + 1] - bstart[p] < 2:
                continue
            for j in range(bstart[p], bstart[p + 1]):
                i = border[j]
                if i == b or dead[i] != 0 or conf[i] > conf[b]:
                    continue
                if _is_duplicate(i, b, pos, nrm, rad, dist2, cos_angle, front_m):
                    dead[i] = 1
                    k += 1
    return k


def flag_duplicates_ref(assoc, bstart, border, pos, nrm, rad, conf, dist_m, cos_angle, front_m, dead):
    """Numpy reference of :func:`flag_duplicates`; returns the rows it would flag (sorted)."""
    H, W = assoc.shape
    counts = np.diff(bstart)
    pair_pix = np.repeat(np.arange(H * W), counts)
    rows = border[: bstart[-1]].astype(np.int64)
    b = assoc.ravel()[pair_pix].astype(np.int64)
    ok = (b >= 0) & (rows != b) & (dead[rows] == 0)
    bb = np.where(ok, b, 0)
    ok &= conf[rows] <= conf[bb]
    d = pos[rows].astype(np.float64) - pos[bb].astype(np.float64)
    d2 = (d**2).sum(-1)
    nb = nrm[bb].astype(np.float64)
    off = (d * nb).sum(-1)
    dot = (nrm[rows].astype(np.float64) * nb).sum(-1)
    reach = rad[rows].astype(np.float64) + rad[bb].astype(np.float64)
    near = (d2 < dist_m**2) | ((off > 0) & (off < front_m) & (d2 - off * off < reach**2))
    ok &= near & (dot > cos_angle)
    return np.sort(rows[ok])


@njit(cache=True, nogil=True)
def _pixel_radius(x, y, z, n0, n1, n2, radius_per_depth, min_cos, max_radius):
    """Surfel radius (metres) for a measurement: ``radius_per_depth * z / max(|cos|, min_cos)``, clamped."""
    norm = math.sqrt(x * x + y * y + z * z)
    c = abs(n0 * x + n1 * y + n2 * z) / norm
    r = radius_per_depth * z / max(c, min_cos)
    return min(r, max_radius)


@dual_njit()
def merge(assoc, vertex, normal, rgb, weight, R, t, frame, max_radius_ratio, radius_per_depth, min_cos,
          max_radius, pos, nrm, col, conf, rad, last_seen, hits):
    """Confidence-weighted update of the associated surfels (in place; rows of ``assoc >= 0``).

    For pixel measurement ``q`` (world), normal ``m``, colour ``c`` and weight ``w`` merged into a surfel of
    confidence ``C``: if the measurement's radius ``r_q <= max_radius_ratio * r``, position, normal
    (renormalised), colour and radius become ``(C x + w x_q) / (C + w)``; always ``C += w``,
    ``last_seen = frame``, ``hits += 1``. ``weight`` float32 ``(H, W)``; ``radius_per_depth`` metres per
    metre of depth (new-radius rule, see :func:`_pixel_radius`).
    """
    H, W = assoc.shape
    for v in prange(H):
        for u in range(W):
            i = assoc[v, u]
            if i < 0:
                continue
            x = vertex[v, u, 0]
            y = vertex[v, u, 1]
            z = vertex[v, u, 2]
            n0 = normal[v, u, 0]
            n1 = normal[v, u, 1]
            n2 = normal[v, u, 2]
            w = np.float64(weight[v, u])
            C = np.float64(conf[i])
            rq = _pixel_radius(x, y, z, n0, n1, n2, radius_per_depth, min_cos, max_radius)
            if rq <= max_radius_ratio * rad[i]:
                a = C / (C + w)
                b = w / (C + w)
                for k in range(3):
                    qk = R[k, 0] * x + R[k, 1] * y + R[k, 2] * z + t[k]
                    pos[i, k] = a * pos[i, k] + b * qk
                mx = a * nrm[i, 0] + b * (R[0, 0] * n0 + R[0, 1] * n1 + R[0, 2] * n2)
                my = a * nrm[i, 1] + b * (R[1, 0] * n0 + R[1, 1] * n1 + R[1, 2] * n2)
                mz = a * nrm[i, 2] + b * (R[2, 0] * n0 + R[2, 1] * n1 + R[2, 2] * n2)
                s = math.sqrt(mx * mx + my * my + mz * mz)
                if s > 0:
                    nrm[i, 0] = mx / s
                    nrm[i, 1] = my / s
                    nrm[i, 2] = mz / s
                for k in range(3):
                    col[i, k] = a * col[i, k] + b * rgb[v, u, k]
                rad[i] = a * rad[i] + b * rq
            conf[i] = C + w
            last_seen[i] = frame
            hits[i] += 1


def merge_ref(assoc, vertex, normal, rgb, weight, R, t, frame, max_radius_ratio, radius_per_depth, min_cos,
              max_radius, pos, nrm, col, conf, rad, last_seen, hits):
    """Numpy reference of :func:`merge`; returns updated copies ``(pos, nrm, col, conf, rad, last_seen, hits)``."""
    pos, nrm, col, conf, rad, last_seen, hits = (a.copy() for a in (pos, nrm, col, conf, rad, last_seen, hits))
    vv, uu = np.nonzero(assoc >= 0)
    i = assoc[vv, uu]
    p = vertex[vv, uu].astype(np.float64)
    n = normal[vv, uu].astype(np.float64)
    w = weight[vv, uu].astype(np.float64)
    C = conf[i].astype(np.float64)
    cosang = np.abs((n * p).sum(1)) / np.linalg.norm(p, axis=1)
    rq = np.minimum(radius_per_depth * p[:, 2] / np.maximum(cosang, min_cos), max_radius)
    full = rq <= max_radius_ratio * rad[i]
    a = (C / (C + w))[:, None]
    b = (w / (C + w))[:, None]
    f = full
    fi = i[f]
    pos[fi] = a[f] * pos[fi] + b[f] * (p[f] @ R.T + t)
    m = a[f] * nrm[fi] + b[f] * (n[f] @ R.T)
    nrm[fi] = m / np.linalg.norm(m, axis=1, keepdims=True)
    col[fi] = a[f] * col[fi] + b[f] * rgb[vv[f], uu[f]]
    rad[fi] = a[f, 0] * rad[fi] + b[f, 0] * rq[f]
    conf[i] = C + w
    last_seen[i] = frame
    hits[i] += 1
    return pos, nrm, col, conf, rad, last_seen, hits


@njit(cache=True, nogil=True)
def add_new(assoc, vertex, normal, rgb, weight, R, t, frame, radius_per_depth, min_cos, max_radius, start,
            pos, nrm, col, conf, rad, first_seen, last_seen, hits, dead):
    """Append a surfel (world frame) for every ``assoc == ASSOC_NEW`` pixel, in raster order, at rows
    ``start, start+1, ...`` (capacity must already suffice). Returns the number added.

    New surfel: position ``R q + t``, normal ``R m``, colour of the pixel, confidence = the pixel weight,
    radius from :func:`_pixel_radius`, ``first_seen = last_seen = frame``, ``hits = 1``.
    """
    H, W = assoc.shape
    j = start
    for v in range(H):
        for u in range(W):
            if assoc[v, u] != ASSOC_NEW:
                continue
            x = vertex[v, u, 0]
            y = vertex[v, u, 1]
            z = vertex[v, u, 2]
            n0 = normal[v, u, 0]
            n1 = normal[v, u, 1]
            n2 = normal[v, u, 2]
            s = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            for k in range(3):
                pos[j, k] = R[k, 0] * x + R[k, 1] * y + R[k, 2] * z + t[k]
                nrm[j, k] = (R[k, 0] * n0 + R[k, 1] * n1 + R[k, 2] * n2) / s
                col[j, k] = rgb[v, u, k]
            conf[j] = weight[v, u]
            rad[j] = _pixel_radius(x, y, z, n0 / s, n1 / s, n2 / s, radius_per_depth, min_cos, max_radius)
            first_seen[j] = frame
            last_seen[j] = frame
            hits[j] = 1
            dead[j] = 0
            j += 1
    return j - start


def add_new_ref(assoc, vertex, normal, rgb, weight, R, t, radius_per_depth, min_cos, max_radius):
    """Numpy reference of :func:`add_new`: ``(pos, nrm, col, conf, rad)`` of the new surfels, raster order."""
    vv, uu = np.nonzero(assoc == ASSOC_NEW)
    p = vertex[vv, uu].astype(np.float64)
    n = normal[vv, uu].astype(np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    cosang = np.abs((n * p).sum(1)) / np.linalg.norm(p, axis=1)
    rad = np.minimum(radius_per_depth * p[:, 2] / np.maximum(cosang, min_cos), max_radius)
    return p @ R.T + t, n @ R.T, rgb[vv, uu].astype(np.float32), weight[vv, uu], rad


@njit(cache=True, nogil=True)
def dormant_scan(first_seen, hits, dead, cursor, size, frame, max_age_frames, min_hits):
    """The reference assignment's dormant-surfel rule, incremental: rows from ``cursor`` on whose age
    ``frame - first_seen`` exceeds ``max_age_frames`` are checked once; those with ``hits < min_hits`` are flagged
    dead.
    Stops at the first row that is still too young (rows are in ``first_seen`` order).

    Returns ``(new_cursor, n_flagged)``.
    """
    i = cursor
    k = 0
    while i < size and frame - first_seen[i] > max_age_frames:
        if dead[i] == 0 and hits[i] < min_hits:
            dead[i] = 1
            k += 1
        i += 1
    return i, k


def dormant_scan_ref(first_seen, hits, dead, cursor, size, frame, max_age_frames, min_hits):
    """Numpy reference of :func:`dormant_scan`; returns ``(new_cursor, flagged_rows)``."""
    young = np.flatnonzero(frame - first_seen[cursor:size] <= max_age_frames)
    stop = cursor + (young[0] if len(young) else size - cursor)
    rows = np.arange(cursor, stop)
    flag = rows[(dead[rows] == 0) & (hits[rows] < min_hits)]
    return stop, flag


@njit(cache=True, nogil=True)
def stale_unstable(cand, m, conf, last_seen, dead, frame, max_age_frames, min_conf):
    """Keller's removal among the surfels in view: confidence below ``min_conf`` and not updated for more
    than ``max_age_frames`` frames -> flagged dead. Returns the number flagged."""
    k = 0
    for j in range(m):
        i = cand[j]
        if dead[i] == 0 and conf[i] < min_conf and frame - last_seen[i] > max_age_frames:
            dead[i] = 1
            k += 1
    return k


def stale_unstable_ref(cand, m, conf, last_seen, dead, frame, max_age_frames, min_conf):
    """Numpy reference of :func:`stale_unstable`; returns the flagged rows."""
    c = cand[:m]
    return c[(dead[c] == 0) & (conf[c] < min_conf) & (frame - last_seen[c] > max_age_frames)]
