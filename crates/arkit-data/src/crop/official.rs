//! The official loader's crop pipeline, reproduced for `render --compat official`.
//!
//! The release's training loader (`data/arkit_dataset.py` of the official code) does not
//! rasterize at crop resolution. It renders the face mask and the correspondence buffer
//! over the whole image (`raster::rasterize_mesh_official`), then:
//! 1. **Box** ([`official_crop`]): centre `c` and larger side `s` of the 68 projected
//!    landmarks' bounding box, then `left = int(c_x - 0.75 s)`, `right = int(c_x +
//!    0.75 s)`, and the same for `top`/`bottom` (Python's `int`, which truncates toward
//!    zero). The box is not square in general: `right - left` and `bottom - top` can
//!    differ by one.
//! 2. **Affine map**: `cv2.getAffineTransform` of the corners `(left, top)`, `(left,
//!    bottom)`, `(right, top)` onto `(0, 0)`, `(0, S - 1)`, `(S - 1, 0)`: image pixel
//!    `left` lands on crop pixel `0` and `right` on `S - 1`. OpenCV puts pixel `i` at
//!    the integer coordinate `i`, as the official rasterizer samples it, so this
//!    [`CropTransform`] has [`RuleSet::Official`], `x0 = left`, `y0 = top`, and box
//!    sides `S (right - left) / (S - 1)` and `S (bottom - top) / (S - 1)`.
//! 3. **Resampling** ([`warp_affine`]): `cv2.warpAffine` with its defaults (bilinear,
//!    black outside), for the image crop and for the full-resolution 0/1 mask, which
//!    is then thresholded `> 0`. OpenCV 4 (the official code's era) computes it in fixed
//!    point, which we reproduce bit for bit: the inverse map's coefficients are rounded
//!    to 1/1024 pixel per row and column (`round(A x 1024)`, ties to even), the source
//!    position to 1/32 pixel, the four weights are `(32 - f_x)(32 - f_y)` ... in units
//!    of 2^-10 (exact), and a pixel is `(sum w p + 2^14) >> 15` in units of 2^-15. For a
//!    0/1 mask that makes a crop pixel face when the face taps' weights sum to at least
//!    one half. (OpenCV 4.11 and later compute the coordinates in float; they differ
//!    from this only on a few boundary pixels.) `warp_mask_of` takes that rule
//!    directly on a mask given as a predicate (a mask held over a window of the image),
//!    tested against [`warp_mask`]'s resampling of the 0/1 image.
//!
//! The correspondences of a crop mask pixel are the official full-resolution buffer's
//! (triangle, screen-space weights) at the face pixel among its four bilinear taps with
//! the largest weight (the first in the order top-left, top-right, bottom-left,
//! bottom-right on a tie): every stored row is one the official loader computes, at the
//! image pixel nearest to where the crop pixel looks.

use super::rules::{MaskRule, Resampling, RuleBook, UvLayout};
use super::{CropTransform, RuleSet};
use crate::lanes::warp::{AxisTap, COEF_BITS, INTER_BITS, round_sum};
use crate::lanes::{self, Level};
use arkit_core::{ScreenVertex, VisibilityBuffer};

/// The official crop box and its affine map (module docs, steps 1-2) around the
/// projected landmarks `(u, v)`, or `None` when the box is empty (the official loader
/// then fails on the sample and draws another). Give the landmarks in `f64`, as the
/// official loader computes them: `int()` of a box edge within float32 rounding of an
/// integer could go either way (`FaceRenderer::official_crop` projects them so).
pub fn official_crop(
    landmarks: impl IntoIterator<Item = (f64, f64)>,
    size: u32,
) -> Option<CropTransform> {
    let [left, top, right, bottom] = official_box(LandmarkExtent::of(landmarks), None);
    if !(right > left && bottom > top) || size < 2 {
        return None;
    }
    Some(box_crop(left, top, right, bottom, size))
}

/// The centre and the larger side of the bounding box of landmarks `(u, v)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LandmarkExtent {
    /// Centre, x.
    pub cx: f64,
    /// Centre, y.
    pub cy: f64,
    /// The larger side.
    pub size: f64,
}

impl LandmarkExtent {
    /// The extent of `landmarks`.
    pub fn of(landmarks: impl IntoIterator<Item = (f64, f64)>) -> Self {
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for (u, v) in landmarks {
            x0 = x0.min(u);
            x1 = x1.max(u);
            y0 = y0.min(v);
            y1 = y1.max(v);
        }
        LandmarkExtent {
            cx: 0.5 * (x0 + x1),
            cy: 0.5 * (y0 + y1),
            size: (x1 - x0).max(y1 - y0),
        }
    }
}

/// The official box (module docs, step 1) `[left, top, right, bottom]`: each
/// `int(centre -/+ 0.75 size)`, Python's `int` (truncation toward zero), with the
/// training jitter `(dx, dy, scale)` when given (the centre moved, 0.75 scaled, as the
/// official loader's `ss *= uniform(0.95, 1.05)`).
pub fn official_box(extent: LandmarkExtent, jitter: Option<(f64, f64, f64)>) -> [f64; 4] {
    let LandmarkExtent {
        mut cx,
        mut cy,
        size,
    } = extent;
    let mut ss = 0.75;
    if let Some((dx, dy, scale)) = jitter {
        cx += dx;
        cy += dy;
        ss *= scale;
    }
    [
        (cx - ss * size).trunc(),
        (cy - ss * size).trunc(),
        (cx + ss * size).trunc(),
        (cy + ss * size).trunc(),
    ]
}

