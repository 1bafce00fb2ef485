"""The numba kernel of `ms_drake.station.labels.DepthLabeler` (private).

The first call compiles it (~2 s); compiled code is cached next to this file where a cache
directory is writable (ms_drake.jit.njit_cached).
"""

from __future__ import annotations

import math

import numpy as np

from ms_drake.jit import njit_cached

BOX, CYLINDER, SPHERE = 0, 1, 2


@njit_cached
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


@njit_cached
def _row64(M, i, r, x, y, z):
    """Row r of M[i] (float32) applied to (x, y, z, 1) in float64."""
    return (np.float64(M[i, r, 0]) * x + np.float64(M[i, r, 1]) * y + np.float64(M[i, r, 2]) * z
            + np.float64(M[i, r, 3]))


@njit_cached
def label_rows(depth, rx, ry, label, r0, r1, v0, v1, u0, u1, seen, rects, M, kind, half, r2, size, eps, labs,
               default, empty):
    """Write rows [r0, r1) of `label` (int16, H x W) from `depth` (float32, H x W, metres).

    Pixels without depth (inf, Drake's kTooFar) take `empty`; other pixels take the label of the
    primitive that claims them, else `default`. A primitive i of `seen` (in that order) claims
    pixel (v, u) inside its rectangle rects[i] = [v0, v1, u0, u1) when the de-projected point
    (rx[u] z, ry[v] z, z), moved into its frame by M[i] (float32 3 x 4, X_GC), lies in its
    claim region, half extents half[i] = size[i] + eps[i] (float32): box |p_k| <= half_k;
    cylinder x^2 + y^2 <= r2[i] = half_x^2 and |p_k| <= half_k; sphere |p|^2 <= r2[i]. One
    claimer takes the pixel. Of several, the one with the smallest |signed distance| (float64,
    to the true shape `size`) among those within eps wins, the first of equals in `seen` order;
    when none is within eps, the last claimer. (v0, v1, u0, u1) bound the union of the
    rectangles of `seen`. The claim test is float32 arithmetic as in the OpenCV reference
    labeller of tests/test_depth_labels.py (cv2.transform, cv2.inRange), and 8 pixels per AVX2
    instruction.

    Each row is visited primitive by primitive over the primitive's columns: a branch-free
    (vectorised) claim test into a row mask, then branch-free bookkeeping (claim count, first
    claimer, the claimer's label written); pixels claimed before then get the resolution of
    their claims so far, so after the last claimer the label is final. Distances are computed
    only for pixels with a second claimer.

    Returns True when a pixel of these rows has depth <= 0 (kTooClose), where the caller
    must render instead.
    """
    W = depth.shape[1]
    K = seen.shape[0]
    count = np.zeros(W, np.int32)  # claims of each pixel of the current row
    first = np.zeros(W, np.int32)  # its first claimer
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
            hx, hy, hz, hx2 = half[i, 0], half[i, 1], half[i, 2], r2[i]
            li = labs[i]
            i32 = np.int32(i)
            a, b = rects[i, 2], rects[i, 3]
            # 1) which columns the primitive claims: a branch-free loop (SIMD) into `inside`
            n = b - a
            dseg, rseg, iseg = drow[a:b], rx[a:b], inside[a:b]
            if ki == BOX:
                for j in range(n):  # from 0: no negative-index wrap-around test, so LLVM vectorizes
                    z = dseg[j]
                    x, y = rseg[j] * z, yv * z
                    px = m00 * x + m01 * y + m02 * z + m03
                    py = m10 * x + m11 * y + m12 * z + m13
                    pz = m20 * x + m21 * y + m22 * z + m23
                    iseg[j] = (abs(px) <= hx) & (abs(py) <= hy) & (abs(pz) <= hz) & (z > 0.0) & (z < np.inf)
            elif ki == CYLINDER:
                for j in range(n):  # from 0: no negative-index wrap-around test, so LLVM vectorizes
                    z = dseg[j]
                    x, y = rseg[j] * z, yv * z
                    px = m00 * x + m01 * y + m02 * z + m03
                    py = m10 * x + m11 * y + m12 * z + m13
                    pz = m20 * x + m21 * y + m22 * z + m23
                    iseg[j] = ((px * px + py * py <= hx2) & (abs(px) <= hx) & (abs(py) <= hy) & (abs(pz) <= hz)
                               & (z > 0.0) & (z < np.inf))
            else:
                for j in range(n):  # from 0: no negative-index wrap-around test, so LLVM vectorizes
                    z = dseg[j]
                    x, y = rseg[j] * z, yv * z
                    px = m00 * x + m01 * y + m02 * z + m03
                    py = m10 * x + m11 * y + m12 * z + m13
                    pz = m20 * x + m21 * y + m22 * z + m23
                    iseg[j] = (px * px + py * py + pz * pz <= hx2) & (z > 0.0) & (z < np.inf)
            # 2) the claims, branch-free: count them, note the first claimer, the label of the
            # last claimer; pixels claimed before are then resolved one by one
            cseg, fseg, lseg = count[a:b], first[a:b], lrow[a:b]
            crowded = False
            for j in range(n):
                ins = iseg[j]
                c = cseg[j]
                crowded |= ins & (c > 0)
                cseg[j] = c + np.int32(ins)
                fseg[j] = i32 if ins & (c == 0) else fseg[j]
                lseg[j] = li if ins else lseg[j]
            if not crowded:
                continue
            for u in range(a, b):
                if not inside[u] or count[u] < 2:
                    continue
                z = drow[u]
                x, y, zd = np.float64(rx[u] * z), np.float64(yv * z), np.float64(z)
                if count[u] == 2:  # a second claimer: the first one's distance too
                    f = np.int64(first[u])
                    d = _abs_signed_distance(kind[f], size[f, 0], size[f, 1], size[f, 2], _row64(M, f, 0, x, y, zd),
                                             _row64(M, f, 1, x, y, zd), _row64(M, f, 2, x, y, zd))
                    best[u] = d if d <= eps[f] else np.inf
                    best_lab[u] = labs[f]
                d = _abs_signed_distance(ki, size[i, 0], size[i, 1], size[i, 2], _row64(M, i, 0, x, y, zd),
                                         _row64(M, i, 1, x, y, zd), _row64(M, i, 2, x, y, zd))
                if d <= eps[i] and d < best[u]:
                    best[u] = d
                    best_lab[u] = li
                lrow[u] = best_lab[u] if best[u] < np.inf else li
    return too_close


