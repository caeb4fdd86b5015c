//! `photo`: a photo made ready for the network as the official `demo.py` makes it.
//!
//! The demo pads the photo with black to a square (the extra row or column of an odd
//! difference on the top or left), resizes the square to 800 x 800 with
//! `cv2.resize(..., INTER_LINEAR)`, maps each face box `x0 y0 x1 y1` with it, and cuts
//! the network's crop from the square by the 0.75 rule: centre of the box, half-side
//! `0.75 x max(w, h)`, the corners `(left, top)`, `(left, bottom)`, `(right, top)` onto
//! crop pixels `0` and `size - 1` by `cv2.getAffineTransform` and `cv2.warpAffine`.
//!
//! [`DemoSquare`] is the padding and scale (photo pixels to square pixels and back),
//! `resize_linear` OpenCV's bilinear resize of 8-bit images (its fixed-point weights
//! and rounding), and [`demo_crop`] the crop of a box. The crop is resampled by
//! [`CropTransform::crop_image`], the same `cv2.warpAffine` the official loader uses.

use crate::crop::CropTransform;
use crate::crop::official::box_crop;
use arkit_core::{Error, Result};
use image::RgbImage;

/// The side of the official demo's square (`resize_img(..., 800)`).
pub const DEMO_SIDE: u32 = 800;

/// OpenCV's fixed-point weights of bilinear resizing: `INTER_RESIZE_COEF_BITS`.
const COEF_BITS: u32 = 11;
const COEF_SCALE: i32 = 1 << COEF_BITS;

/// Where a photo sits in the demo's square: the black rows or columns added before it
/// (`pad_left`, `pad_top`), the padded side, and the resize factor to the square's
/// `side` (`side / padded`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DemoSquare {
    /// Photo width, pixels.
    pub width: u32,
    /// Photo height, pixels.
    pub height: u32,
    /// Columns of black added on the left (the larger half of an odd difference).
    pub pad_left: u32,
    /// Rows of black added on the top (the larger half of an odd difference).
    pub pad_top: u32,
    /// The padded square's side, `max(width, height)`.
    pub padded: u32,
    /// The resized square's side (800 in the demo).
    pub side: u32,
}

impl DemoSquare {
    /// The padding of a `width x height` photo and its resize to `side`, as
    /// `demo.py`'s `resize_img` computes them.
    pub fn of(width: u32, height: u32, side: u32) -> Self {
        let padded = width.max(height);
        let diff = padded - width.min(height);
        let pad1 = diff.div_ceil(2);
        let (pad_left, pad_top) = if width > height { (0, pad1) } else { (pad1, 0) };
        DemoSquare {
            width,
            height,
            pad_left,
            pad_top,
            padded,
            side,
        }
    }

    /// Square pixels a photo pixel spans (`side / padded`, the demo's `scale`).
    pub fn scale(&self) -> f64 {
        self.side as f64 / self.padded as f64
    }

    /// A box `[x0, y0, x1, y1]` in photo pixels, in the square's (`bbox += pad;
    /// bbox *= scale`).
    pub fn box_to_square(&self, b: [f64; 4]) -> [f64; 4] {
        let s = self.scale();
        let (px, py) = (self.pad_left as f64, self.pad_top as f64);
        [
            (b[0] + px) * s,
            (b[1] + py) * s,
            (b[2] + px) * s,
            (b[3] + py) * s,
        ]
    }

    /// A point of the square, in photo pixels (the inverse of the box map).
    pub(crate) fn point_to_photo(&self, u: f64, v: f64) -> (f64, f64) {
        let s = self.scale();
        (u / s - self.pad_left as f64, v / s - self.pad_top as f64)
    }

    /// The photo padded to a square with black and resized to `side`.
    pub fn image(&self, photo: &RgbImage) -> RgbImage {
        assert_eq!(
            photo.dimensions(),
            (self.width, self.height),
            "the photo measured"
        );
        let mut padded = RgbImage::new(self.padded, self.padded);
        image::imageops::replace(
            &mut padded,
            photo,
            self.pad_left as i64,
            self.pad_top as i64,
        );
        resize_linear(&padded, self.side, self.side)
    }
}