/// The crop `cv2.getAffineTransform` makes of the box `left..right` x `top..bottom`
/// (integers in the official loader): the corners onto crop pixels `0` and `size - 1`.
pub fn box_crop(left: f64, top: f64, right: f64, bottom: f64, size: u32) -> CropTransform {
    let s = size as f64;
    CropTransform {
        x0: left,
        y0: top,
        side: s * (right - left) / (s - 1.0),
        side_y: s * (bottom - top) / (s - 1.0),
        size,
        rules: RuleSet::Official,
    }
}

/// `cv2.getAffineTransform(src, dst)`: the 2x3 map (row-major) taking the three `src`
/// points (float32, as OpenCV takes them) onto `dst`, solved as OpenCV solves it: the
/// 6x6 system `[x y 1 0 0 0 | u]`, `[0 0 0 x y 1 | v]` by Gaussian elimination with
/// partial pivoting in double (its `LU` decomposition: the first row of largest pivot,
/// rows updated by `alpha = A[j][i] * (-1 / A[i][i])`, back substitution dividing by the
/// pivot). The bits matter: the official loader floors points mapped through this
/// matrix, and a coefficient one ulp off moves a point on an exact integer by a pixel.
/// `None` when the points are collinear.
pub fn affine_transform(src: [[f32; 2]; 3], dst: [[f32; 2]; 3]) -> Option<[f64; 6]> {
    let mut a = [[0f64; 6]; 6];
    let mut b = [0f64; 6];
    for i in 0..3 {
        let (x, y) = (src[i][0] as f64, src[i][1] as f64);
        a[2 * i][..3].copy_from_slice(&[x, y, 1.0]);
        a[2 * i + 1][3..].copy_from_slice(&[x, y, 1.0]);
        b[2 * i] = dst[i][0] as f64;
        b[2 * i + 1] = dst[i][1] as f64;
    }
    for i in 0..6 {
        let mut k = i;
        for j in i + 1..6 {
            if a[j][i].abs() > a[k][i].abs() {
                k = j;
            }
        }
        if a[k][i].abs() < f64::EPSILON * 10.0 {
            return None;
        }
        if k != i {
            a.swap(i, k);
            b.swap(i, k);
        }
        let d = -1.0 / a[i][i];
        let pivot = a[i];
        for j in i + 1..6 {
            let alpha = a[j][i] * d;
            for (x, p) in a[j][i + 1..].iter_mut().zip(&pivot[i + 1..]) {
                *x += alpha * p;
            }
            b[j] += alpha * b[i];
        }
    }
    for i in (0..6).rev() {
        let mut s = b[i];
        for c in i + 1..6 {
            s -= a[i][c] * b[c];
        }
        b[i] = s / a[i][i];
    }
    Some(b)
}

/// Fractional bits of the inverse map's per-row and per-column terms (`AB_BITS`).
const AB_BITS: u32 = 10;

/// Half of the weights' sum: the warped 0/1 mask rounds to 1 from this face weight up.
pub(crate) const HALF_WEIGHT: u32 = 1 << (COEF_BITS - 1);

/// Where one crop pixel reads: the top-left tap `(x, y)` and the position's fraction in
/// 1/32 pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct WarpTap {
    /// Column of the top-left tap (may be outside the image).
    pub x: i32,
    /// Row of the top-left tap.
    pub y: i32,
    /// Horizontal fraction, 0..32.
    pub fx: u32,
    /// Vertical fraction, 0..32.
    pub fy: u32,
}

impl WarpTap {
    /// The four bilinear weights of taps `(x, y)`, `(x + 1, y)`, `(x, y + 1)`,
    /// `(x + 1, y + 1)`, in units of 2^-15 (they sum to 2^15).
    pub fn weights(self) -> [u32; 4] {
        let (fx, fy) = (self.fx, self.fy);
        let scale = 1 << (COEF_BITS - 2 * INTER_BITS);
        [
            (32 - fx) * (32 - fy) * scale,
            fx * (32 - fy) * scale,
            (32 - fx) * fy * scale,
            fx * fy * scale,
        ]
    }
}

/// OpenCV's `cvRound` for the values here: nearest, ties to even.
fn cv_round(v: f64) -> i64 {
    v.round_ties_even() as i64
}

/// The taps of every crop pixel, row-major, as `cv2.warpAffine` computes them for
/// `crop` (which should have [`RuleSet::Official`]).
pub(crate) fn warp_taps(crop: &CropTransform) -> Vec<WarpTap> {
    warp_taps_window(crop, 0, crop.size as usize)
}

