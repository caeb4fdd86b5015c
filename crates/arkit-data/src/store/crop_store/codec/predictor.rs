//! `predictor`: the pixel predictor of the `pred-zstd` codec ([`super::pred_zstd`]) and
//! its decoders. Each pixel of an RGB rectangle is predicted from its decoded
//! neighbours, per plane (green, then red and blue less green), by the median edge
//! detector of LOCO-I (JPEG-LS); [`predict_rect`] gives the prediction errors and
//! [`unpredict_rect`] / [`unpredict_in_place`] undo them exactly. The decoder runs in
//! SSE2 lanes (the x86-64 baseline; VEX-encoded, with bands of eight rows in AVX2
//! registers, where the CPU has AVX2) and one pixel at a time elsewhere; all are tested
//! against the prediction's per-pixel definition and each other. Uses only
//! [`super::super::format`] (the rectangles).

use super::super::format::PixelRect;

pub(crate) use crate::lanes::predictor::med;

/// The three plane values of a pixel: green, red less green, blue less green.
#[inline]
fn planes_of(rgb: &[u8]) -> [i16; 3] {
    let g = rgb[1] as i16;
    [g, rgb[0] as i16 - g, rgb[2] as i16 - g]
}

/// The predictions of the pixel at row `y`, column `x` (plane values of the row above,
/// `prev`, and of this row, `cur`): none for the first pixel, the left one along the
/// first row, the one above down the first column, else [`med`].
#[inline]
fn predict(prev: &[[i16; 3]], cur: &[[i16; 3]], y: usize, x: usize) -> [i16; 3] {
    match (y, x) {
        (0, 0) => [0; 3],
        (0, _) => cur[x - 1],
        (_, 0) => prev[0],
        _ => {
            let (a, b, c) = (cur[x - 1], prev[x], prev[x - 1]);
            [
                med(a[0], b[0], c[0]),
                med(a[1], b[1], c[1]),
                med(a[2], b[2], c[2]),
            ]
        }
    }
}

/// `rect` of the RGB image `image` (`image_width` pixels wide) transposed: an RGB
/// image `rect.height` wide and `rect.width` tall, whose pixel `(y, x)` is the image's
/// pixel at row `rect.y + x`, column `rect.x + y`.
pub(super) fn transposed(image: &[u8], image_width: usize, rect: PixelRect) -> Vec<u8> {
    (0..rect.width)
        .flat_map(|y| (0..rect.height).map(move |x| 3 * ((rect.y + x) * image_width + rect.x + y)))
        .flat_map(|at| [image[at], image[at + 1], image[at + 2]])
        .collect()
}

/// The prediction errors of `rect` of an RGB image `image_width` pixels wide
/// (row-major, `image`), the rectangle predicted as an image of its own: per pixel
/// (row-major) three bytes, the errors of green, of red less green and of blue less
/// green, each plane's value less its `predict`ion from that plane, modulo 256 (so
/// every rectangle has one, and [`unpredict_rect`] undoes it exactly). Panics when
/// `rect` is not inside the image.
pub fn predict_rect(image: &[u8], image_width: usize, rect: PixelRect) -> Vec<u8> {
    assert!(
        image_width > 0
            && image.len().is_multiple_of(3 * image_width)
            && rect.inside(image_width, image.len() / (3 * image_width)),
        "{rect:?} inside an RGB image {image_width} pixels wide"
    );
    let mut out = Vec::with_capacity(3 * rect.pixels());
    let (mut prev, mut cur) = (vec![[0i16; 3]; rect.width], vec![[0i16; 3]; rect.width]);
    for y in 0..rect.height {
        let row = 3 * ((rect.y + y) * image_width + rect.x);
        for x in 0..rect.width {
            let i = row + 3 * x;
            let p = predict(&prev, &cur, y, x);
            let v = planes_of(&image[i..i + 3]);
            out.extend(v.iter().zip(p).map(|(v, p)| (v - p) as u8));
            cur[x] = v;
        }
        std::mem::swap(&mut prev, &mut cur);
    }
    out
}