/// One axis of a bilinear resize: for each output index, the two source indices and
/// their fixed-point weights (summing to 2048), with OpenCV's geometry: output pixel
/// `d` samples source `(d + 0.5) * src / dst - 0.5` (in `f32`, as OpenCV computes it),
/// clamped to the first and last pixel.
fn linear_taps(src: u32, dst: u32) -> Vec<(usize, usize, i32, i32)> {
    // As OpenCV computes it: the inverse of the inverse scale.
    let scale = 1.0 / (dst as f64 / src as f64);
    (0..dst)
        .map(|d| {
            let f = ((d as f64 + 0.5) * scale - 0.5) as f32;
            let mut s = f.floor() as i64;
            let mut frac = f - s as f32;
            if s < 0 {
                s = 0;
                frac = 0.0;
            }
            if s >= src as i64 - 1 {
                s = src as i64 - 1;
                frac = 0.0;
            }
            // `saturate_cast<short>` of a float rounds half to even.
            let w0 = ((1.0 - frac) * COEF_SCALE as f32).round_ties_even() as i32;
            let s = s as usize;
            (s, (s + 1).min(src as usize - 1), w0, COEF_SCALE - w0)
        })
        .collect()
}

/// `cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR)` of an 8-bit RGB
/// image: OpenCV's sampling geometry and fixed-point arithmetic (11-bit weights; each
/// row's horizontal sums, then the vertical blend rounded as its vector path rounds
/// it). A resize to the same size is a copy; a halving in both axes is the mean of
/// each 2 x 2 block, rounded (OpenCV takes its area path there).
///
/// Panics on an empty image or size.
pub(crate) fn resize_linear(image: &RgbImage, width: u32, height: u32) -> RgbImage {
    let (w, h) = image.dimensions();
    assert!(
        w > 0 && h > 0 && width > 0 && height > 0,
        "a non-empty resize"
    );
    if (w, h) == (width, height) {
        return image.clone();
    }
    if (w, h) == (2 * width, 2 * height) {
        let at = |x: u32, y: u32, c: usize| image.get_pixel(x, y).0[c] as u32;
        return RgbImage::from_fn(width, height, |x, y| {
            let (x, y) = (2 * x, 2 * y);
            image::Rgb([0, 1, 2].map(|c| {
                ((at(x, y, c) + at(x + 1, y, c) + at(x, y + 1, c) + at(x + 1, y + 1, c) + 2) >> 2)
                    as u8
            }))
        });
    }
    let xs = linear_taps(w, width);
    let ys = linear_taps(h, height);
    let src = image.as_raw();
    let row = |y: usize| -> Vec<i32> {
        let line = &src[y * w as usize * 3..(y + 1) * w as usize * 3];
        let mut out = Vec::with_capacity(width as usize * 3);
        for &(a, b, wa, wb) in &xs {
            for c in 0..3 {
                out.push(line[a * 3 + c] as i32 * wa + line[b * 3 + c] as i32 * wb);
            }
        }
        out
    };
    let mut out = Vec::with_capacity(width as usize * height as usize * 3);
    // Output rows read source rows in increasing order, each for a few output rows in a
    // row (as OpenCV keeps them): the horizontal sums of the two last read are kept.
    let mut kept: [(usize, Vec<i32>); 2] = [(usize::MAX, Vec::new()), (usize::MAX, Vec::new())];
    for &(a, b, wa, wb) in &ys {
        for (slot, y) in [a, b].into_iter().enumerate() {
            if kept[slot].0 != y {
                kept[slot] = match kept.iter().position(|k| k.0 == y) {
                    Some(other) => kept[other].clone(),
                    None => (y, row(y)),
                };
            }
        }
        let [(_, r0), (_, r1)] = &kept;
        for (&s0, &s1) in r0.iter().zip(r1) {
            // The vector path: each sum to 16 bits (>> 4), times the weight, the high
            // 16 bits of each product, then (sum + 2) >> 2.
            let v = (((s0 >> 4) * wa) >> 16) + (((s1 >> 4) * wb) >> 16);
            out.push(((v + 2) >> 2).clamp(0, 255) as u8);
        }
    }
    RgbImage::from_raw(width, height, out).expect("size matches")
}