/// The taps of crop pixels `first..first + count` in both axes (`first` may be
/// negative: the crop grid extended past its edges), row-major, each computed by
/// `cv2.warpAffine`'s formula for its output position, so the pixels shared with
/// [`warp_taps`] get the same taps.
fn warp_taps_window(crop: &CropTransform, first: i64, count: usize) -> Vec<WarpTap> {
    let (columns, rows) = warp_axes(crop, first, count);
    let mut taps = Vec::with_capacity(count * count);
    for &(y, fy) in &rows {
        taps.extend(columns.iter().map(|&(x, fx)| WarpTap { x, y, fx, fy }));
    }
    taps
}

/// The taps of crop pixels `first..first + count` along each axis: `(column, fraction)`
/// of every crop column, then `(row, fraction)` of every crop row. The crop's map is
/// axis-aligned, so `cv2.warpAffine`'s tap of crop pixel `(i, j)` is column `i`'s
/// horizontal tap with row `j`'s vertical one ([`warp_taps_window`] pairs them).
fn warp_axes(crop: &CropTransform, first: i64, count: usize) -> (Vec<AxisTap>, Vec<AxisTap>) {
    // The forward map as cv2.getAffineTransform gives it, then its inverse as
    // cv2.invertAffineTransform computes it (the map is axis-aligned).
    let (a, e) = crop.scales();
    let (c, f) = (-crop.x0 * a, -crop.y0 * e);
    let d = 1.0 / (a * e);
    let (ia, ie) = (e * d, a * d);
    let (ic, if_) = (-ia * c, -ie * f);
    let one = (1i64 << AB_BITS) as f64;
    let round_delta = 1i64 << (AB_BITS - INTER_BITS - 1);
    let span = first..first + count as i64;
    let x0 = cv_round(ic * one) + round_delta;
    let split = |v: i64| ((v >> INTER_BITS) as i32, (v & 31) as u32);
    let columns = span
        .clone()
        .map(|x| split((x0 + cv_round(ia * x as f64 * one)) >> (AB_BITS - INTER_BITS)))
        .collect();
    let rows = span
        .map(|y| {
            split((cv_round((ie * y as f64 + if_) * one) + round_delta) >> (AB_BITS - INTER_BITS))
        })
        .collect();
    (columns, rows)
}

/// The columns and rows (inclusive) [`warp_affine_window`]'s taps reach: each output
/// pixel's `x` and `x + 1` per axis ([`CropTransform::window_reach`]). `count > 0`.
pub(super) fn warp_reach(crop: &CropTransform, first: i64, count: usize) -> [(i64, i64); 2] {
    let (columns, rows) = warp_axes(crop, first, count);
    let reach = |taps: &[AxisTap]| {
        let lo = taps.iter().map(|t| t.0 as i64).min().unwrap_or(0);
        let hi = taps.iter().map(|t| t.0 as i64 + 1).max().unwrap_or(0);
        (lo, hi)
    };
    [reach(&columns), reach(&rows)]
}

/// `cv2.warpAffine(src, M, (S, S))` with its defaults (bilinear, black outside) for an
/// interleaved 8-bit image of `channels` channels, `width x height`, into the crop.
pub fn warp_affine(
    src: &[u8],
    width: u32,
    height: u32,
    channels: usize,
    crop: &CropTransform,
) -> Vec<u8> {
    warp_affine_window(src, width, height, channels, crop, 0, crop.size as usize)
}

