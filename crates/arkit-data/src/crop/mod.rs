//! `crop`: the square crop a face is cut to, and the resampling of an image into it.
//!
//! [`CropTransform`] is the axis-aligned map from image pixels to a `size x size` crop:
//! the box edge `[x0, x0 + side]` maps to `[0, size]` in the crop's continuous
//! coordinates. Where a crop pixel samples the box follows its [`RuleSet`]: at its centre
//! `(i + 0.5, j + 0.5)` (ours, the crate's pixel-centre rule of `conventions::camera`) or
//! at the integer point `(i, j)` (OpenCV's, the official loader's). Which box is cut
//! around a face follows the [`RuleSet`] too: ours ([`CropTransform::around_landmarks`], the
//! square of half-side 0.75 x the larger side of the 68 projected landmarks' bounding
//! box) or the official loader's ([`official_crop`]).
//!
//! [`CropTransform::crop_image`] resamples an image into the crop: bilinear with black
//! outside for pixel centres (table-driven, with SSE2/AVX2 paths whose bits equal the
//! scalar path's), and `cv2.warpAffine`'s fixed-point bilinear for pixel corners
//! ([`warp_affine`]).
//!
//! Tested here: the map's round trip and its affine matrix against each other, the
//! table-driven crop against per-pixel bilinear sampling across the image border, each
//! vector path against the scalar one bit for bit; in `official.rs`, the box and warp
//! against OpenCV's formulas (and `tests/official_crop.rs` against OpenCV's output).

mod exact;
pub(crate) mod official;
#[cfg(test)]
pub(crate) mod probe;
pub(crate) mod rules;

use self::rules::Resampling;

pub use self::official::{
    LandmarkExtent, affine_transform, box_crop, official_box, official_crop, warp_affine, warp_mask,
};

// The registration of the rule sets (see `rules`): one line each.
rules::rule_sets! {
    /// Ours: the square box of half-side 0.75 x the landmarks' larger side, sampled at
    /// pixel centres with our bilinear crop; the top-left fill rule and
    /// perspective-correct weights, rendered at the crop's resolution.
    Exact => exact::Exact,
    /// The official loader's: its integer box and `cv2` affine map sampled at pixel
    /// corners (`cv2.warpAffine`), its rasterizer over the whole image with
    /// screen-space weights, the mask warped into the crop.
    Official => official::Official,
    #[cfg(test)]
    /// A third rule set, for the tests only: ours with a wider box.
    Probe => probe::Probe,
}

use crate::lanes::{
    self,
    crop::{PairWeights, blend_rows, round_row_to_u8},
};
use image::RgbImage;

/// The affine map from image pixels to a square crop (see module docs, stage 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CropTransform {
    /// Left edge of the box in image pixels.
    pub x0: f64,
    /// Top edge of the box in image pixels.
    pub y0: f64,
    /// Width of the box in image pixels.
    pub side: f64,
    /// Height of the box in image pixels: `side` for our square box; the official box
    /// ([`official_crop`]) can be a pixel taller or wider.
    pub side_y: f64,
    /// Side of the crop in pixels.
    pub size: u32,
    /// Whose rules the crop follows: where a crop pixel samples the box
    /// (`RuleSet::sample_offset`) and how the image is resampled.
    pub rules: RuleSet,
}

impl CropTransform {
    /// The official box around projected landmarks `[u0, v0, u1, v1, ...]` (an odd
    /// last value is ignored; no landmarks give a box that renders nothing).
    pub fn around_landmarks(landmarks_2d: &[f32], size: u32) -> Self {
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for p in landmarks_2d.chunks_exact(2) {
            let (u, v) = (p[0] as f64, p[1] as f64);
            x0 = x0.min(u);
            x1 = x1.max(u);
            y0 = y0.min(v);
            y1 = y1.max(v);
        }
        let half = 0.75 * (x1 - x0).max(y1 - y0);
        let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
        CropTransform {
            x0: cx - half,
            y0: cy - half,
            side: 2.0 * half,
            side_y: 2.0 * half,
            size,
            rules: RuleSet::Exact,
        }
    }

