"""Independent numpy re-implementation of the official ARKitFace loader's per-sample formulas.

What it reproduces: ``ARKitDataset.get_item`` of the public PerspNet code (repository
cbsropenproject/6dof_face, file ``data/arkit_dataset.py``) in eval (test) mode, for ONE sample,
with the random point draw supplied by the caller (``choose_box``) so a comparison is
deterministic.  Written from the formulas; no official code is copied.  Comments cite the
official source as ``arkit_dataset.py:LINE`` (``data/arkit_dataset.py``), ``mesh_core.cpp:LINE``
(``lib/mesh/cython/mesh_core.cpp``; ``lib/mesh_p/cython/mesh_core.cpp`` is the same rasterizer
that also records vertex ids and weights), ``render.py`` (``lib/mesh/render.py`` and
``lib/mesh_p/render.py``).  OpenCV behaviour (``cv2.getAffineTransform``, ``cv2.warpAffine``
INTER_LINEAR / BORDER_CONSTANT, OpenCV 4.x ``imgwarp.cpp`` fixed-point path and
``matrix_decomp.cpp`` LU) and torchvision's ``ToTensor`` + ``Normalize`` are re-implemented too.

Dependencies: numpy and the Python standard library only.

Differences from the official code that are known and deliberate (see ``derive_topology``):
* The eye / mouth "organ" triangles (official ``lib/eyemouth_index.py``, not copied) are derived
  from ``tris_2500x3_202110.npy``.  They are the same 78 triangles (same vertex sets, same order)
  as the official ``vert_index[face_em]``, and ``organ_verts`` equals ``vert_index``; in three
  triangles the order of the vertices inside the triangle differs (the 3rd of each eye: official
  [2, n-2, n-1], here [2, n-1, n-2]; the last of the mouth: official [17, 19, 18], here
  [17, 18, 19]; local loop ids).  Swapping p1 and p2 changes neither the inside test (u and v
  swap) nor the colour (all three attributes are 0); it can only change the float32 rounding
  of the interpolated depth (the sum order), i.e. a depth tie within one ulp: none was seen in
  266 samples compared with the official code.
* Where the official code replaces an out-of-range crop index by ``np.random.randint``
  (arkit_dataset.py:226-230) the reference cannot know the draw: such entries are returned as
  -1 and flagged in ``choose_random``.
"""
from __future__ import annotations

import os

import numpy as np

F32 = np.float32


class OfficialFailure(ValueError):
    """The official get_item raises on this sample (it then silently trains on another one)."""

# ----------------------------------------------------------------------------------------------
# resources and topology
# ----------------------------------------------------------------------------------------------

RESOURCE_FILES = {
    "triangles": "triangles.npy",  # == official data/triangles.npy (arkit_dataset.py:70)
    "kpt_ind": "kpt_ind.npy",  # arkit_dataset.py:21-22
    "uv_coords": "uv_coords_std_202109.npy",  # arkit_dataset.py:24-25
    "tris_full": "tris_2500x3_202110.npy",  # arkit_dataset.py:27-28
}


def load_resources(directory):
    """Load the resource arrays the official loader reads from ``npy/`` and ``data/``."""
    res = {k: np.load(os.path.join(directory, f)) for k, f in RESOURCE_FILES.items()}
    # arkit_dataset.py:32-33: the projection matrix is read as float32.
    res["proj"] = np.loadtxt(os.path.join(directory, "projection_matrix.txt"), dtype=np.float32)
    return res