/// Decodes `errors`, the [`predict_rect`] errors of `rect` (`3 * width * height`
/// bytes), into `rect` of the RGB image `image` (`image_width` pixels wide), leaving
/// its other pixels as they were. Panics when the sizes do not match.
pub fn unpredict_rect(errors: &[u8], rect: PixelRect, image: &mut [u8], image_width: usize) {
    assert!(
        errors.len() == 3 * rect.pixels()
            && image_width > 0
            && image.len().is_multiple_of(3 * image_width)
            && rect.inside(image_width, image.len() / (3 * image_width)),
        "the errors of {rect:?} and an RGB image {image_width} pixels wide holding it"
    );
    // SAFETY: `errors` holds the rectangle's rows and `image` its pixels (asserted);
    // they are two slices, so they do not overlap.
    unsafe { unpredict_rect_raw(errors, rect, image.as_mut_ptr(), image_width) };
}

/// [`unpredict_rect`] into the image at `image`, which may be uninitialised: only the
/// rectangle's bytes are written, none is read.
///
/// # Safety
///
/// `errors` is `3 * rect.pixels()` bytes; `image` is valid for writes of an RGB image
/// `image_width` pixels wide that holds `rect`, and does not overlap `errors`.
pub(super) unsafe fn unpredict_rect_raw(
    errors: &[u8],
    rect: PixelRect,
    image: *mut u8,
    image_width: usize,
) {
    debug_assert_eq!(errors.len(), 3 * rect.pixels());
    let io = RectIo {
        src: errors.as_ptr(),
        src_row: 3 * rect.width,
        // SAFETY: the rectangle's first pixel is inside the image (the caller's).
        dst: unsafe { image.add(3 * (rect.y * image_width + rect.x)) },
        dst_row: 3 * image_width,
        dst_col: 3,
        width: rect.width,
        height: rect.height,
    };
    // SAFETY: the caller's.
    unsafe { unpredict_io(io) };
}

/// [`unpredict_rect`] in place: `buf` holds the [`predict_rect`] errors of a whole
/// `width x height` image and is left holding its RGB bytes. Panics when `buf` is not
/// `3 * width * height` bytes.
pub fn unpredict_in_place(buf: &mut [u8], width: usize, height: usize) {
    assert_eq!(
        buf.len(),
        3 * width * height,
        "the errors of a {width}x{height} image"
    );
    let dst = buf.as_mut_ptr();
    let io = RectIo {
        src: dst,
        src_row: 3 * width,
        dst,
        dst_row: 3 * width,
        dst_col: 3,
        width,
        height,
    };
    // SAFETY: `buf` holds the image (asserted); source and destination are the same
    // bytes with the same rows, as [`RectIo`] allows.
    unsafe { unpredict_io(io) };
}