/// [`warp_affine`] over the crop window `first..first + count` (see
/// `warp_taps_window`): `count x count` pixels, those shared with the crop equal.
///
/// Each pixel is OpenCV's fixed-point sum of its four taps' weighted bytes (a tap
/// outside the image adds nothing), rounded: [`WarpTap::weights`] are products of a
/// horizontal and a vertical factor, so the sum is taken as the horizontal blend of a
/// vertical one, in integers, hence exactly the same sum. Each crop row's two image
/// rows are blended once for the whole row (`(32 - fy) top + fy bottom`, a loop the
/// compiler vectorises), then each pixel whose four taps are all in the image blends
/// two of those values per channel (`blend_columns`); the border's pixels sum their
/// taps one by one.
pub(crate) fn warp_affine_window(
    src: &[u8],
    width: u32,
    height: u32,
    channels: usize,
    crop: &CropTransform,
    first: i64,
    count: usize,
) -> Vec<u8> {
    let (w, h) = (width as i64, height as i64);
    assert_eq!(
        src.len(),
        w as usize * h as usize * channels,
        "a {width}x{height} image"
    );
    let stride = w as usize * channels;
    let (columns, rows) = warp_axes(crop, first, count);
    let inside = |x: i32, len: i64| x >= 0 && (x as i64) + 1 < len;
    let mut out = vec![0u8; count * count * channels];
    let mut vertical = vec![0u16; stride];
    // Eight RGB pixels at a time in AVX2 where the SIMD level has it
    // ([`lanes::warp::blend_rgb_columns_at`]): `pairs[j]` holds blended values `j` and
    // `j + 3` side by side.
    let level = lanes::level();
    let wide = channels == 3 && level >= Level::Avx2;
    let mut pairs = vec![0u32; if wide { stride } else { 0 }];
    for (o_row, &(y, fy)) in out.chunks_exact_mut(count * channels).zip(&rows) {
        let whole_rows = inside(y, h);
        #[allow(unused_mut)]
        let mut done = 0..0;
        if whole_rows {
            let at = y as usize * stride;
            let (top, bottom) = (&src[at..at + stride], &src[at + stride..at + 2 * stride]);
            let (up, down) = ((32 - fy) as u16, fy as u16);
            for ((v, &t), &b) in vertical.iter_mut().zip(top).zip(bottom) {
                *v = up * t as u16 + down * b as u16;
            }
            if wide {
                let (near, far) = (&vertical[..stride - 3], &vertical[3..]);
                for ((p, &a), &b) in pairs.iter_mut().zip(near).zip(far) {
                    *p = a as u32 | (b as u32) << 16;
                }
                // The crop columns whose taps are all in the image (a run: the taps
                // move one way along a row), whole groups of eight.
                let first = columns.iter().position(|&(x, _)| inside(x, w));
                if let Some(first) = first {
                    let run = columns[first..]
                        .iter()
                        .take_while(|&&(x, _)| inside(x, w))
                        .count();
                    done = first..first + run / 8 * 8;
                    // Every column of `done` has its taps in the image, so each pair
                    // it reads is in `pairs`.
                    lanes::warp::blend_rgb_columns_at(
                        level,
                        &mut o_row[3 * done.start..3 * done.end],
                        &pairs,
                        &columns[done.clone()],
                    );
                }
            }
        }
        // The columns the lanes did not take: those before and those after.
        let (before, rest) = o_row.split_at_mut(done.start * channels);
        let after = &mut rest[(done.end - done.start) * channels..];
        let parts = [
            (before, &columns[..done.start]),
            (after, &columns[done.end..]),
        ];
        for (part, cols) in parts {
            for (o, &(x, fx)) in part.chunks_exact_mut(channels).zip(cols) {
                if whole_rows && inside(x, w) {
                    let left = &vertical[x as usize * channels..];
                    // RGB with the channel count known to the compiler.
                    match channels {
                        3 => blend_columns(o, left, fx, 3),
                        c => blend_columns(o, left, fx, c),
                    }
                    continue;
                }
                let t = WarpTap { x, y, fx, fy };
                let wts = t.weights();
                let (x, y) = (x as i64, y as i64);
                let corners = [(x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1)];
                for (k, o) in o.iter_mut().enumerate() {
                    let mut sum = 0u32;
                    for (&(cx, cy), &wt) in corners.iter().zip(&wts) {
                        if (0..w).contains(&cx) && (0..h).contains(&cy) {
                            sum +=
                                wt * src[cy as usize * stride + cx as usize * channels + k] as u32;
                        }
                    }
                    *o = round_sum(sum);
                }
            }
        }
    }
    out
}

/// One pixel of [`warp_affine_window`] whose four taps are in the image, `channels`
/// bytes: `left` starts at the vertically blended values of its left taps, its right
/// taps' follow. The weights are `(32 - f)` and `f` in 1/32 along each axis, their
/// products in 2^-15 once scaled.
#[inline(always)]
fn blend_columns(o: &mut [u8], left: &[u16], fx: u32, channels: usize) {
    let (o, left) = (&mut o[..channels], &left[..2 * channels]);
    let scale = 1u32 << (COEF_BITS - 2 * INTER_BITS);
    for (k, o) in o.iter_mut().enumerate() {
        let sum = (32 - fx) * left[k] as u32 + fx * left[channels + k] as u32;
        *o = round_sum(sum * scale);
    }
}

/// The official crop mask: the full-resolution mask (row-major `width x height`)
/// warped into the crop as a 0/1 image and thresholded `> 0`.
pub fn warp_mask(full_mask: &[bool], width: u32, height: u32, crop: &CropTransform) -> Vec<bool> {
    let bytes: Vec<u8> = full_mask.iter().map(|&m| m as u8).collect();
    warp_affine(&bytes, width, height, 1, crop)
        .into_iter()
        .map(|v| v > 0)
        .collect()
}

#[cfg(test)]
/// [`warp_mask`] of the mask `is_face(x, y)` (called only for pixels some tap weighs,
/// which may be outside the image: answer `false` there): a crop pixel is face when
/// its face taps weigh at least [`HALF_WEIGHT`], which is where `cv2.warpAffine`'s
/// rounding of the warped 0/1 mask is above 0. For a mask held over a window of the
/// image, without the whole image's mask.
pub(crate) fn warp_mask_of(crop: &CropTransform, is_face: impl Fn(i64, i64) -> bool) -> Vec<bool> {
    let (columns, rows) = warp_axes(crop, 0, crop.size as usize);
    let mut out = Vec::with_capacity(columns.len() * rows.len());
    for &(y, fy) in &rows {
        out.extend(columns.iter().map(|&(x, fx)| {
            let t = WarpTap { x, y, fx, fy };
            let (x, y) = (x as i64, y as i64);
            let corners = [(x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1)];
            let face_weight: u32 = corners
                .iter()
                .zip(t.weights())
                .filter(|&(&(cx, cy), wt)| wt > 0 && is_face(cx, cy))
                .map(|(_, wt)| wt)
                .sum();
            face_weight >= HALF_WEIGHT
        }));
    }
    out
}