def derive_topology(tris_full, uv_coords, n_verts=1220):
    """Index lists the official code hard-codes, derived from the resource files.

    ``tris_2500x3_202110.npy`` holds, after the 2304 mesh triangles, the ring triangles
    ``[c_k, 1220+k+1, 1220+k], [c_k, c_k+1, 1220+k+1]`` (k = 0..55) and one fan per hole around
    the centroid vertices 1276 (mouth), 1277 (eye 1), 1278 (eye 2), each ``[l_k, centre, l_k+1]``.
    * contour (official ``contour_ind``, arkit_dataset.py:77-84): first column of the even ring
      triangles; ring vertex 1220+k is contour[k] * 1.1 (arkit_dataset.py:94).
    * mouth / eye1 / eye2 loops (official ``mouth_ind``, ``eye1_ind``, ``eye2_ind``,
      arkit_dataset.py:85-90): first column of each fan, in fan order (same lists, same order,
      so the centroid means of arkit_dataset.py:95-97 are bit-identical).
    * organ triangles (official ``vert_index[face_em]``, arkit_dataset.py:148): each hole loop
      (eye 1, eye 2, mouth; the official ``vert_index`` order) rotated to start at its vertex of
      smallest u in uv_coords_std (an eye / mouth corner), then closed by the zig-zag strip
      between the two ends: local ids a = 1, b = n-1 after the first triangle [0, 1, n-1];
      then alternately [a, a+1, b] (a += 1) and [a, b, b-1] (b -= 1) until n-2 triangles.
    """
    tris_full = np.asarray(tris_full).astype(np.int64)
    n_mesh = None
    for i in range(len(tris_full)):
        if tris_full[i].max() >= n_verts:
            n_mesh = i
            break
    extra = tris_full[n_mesh:]
    ring = extra[(extra >= n_verts + 0).any(1) & ~np.isin(extra, [n_verts + 56, n_verts + 57, n_verts + 58]).any(1)]
    contour = ring[0::2, 0]
    assert len(contour) == 56, len(contour)

    def fan(centre):
        t = extra[(extra == centre).any(1)]
        assert (t[:, 1] == centre).all()
        return t[:, 0].copy()

    mouth, eye1, eye2 = fan(n_verts + 56), fan(n_verts + 57), fan(n_verts + 58)

    organ = []
    for loop in (eye1, eye2, mouth):
        s = int(np.argmin(uv_coords[loop, 0]))
        lp = np.roll(loop, -s)
        n = len(lp)
        tri = [[0, 1, n - 1]]
        a, b, step_a = 1, n - 1, True
        while len(tri) < n - 2:
            if step_a:
                tri.append([a, a + 1, b]); a += 1
            else:
                tri.append([a, b, b - 1]); b -= 1
            step_a = not step_a
        organ.append(lp[np.array(tri)])
    organ = np.concatenate(organ, axis=0)
    organ_verts = np.concatenate([np.roll(l, -int(np.argmin(uv_coords[l, 0]))) for l in (eye1, eye2, mouth)])
    return {"contour": contour, "mouth": mouth, "eye1": eye1, "eye2": eye2,
            "organ_tris": organ, "organ_verts": organ_verts}


# ----------------------------------------------------------------------------------------------
# rasterizer: render_colors_core of mesh_core.cpp, vectorised, float32 arithmetic as in C
# ----------------------------------------------------------------------------------------------

