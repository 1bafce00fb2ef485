"""The numba kernel of `ms_drake.perception.masks.DepthLabeler` (private).

Imported on the first `DepthLabeler.label` call, not with ms_drake.perception (importing numba
costs ~0.3 s and the first call compiles, ~2 s). Compiled code is cached next to this file
(`__pycache__`, numba's cache=True); where no cache directory is writable (numba tries
NUMBA_CACHE_DIR, this package's __pycache__ and ~/.cache, and raises RuntimeError at decoration
when none is writable) the kernel is compiled without a cache instead, in every process.
"""

from __future__ import annotations

import math

import numba
import numpy as np

BOX, CYLINDER, SPHERE = 0, 1, 2


def _jit(f):
    try:
        return numba.njit(cache=True, nogil=True, fastmath=False)(f)
    except RuntimeError:  # "cannot cache function ...: no locator available": no writable cache dir
        return numba.njit(cache=False, nogil=True, fastmath=False)(f)


@_jit
def _abs_signed_distance(kind, sx, sy, sz, px, py, pz):
    """|signed distance| of the point p (primitive frame) to a box (half extents s), a
    cylinder (radius sx, half length sz) or a sphere (radius sx)."""
    if kind == BOX:
        qx, qy, qz = abs(px) - sx, abs(py) - sy, abs(pz) - sz
        ox, oy, oz = max(qx, 0.0), max(qy, 0.0), max(qz, 0.0)
        return abs(math.sqrt(ox * ox + oy * oy + oz * oz) + min(max(qx, max(qy, qz)), 0.0))
    if kind == CYLINDER:
        rr = math.hypot(px, py) - sx
        qz = abs(pz) - sz
        return abs(math.hypot(max(rr, 0.0), max(qz, 0.0)) + min(max(rr, qz), 0.0))
    return abs(math.sqrt(px * px + py * py + pz * pz) - sx)