/// [`warp_mask_of`] for a mask held over `window` of the image (row-major
/// `window.width x window.height`; pixels outside it are not face): the same crop
/// mask, its face weight summed as [`warp_affine_window`] sums bytes, the horizontal
/// blend of a vertical one (the same integer): each crop row blends its two window
/// rows once (`(32 - fy) top + fy bottom` of 0/1 values, zero for a row outside the
/// window), then each pixel two of those values (tested equal to the tap-by-tap sum).
pub(crate) fn warp_mask_in(
    crop: &CropTransform,
    window: arkit_core::PixelWindow,
    mask: &[bool],
) -> Vec<bool> {
    let (ww, wh) = (window.width as usize, window.height as usize);
    assert_eq!(mask.len(), ww * wh, "a {ww}x{wh} window's mask");
    let (columns, rows) = warp_axes(crop, 0, crop.size as usize);
    // Window column k is at k + 1 of the blended row; 0 and ww + 1 stay zero, and
    // every tap outside the window is clamped to one of them (it adds nothing).
    let padded = |x: i64| (x - window.x0 as i64 + 1).clamp(0, ww as i64 + 1) as usize;
    let taps: Vec<[usize; 2]> = columns
        .iter()
        .map(|&(x, _)| [padded(x as i64), padded(x as i64 + 1)])
        .collect();
    let in_window = |v: i64| {
        let k = v - window.y0 as i64;
        (0..wh as i64)
            .contains(&k)
            .then(|| &mask[k as usize * ww..(k as usize + 1) * ww])
    };
    let scale = 1u32 << (COEF_BITS - 2 * INTER_BITS);
    // The taps move right with the column (a crop's scale is positive), so the columns
    // whose taps can touch a span of the blended row are one run, found by bisection;
    // checked, and every column computed when it is not so.
    let ordered = taps
        .windows(2)
        .all(|p| p[0][0] <= p[1][0] && p[0][1] <= p[1][1]);
    let mut vertical = vec![0u16; ww + 2];
    // The window columns of `vertical` that may be non-zero (those of the last row).
    let mut written = 0..0;
    let mut out = Vec::with_capacity(columns.len() * rows.len());
    for &(y, fy) in &rows {
        let (top, bottom) = (in_window(y as i64), in_window(y as i64 + 1));
        let (up, down) = ((32 - fy) as u16, fy as u16);
        // Only the columns between the two rows' first and last face pixels can blend
        // to a non-zero value; the rest of `vertical` is kept zero.
        let span = match (top.and_then(face_span), bottom.and_then(face_span)) {
            (Some(a), Some(b)) => a.start.min(b.start)..a.end.max(b.end),
            (Some(a), None) | (None, Some(a)) => a,
            (None, None) => 0..0,
        };
        vertical[1 + written.start..1 + written.end].fill(0);
        let inner = &mut vertical[1 + span.start..1 + span.end];
        match (top, bottom) {
            (Some(t), Some(b)) => {
                for ((v, &t), &b) in inner.iter_mut().zip(&t[span.clone()]).zip(&b[span.clone()]) {
                    *v = up * t as u16 + down * b as u16;
                }
            }
            (Some(t), None) => inner
                .iter_mut()
                .zip(&t[span.clone()])
                .for_each(|(v, &t)| *v = up * t as u16),
            (None, Some(b)) => inner
                .iter_mut()
                .zip(&b[span.clone()])
                .for_each(|(v, &b)| *v = down * b as u16),
            (None, None) => {}
        }
        written = span.clone();
        // Columns whose right tap is left of the span, or left tap right of it, see
        // only zeros.
        let (first, last) = if !ordered {
            (0, columns.len())
        } else if span.is_empty() {
            (0, 0)
        } else {
            let (lo, hi) = (1 + span.start, span.end);
            let first = taps.partition_point(|&[_, r]| r < lo);
            (first, taps.partition_point(|&[l, _]| l <= hi).max(first))
        };
        out.extend(std::iter::repeat_n(false, first));
        out.extend(columns[first..last].iter().zip(&taps[first..last]).map(
            |(&(_, fx), &[l, r])| {
                let face_weight = (32 - fx) * vertical[l] as u32 + fx * vertical[r] as u32;
                face_weight * scale >= HALF_WEIGHT
            },
        ));
        out.extend(std::iter::repeat_n(false, columns.len() - last));
    }
    out
}

/// The columns from a mask row's first face pixel to its last (`None` for a row
/// without one), eight pixels a test.
fn face_span(row: &[bool]) -> Option<std::ops::Range<usize>> {
    // SAFETY: a `bool` is one byte, 0 or 1: the row read as its bytes.
    let bytes = unsafe { std::slice::from_raw_parts(row.as_ptr().cast::<u8>(), row.len()) };
    let word = |c: &[u8]| u64::from_le_bytes(c.try_into().expect("chunks of 8"));
    let chunks = bytes.chunks_exact(8);
    let tail = chunks.remainder();
    let first = match chunks.clone().position(|c| word(c) != 0) {
        Some(k) => 8 * k + word(&bytes[8 * k..8 * k + 8]).trailing_zeros() as usize / 8,
        None => 8 * (bytes.len() / 8) + tail.iter().position(|&b| b != 0)?,
    };
    let last = match tail.iter().rposition(|&b| b != 0) {
        Some(k) => 8 * (bytes.len() / 8) + k,
        None => {
            let k = chunks.clone().rposition(|c| word(c) != 0)?;
            8 * k + 7 - word(&bytes[8 * k..8 * k + 8]).leading_zeros() as usize / 8
        }
    };
    Some(first..last + 1)
}