def render_colors(vertices, triangles, colors, h, w):
    """Emulate ``render_colors`` (render.py) -> ``_render_colors_core`` (mesh_core.cpp:169-234).

    Returns (image HxWxC float32, corr HxWx6 float32) where corr is what the mesh_p variant
    records for the winning triangle: [id0, id1, id2, w0, w1, w2] (mesh_p mesh_core.cpp, the
    six ``corrs`` writes after the colour loop).  Rules:
    * vertices, colours cast to float32, triangles to int32 (render.py, before the core call);
      image zero, depth buffer float32 -999999 (render.py).
    * per triangle, in order, the integer pixel grid of its bounding box
      [max(ceil(min x), 0), min(floor(max x), w-1)] x same for y (mesh_core.cpp:195-204); the
      sample point is the integer pixel coordinate itself (mesh_core.cpp:210).
    * accepted if the pixel lies in the 2-pixel border band (x < 2, x > w-3, y < 2, y > h-3:
      no inside test there!) or ``isPointInTri`` (mesh_core.cpp:211, 23-50):
      u >= 0, v >= 0, u + v < 1 with u, v the float32 screen-space barycentrics of
      v0 = p2-p0, v1 = p1-p0, v2 = p-p0 via dot products (inverse denominator 0 when the
      denominator is 0).
    * weights [1-u-v, v, u] (mesh_core.cpp:53-82), depth w0*z0 + w1*z1 + w2*z2 (:214); written
      when depth > buffer, strictly (:216), so at a pixel the FIRST triangle (in order)
      reaching the maximal depth wins; colour w0*c0 + w1*c1 + w2*c2 (:224).
    """
    V = np.asarray(vertices).astype(np.float32)
    T = np.asarray(triangles).astype(np.int32).astype(np.int64)
    C = np.asarray(colors).astype(np.float32)
    c = C.shape[1]
    image = np.zeros((h, w, c), np.float32)
    corr = np.zeros((h, w, 6), np.float32)

    P = V[T]  # (nt, 3 vertices, xyz)
    xs, ys = P[:, :, 0], P[:, :, 1]
    with np.errstate(invalid="ignore"):
        x_min = np.maximum(np.ceil(xs.min(1)), 0)
        x_max = np.minimum(np.floor(xs.max(1)), w - 1)
        y_min = np.maximum(np.ceil(ys.min(1)), 0)
        y_max = np.minimum(np.floor(ys.max(1)), h - 1)
        ok = (x_max >= x_min) & (y_max >= y_min)
    x_min = np.where(ok, x_min, 0).astype(np.int64); x_max = np.where(ok, x_max, -1).astype(np.int64)
    y_min = np.where(ok, y_min, 0).astype(np.int64); y_max = np.where(ok, y_max, -1).astype(np.int64)
    nx = x_max - x_min + 1
    ny = y_max - y_min + 1
    cnt = np.where(ok, nx * ny, 0)
    total = int(cnt.sum())
    if total == 0:
        return image, corr
    tid = np.repeat(np.arange(len(T)), cnt)
    start = np.cumsum(cnt) - cnt
    off = np.arange(total) - np.repeat(start, cnt)
    px = x_min[tid] + off % nx[tid]
    py = y_min[tid] + off // nx[tid]

    p0x, p0y, p0z = P[tid, 0, 0], P[tid, 0, 1], P[tid, 0, 2]
    p1x, p1y, p1z = P[tid, 1, 0], P[tid, 1, 1], P[tid, 1, 2]
    p2x, p2y, p2z = P[tid, 2, 0], P[tid, 2, 1], P[tid, 2, 2]
    fx, fy = px.astype(np.float32), py.astype(np.float32)
    with np.errstate(all="ignore"):
        v0x, v0y = p2x - p0x, p2y - p0y
        v1x, v1y = p1x - p0x, p1y - p0y
        v2x, v2y = fx - p0x, fy - p0y
        dot00 = v0x * v0x + v0y * v0y
        dot01 = v0x * v1x + v0y * v1y
        dot02 = v0x * v2x + v0y * v2y
        dot11 = v1x * v1x + v1y * v1y
        dot12 = v1x * v2x + v1y * v2y
        den = dot00 * dot11 - dot01 * dot01
        inv = np.where(den == 0, F32(0), F32(1) / np.where(den == 0, F32(1), den)).astype(np.float32)
        u = (dot11 * dot02 - dot01 * dot12) * inv
        v = (dot00 * dot12 - dot01 * dot02) * inv
        inside = (u >= 0) & (v >= 0) & (u + v < 1)
        band = (px < 2) | (px > w - 3) | (py < 2) | (py > h - 3)
        w0 = (F32(1) - u) - v
        w1, w2 = v, u
        depth = (w0 * p0z + w1 * p1z) + w2 * p2z
        keep = (band | inside) & (depth > F32(-999999.0))  # NaN depth never passes (:216)
    sel = np.nonzero(keep)[0]
    if len(sel) == 0:
        return image, corr
    pix = py[sel] * w + px[sel]
    # winner per pixel: max depth, ties -> first triangle in order (strict '>' at :216)
    order = np.lexsort((tid[sel], -depth[sel], pix))
    pix_sorted = pix[order]
    first = np.ones(len(order), bool)
    first[1:] = pix_sorted[1:] != pix_sorted[:-1]
    win = sel[order[first]]
    wp = pix_sorted[first]
    wy, wx = wp // w, wp % w
    t = T[tid[win]]
    W0, W1, W2 = w0[win], w1[win], w2[win]
    with np.errstate(all="ignore"):
        for k in range(c):
            image[wy, wx, k] = (W0 * C[t[:, 0], k] + W1 * C[t[:, 1], k]) + W2 * C[t[:, 2], k]
    corr[wy, wx, 0] = t[:, 0].astype(np.float32)
    corr[wy, wx, 1] = t[:, 1].astype(np.float32)
    corr[wy, wx, 2] = t[:, 2].astype(np.float32)
    corr[wy, wx, 3], corr[wy, wx, 4], corr[wy, wx, 5] = W0, W1, W2
    return image, corr