    /// Crop scales: crop pixels per image pixel, horizontally and vertically.
    pub fn scales(&self) -> (f64, f64) {
        (self.size as f64 / self.side, self.size as f64 / self.side_y)
    }

    /// Image point to crop point.
    pub fn to_crop(&self, u: f64, v: f64) -> (f64, f64) {
        let (sx, sy) = self.scales();
        ((u - self.x0) * sx, (v - self.y0) * sy)
    }

    /// Crop point to image point.
    pub fn to_image(&self, cu: f64, cv: f64) -> (f64, f64) {
        let (sx, sy) = self.scales();
        (self.x0 + cu / sx, self.y0 + cv / sy)
    }

    /// The image point crop pixel `(i, j)` samples (its centre or its corner, by
    /// [`CropTransform::rules`]).
    pub fn pixel_to_image(&self, i: u32, j: u32) -> (f64, f64) {
        let o = self.rules.sample_offset();
        self.to_image(i as f64 + o, j as f64 + o)
    }

    /// The map as a 2x3 row-major affine matrix, image to crop: `[a, b, c, d, e, f]` with
    /// `cu = a u + b v + c`, `cv = d u + e v + f`.
    pub fn affine(&self) -> [f64; 6] {
        let (sx, sy) = self.scales();
        [sx, 0.0, -self.x0 * sx, 0.0, sy, -self.y0 * sy]
    }

    /// Resamples `image` into the crop (bilinear, each crop pixel centre mapped to the
    /// image; outside the image reads as black).
    ///
    /// The map is an axis-aligned scale, so the bilinear taps and weights of a column
    /// depend only on its x and those of a row only on its y: they are computed once per
    /// column and row (`Taps`, `ColumnTaps`), a tap outside the image getting weight 0.
    /// Each crop row then blends its two source rows over the span the columns read
    /// (`blend_rows`: SSE2, or AVX2 where the CPU has it), reads its pixels from that
    /// blend with two taps each (one four-float operation per pixel, the span padded
    /// with a zero pixel on each side so that no tap is tested for the border), and
    /// rounds the float row to bytes (`round_row_to_u8`). Invariant: every vector path
    /// gives the scalar path's bits (tested), and the whole equals per-pixel bilinear
    /// sampling with black outside (tested across the image border). The measurements
    /// that chose this shape are in `docs/performance.md` ("The crop").
    ///
    /// Resampled by the crop's rules ([`RuleSet`]): a crop with [`RuleSet::Official`] is
    /// resampled as `cv2.warpAffine` does instead ([`warp_affine`]).
    pub fn crop_image(&self, image: &RgbImage) -> RgbImage {
        let out = self.crop_window(image, 0, self.size as usize);
        RgbImage::from_raw(self.size, self.size, out).expect("size matches")
    }

    /// Crop pixels `first..first + count` in both axes (interleaved RGB, row-major,
    /// `count x count`): the crop grid extended past its edges (`first` may be
    /// negative) with every pixel computed by the same formula as in
    /// [`CropTransform::crop_image`], so the pixels the two share are bit for bit the
    /// same. `crop_image` is `crop_window(image, 0, size)`; the crop store keeps such a
    /// window around each sample's evaluation crop (`crate::store::crop_store`).
    pub(crate) fn crop_window(&self, image: &RgbImage, first: i64, count: usize) -> Vec<u8> {
        match self.rules.book().resampling() {
            Resampling::Bilinear => self.bilinear_window(image, first, count),
            Resampling::WarpAffine => {
                let (w, h) = image.dimensions();
                official::warp_affine_window(image.as_raw(), w, h, 3, self, first, count)
            }
        }
    }