/// The network's crop of a face box `[x0, y0, x1, y1]` in the square's pixels, by the
/// demo's rule: centre of the box, half-side `0.75 x max(w, h)`, resampled as
/// `cv2.warpAffine` does. An error when the box is not finite or has no extent.
pub fn demo_crop(b: [f64; 4], size: u32) -> Result<CropTransform> {
    let [x0, y0, x1, y1] = b;
    let extent = (x1 - x0).max(y1 - y0);
    if !b.iter().all(|v| v.is_finite()) || extent <= 0.0 || x1 < x0 || y1 < y0 {
        return Err(Error::invalid(
            "face box",
            format!("[{x0}, {y0}, {x1}, {y1}]: expected x0 <= x1, y0 <= y1, finite, not a point"),
        ));
    }
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let half = 0.75 * extent;
    Ok(box_crop(cx - half, cy - half, cx + half, cy + half, size))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_odd_row_or_column_goes_on_top_or_left() {
        // demo.py: pad1 = (diff + 1) // 2 before the photo, the rest after.
        let wide = DemoSquare::of(641, 480, 800);
        assert_eq!((wide.pad_left, wide.pad_top, wide.padded), (0, 81, 641));
        let tall = DemoSquare::of(480, 640, 800);
        assert_eq!((tall.pad_left, tall.pad_top, tall.padded), (80, 0, 640));
        let square = DemoSquare::of(800, 800, 800);
        assert_eq!(
            (square.pad_left, square.pad_top, square.scale()),
            (0, 0, 1.0)
        );
        // A box round trip through the square.
        let b = wide.box_to_square([10.0, 20.0, 110.0, 220.0]);
        assert_eq!(b[1], (20.0 + 81.0) * 800.0 / 641.0);
        let (x, y) = wide.point_to_photo(b[2], b[3]);
        assert!((x - 110.0).abs() < 1e-9 && (y - 220.0).abs() < 1e-9);
    }

    #[test]
    fn padding_is_black_and_the_photo_is_kept() {
        let photo = RgbImage::from_fn(4, 2, |x, y| image::Rgb([x as u8 * 10 + 1, y as u8 + 1, 7]));
        let sq = DemoSquare::of(4, 2, 4);
        let out = sq.image(&photo);
        assert_eq!(out.dimensions(), (4, 4));
        assert_eq!(out.get_pixel(0, 0).0, [0, 0, 0]);
        assert_eq!(out.get_pixel(3, 1).0, photo.get_pixel(3, 0).0); // pad_top 1
        assert_eq!(out.get_pixel(0, 3).0, [0, 0, 0]);
    }

    #[test]
    fn doubling_interpolates_a_quarter_and_three_quarters() {
        // Upscaling 2 -> 4: output 1 samples source 0.25, output 2 samples 0.75; the
        // ends are clamped to the edge pixels. Values by hand: 0, 100 -> 0, 25, 75, 100.
        let img = RgbImage::from_fn(2, 1, |x, _| image::Rgb([x as u8 * 100; 3]));
        let out = resize_linear(&img, 4, 1);
        let row: Vec<u8> = out.pixels().map(|p| p.0[0]).collect();
        assert_eq!(row, [0, 25, 75, 100]);
        // The same size is a copy; a constant image stays constant.
        assert_eq!(resize_linear(&img, 2, 1), img);
        let flat = RgbImage::from_pixel(7, 5, image::Rgb([200, 13, 255]));
        assert!(
            resize_linear(&flat, 16, 3)
                .pixels()
                .all(|p| p.0 == [200, 13, 255])
        );
    }

    #[test]
    fn the_box_rule_and_bad_boxes() {
        // A 100 x 60 box centred at (200, 300): half-side 75, so the crop's corners are
        // (125, 225) and (275, 375), mapped onto crop pixels 0 and 191.
        let c = demo_crop([150.0, 270.0, 250.0, 330.0], 192).unwrap();
        let (u, v) = c.to_image(0.0, 0.0);
        assert!((u - 125.0).abs() < 1e-9 && (v - 225.0).abs() < 1e-9);
        let (u, v) = c.to_image(191.0, 191.0);
        assert!((u - 275.0).abs() < 1e-9 && (v - 375.0).abs() < 1e-9);
        for bad in [
            [0.0, 0.0, 0.0, 0.0],
            [10.0, 0.0, 5.0, 20.0],
            [0.0, f64::NAN, 5.0, 5.0],
        ] {
            assert!(demo_crop(bad, 192).is_err(), "{bad:?}");
        }
    }
}