# ----------------------------------------------------------------------------------------------
# OpenCV: getAffineTransform (6x6 LU solve) and warpAffine INTER_LINEAR fixed point
# ----------------------------------------------------------------------------------------------

def _cv_lu_solve(A, b):
    """OpenCV ``hal::LU64f`` (core/src/matrix_decomp.cpp, LUImpl): Gaussian elimination with
    partial pivoting (first row of largest |pivot|), row updates A[j] += (-A[j][i]/A[i][i]) * A[i]
    written as alpha = A[j][i] * (-1/A[i][i]), back substitution s / A[i][i]."""
    A = [list(map(float, r)) for r in A]
    b = [float(x) for x in b]
    m = len(A)
    for i in range(m):
        k = i
        for j in range(i + 1, m):
            if abs(A[j][i]) > abs(A[k][i]):
                k = j
        if abs(A[k][i]) < np.finfo(np.float64).eps * 10:
            raise np.linalg.LinAlgError("singular affine system")
        if k != i:
            A[i], A[k] = A[k], A[i]
            b[i], b[k] = b[k], b[i]
        d = -1.0 / A[i][i]
        for j in range(i + 1, m):
            alpha = A[j][i] * d
            for kk in range(i + 1, m):
                A[j][kk] += alpha * A[i][kk]
            b[j] += alpha * b[i]
    for i in range(m - 1, -1, -1):
        s = b[i]
        for kk in range(i + 1, m):
            s -= A[i][kk] * b[kk]
        b[i] = s / A[i][i]
    return b


def get_affine_transform(src, dst):
    """``cv2.getAffineTransform`` (imgwarp.cpp): float32 points, the 6x6 system
    [x y 1 0 0 0 | u], [0 0 0 x y 1 | v] per point, solved by LU in double; 2x3 float64."""
    src = np.asarray(src, np.float32).astype(np.float64)
    dst = np.asarray(dst, np.float32).astype(np.float64)
    A = np.zeros((6, 6)); B = np.zeros(6)
    for i in range(3):
        A[2 * i, 0:3] = [src[i, 0], src[i, 1], 1.0]
        A[2 * i + 1, 3:6] = [src[i, 0], src[i, 1], 1.0]
        B[2 * i], B[2 * i + 1] = dst[i, 0], dst[i, 1]
    return np.array(_cv_lu_solve(A, B), np.float64).reshape(2, 3)


_INTER_BITS = 5
_INTER_TAB = 1 << _INTER_BITS  # 32
_AB_BITS = 10
_AB_SCALE = 1 << _AB_BITS  # 1024
_COEF_BITS = 15