    /// [`CropTransform::crop_window`] by our rules: bilinear at pixel centres, black
    /// outside the image (see [`CropTransform::crop_image`]).
    #[inline]
    pub(crate) fn bilinear_window(&self, image: &RgbImage, first: i64, count: usize) -> Vec<u8> {
        let n = count;
        let mut out = vec![0u8; n * n * 3];
        if image.width() == 0 || image.height() == 0 || n == 0 {
            return out;
        }
        let stride = image.width() as usize * 3;
        let (sx, sy) = self.scales();
        let cols = ColumnTaps::new(first, n, self.x0, sx, image.width());
        let rows = Taps::new(first, n, self.y0, sy, image.height(), stride);
        // The blended span: pixels `cols.first..=cols.last` of the two source rows, one
        // float more for the last four-float read, and zero where a pixel is off the
        // image (at most the pads at -1 and `width`).
        let mut blend = vec![0f32; cols.span_floats()];
        let (real_lo, real_hi) = cols.on_image(image.width());
        let real_at = 3 * (real_lo - cols.first) as usize;
        let (lo, hi) = (3 * real_lo as usize, 3 * (real_hi as usize + 1));
        let mut row = vec![0f32; n * 3 + 1];
        let src = image.as_raw();
        for (dst, r) in out.chunks_exact_mut(n * 3).zip(&rows.0) {
            let (ra, rb) = (&src[r.a + lo..r.a + hi], &src[r.b + lo..r.b + hi]);
            blend_rows(ra, rb, r.wa, r.wb, &mut blend[real_at..]);
            cols.blend_columns(&blend, &mut row);
            round_row_to_u8(&row, dst);
        }
        out
    }

    /// The image pixels `crop_window(image, first, count)` can read: the columns and
    /// the rows (inclusive, in image coordinates, not clipped to any image) its
    /// bilinear taps reach, two per output pixel and axis. A pixel outside them never
    /// changes the output; `None` for an empty window. From the same taps the
    /// resampling uses (`bilinear_position`; `cv2.warpAffine`'s fixed-point ones for
    /// [`RuleSet::Official`]), so the two cannot drift apart (tested: pixels
    /// outside changed, the output is the same).
    pub(crate) fn window_reach(&self, first: i64, count: usize) -> Option<[(i64, i64); 2]> {
        if count == 0 {
            return None;
        }
        Some(match self.rules.book().resampling() {
            Resampling::Bilinear => self.bilinear_reach(first, count),
            Resampling::WarpAffine => official::warp_reach(self, first, count),
        })
    }

    /// [`CropTransform::window_reach`] of [`CropTransform::bilinear_window`], for a
    /// window of `count > 0` pixels.
    pub(crate) fn bilinear_reach(&self, first: i64, count: usize) -> [(i64, i64); 2] {
        let last = first + count as i64 - 1;
        // The taps move with the pixel index (a positive scale): the window's first and
        // last pixels reach furthest.
        let (sx, sy) = self.scales();
        let reach = |origin: f64, scale: f64| {
            let (lo, _) = bilinear_position(first, origin, scale);
            let (hi, _) = bilinear_position(last, origin, scale);
            (lo, hi + 1)
        };
        [reach(self.x0, sx), reach(self.y0, sy)]
    }

    /// This crop in the pixel grid of `window`'s crop window `first..first + count`
    /// (see [`CropTransform::crop_window`]): the transform that cuts the same box out
    /// of the window image that `self` cuts out of the image, for the same sampling.
    /// A window pixel `j` sits at image position `window.x0 + (first + j + o) * p`
    /// (`p = window.side / size`, `o` the sampling offset), so a box edge `x` is at
    /// `(x - window.x0) / p - first` in the window, and a side `s` is `s / p` there.
    pub(crate) fn in_window(&self, window: &CropTransform, first: i64) -> CropTransform {
        let (px, py) = (
            window.side / window.size as f64,
            window.side_y / window.size as f64,
        );
        CropTransform {
            x0: (self.x0 - window.x0) / px - first as f64,
            y0: (self.y0 - window.y0) / py - first as f64,
            side: self.side / px,
            side_y: self.side_y / py,
            size: self.size,
            rules: self.rules,
        }
    }
}