/// For crop pixel tap `t`, the image pixel (row-major index) the official correspondence
/// is taken from: the face pixel among the four taps with the largest weight, the
/// first on a tie; `None` when no tap is a face pixel.
pub(crate) fn nearest_face_tap(
    t: WarpTap,
    is_face: impl Fn(i64, i64) -> bool,
) -> Option<(i64, i64)> {
    let (x, y) = (t.x as i64, t.y as i64);
    let corners = [(x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1)];
    let mut best: Option<((i64, i64), u32)> = None;
    for (&(cx, cy), &wt) in corners.iter().zip(&t.weights()) {
        if wt > 0 && is_face(cx, cy) && best.is_none_or(|(_, b)| wt > b) {
            best = Some(((cx, cy), wt));
        }
    }
    best.map(|(p, _)| p)
}

/// The official loader's rule set's book: its integer box and `cv2` affine map
/// sampled at pixel corners ([`official_crop`], [`warp_affine`]); the projection matrix
/// read as float32, as the official loader reads it (`np.loadtxt(..., dtype=np.float32)`);
/// its rasterizer over the whole image ([`arkit_core::rasterize_mesh_official`]:
/// integer sample points, its inside test, screen-space weights, earlier triangle on
/// ties), the mask warped into the crop; its UV layout.
pub(crate) struct Official;

impl RuleBook for Official {
    fn name(&self) -> &'static str {
        "official"
    }

    fn sampling_name(&self) -> &'static str {
        "corner"
    }

    fn header_code(&self) -> u32 {
        1
    }

    fn sample_offset(&self) -> f64 {
        0.0
    }

    fn crop_around(
        &self,
        landmarks: &[(f64, f64)],
        size: u32,
    ) -> std::result::Result<CropTransform, String> {
        let [l, t, r, b] = official_box(LandmarkExtent::of(landmarks.iter().copied()), None);
        if !(r > l && b > t) || size < 2 {
            return Err(format!("the box {:?} is empty", [l, t, r, b]));
        }
        Ok(box_crop(l, t, r, b, size))
    }

    fn resampling(&self) -> Resampling {
        Resampling::WarpAffine
    }

    fn projection(&self, release: nalgebra::Matrix4<f64>) -> nalgebra::Matrix4<f64> {
        release.map(|x| x as f32 as f64)
    }

    fn rasterize(
        &self,
        buffer: &mut VisibilityBuffer,
        screen: &[ScreenVertex],
        triangles: &[[u32; 3]],
        _weights: bool,
    ) -> std::result::Result<(), String> {
        arkit_core::rasterize_mesh_official(buffer, screen, triangles).map_err(|e| e.to_string())
    }

    fn mask(&self) -> MaskRule {
        MaskRule::WarpedFromImage
    }

    fn uv_layout(&self) -> UvLayout {
        UvLayout::Official
    }
}

#[cfg(test)]
mod tests {