pub(super) use crate::lanes::predictor::{RectIo, unpredict_io};

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// A xorshift stream of bytes for the codec tests.
    pub(in super::super) fn noise(seed: u32) -> impl FnMut() -> u8 {
        let mut x = seed;
        move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as u8
        }
    }

    /// [`unpredict_scalar`] of the errors of a whole `width x height` image, into a
    /// buffer of its own.
    fn unpredict_by_scalar(errors: &[u8], width: usize, height: usize) -> Vec<u8> {
        assert_eq!(errors.len(), 3 * width * height);
        let mut out = vec![0u8; errors.len()];
        let io = RectIo {
            src: errors.as_ptr(),
            src_row: 3 * width,
            dst: out.as_mut_ptr(),
            dst_row: 3 * width,
            dst_col: 3,
            width,
            height,
        };
        // SAFETY: two buffers of the image's bytes.
        unsafe { crate::lanes::predictor::unpredict_scalar(io) };
        out
    }

    #[test]
    fn the_decoders_lanes_and_rows_give_the_scalar_paths_bytes() {
        let mut next = noise(0x9e37_79b9);
        // Every width up to 40 (the bands' first, inner and last steps; a width of one
        // or two has no inner step) at heights of one to three bands of eight, four
        // and one rows and their remainders, and the window's parts at S = 192.
        let shapes = (0..=40usize)
            .flat_map(|w| [(w, w), (w, 1), (w, 9), (w, 17)])
            .chain([(244, 244), (192, 192), (244, 26), (26, 192), (3, 40)]);
        for (width, height) in shapes {
            let noise: Vec<u8> = (0..3 * width * height).map(|_| next()).collect();
            let smooth: Vec<u8> = (0..width * height)
                .flat_map(|i| {
                    [
                        (i / width.max(1) * 3) as u8,
                        (i % width.max(1) * 5) as u8,
                        90,
                    ]
                })
                .collect();
            let whole = PixelRect {
                x: 0,
                y: 0,
                width,
                height,
            };
            let smooth_errors = if width == 0 {
                Vec::new()
            } else {
                predict_rect(&smooth, width, whole)
            };
            for errors in [noise, smooth_errors] {
                let scalar = unpredict_by_scalar(&errors, width, height);
                let mut fast = errors.clone();
                unpredict_in_place(&mut fast, width, height);
                assert_eq!(fast, scalar, "{width}x{height} in place");
                // Into a rectangle of a larger image: the same bytes there, the
                // image's other bytes left as they were.
                let (iw, ih) = (width + 5, height + 3);
                let mut image: Vec<u8> = (0..3 * iw * ih).map(|i| (i % 253) as u8).collect();
                let before = image.clone();
                let rect = PixelRect {
                    x: 2,
                    y: 1,
                    width,
                    height,
                };
                unpredict_rect(&errors, rect, &mut image, iw);
                for y in 0..ih {
                    for x in 0..iw {
                        let at = 3 * (y * iw + x);
                        let inside = (2..2 + width).contains(&x) && (1..1 + height).contains(&y);
                        let want = if inside {
                            let i = 3 * ((y - 1) * width + x - 2);
                            &scalar[i..i + 3]
                        } else {
                            &before[at..at + 3]
                        };
                        assert_eq!(&image[at..at + 3], want, "{width}x{height} at ({x}, {y})");
                    }
                }
                // Written transposed (as the window's strips are): pixel (y, x) at
                // row x, column y of an image `height` wide.
                let mut flipped = vec![0u8; errors.len()];
                let io = RectIo {
                    src: errors.as_ptr(),
                    src_row: 3 * width,
                    dst: flipped.as_mut_ptr(),
                    dst_row: 3,
                    dst_col: 3 * height,
                    width,
                    height,
                };
                // SAFETY: every pixel's address is inside `flipped`, another buffer.
                unsafe { unpredict_io(io) };
                for y in 0..height {
                    for x in 0..width {
                        let (a, b) = (3 * (x * height + y), 3 * (y * width + x));
                        assert_eq!(
                            flipped[a..a + 3],
                            scalar[b..b + 3],
                            "{width}x{height} transposed at ({x}, {y})"
                        );
                    }
                }
                // Every level the CPU has (SSE2 at `Scalar`, the VEX encoding and
                // AVX2 bands above), each called directly.
                for level in crate::lanes::available() {
                    let mut lanes = errors.clone();
                    let p = lanes.as_mut_ptr();
                    let io = RectIo {
                        src: p,
                        src_row: 3 * width,
                        dst: p,
                        dst_row: 3 * width,
                        dst_col: 3,
                        width,
                        height,
                    };
                    // SAFETY: in place, a whole image.
                    unsafe { crate::lanes::predictor::unpredict_io_at(level, io) };
                    assert_eq!(lanes, scalar, "{level}, {width}x{height}");
                }
            }
        }
    }
}