/// The two bilinear taps of one crop row (columns have [`ColumnTaps`]): byte offsets of
/// the source rows in the image and their weights; a tap outside the image has weight 0
/// and offset 0, so reading it is always in bounds and adds nothing.
#[derive(Clone, Copy, Debug)]
struct Tap {
    a: usize,
    b: usize,
    wa: f32,
    wb: f32,
}

/// The taps of every crop row.
struct Taps(Vec<Tap>);

impl Taps {
    /// For crop pixels `i` in `first..first + n` whose centres look at `origin + (i +
    /// 0.5) / scale` along an image axis of `count` pixels, `step` bytes apart.
    fn new(first: i64, n: usize, origin: f64, scale: f64, count: u32, step: usize) -> Self {
        Taps(
            (first..first + n as i64)
                .map(|i| {
                    let (x, t) = bilinear_position(i, origin, scale);
                    let tap = |x: i64, w: f32| {
                        if (0..count as i64).contains(&x) {
                            (x as usize * step, w)
                        } else {
                            (0, 0.0)
                        }
                    };
                    let ((a, wa), (b, wb)) = (tap(x, 1.0 - t), tap(x + 1, t));
                    Tap { a, b, wa, wb }
                })
                .collect(),
        )
    }
}

/// Crop pixel `i`'s centre along an image axis, `origin + (i + 0.5) / scale`, as the
/// pixel `x` left of (or above) it and the fraction `t` past that pixel's centre: the
/// bilinear weights are `1 - t` for `x` and `t` for `x + 1`.
fn bilinear_position(i: i64, origin: f64, scale: f64) -> (i64, f32) {
    let f = origin + (i as f64 + 0.5) / scale - 0.5;
    let x = f.floor() as i64;
    (x, (f - x as f64) as f32)
}

/// The horizontal taps of every crop column, read from a row of blended pixels (the
/// vertical pass's output, three floats per pixel) that covers image pixels `first` to
/// `last` and reads as zero off the image: column `i` is `pixel(x) * (1 - t) +
/// pixel(x + 1) * t`, and a pair wholly off the image has weights 0. As the pair is
/// adjacent, one column is two four-float reads (the pair's pixels and the next
/// float), two products and a sum in SSE2 on x86-64, whose fourth lane is junk that
/// the next column's store overwrites; the same products and sums as
/// [`ColumnTaps::blend_columns_scalar`], so the same bits (tested).
struct ColumnTaps {
    /// The span's first pixel: -1 when a column reads the zero left of the image.
    first: i64,
    /// The span's last pixel: the image width when a column reads the zero right of it.
    last: i64,
    /// Per column, the float offset of its pair's first pixel in the span.
    starts: Vec<usize>,
    /// Per column, the pair's two weights, each in four lanes.
    weights: Vec<PairWeights>,
}

impl ColumnTaps {
    /// For crop columns `i` in `first..first + n` whose centres look at `origin + (i +
    /// 0.5) / scale` along an image row of `width` (at least 1) pixels.
    fn new(first: i64, n: usize, origin: f64, scale: f64, width: u32) -> Self {
        let w = width as i64;
        let pairs: Vec<(i64, f32, f32)> = (first..first + n as i64)
            .map(|i| {
                let (x, t) = bilinear_position(i, origin, scale);
                if (-1..w).contains(&x) {
                    (x, 1.0 - t, t)
                } else {
                    (x.clamp(-1, w - 1), 0.0, 0.0)
                }
            })
            .collect();
        let first = pairs.iter().map(|p| p.0).min().unwrap_or(0);
        let last = pairs.iter().map(|p| p.0 + 1).max().unwrap_or(1);
        ColumnTaps {
            first,
            last,
            starts: pairs.iter().map(|p| 3 * (p.0 - first) as usize).collect(),
            weights: pairs
                .iter()
                .map(|&(_, a, b)| PairWeights {
                    a: [a; 4],
                    b: [b; 4],
                })
                .collect(),
        }
    }

    /// Floats in the blended span: three per pixel and one for the last column's read.
    fn span_floats(&self) -> usize {
        3 * (self.last - self.first + 1) as usize + 1
    }