def warp_affine_linear(src, M, dsize):
    """``cv2.warpAffine(src, M, dsize)`` for uint8, INTER_LINEAR, BORDER_CONSTANT 0 (OpenCV 4.x
    imgwarp.cpp, the fixed-point path): M is inverted in double; per destination pixel the
    source position is accumulated in 1/1024 pixel units with cvRound (round half to even),
    quantised to 1/32 pixel (INTER_BITS = 5) with the +16 rounding offset, and interpolated
    with integer weights w = (1-fy)(1-fx)*32768 ... (exact multiples of 1/1024 * 32768), result
    (sum + 2^14) >> 15; taps outside the source are 0."""
    src = np.asarray(src)
    assert src.dtype == np.uint8
    squeeze = src.ndim == 2
    if squeeze:
        src = src[:, :, None]
    H, Wd, cn = src.shape
    dw, dh = dsize
    m = [float(x) for x in np.asarray(M, np.float64).reshape(-1)]
    D = m[0] * m[4] - m[1] * m[3]
    D = 1.0 / D if D != 0 else 0.0
    A11, A22 = m[4] * D, m[0] * D
    m[0] = A11; m[1] *= -D; m[3] *= -D; m[4] = A22
    b1 = -m[0] * m[2] - m[1] * m[5]
    b2 = -m[3] * m[2] - m[4] * m[5]
    m[2], m[5] = b1, b2

    xs = np.arange(dw, dtype=np.float64)
    ys = np.arange(dh, dtype=np.float64)
    adelta = np.rint(m[0] * xs * _AB_SCALE).astype(np.int64)
    bdelta = np.rint(m[3] * xs * _AB_SCALE).astype(np.int64)
    rd = _AB_SCALE // _INTER_TAB // 2  # 16
    X0 = np.rint((m[1] * ys + m[2]) * _AB_SCALE).astype(np.int64) + rd
    Y0 = np.rint((m[4] * ys + m[5]) * _AB_SCALE).astype(np.int64) + rd
    X = (X0[:, None] + adelta[None, :]) >> (_AB_BITS - _INTER_BITS)
    Y = (Y0[:, None] + bdelta[None, :]) >> (_AB_BITS - _INTER_BITS)
    sx = np.clip(X >> _INTER_BITS, -32768, 32767)
    sy = np.clip(Y >> _INTER_BITS, -32768, 32767)
    fx = X & (_INTER_TAB - 1)
    fy = Y & (_INTER_TAB - 1)
    # interpolateLinear: [1 - t, t] with t = i/32 in float; products * 32768 are exact integers
    wx1 = fx * 32; wx0 = 1024 - wx1  # (x/32)*1024
    wy1 = fy * 32; wy0 = 1024 - wy1
    w00, w01, w10, w11 = wy0 * wx0, wy0 * wx1, wy1 * wx0, wy1 * wx1  # sum 1024*1024 ... scale
    # 1024*1024 = 2^20; the table is at 2^15: divide by 32 (exact: every product is a multiple of 32*32)
    w00, w01, w10, w11 = w00 >> 5, w01 >> 5, w10 >> 5, w11 >> 5
    pad = np.zeros((H + 2, Wd + 2, cn), np.int64)
    pad[1:-1, 1:-1] = src
    # taps (sy, sx), (sy, sx+1), (sy+1, sx), (sy+1, sx+1); out-of-range -> border 0
    def tap(yy, xx):
        inb = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < Wd)
        yy2 = np.where(inb, yy + 1, 0); xx2 = np.where(inb, xx + 1, 0)
        return pad[yy2, xx2]
    s = (tap(sy, sx) * w00[..., None] + tap(sy, sx + 1) * w01[..., None]
         + tap(sy + 1, sx) * w10[..., None] + tap(sy + 1, sx + 1) * w11[..., None])
    out = np.clip((s + (1 << (_COEF_BITS - 1))) >> _COEF_BITS, 0, 255).astype(np.uint8)
    return out[:, :, 0] if squeeze else out


# ----------------------------------------------------------------------------------------------
# get_item
# ----------------------------------------------------------------------------------------------

IMG_MEAN = np.array([0.485, 0.456, 0.406])  # arkit_dataset.py:51
IMG_STD = np.array([0.229, 0.224, 0.225])  # arkit_dataset.py:52


def to_tensor_normalize(img_u8):
    """torchvision ToTensor (HWC uint8 -> CHW float32 / 255) then Normalize with float32
    mean/std: (x - mean) / std (arkit_dataset.py:58-61, applied at :186)."""
    x = np.ascontiguousarray(img_u8.transpose(2, 0, 1)).astype(np.float32) / F32(255)
    m = IMG_MEAN.astype(np.float32)[:, None, None]
    s = IMG_STD.astype(np.float32)[:, None, None]
    return ((x - m) / s).astype(np.float32)


