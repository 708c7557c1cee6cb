"""Numba kernels of the runtime synthesis (pure array functions; the Engine class is a thin shell over them).

Shapes: V garment vertices, B bones, N anchors (or pose-model examples), C PCA components, R = 7 regions,
K neighbours per region, Da active pose dofs, I = 4 skin influences. Float arrays named `*_f` follow the engine's
run dtype (float32 by default); pose, distance and weight arithmetic is float64 (tiny arrays, no accuracy to lose).

Skinning convention: for skin weights w_k of bones b_k and transforms T_b = [G_b | t_b] (B, 3, 4), a vertex's blended
transform is A = sum_k w_k G_{b_k} (3, 3) and t = sum_k w_k t_{b_k}, so LBS(x) = A x + t. The rotations G_b depend
on the pose only, not on the body shape (only the translations do), so one A serves every shape at a pose.
LBS from pose theta_s to theta (the paper's LBS_{theta_s -> theta}) is done as "unpose then skin":
x -> A_theta A_{theta_s}^{-1} (x - t_{theta_s}) + t_theta. It equals the paper's per-bone relative transform exactly
for single-bone vertices and at theta = theta_s for all vertices, and makes the shape term linear: a canonical
(unposed) delta per anchor is computed once per shape and only rotated per frame.
"""
from __future__ import annotations

import numba
import numpy as np

from ..body.kinematics import rotvec_to_matrix, skin_vertex

TWO_PI = 2.0 * np.pi