    /// The span's pixels on an image `width` pixels wide (never empty: each pair has
    /// at least one).
    fn on_image(&self, width: u32) -> (i64, i64) {
        (self.first.max(0), self.last.min(width as i64 - 1))
    }

    /// Fills `row` (three floats per column and one spare) from the blended span
    /// ([`lanes::crop::blend_columns`]).
    #[inline]
    fn blend_columns(&self, blend: &[f32], row: &mut [f32]) {
        assert!(blend.len() >= self.span_floats() && row.len() > 3 * self.starts.len());
        lanes::crop::blend_columns(&self.starts, &self.weights, blend, row);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lanes::crop::round_to_u8;
    use image::Rgb;

    #[test]
    fn pixels_past_a_crops_reach_do_not_change_it() {
        // Boxes inside, across and past the edges of a noise image, both samplings,
        // windows that start before the crop and after.
        let (w, h) = (61u32, 47u32);
        let mut x = 0x1234_5678_u32;
        let image = RgbImage::from_fn(w, h, |_, _| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            Rgb([x as u8, (x >> 8) as u8, (x >> 16) as u8])
        });
        for &rules in RuleSet::ALL {
            for (x0, y0, side, first, count) in [
                (10.3, 7.8, 30.0, 0, 16usize),
                (-5.5, 20.25, 41.7, -3, 22),
                (40.0, -9.0, 25.0, 2, 9),
                (0.0, 0.0, 61.0, 0, 16),
                (12.0, 12.0, 7.5, -4, 24),
            ] {
                let crop = CropTransform {
                    x0,
                    y0,
                    side,
                    side_y: side * 1.03,
                    size: 16,
                    rules,
                };
                let want = crop.crop_window(&image, first, count);
                let [(c0, c1), (r0, r1)] = crop.window_reach(first, count).unwrap();
                // Within two pixels of the window's box in the image.
                let (sx, sy) = crop.scales();
                let box_x = (
                    x0 + first as f64 / sx,
                    x0 + (first + count as i64) as f64 / sx,
                );
                let box_y = (
                    y0 + first as f64 / sy,
                    y0 + (first + count as i64) as f64 / sy,
                );
                assert!(
                    c0 as f64 >= box_x.0 - 2.0 && c1 as f64 <= box_x.1 + 2.0,
                    "{rules:?} {c0}..{c1} {box_x:?}"
                );
                assert!(
                    r0 as f64 >= box_y.0 - 2.0 && r1 as f64 <= box_y.1 + 2.0,
                    "{rules:?} {r0}..{r1} {box_y:?}"
                );
                let mut changed = image.clone();
                for (px, py, p) in changed.enumerate_pixels_mut() {
                    let (px, py) = (px as i64, py as i64);
                    if !((c0..=c1).contains(&px) && (r0..=r1).contains(&py)) {
                        p.0 = p.0.map(|v| 255 - v);
                    }
                }
                assert_eq!(
                    crop.crop_window(&changed, first, count),
                    want,
                    "{rules:?} {x0} {y0}"
                );
            }
            assert!(
                CropTransform {
                    x0: 0.0,
                    y0: 0.0,
                    side: 10.0,
                    side_y: 10.0,
                    size: 16,
                    rules,
                }
                .window_reach(0, 0)
                .is_none()
            );
        }
    }