def project(verts, R_t, proj, img_w, img_h):
    """arkit_dataset.py:124-140: [v 1] @ R_t @ M_proj @ M1, divide by w, depth = -w, y = H - y."""
    verts = np.asarray(verts)
    ones = np.ones([verts.shape[0], 1])
    verts_homo = np.concatenate([verts, ones], axis=1)
    M1 = np.array([[img_w / 2, 0, 0, 0], [0, img_h / 2, 0, 0], [0, 0, 1, 0], [img_w / 2, img_h / 2, 0, 1]])
    p = verts_homo @ np.asarray(R_t) @ np.asarray(proj, np.float32) @ M1
    z = p[:, [3]]
    iv = p / z
    iv[:, 2] = -z[:, 0]
    iv = iv[:, :3]
    iv[:, 1] = img_h - iv[:, 1]
    return iv


def face_box(image_vertices, kpt_ind):
    """arkit_dataset.py:153-170 (eval: no jitter): centre and size of the landmark box, box
    0.75*size each side, Python int() (truncation toward zero)."""
    k = image_vertices[kpt_ind, :]
    mx, mn = np.max(k, 0), np.min(k, 0)
    roi_cnt = 0.5 * (mx[0:2] + mn[0:2])
    size = np.max(mx[0:2] - mn[0:2])
    ss = np.array([0.75, 0.75, 0.75, 0.75])
    xc, yc = roi_cnt[0], roi_cnt[1]
    return (int(xc - ss[0] * size), int(yc - ss[2] * size), int(xc + ss[1] * size), int(yc + ss[3] * size))


def uv_position_map(verts, topo, uv_coords, tris_full, uv_size):
    """arkit_dataset.py:72-75 and 93-101: the 1279 attributes (verts*4.5+0.5, then the 56 contour
    vertices * 1.1 about 0, the mouth / eye means) drawn at uv * (S-1) with depth 0, clipped."""
    v = np.asarray(verts) * 4.5 + 0.5  # arkit_dataset.py:251
    t1 = v[topo["contour"]] * 1.1
    t2 = v[topo["mouth"]].mean(axis=0, keepdims=True)
    t3 = v[topo["eye1"]].mean(axis=0, keepdims=True)
    t4 = v[topo["eye2"]].mean(axis=0, keepdims=True)
    attr = np.vstack([v, t1, t2, t3, t4])
    uv = np.asarray(uv_coords) * (uv_size - 1)
    uvx = np.concatenate([uv, np.zeros([uv.shape[0], 1])], axis=1)
    img, _ = render_colors(uvx, tris_full, attr, uv_size, uv_size)
    img = np.clip(img, 0, 1)
    return img