@numba.njit(cache=True, nogil=True)
def prepare_pose(rotvecs, root_translation, max_translation, theta, root):
    """Validate and canonicalise one pose.

    rotvecs (B, 3), root_translation (3,) any float dtype -> theta (B, 3) float64 with every rotation vector mapped to
    the same rotation with angle in [-pi, pi] (axis * angle, so angles near +-pi and multiples of 2 pi wrap), root (3,)
    clamped to +-max_translation. Returns -1 when all is finite, the index of the first bone with a non-finite
    component, or B when the root translation is non-finite. Huge angles stay finite (norm by scaling, then mod 2 pi).
    """
    n_bones = rotvecs.shape[0]
    for j in range(n_bones):
        x, y, z = rotvecs[j, 0], rotvecs[j, 1], rotvecs[j, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            return j
        m = max(abs(x), abs(y), abs(z))
        if m == 0.0:
            theta[j, 0] = 0.0
            theta[j, 1] = 0.0
            theta[j, 2] = 0.0
            continue
        # scale first: squares of huge components overflow, of subnormal ones underflow
        ux, uy, uz = x / m, y / m, z / m
        unit = np.sqrt(ux * ux + uy * uy + uz * uz)
        angle = m * unit
        if angle <= np.pi:
            theta[j, 0] = x
            theta[j, 1] = y
            theta[j, 2] = z
            continue
        wrapped = angle % TWO_PI  # in [0, 2 pi)
        if wrapped > np.pi:
            wrapped -= TWO_PI  # same rotation about the same axis, angle in (-pi, pi]
        scale = wrapped / unit
        theta[j, 0] = ux * scale
        theta[j, 1] = uy * scale
        theta[j, 2] = uz * scale
    for a in range(3):
        value = root_translation[a]
        if not np.isfinite(value):
            return n_bones
        root[a] = min(max(value, -max_translation), max_translation)
    return -1


@numba.njit(cache=True, nogil=True)
def pose_transforms(theta, root, heads_a, heads_b, parents, rotations, positions_a, positions_b,
                    transforms_a, transforms_b):
    """Forward kinematics of one pose on two skeletons (reference shape a, current shape b) sharing rotations.

    theta (B, 3) float64, root (3,), heads_a/heads_b (B, 3) rest joint positions, parents (B,) with parents[j] < j.
    Scratch: rotations (B, 3, 3), positions_a/positions_b (B, 3) float64. Writes transforms_a/transforms_b (B, 3, 4)
    [G_j | p_j - G_j h_j] (same convention as body.kinematics.forward_kinematics), no allocation.
    """
    n_bones = theta.shape[0]
    local = np.empty((3, 3))
    for j in range(n_bones):
        rotvec_to_matrix(theta[j], local)
        p = parents[j]
        if p < 0:
            for a in range(3):
                for b in range(3):
                    rotations[j, a, b] = local[a, b]
                positions_a[j, a] = heads_a[j, a] + root[a]
                positions_b[j, a] = heads_b[j, a] + root[a]
        else:
            for a in range(3):
                for b in range(3):
                    acc = 0.0
                    for k in range(3):
                        acc += rotations[p, a, k] * local[k, b]
                    rotations[j, a, b] = acc
            for a in range(3):
                acc_a = positions_a[p, a]
                acc_b = positions_b[p, a]
                for k in range(3):
                    acc_a += rotations[p, a, k] * (heads_a[j, k] - heads_a[p, k])
                    acc_b += rotations[p, a, k] * (heads_b[j, k] - heads_b[p, k])
                positions_a[j, a] = acc_a
                positions_b[j, a] = acc_b
        for a in range(3):
            offset_a = positions_a[j, a]
            offset_b = positions_b[j, a]
            for k in range(3):
                transforms_a[j, a, k] = rotations[j, a, k]
                transforms_b[j, a, k] = rotations[j, a, k]
                offset_a -= rotations[j, a, k] * heads_a[j, k]
                offset_b -= rotations[j, a, k] * heads_b[j, k]
            transforms_a[j, a, 3] = offset_a
            transforms_b[j, a, 3] = offset_b


@numba.njit(cache=True, nogil=True, fastmath=True)
def region_neighbours(query, poses, dofs, q, eps, power, eta, state, use_state, selected, weights):
    """Sensitivity distances (Eq. 7), decay (Eq. 9), top-K per region and region weights W_g^s (normalised, Eq. 8).

    query (D,) float64 canonical pose (flattened theta); poses (N, Da) the anchors' values of the active dofs
    `dofs` (Da,) int; q (R, Da) float64 Q_{g,m}; eps (R,) the epsilon of W = 1 / (D + eps)^power per region.
    Theta_m is the difference of rotation-vector components wrapped to [-pi, pi].
    state (R, N) float64 holds the previous frame's (decayed) distances; with use_state the distances are blended
    D = eta D' + (1 - eta) D; state is overwritten with the distances used. Writes selected (R, K) int32 anchor ids
    (nearest first) and weights (R, K) float64 summing to 1 per region. The normalised form
    ((D_min + eps) / (D + eps))^power equals W / sum W but cannot underflow or overflow: the nearest gets 1.
    """
    n_anchors, n_active = poses.shape
    n_regions = q.shape[0]
    k_count = selected.shape[1]
    squared = np.empty(n_active)
    for s in range(n_anchors):
        for i in range(n_active):
            d = query[dofs[i]] - poses[s, i]
            d -= TWO_PI * np.floor(d / TWO_PI + 0.5)  # wrap: rotation-vector components are periodic per axis
            squared[i] = d * d
        for g in range(n_regions):
            acc = 0.0
            for i in range(n_active):
                acc += q[g, i] * squared[i]
            if use_state:
                acc = eta * state[g, s] + (1.0 - eta) * acc
            state[g, s] = acc
    for g in range(n_regions):
        # partial insertion sort: the K smallest distances, nearest first (ties keep the lower anchor id)
        count = 0
        for s in range(n_anchors):
            d = state[g, s]
            if count < k_count:
                pos = count
                count += 1
            elif d < state[g, selected[g, k_count - 1]]:
                pos = k_count - 1
            else:
                continue
            while pos > 0 and state[g, selected[g, pos - 1]] > d:
                selected[g, pos] = selected[g, pos - 1]
                pos -= 1
            selected[g, pos] = s
        nearest = state[g, selected[g, 0]] + eps[g]
        total = 0.0
        for k in range(k_count):
            ratio = nearest / (state[g, selected[g, k]] + eps[g])
            w = ratio**power
            weights[g, k] = w
            total += w
        for k in range(k_count):
            weights[g, k] /= total


# Synthesis modes (EngineConfig.taylor)
AUGMENTED, PLAIN, ZEROTH = 0, 1, 2


@numba.njit(cache=True, nogil=True)
def count_non_finite(out):
    """Rows of out (V, 3) with a NaN or Inf. Compiled without fastmath, which lets LLVM assume every value finite
    and fold np.isfinite to True: a guard inside a fastmath kernel is silently removed."""
    bad = 0
    for o in range(out.shape[0]):
        if not (np.isfinite(out[o, 0]) and np.isfinite(out[o, 1]) and np.isfinite(out[o, 2])):
            bad += 1
    return bad


@numba.njit(cache=True, nogil=True)
def synthesize_vertices(zero, skin_indices, skin_weights, transforms, reference_translations, pose_values,
                        pose_skinned, blended, mode, penetration, body_points, body_normals, clearance, normals, order,
                        out):
    """One frame of Eq. 4 per vertex, and the geometry of Eq. 10 (see synthesize_vertices_fastmath for the
    arguments). Returns the number of non-finite output vertices without penetration; with it, 0 (apply_push,
    which moves the vertices afterwards, counts)."""
    synthesize_vertices_fastmath(zero, skin_indices, skin_weights, transforms, reference_translations, pose_values,
                                 pose_skinned, blended, mode, penetration, body_points, body_normals, clearance,
                                 normals, order, out)
    return 0 if penetration else count_non_finite(out)


@numba.njit(cache=True, nogil=True, fastmath=True)
def synthesize_vertices_fastmath(zero, skin_indices, skin_weights, transforms, reference_translations, pose_values,
                                 pose_skinned, blended, mode, penetration, body_points, body_normals, clearance,
                                 normals, order, out):
    """One frame of Eq. 4 per vertex, and the geometry of Eq. 10, with no finiteness check (fastmath would drop it:
    synthesize_vertices checks the output).

    Internal vertex order (see block_accumulate); out (V, 3) is in the caller's order: internal vertex v is written
    to out[order[v]]. skin_indices/skin_weights (V, I); transforms (B, 3, 4) at the query pose for the current shape
    beta; reference_translations (B, 3): the translation columns of the same pose for beta0 (rotations are shared).
    pose_values (3, V): the pose model, canonical (rest frame) when pose_skinned, else posed world positions; it is
    skinned with beta's transforms in mode AUGMENTED (beta's bone translations carry the skeleton's change of
    proportions exactly at any pose) and with beta0's translations in mode PLAIN. blended (3, V): sum_s w^s rows_s
    from block_accumulate, where rows are the canonical shape deltas d_s = A_s^{-1} (f(beta, theta_s) -
    f(beta0, theta_s) - (t_s(beta) - t_s(beta0))) (mode AUGMENTED; t_s the blended bone translation), world deltas
    (PLAIN: Eq. 2 blended, not re-posed) or canonical anchor drapes f(beta, theta_s) (ZEROTH: the ablation of
    Sec. 4.6, pose model unused). With penetration, writes clearance (V,) h = signed distance along the bound body vertex's posed unit
    normal, and normals (3, V) that normal; body_points/body_normals (V, 3) are the bound body vertex and its unit
    normal at rest for beta, skinned with the garment vertex's own transform (the paper gives the garment vertex its
    closest body vertex's bone weights, so they share them). `zero` is 0 in the run dtype: the accumulators take its
    type, so float32 runs never convert to float64 and back (1.4x faster), and the loop has no data-dependent branch.
    """
    n_vertices = order.shape[0]
    tiny = zero + 1e-30
    for v in range(n_vertices):
        a00 = a01 = a02 = a10 = a11 = a12 = a20 = a21 = a22 = zero
        tx = ty = tz = zero
        rx = ry = rz = zero
        for i in range(skin_indices.shape[1]):
            w = skin_weights[v, i]
            b = skin_indices[v, i]
            t = transforms[b]
            a00 += w * t[0, 0]
            a01 += w * t[0, 1]
            a02 += w * t[0, 2]
            a10 += w * t[1, 0]
            a11 += w * t[1, 1]
            a12 += w * t[1, 2]
            a20 += w * t[2, 0]
            a21 += w * t[2, 1]
            a22 += w * t[2, 2]
            tx += w * t[0, 3]
            ty += w * t[1, 3]
            tz += w * t[2, 3]
            rx += w * reference_translations[b, 0]
            ry += w * reference_translations[b, 1]
            rz += w * reference_translations[b, 2]
        dx, dy, dz = blended[0, v], blended[1, v], blended[2, v]
        if mode == ZEROTH:
            ox = a00 * dx + a01 * dy + a02 * dz + tx
            oy = a10 * dx + a11 * dy + a12 * dz + ty
            oz = a20 * dx + a21 * dy + a22 * dz + tz
        else:
            cx, cy, cz = pose_values[0, v], pose_values[1, v], pose_values[2, v]
            if pose_skinned:
                if mode == AUGMENTED:  # A c + t + A d = A (c + d) + t, with beta's translations t
                    cx += dx
                    cy += dy
                    cz += dz
                    rx, ry, rz = tx, ty, tz
                ox = a00 * cx + a01 * cy + a02 * cz + rx
                oy = a10 * cx + a11 * cy + a12 * cz + ry
                oz = a20 * cx + a21 * cy + a22 * cz + rz
                if mode == PLAIN:
                    ox += dx
                    oy += dy
                    oz += dz
            elif mode == AUGMENTED:  # a posed beta0 drape: add the change of bone translations, beta vs beta0
                ox = cx + a00 * dx + a01 * dy + a02 * dz + tx - rx
                oy = cy + a10 * dx + a11 * dy + a12 * dz + ty - ry
                oz = cz + a20 * dx + a21 * dy + a22 * dz + tz - rz
            else:
                ox = cx + dx
                oy = cy + dy
                oz = cz + dz
        if penetration:
            mx, my, mz = body_normals[v, 0], body_normals[v, 1], body_normals[v, 2]
            nx = a00 * mx + a01 * my + a02 * mz
            ny = a10 * mx + a11 * my + a12 * mz
            nz = a20 * mx + a21 * my + a22 * mz
            # a degenerate normal (antipodal bone blend) comes out ~0: the push along it then moves nothing
            inv = 1 / np.sqrt(nx * nx + ny * ny + nz * nz + tiny)
            nx *= inv
            ny *= inv
            nz *= inv
            bx, by, bz = body_points[v, 0], body_points[v, 1], body_points[v, 2]
            qx = a00 * bx + a01 * by + a02 * bz + tx
            qy = a10 * bx + a11 * by + a12 * bz + ty
            qz = a20 * bx + a21 * by + a22 * bz + tz
            h = (ox - qx) * nx + (oy - qy) * ny + (oz - qz) * nz
            clearance[v] = h
            normals[0, v] = nx
            normals[1, v] = ny
            normals[2, v] = nz
        o = order[v]
        out[o, 0] = ox
        out[o, 1] = oy
        out[o, 2] = oz


@numba.njit(cache=True, nogil=True)
def apply_push(push, normals, order, out):
    """out[order[v]] += push[v] * normals[:, v] (Eq. 10's blended re-projection). Returns the non-finite count."""
    bad = 0
    for v in range(order.shape[0]):
        o = order[v]
        p = push[v]
        if p != 0.0:
            out[o, 0] += p * normals[0, v]
            out[o, 1] += p * normals[1, v]
            out[o, 2] += p * normals[2, v]
        if not (np.isfinite(out[o, 0]) and np.isfinite(out[o, 1]) and np.isfinite(out[o, 2])):
            bad += 1
    return bad


@numba.njit(cache=True, nogil=True, inline="always")
def _blended_transform(transforms, skin_indices, skin_weights, v):
    """Row v's linear blend of its bones' transforms (B, 3, 4): the 3x3 part row-major, then the translation."""
    a00 = a01 = a02 = a10 = a11 = a12 = a20 = a21 = a22 = tx = ty = tz = 0.0
    for j in range(skin_indices.shape[1]):
        w = skin_weights[v, j]
        b = skin_indices[v, j]
        a00 += w * transforms[b, 0, 0]
        a01 += w * transforms[b, 0, 1]
        a02 += w * transforms[b, 0, 2]
        a10 += w * transforms[b, 1, 0]
        a11 += w * transforms[b, 1, 1]
        a12 += w * transforms[b, 1, 2]
        a20 += w * transforms[b, 2, 0]
        a21 += w * transforms[b, 2, 1]
        a22 += w * transforms[b, 2, 2]
        tx += w * transforms[b, 0, 3]
        ty += w * transforms[b, 1, 3]
        tz += w * transforms[b, 2, 3]
    return a00, a01, a02, a10, a11, a12, a20, a21, a22, tx, ty, tz


@numba.njit(cache=True, nogil=True)
def spaced_candidates(table, points, spacing):
    """(V, C) bool: for each row of table (V, C) (ids into points (N, 3), in order of preference), the ids that lie
    at least `spacing` from every id kept before them in the row (a repeated id is never kept twice)."""
    limit = spacing * spacing
    keep = np.zeros(table.shape, dtype=np.bool_)
    for v in range(table.shape[0]):
        for i in range(table.shape[1]):
            u = table[v, i]
            keep[v, i] = True
            for j in range(i):
                if keep[v, j]:
                    w = table[v, j]
                    dx = points[u, 0] - points[w, 0]
                    dy = points[u, 1] - points[w, 1]
                    dz = points[u, 2] - points[w, 2]
                    if u == w or dx * dx + dy * dy + dz * dz < limit:
                        keep[v, i] = False
                        break
    return keep


@numba.njit(cache=True, nogil=True)
def project_out_of_body(out, offsets, candidates, partners, points, skin_indices, skin_weights, transforms, posed,
                        stamps, frame, margin):
    """In place: each garment vertex out[v] (V, 3) closer than `margin` in front of (or behind) the nearest of its
    candidate body vertices moves out to `margin` along the posed body surface's normal there. Returns the count of
    non-finite output vertices.

    Body rows (U', 3): points (rest positions at the current shape), skin_indices/skin_weights (U', I), posed (U',
    3) the frame's skinned positions. Rows [0, U) are the candidates (CSR: candidates[offsets[v]:offsets[v + 1]],
    int32 rows < U), all skinned here first; the normal at the nearest candidate u is that of its largest incident
    body face at rest, (p_a - p_u) x (p_b - p_u) for its other corners a, b = partners[u] in winding order, posed -
    the skinned rest normal tilts where the skin folds (armpit, crotch) and lets cloth stay inside there (README
    "Speed vs accuracy"). Partner rows [U, U') that are no candidate are skinned on first use in a frame: stamps
    (U' - U,) int64 hold the frame number that last skinned them. Compiled without fastmath (its isfinite checks
    must stay)."""
    n_candidates = posed.shape[0] - stamps.shape[0]
    for u in range(n_candidates):
        posed[u, 0], posed[u, 1], posed[u, 2] = skin_vertex(points, skin_indices, skin_weights, transforms, u)
    bad = 0
    for v in range(out.shape[0]):
        x, y, z = out[v, 0], out[v, 1], out[v, 2]
        best = np.inf
        nearest = candidates[offsets[v]]
        for i in range(offsets[v], offsets[v + 1]):
            u = candidates[i]
            dx, dy, dz = x - posed[u, 0], y - posed[u, 1], z - posed[u, 2]
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < best:
                best, nearest = d2, u
        a, b = partners[nearest, 0], partners[nearest, 1]
        for w in (a, b):
            if w >= n_candidates and stamps[w - n_candidates] != frame:
                posed[w, 0], posed[w, 1], posed[w, 2] = skin_vertex(points, skin_indices, skin_weights, transforms, w)
                stamps[w - n_candidates] = frame
        px, py, pz = posed[nearest, 0], posed[nearest, 1], posed[nearest, 2]
        ax, ay, az = posed[a, 0] - px, posed[a, 1] - py, posed[a, 2] - pz
        bx, by, bz = posed[b, 0] - px, posed[b, 1] - py, posed[b, 2] - pz
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length > 1e-12:  # a face collapsed by the pose gives no direction: the vertex stays
            nx, ny, nz = nx / length, ny / length, nz / length
            h = (x - px) * nx + (y - py) * ny + (z - pz) * nz
            if h < margin:
                out[v, 0] = x + (margin - h) * nx
                out[v, 1] = y + (margin - h) * ny
                out[v, 2] = z + (margin - h) * nz
        if not (np.isfinite(out[v, 0]) and np.isfinite(out[v, 1]) and np.isfinite(out[v, 2])):
            bad += 1
    return bad


@numba.njit(cache=True, nogil=True, fastmath=True)
def block_accumulate(block_start, block_regions, region_w, selected, weights, rows, out):
    """out (C, V) = sum_g w_{g,y} sum_k W_g^k rows[selected[g, k], :, y]: the per-vertex blend of Eq. 8.

    Vertices are stored sorted by their set of non-zero regions, so that set is constant over each block
    [block_start[b], block_start[b + 1]) and listed in block_regions (nb, 4) (-1 padded); region_w (4, V) holds
    each vertex's weight of the block's j-th region. rows (N, C, V). Every inner loop runs over contiguous memory
    from index 0 (numba then drops its negative-index checks), which lets LLVM vectorise it: ~6x faster than a
    per-vertex gather over anchors.
    """
    n_blocks = block_start.shape[0] - 1
    k_count = selected.shape[1]
    n_channels = out.shape[0]
    for b in range(n_blocks):
        lo = block_start[b]
        hi = block_start[b + 1]
        n = hi - lo
        for ch in range(n_channels):
            dst = out[ch, lo:hi]
            for i in range(n):
                dst[i] = 0.0
        for j in range(block_regions.shape[1]):
            g = block_regions[b, j]
            if g < 0:
                break
            wj = region_w[j, lo:hi]
            for k in range(k_count):
                c = weights[g, k]
                s = selected[g, k]
                for ch in range(n_channels):
                    src = rows[s, ch, lo:hi]
                    dst = out[ch, lo:hi]
                    for i in range(n):
                        dst[i] += c * wj[i] * src[i]


@numba.njit(cache=True, nogil=True, fastmath=True)
def block_push(zero, block_start, block_regions, region_w, selected, weights, clearances, clearance, push):
    """push (V,) = sum_s w^s max(0, d0^s - h) of Eq. 10, blocked like block_accumulate.

    clearances (N, V) d0^s per anchor; clearance (V,) the current clearance h of each synthesised vertex; zero: 0 in
    the run dtype.
    """
    n_blocks = block_start.shape[0] - 1
    k_count = selected.shape[1]
    for b in range(n_blocks):
        lo = block_start[b]
        hi = block_start[b + 1]
        n = hi - lo
        dst = push[lo:hi]
        h = clearance[lo:hi]
        for i in range(n):
            dst[i] = 0.0
        for j in range(block_regions.shape[1]):
            g = block_regions[b, j]
            if g < 0:
                break
            wj = region_w[j, lo:hi]
            for k in range(k_count):
                c = weights[g, k]
                src = clearances[selected[g, k], lo:hi]
                for i in range(n):
                    dst[i] += c * wj[i] * max(src[i] - h[i], zero)


@numba.njit(cache=True, nogil=True, fastmath=True)
def _blend_transform(skin_indices, skin_weights, transforms, v, a, t):
    """a (3, 3), t (3,) = the blended transform of vertex v."""
    for r in range(3):
        t[r] = 0.0
        for c in range(3):
            a[r, c] = 0.0
    for i in range(skin_indices.shape[1]):
        w = skin_weights[v, i]
        if w == 0.0:
            continue
        m = transforms[skin_indices[v, i]]
        for r in range(3):
            t[r] += w * m[r, 3]
            for c in range(3):
                a[r, c] += w * m[r, c]


@numba.njit(cache=True, nogil=True, fastmath=True)
def _solve3(a00, a01, a02, a10, a11, a12, a20, a21, a22, x, y, z):
    """a^{-1} (x, y, z) by the adjugate, as a tuple; a near-singular blend (antipodal bones) falls back to identity."""
    c00 = a11 * a22 - a12 * a21
    c01 = a12 * a20 - a10 * a22
    c02 = a10 * a21 - a11 * a20
    det = a00 * c00 + a01 * c01 + a02 * c02
    if abs(det) < 1e-6:
        return x, y, z
    inv = 1.0 / det
    return ((c00 * x + (a02 * a21 - a01 * a22) * y + (a01 * a12 - a02 * a11) * z) * inv,
            (c01 * x + (a00 * a22 - a02 * a20) * y + (a02 * a10 - a00 * a12) * z) * inv,
            (c02 * x + (a01 * a20 - a00 * a21) * y + (a00 * a11 - a01 * a10) * z) * inv)


@numba.njit(cache=True, nogil=True)
def unpose(points, skin_indices, skin_weights, transforms, out):
    """out (V, 3) = A^{-1} (points - t) per vertex: posed points (V, 3) back to the rest frame of `transforms`."""
    a = np.empty((3, 3))
    t = np.empty(3)
    for v in range(points.shape[0]):
        _blend_transform(skin_indices, skin_weights, transforms, v, a, t)
        x, y, z = _solve3(a[0, 0], a[0, 1], a[0, 2], a[1, 0], a[1, 1], a[1, 2], a[2, 0], a[2, 1], a[2, 2],
                          points[v, 0] - t[0], points[v, 1] - t[1], points[v, 2] - t[2])
        out[v, 0] = x
        out[v, 1] = y
        out[v, 2] = z
    return out


@numba.njit(cache=True, nogil=True, fastmath=True)
def shape_anchors(delta_coefficients, coefficients, means, components, anchor_transforms, skin_indices,
                  skin_weights, mode, penetration, body_points, body_normals, margin, deltas, clearances,
                  use_base, base, base0, anchor_transforms0):
    """Per anchor, once per shape: the rows of `deltas` and `clearances` of the frame kernels.

    delta_coefficients (N, C) = phi(beta) - phi(beta0); coefficients (N, C) = phi(beta) (Eq. 6); means (N, V, 3),
    components (N, C', V, 3) with C' >= C (the first C are used); anchor_transforms (N, B, 3, 4) at theta_s for beta.
    The PCA mean cancels in f(beta, theta_s) - f(beta0, theta_s). Writes deltas (N, 3, V) (see synthesize_vertices for
    the mode) and, with penetration, clearances (N, V) = min(h0, margin) with h0 the signed distance of
    f(beta, theta_s) from its bound body vertex along that vertex's normal.
    use_base (skinned_residual databases): the PCA models residuals, and f(beta, theta_s) = base[s] + mean + ...,
    f(beta0, theta_s) = base0[s] + mean + ... with base, base0 (N, V, 3) the fitted garment skinned to theta_s.
    anchor_transforms0 (N, B, 3, 4): the anchors' transforms for beta0; AUGMENTED deltas leave out the difference of
    the blended bone translations (beta vs beta0) at theta_s, which the frame kernel applies exactly at theta.
    """
    n_anchors, n_components = delta_coefficients.shape
    n_vertices = deltas.shape[2]
    for s in range(n_anchors):
        transforms = anchor_transforms[s]
        for v in range(n_vertices):
            a00, a01, a02, a10, a11, a12, a20, a21, a22, tx, ty, tz = _blended_transform(transforms, skin_indices,
                                                                                          skin_weights, v)
            dx = dy = dz = 0.0
            fx, fy, fz = means[s, v, 0], means[s, v, 1], means[s, v, 2]
            if use_base:
                dx = base[s, v, 0] - base0[s, v, 0]
                dy = base[s, v, 1] - base0[s, v, 1]
                dz = base[s, v, 2] - base0[s, v, 2]
                fx += base[s, v, 0]
                fy += base[s, v, 1]
                fz += base[s, v, 2]
            for c in range(n_components):
                cx, cy, cz = components[s, c, v, 0], components[s, c, v, 1], components[s, c, v, 2]
                dc = delta_coefficients[s, c]
                dx += dc * cx
                dy += dc * cy
                dz += dc * cz
                fc = coefficients[s, c]
                fx += fc * cx
                fy += fc * cy
                fz += fc * cz
            if mode == ZEROTH:
                # the anchor's shape model at beta, f(beta, theta_s), unposed with beta's bones
                ux, uy, uz = fx - tx, fy - ty, fz - tz
            elif mode == AUGMENTED:
                # The frame kernel skins with beta's bone translations, which carry the skeleton's change of
                # proportions exactly at every pose; the delta keeps only the rest, which rotates with the bones.
                t0x = t0y = t0z = 0.0
                for i in range(skin_indices.shape[1]):
                    w = skin_weights[v, i]
                    b = skin_indices[v, i]
                    t0x += w * anchor_transforms0[s, b, 0, 3]
                    t0y += w * anchor_transforms0[s, b, 1, 3]
                    t0z += w * anchor_transforms0[s, b, 2, 3]
                ux, uy, uz = dx - (tx - t0x), dy - (ty - t0y), dz - (tz - t0z)
            else:
                ux, uy, uz = dx, dy, dz
            if mode != PLAIN:
                ux, uy, uz = _solve3(a00, a01, a02, a10, a11, a12, a20, a21, a22, ux, uy, uz)
            deltas[s, 0, v] = ux
            deltas[s, 1, v] = uy
            deltas[s, 2, v] = uz
            if penetration:
                bx, by, bz = body_points[v, 0], body_points[v, 1], body_points[v, 2]
                mx, my, mz = body_normals[v, 0], body_normals[v, 1], body_normals[v, 2]
                nx = a00 * mx + a01 * my + a02 * mz
                ny = a10 * mx + a11 * my + a12 * mz
                nz = a20 * mx + a21 * my + a22 * mz
                norm = np.sqrt(nx * nx + ny * ny + nz * nz)
                h0 = margin
                if norm > 1e-12:
                    qx = a00 * bx + a01 * by + a02 * bz + tx
                    qy = a10 * bx + a11 * by + a12 * bz + ty
                    qz = a20 * bx + a21 * by + a22 * bz + tz
                    h0 = ((fx - qx) * nx + (fy - qy) * ny + (fz - qz) * nz) / norm
                clearances[s, v] = min(h0, margin)


@numba.njit(cache=True, nogil=True, fastmath=True)
def add_to_columns(out, columns, values):
    """out[:, columns[i]] += values[:, i] for out (C, V), columns (n,), values (C, n): decoded vertices added into the
    whole garment (numpy's fancy-index gather and scatter costs 6x more)."""
    for c in range(out.shape[0]):
        for i in range(columns.shape[0]):
            out[c, columns[i]] += values[c, i]