    #[test]
    fn a_crop_window_holds_the_crop_and_a_box_cut_from_it_matches_the_image() {
        // Smooth, as faces are at the crop's scale (a second resampling of fine
        // texture differs by its aliasing, not by a fault).
        let img = RgbImage::from_fn(300, 260, |x, y| {
            let (x, y) = (x as f32, y as f32);
            let v = |a: f32| (128.0 + 100.0 * a.sin()) as u8;
            Rgb([v(x / 17.0), v(y / 23.0 + x / 41.0), v((x - y) / 29.0)])
        });
        for &rules in RuleSet::ALL {
            // Near the image's corner, so the window runs off the image.
            let c = CropTransform {
                x0: -12.3,
                y0: 30.7,
                side: 141.9,
                side_y: 143.2,
                size: 37,
                rules,
            };
            let (first, count) = (-7i64, 51usize);
            let window = c.crop_window(&img, first, count);
            let crop = c.crop_image(&img).into_raw();
            for r in 0..37 {
                let w = 3 * ((r + 7) * count + 7);
                assert_eq!(
                    &window[w..w + 3 * 37],
                    &crop[3 * r * 37..3 * (r + 1) * 37],
                    "{rules:?} row {r}"
                );
            }
            // The crop itself, cut from the window, is the window's centre again up to
            // the second resampling's rounding; a shifted box is close to its crop from
            // the image.
            let as_image = RgbImage::from_raw(count as u32, count as u32, window).unwrap();
            for (dx, scale) in [(0.0, 1.0), (9.4, 1.04)] {
                let moved = CropTransform {
                    x0: c.x0 + dx,
                    y0: c.y0 - dx / 2.0,
                    side: c.side * scale,
                    side_y: c.side_y * scale,
                    ..c
                };
                let direct = moved.crop_image(&img).into_raw();
                let via = moved.in_window(&c, first).crop_window(&as_image, 0, 37);
                let mean = direct
                    .iter()
                    .zip(&via)
                    .map(|(a, b)| (*a as f64 - *b as f64).abs())
                    .sum::<f64>()
                    / direct.len() as f64;
                assert!(
                    mean < if dx == 0.0 { 0.01 } else { 6.0 },
                    "{rules:?} {dx}: {mean}"
                );
            }
        }
    }

    #[test]
    fn crop_transform_round_trip_and_affine() {
        let c = CropTransform {
            x0: 100.0,
            y0: 50.0,
            side: 300.0,
            side_y: 300.0,
            size: 192,
            rules: RuleSet::Exact,
        };
        let (cu, cv) = c.to_crop(250.0, 200.0);
        assert!((cu - 96.0).abs() < 1e-12 && (cv - 96.0).abs() < 1e-12);
        let (u, v) = c.to_image(cu, cv);
        assert!((u - 250.0).abs() < 1e-12 && (v - 200.0).abs() < 1e-12);
        let a = c.affine();
        assert!((a[0] * 250.0 + a[1] * 200.0 + a[2] - cu).abs() < 1e-12);
        assert!((a[3] * 250.0 + a[4] * 200.0 + a[5] - cv).abs() < 1e-12);
        // Cropping a constant image inside its bounds gives the constant.
        let img = RgbImage::from_pixel(640, 480, Rgb([10, 20, 30]));
        assert!(c.crop_image(&img).pixels().all(|p| p.0 == [10, 20, 30]));
        // A horizontal ramp is resampled linearly: crop pixel i looks at image u.
        let ramp = RgbImage::from_fn(640, 480, |x, _| Rgb([(x / 3) as u8, 0, 0]));
        let out = c.crop_image(&ramp);
        let (u, _) = c.to_image(10.5, 10.5);
        let expected = (u - 0.5) / 3.0;
        assert!((out.get_pixel(10, 10).0[0] as f64 - expected).abs() <= 1.0);
    }

    #[test]
    fn round_to_u8_equals_the_saturating_cast() {
        // Every 61st float in [0, 300], plus the halves and their neighbours, where
        // rounding ties would show.
        let mut values: Vec<f32> = (0..=300.0f32.to_bits())
            .step_by(61)
            .map(f32::from_bits)
            .collect();
        for k in 0..=600 {
            let h = k as f32 * 0.5;
            values.extend([h, h.next_down(), h.next_up()]);
        }
        values.retain(|v| *v >= 0.0);
        for &v in &values {
            assert_eq!(round_to_u8(v), (v + 0.5).min(255.0) as u8, "{v}");
        }
        // The row version (sixteen at a time on x86-64, then a tail) gives the same.
        let mut row = vec![0u8; values.len()];
        round_row_to_u8(&values, &mut row);
        for (&v, &r) in values.iter().zip(&row) {
            assert_eq!(r, round_to_u8(v), "{v}");
        }
    }