@_jit
def label_rows(depth, rx, ry, label, r0, r1, v0, v1, u0, u1, seen, rects, M, kind, half, size, eps, labs,
               default, empty):
    """Write rows [r0, r1) of `label` (int16, H x W) from `depth` (float32, H x W, metres).

    Pixels without depth (inf, Drake's kTooFar) take `empty`; other pixels take the label of the
    primitive that claims them, else `default`. A primitive i of `seen` (in that order) claims
    pixel (v, u) inside its rectangle rects[i] = [v0, v1, u0, u1) when the de-projected point
    (rx[u] z, ry[v] z, z), moved into its frame by M[i] (3 x 4, X_GC), lies in its claim region
    (half extents half[i] = size[i] + eps[i]: box |p_k| <= half_k; cylinder x^2 + y^2 <= half_x^2
    and |z| <= half_z; sphere |p|^2 <= half_x^2). One claimer takes the pixel. Of several, the
    one with the smallest |signed distance| (to the true shape `size`) among those within eps
    wins, the first of equals in `seen` order; when none is within eps, the last claimer.
    (v0, v1, u0, u1) bound the union of the rectangles of `seen`.

    Each row is visited primitive by primitive over the primitive's columns (the transform
    stays in registers); the label written at each claim is the resolution of the claims so
    far, so after the last claimer it is final. Distances are computed only for pixels with a
    second claimer.

    Returns True when a pixel of these rows has depth <= 0 (kTooClose), where the caller
    must render instead.
    """
    W = depth.shape[1]
    K = seen.shape[0]
    count = np.zeros(W, np.int32)  # claims of each pixel of the current row
    first = np.zeros(W, np.int64)  # its first claimer
    best = np.empty(W, np.float64)  # smallest |signed distance| within eps so far (inf: none), ...
    best_lab = np.empty(W, np.int16)  # ... and its label (valid where count >= 2)
    inside = np.zeros(W, np.bool_)  # claim test of one primitive along the current row
    too_close = False
    for v in range(r0, r1):
        drow, lrow = depth[v], label[v]
        close = False
        for u in range(W):  # branch-free (SIMD)
            z = drow[u]
            lrow[u] = empty if z == np.inf else default
            close |= z <= 0.0  # kTooClose
        too_close |= close
        if not v0 <= v < v1:
            continue
        count[u0:u1] = 0
        yv = ry[v]
        for k in range(K):
            i = seen[k]
            if not rects[i, 0] <= v < rects[i, 1]:
                continue
            m00, m01, m02, m03 = M[i, 0, 0], M[i, 0, 1], M[i, 0, 2], M[i, 0, 3]
            m10, m11, m12, m13 = M[i, 1, 0], M[i, 1, 1], M[i, 1, 2], M[i, 1, 3]
            m20, m21, m22, m23 = M[i, 2, 0], M[i, 2, 1], M[i, 2, 2], M[i, 2, 3]
            ki = kind[i]
            hx, hy, hz = half[i, 0], half[i, 1], half[i, 2]
            hx2 = hx * hx
            li = labs[i]
            a, b = rects[i, 2], rects[i, 3]
            # 1) which columns the primitive claims: a branch-free loop (SIMD) into `inside`
            n = b - a
            dseg, rseg, iseg = drow[a:b], rx[a:b], inside[a:b]
            if ki == BOX:
                for j in range(n):  # from 0: no negative-index wrap-around test, so LLVM vectorizes
                    z = dseg[j]
                    x, y, zd = np.float64(rseg[j] * z), np.float64(yv * z), np.float64(z)
                    px = m00 * x + m01 * y + m02 * zd + m03
                    py = m10 * x + m11 * y + m12 * zd + m13
                    pz = m20 * x + m21 * y + m22 * zd + m23
                    iseg[j] = (abs(px) <= hx) & (abs(py) <= hy) & (abs(pz) <= hz) & (z > 0.0) & (z < np.inf)
            elif ki == CYLINDER:
                for j in range(n):  # from 0: no negative-index wrap-around test, so LLVM vectorizes
                    z = dseg[j]
                    x, y, zd = np.float64(rseg[j] * z), np.float64(yv * z), np.float64(z)
                    px = m00 * x + m01 * y + m02 * zd + m03
                    py = m10 * x + m11 * y + m12 * zd + m13
                    pz = m20 * x + m21 * y + m22 * zd + m23
                    iseg[j] = (px * px + py * py <= hx2) & (abs(pz) <= hz) & (z > 0.0) & (z < np.inf)
            else:
                for j in range(n):  # from 0: no negative-index wrap-around test, so LLVM vectorizes
                    z = dseg[j]
                    x, y, zd = np.float64(rseg[j] * z), np.float64(yv * z), np.float64(z)
                    px = m00 * x + m01 * y + m02 * zd + m03
                    py = m10 * x + m11 * y + m12 * zd + m13
                    pz = m20 * x + m21 * y + m22 * zd + m23
                    iseg[j] = (px * px + py * py + pz * pz <= hx2) & (z > 0.0) & (z < np.inf)
            # 2) the claims
            for u in range(a, b):
                if not inside[u]:
                    continue
                c = count[u]
                count[u] = c + 1
                if c == 0:
                    first[u] = i
                    label[v, u] = li
                    continue
                z = drow[u]
                x, y, zd = np.float64(rx[u] * z), np.float64(yv * z), np.float64(z)
                px = m00 * x + m01 * y + m02 * zd + m03
                py = m10 * x + m11 * y + m12 * zd + m13
                pz = m20 * x + m21 * y + m22 * zd + m23
                if c == 1:  # a second claimer: the first one's distance too
                    f = first[u]
                    qx = M[f, 0, 0] * x + M[f, 0, 1] * y + M[f, 0, 2] * zd + M[f, 0, 3]
                    qy = M[f, 1, 0] * x + M[f, 1, 1] * y + M[f, 1, 2] * zd + M[f, 1, 3]
                    qz = M[f, 2, 0] * x + M[f, 2, 1] * y + M[f, 2, 2] * zd + M[f, 2, 3]
                    d = _abs_signed_distance(kind[f], size[f, 0], size[f, 1], size[f, 2], qx, qy, qz)
                    best[u] = d if d <= eps[f] else np.inf
                    best_lab[u] = labs[f]
                d = _abs_signed_distance(ki, size[i, 0], size[i, 1], size[i, 2], px, py, pz)
                if d <= eps[i] and d < best[u]:
                    best[u] = d
                    best_lab[u] = li
                label[v, u] = best_lab[u] if best[u] < np.inf else li
    return too_close