    #[test]
    fn affine_transform_solves_the_three_point_map() {
        // A box (10, 20)-(200, 210) onto a 192 crop: scale 191/190, offset -scale * corner.
        let m = affine_transform(
            [[10.0, 20.0], [10.0, 210.0], [200.0, 20.0]],
            [[0.0, 0.0], [0.0, 191.0], [191.0, 0.0]],
        )
        .unwrap();
        let s = 191.0 / 190.0;
        let hand = [s, 0.0, -10.0 * s, 0.0, s, -20.0 * s];
        for (a, b) in m.iter().zip(hand) {
            assert!((a - b).abs() < 1e-12, "{m:?}");
        }
        // The corners land on the crop's corners.
        let at = |x: f64, y: f64| (m[0] * x + m[1] * y + m[2], m[3] * x + m[4] * y + m[5]);
        let (u, v) = at(200.0, 210.0);
        assert!((u - 191.0).abs() < 1e-12 && (v - 191.0).abs() < 1e-12);
        // Collinear points have no map.
        assert!(affine_transform([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]], [[0.0; 2]; 3]).is_none());
    }

    use super::*;

    fn crop(left: f64, top: f64, right: f64, bottom: f64, size: u32) -> CropTransform {
        box_crop(left, top, right, bottom, size)
    }

    #[test]
    fn box_truncates_toward_zero_like_python_int() {
        // Landmarks spanning x 10..30 (side 20, centre 20) and y -5..5 (centre 0).
        let c = official_crop([(10.0, -5.0), (30.0, 5.0)], 192).unwrap();
        // left = int(20 - 15) = 5, right = int(35) = 35; top = int(-15) = -15.
        assert_eq!((c.x0, c.y0), (5.0, -15.0));
        let (a, e) = c.scales();
        assert!((a - 191.0 / 30.0).abs() < 1e-12 && (e - 191.0 / 30.0).abs() < 1e-12);
        // int(-1.5) is -1, not floor's -2: a box edge left of 0 truncates up.
        let d = official_crop([(-1.0, 0.0), (1.0, 0.0)], 8).unwrap();
        assert_eq!((d.x0, d.y0), (-1.0, -1.0));
        // The corners land on the first and last crop pixels.
        let (u, v) = c.to_crop(35.0, 15.0);
        assert!(
            (u - 191.0).abs() < 1e-9 && (v - 191.0).abs() < 1e-9,
            "{u} {v}"
        );
        assert!(official_crop([(3.0, 3.0), (3.0, 3.0)], 192).is_none());
    }

    /// `cv2.warpAffine`'s sum over the four taps of every pixel, bounds checked tap by
    /// tap: the definition [`warp_affine_window`] is tested against.
    fn warp_by_taps(
        src: &[u8],
        w: u32,
        h: u32,
        ch: usize,
        crop: &CropTransform,
        first: i64,
        count: usize,
    ) -> Vec<u8> {
        let (w, h) = (w as i64, h as i64);
        let mut out = Vec::new();
        for t in warp_taps_window(crop, first, count) {
            let (x, y) = (t.x as i64, t.y as i64);
            let corners = [(x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1)];
            for k in 0..ch {
                let mut sum = 0u32;
                for (&(cx, cy), wt) in corners.iter().zip(t.weights()) {
                    if (0..w).contains(&cx) && (0..h).contains(&cy) {
                        sum += wt * src[(cy * w + cx) as usize * ch + k] as u32;
                    }
                }
                out.push(((sum + (1 << (COEF_BITS - 1))) >> COEF_BITS).min(255) as u8);
            }
        }
        out
    }

    #[test]
    fn the_separable_warp_is_the_tap_by_tap_sum() {
        // Boxes inside the image, across each edge and beyond it, shrinking and
        // enlarging, grey and RGB, crops and windows around them: byte for byte.
        let mut r = arkit_core::Rng::new(7);
        for case in 0..200 {
            let (w, h) = (20 + r.below(60) as u32, 20 + r.below(60) as u32);
            let ch = if case % 2 == 0 { 3 } else { 1 };
            let src: Vec<u8> = (0..w as usize * h as usize * ch)
                .map(|_| r.below(256) as u8)
                .collect();
            let left = r.uniform(-30.0, w as f64);
            let top = r.uniform(-30.0, h as f64);
            let side = r.uniform(2.0, 90.0);
            let size = 4 + r.below(40) as u32;
            let c = crop(
                left.trunc(),
                top.trunc(),
                (left + side).trunc(),
                (top + side).trunc(),
                size,
            );
            for (first, count) in [(0i64, size as usize), (-3, size as usize + 6)] {
                assert_eq!(
                    warp_affine_window(&src, w, h, ch, &c, first, count),
                    warp_by_taps(&src, w, h, ch, &c, first, count),
                    "case {case}"
                );
            }
        }
    }

    #[test]
    fn the_windowed_mask_warp_is_the_closures() {
        // Random masks over windows inside, across and off the crop's taps.
        let mut r = arkit_core::Rng::new(11);
        for case in 0..200 {
            let window = arkit_core::PixelWindow {
                x0: r.below(30) as u32,
                y0: r.below(30) as u32,
                width: r.below(50) as u32,
                height: r.below(50) as u32,
            };
            let density = r.uniform(0.0, 1.0);
            let (w, h) = (window.width as f64, window.height as f64);
            // Half the cases a face-like blob (an ellipse with noise at its edge and
            // holes): rows without a face pixel, and rows whose face pixels are one
            // run well inside the window; the others uniform noise.
            let (cx, cy) = (r.uniform(0.0, w), r.uniform(0.0, h));
            let (rx, ry) = (r.uniform(1.0, w / 2.0 + 1.0), r.uniform(1.0, h / 2.0 + 1.0));
            let mask: Vec<bool> = (0..window.width * window.height)
                .map(|i| {
                    let (x, y) = ((i % window.width) as f64, (i / window.width) as f64);
                    let e = ((x - cx) / rx).powi(2) + ((y - cy) / ry).powi(2);
                    let noise = r.uniform(0.0, 1.0);
                    if case % 2 == 0 {
                        e + 0.3 * noise < 1.0 && noise > 0.05
                    } else {
                        noise < density
                    }
                })
                .collect();
            let left = r.uniform(-10.0, 60.0).trunc();
            let top = r.uniform(-10.0, 60.0).trunc();
            let side = r.uniform(2.0, 60.0).trunc();
            let c = crop(left, top, left + side, top + side, 4 + r.below(30) as u32);
            let is_face = |x: i64, y: i64| {
                let (cx, cy) = (x - window.x0 as i64, y - window.y0 as i64);
                (0..window.width as i64).contains(&cx)
                    && (0..window.height as i64).contains(&cy)
                    && mask[(cy * window.width as i64 + cx) as usize]
            };
            assert_eq!(
                warp_mask_in(&c, window, &mask),
                warp_mask_of(&c, is_face),
                "case {case}"
            );
        }
    }

    #[test]
    fn a_rows_face_span_runs_from_its_first_face_pixel_to_its_last() {
        // Every row of up to 20 pixels with one or two face pixels anywhere (around the
        // eight-pixel words and the tail), and none.
        for len in 0..20 {
            assert_eq!(face_span(&vec![false; len]), None, "length {len}");
            for a in 0..len {
                for b in a..len {
                    let mut row = vec![false; len];
                    row[a] = true;
                    row[b] = true;
                    assert_eq!(face_span(&row), Some(a..b + 1), "length {len}, {a} and {b}");
                }
            }
        }
    }

    #[test]
    fn taps_of_an_integer_scale_are_exact() {
        // Box 0..30 into 16 pixels: crop pixel i looks at image x = 2 i exactly.
        let c = crop(0.0, 0.0, 30.0, 15.0, 16);
        let taps = warp_taps(&c);
        for (k, t) in taps.iter().enumerate() {
            let (i, j) = (k % 16, k / 16);
            assert_eq!((t.x, t.fx), (2 * i as i32, 0), "column {i}");
            assert_eq!((t.y, t.fy), (j as i32, 0), "row {j}");
        }
        // Half-pixel steps: box 0..7.5 -> fractions of 16/32 on odd columns.
        let h = crop(0.0, 0.0, 15.0, 15.0, 31);
        let t = warp_taps(&h)[1];
        assert_eq!((t.x, t.fx), (0, 16));
    }

    #[test]
    fn weights_sum_to_one_and_match_the_fraction() {
        for fx in 0..32 {
            for fy in 0..32 {
                let w = WarpTap { x: 0, y: 0, fx, fy }.weights();
                assert_eq!(w.iter().sum::<u32>(), 1 << COEF_BITS);
                let t = (fx as f64 / 32.0, fy as f64 / 32.0);
                assert_eq!(w[3] as f64 / 32768.0, t.0 * t.1);
            }
        }
    }

    #[test]
    fn warp_reproduces_a_hand_computed_bilinear_value() {
        // A 2x2 image, crop pixel (1, 0) looking at x = 0.5: (10 + 20) / 2 = 15; crop
        // pixel (1, 1) at (0.5, 0.5): (10 + 20 + 30 + 41) / 4 = 25.25 -> 25.
        let src = [10u8, 20, 30, 41];
        let c = crop(0.0, 0.0, 1.0, 1.0, 3);
        let out = warp_affine(&src, 2, 2, 1, &c);
        assert_eq!(out[1], 15);
        assert_eq!(out[4], 25);
        // (2, 2) looks at (1, 1): the bottom-right pixel, its right and lower taps
        // outside the image with weight 0.
        assert_eq!(out[8], 41);
        // A 0/1 mask is face where the face taps weigh at least one half: pixel (1, 0)
        // sees (1, 0) half and (0, 0) half.
        let m = warp_mask(&[false, true, false, false], 2, 2, &c);
        assert_eq!(&m[..3], &[false, true, true]);
        assert!(!m[3] && !m[6]);
        assert!(!m[4], "a quarter is not enough");
    }

    #[test]
    fn warp_mask_of_a_predicate_is_the_warped_full_mask() {
        // Random masks and boxes, some leaving the image: the weight rule against
        // cv2's resampling of the 0/1 image (warp_affine), tap by tap.
        let mut r = arkit_core::Rng::new(3);
        let (w, h) = (40u32, 30u32);
        for _ in 0..200 {
            let mask: Vec<bool> = (0..w * h).map(|_| r.below(3) == 0).collect();
            let left = r.uniform(-15.0, 30.0).trunc();
            let top = r.uniform(-15.0, 20.0).trunc();
            let side = r.uniform(2.0, 40.0).trunc();
            let c = crop(left, top, left + side, top + side + r.below(2) as f64, 23);
            let face = |x: i64, y: i64| {
                (0..w as i64).contains(&x)
                    && (0..h as i64).contains(&y)
                    && mask[(y * w as i64 + x) as usize]
            };
            assert_eq!(warp_mask_of(&c, face), warp_mask(&mask, w, h, &c), "{c:?}");
        }
    }

    #[test]
    fn nearest_face_tap_prefers_the_heaviest_face_tap() {
        let t = WarpTap {
            x: 4,
            y: 7,
            fx: 20,
            fy: 8,
        };
        // Weights: (12*24, 20*24, 12*8, 20*8) -> top-right is heaviest.
        assert_eq!(nearest_face_tap(t, |_, _| true), Some((5, 7)));
        assert_eq!(nearest_face_tap(t, |x, _| x == 4), Some((4, 7)));
        assert_eq!(nearest_face_tap(t, |_, y| y == 8), Some((5, 8)));
        assert_eq!(nearest_face_tap(t, |_, _| false), None);
        // A zero-weight tap is never chosen.
        let z = WarpTap {
            x: 0,
            y: 0,
            fx: 0,
            fy: 0,
        };
        assert_eq!(nearest_face_tap(z, |x, _| x == 1), None);
    }
}