    #[test]
    fn crop_image_equals_per_pixel_bilinear_across_the_border() {
        // Straightforward per-pixel bilinear sampling with black outside, against the
        // table-driven crop, for a box hanging over the image's top-left corner.
        let img = RgbImage::from_fn(97, 61, |x, y| {
            Rgb([
                (x * 7 + y * 3) as u8,
                (x * y % 251) as u8,
                ((x ^ y) * 5) as u8,
            ])
        });
        // Over the top-left corner, over the bottom-right one (reading the zero pads on
        // both sides of the blended span), inside and downscaled, wholly off the image.
        for (x0, y0, side) in [
            (-13.3, -7.9, 83.7),
            (41.6, 20.2, 70.1),
            (3.2, 4.9, 91.0),
            (120.0, -90.0, 40.0),
        ] {
            let c = CropTransform {
                x0,
                y0,
                side,
                side_y: side,
                size: 50,
                rules: RuleSet::Exact,
            };
            assert_crop_is_bilinear(&img, &c);
        }
        // An empty image crops to black.
        let c = CropTransform {
            x0: -13.3,
            y0: -7.9,
            side: 83.7,
            side_y: 83.7,
            size: 50,
            rules: RuleSet::Exact,
        };
        assert!(
            c.crop_image(&RgbImage::new(0, 0))
                .pixels()
                .all(|p| p.0 == [0; 3])
        );
    }

    /// Asserts `c.crop_image(img)` is, byte for byte, plain per-pixel bilinear sampling
    /// (black off the image) rounded.
    fn assert_crop_is_bilinear(img: &RgbImage, c: &CropTransform) {
        let out = c.crop_image(img);
        let (w, h) = (img.width() as i64, img.height() as i64);
        let texel = |x: i64, y: i64, k: usize| -> f32 {
            if (0..w).contains(&x) && (0..h).contains(&y) {
                img.get_pixel(x as u32, y as u32).0[k] as f32
            } else {
                0.0
            }
        };
        for j in 0..50u32 {
            for i in 0..50u32 {
                let (u, v) = c.to_image(i as f64 + 0.5, j as f64 + 0.5);
                let (fx, fy) = (u - 0.5, v - 0.5);
                let (x, y) = (fx.floor() as i64, fy.floor() as i64);
                let (tx, ty) = ((fx - x as f64) as f32, (fy - y as f64) as f32);
                for k in 0..3 {
                    let v = texel(x, y, k) * ((1.0 - tx) * (1.0 - ty))
                        + texel(x + 1, y, k) * (tx * (1.0 - ty))
                        + texel(x, y + 1, k) * ((1.0 - tx) * ty)
                        + texel(x + 1, y + 1, k) * (tx * ty);
                    let got = out.get_pixel(i, j).0[k] as f32;
                    assert!(
                        (got - v).abs() <= 0.5 + 1e-3,
                        "{c:?} ({i}, {j}, {k}): {got} vs {v}"
                    );
                }
            }
        }
    }

    #[test]
    fn column_taps_equal_the_scalar_taps() {
        // The four-float SSE2 columns (on x86-64) against one float at a time, for a
        // downscale, an upscale and columns reading both pads and beyond.
        for (origin, scale, width) in [(10.3, 0.51, 400u32), (-3.7, 2.3, 20), (-30.0, 0.8, 45)] {
            let cols = ColumnTaps::new(0, 64, origin, scale, width);
            let blend: Vec<f32> = (0..cols.span_floats())
                .map(|i| (i * 37 % 255) as f32 * 0.731)
                .collect();
            let (mut fast, mut slow) = (vec![0f32; 64 * 3 + 1], vec![0f32; 64 * 3 + 1]);
            cols.blend_columns(&blend, &mut fast);
            lanes::crop::blend_columns_scalar(&cols.starts, &cols.weights, &blend, &mut slow);
            let bits = |v: &[f32]| v[..64 * 3].iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&fast), bits(&slow), "{origin} {scale} {width}");
        }
    }
}