def official_get_item(verts, R_t, image, resources, img_size=192, n_pts=1024, choose_box=None,
                      topo=None):
    """One sample of the official ``get_item`` in eval mode.

    verts: (1220, 3) canonical vertices (the npz ``verts``; its dtype is kept, as the official
    code keeps it); R_t (4, 4); image: RGB uint8 HxWx3 (after cv2.imread + BGR2RGB,
    arkit_dataset.py:119-120); resources: dict from ``load_resources`` (``proj`` key = the
    projection matrix); choose_box: the official post-draw ``choose`` (arkit_dataset.py:191-199):
    n_pts flat indices into mask[top:bottom+1, left:right+1]; if None the first n_pts face
    pixels (or the wrap-padded list) are used.
    """
    verts = np.asarray(verts)
    R_t = np.asarray(R_t)
    if topo is None:
        topo = derive_topology(resources["tris_full"], resources["uv_coords"])
    faces = resources["triangles"]
    img_h, img_w = image.shape[:2]
    assert R_t[3, 2] < 0  # arkit_dataset.py:127
    iv = project(verts, R_t, resources["proj"], img_w, img_h)

    # arkit_dataset.py:142-144: NOCS colours and correspondences (mesh_p renderer)
    attribute = (verts * 4.5 + 0.5) * 255
    coord, corr_weight = render_colors(iv, faces, attribute, img_h, img_w)
    coord = coord / 255.0

    # arkit_dataset.py:146-151: visibility mask, organ holes closed with attribute 0
    att = np.ones((verts.shape[0], 1))
    att[topo["organ_verts"]] = 0
    tris = np.concatenate((np.asarray(faces).astype(np.int64), topo["organ_tris"]), axis=0)
    mask_full, _ = render_colors(iv, tris, att, img_h, img_w)
    mask = (np.squeeze(mask_full) > 0).astype(np.uint8)

    left, top, right, bottom = face_box(iv, resources["kpt_ind"])
    src_pts = np.float32([[left, top], [left, bottom], [right, top]])  # arkit_dataset.py:172-176
    dst_pts = np.float32([[0, 0], [0, img_size - 1], [img_size - 1, 0]])  # arkit_dataset.py:64-68
    tform = get_affine_transform(src_pts, dst_pts)  # :178
    img = warp_affine_linear(image, tform, (img_size, img_size))  # :179
    img = to_tensor_normalize(img)  # :186

    # arkit_dataset.py:191-199: candidate points = face pixels of the full-resolution mask in the box
    box_mask = mask[top:bottom + 1, left:right + 1]  # Python slicing: a negative left/top wraps
    lst = box_mask.flatten().nonzero()[0]
    if len(lst) == 0:
        # official: np.pad(empty, ..., 'wrap') raises, get_item returns None (:199, :278-280) and
        # __getitem__ draws another sample (:282-286)
        raise OfficialFailure("official get_item fails: no face pixel in mask[top:bottom+1, left:right+1] "
                              "(box %r)" % ((left, top, right, bottom),))
    if choose_box is None:
        choose_box = lst[:n_pts] if len(lst) > n_pts else np.pad(lst, (0, n_pts - len(lst)), "wrap")
    choose = np.asarray(choose_box).astype(np.int64)

    # arkit_dataset.py:210-215: NOCS and dense correspondence rows at those pixels
    nocs = coord[top:bottom + 1, left:right + 1, :].reshape((-1, 3))[choose, :] - 0.5
    c23 = corr_weight[top:bottom + 1, left:right + 1, :].reshape((-1, 6))[choose, :]
    corr_mat = np.zeros((n_pts, verts.shape[0]))
    r = np.arange(n_pts)
    corr_mat[r, c23[:, 0].astype(np.int16)] = c23[:, 3]
    corr_mat[r, c23[:, 1].astype(np.int16)] = c23[:, 4]
    corr_mat[r, c23[:, 2].astype(np.int16)] = c23[:, 5]

    # arkit_dataset.py:218-230: box pixel -> crop pixel through tform, floor
    crop_w = right - left + 1
    col_idx = choose % crop_w + left
    row_idx = choose // crop_w + top
    Wm, b = tform.T[:2], tform.T[2]
    point2d = np.concatenate((col_idx.reshape(-1, 1), row_idx.reshape(-1, 1)), axis=1)
    point2d = point2d @ Wm + b
    choose_crop = (np.floor(point2d[:, 1]) * img_size + np.floor(point2d[:, 0])).astype(np.int64)
    rnd = (choose_crop > img_size * img_size - 1) | (choose_crop < 0)
    choose_crop[rnd] = -1  # official: np.random.randint (not reproducible)

    mask_c = warp_affine_linear(mask, tform, (img_size, img_size))  # :232
    mask_c = np.array(mask_c > 0).astype(np.int64)  # :233

    uvmap = uv_position_map(verts, topo, resources["uv_coords"], resources["tris_full"], img_size)
    uvmap = uvmap * 2 - 1  # :253
    uvmap = np.ascontiguousarray(uvmap.astype(np.float32).transpose(2, 0, 1))  # :254

    tform_inv = get_affine_transform(dst_pts, src_pts)  # :268 (eval; overrides :245)
    return {
        "img": img,
        "choose": choose_crop,
        "model": verts.astype(np.float32),
        "uvmap": uvmap,
        "nocs": nocs.astype(np.float32),
        "mask": mask_c,
        "corr_mat": corr_mat.astype(np.float32),
        "tform_inv": tform_inv,
        "R_t": R_t,
        "box": (left, top, right, bottom),
        "choose_random": rnd,
        # intermediates, for diagnosis
        "_mask_full": mask,
        "_coord_full": coord,
        "_corr_full": corr_weight,
    }