@njit_cached
def prepare(X_CW, X_WG, corners, fx, fy, cx, cy, height, width, z_near, z_far):
    """Per image: M (N x 3 x 4, float32), the rows of X_GC = (X_CW X_WG)^-1, and the pixel
    rectangles rects (N x 4, [v0, v1, u0, u1)) that can see each primitive: the bounds of its
    8 `corners` (N x 8 x 3, frame G) projected with the +0.5 pixel convention; an empty
    rectangle when it is out of view or wholly before z_near or beyond z_far, the whole image
    when it straddles the camera plane."""
    N = X_WG.shape[0]
    M = np.empty((N, 3, 4), np.float32)
    rects = np.zeros((N, 4), np.int64)
    X = np.empty((4, 4))
    for n in range(N):
        for r in range(3):
            for c in range(4):
                X[r, c] = (X_CW[r, 0] * X_WG[n, 0, c] + X_CW[r, 1] * X_WG[n, 1, c] + X_CW[r, 2] * X_WG[n, 2, c]
                           + X_CW[r, 3] * X_WG[n, 3, c])
        for r in range(3):  # X_GC = [R^T, -R^T p]
            for c in range(3):
                M[n, r, c] = X[c, r]
            M[n, r, 3] = -(X[0, r] * X[0, 3] + X[1, r] * X[1, 3] + X[2, r] * X[2, 3])
        umin = vmin = np.inf
        umax = vmax = -np.inf
        behind = False
        near = far = True
        for k in range(8):
            q = corners[n, k]
            x = X[0, 0] * q[0] + X[0, 1] * q[1] + X[0, 2] * q[2] + X[0, 3]
            y = X[1, 0] * q[0] + X[1, 1] * q[1] + X[1, 2] * q[2] + X[1, 3]
            z = X[2, 0] * q[0] + X[2, 1] * q[1] + X[2, 2] * q[2] + X[2, 3]
            behind |= z <= 1e-6
            near &= z <= z_near
            far &= z > z_far
            zs = z if z > 1e-6 else 1.0
            u, v = fx * x / zs + cx - 0.5, fy * y / zs + cy - 0.5
            umin, umax, vmin, vmax = min(umin, u), max(umax, u), min(vmin, v), max(vmax, v)
        if near or far:
            continue
        if behind:
            rects[n, 1], rects[n, 3] = height, width
            continue
        rects[n, 0] = int(min(max(math.floor(vmin), 0.0), height))
        rects[n, 1] = int(min(max(math.ceil(vmax) + 1, 0.0), height))
        rects[n, 2] = int(min(max(math.floor(umin), 0.0), width))
        rects[n, 3] = int(min(max(math.ceil(umax) + 1, 0.0), width))
    return M, rects
