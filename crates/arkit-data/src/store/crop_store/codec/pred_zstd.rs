//! `pred-zstd`, the default codec: each pixel predicted from its decoded neighbours
//! ([`super::predictor`]: green, then red and blue less green, each plane by the median
//! edge detector of LOCO-I) and the prediction errors compressed by zstd. The window's
//! five parts ([`window_parts`]: the centre, which is the evaluation crop, and the four
//! parts of the ring around it) are predicted each as an image of its own, the strips
//! left and right transposed (`S` wide and `m` tall: upright, a strip is so narrow
//! that the decoder's rows would spend half their steps at its edges, 1.6 against 0.9
//! ns a pixel), and stored as a zstd frame each, after the byte counts of the first four
//! (four bytes each, little endian), so that evaluation decodes the centre alone and a
//! training crop the parts it reaches. About a fifth of the raw bytes.

use super::super::format::{PixelRect, WindowPart, window_parts, window_side};
use super::super::zstd_frame::zstd_frame;
use super::coder::WindowCoder;
use super::predictor::{
    RectIo, predict_rect, transposed, unpredict_in_place, unpredict_io, unpredict_rect_raw,
};
use arkit_core::{Error, Result};

/// The `pred-zstd` codec.
pub(super) struct PredZstd;

/// zstd's level for `pred-zstd`: on the codec bench's windows, level 19 is about 1%
/// smaller and takes 2-3x the time to encode (`crops` spends most of its time here);
/// below 15 the windows grow by 5% (level 13) to 15% (level 9).
const ZSTD_LEVEL: i32 = 15;

/// Bytes before a `pred-zstd` window's frames: the byte counts of its first four.
const FRAME_TABLE: usize = 16;

impl WindowCoder for PredZstd {
    fn encode(window: &image::RgbImage, size: u32) -> Result<Vec<u8>> {
        let w = window_side(size);
        let zstd = |errors: &[u8]| {
            zstd::bulk::compress(errors, ZSTD_LEVEL)
                .map_err(|e| Error::invalid("crop store", format!("zstd: {e}")))
        };
        let raw = window.as_raw();
        let mut frames = Vec::with_capacity(5);
        for (i, part) in window_parts(size).into_iter().enumerate() {
            let errors = if (2..4).contains(&i) {
                // A strip, transposed.
                let upright = PixelRect {
                    x: 0,
                    y: 0,
                    width: part.height,
                    height: part.width,
                };
                predict_rect(&transposed(raw, w, part), upright.width, upright)
            } else {
                predict_rect(raw, w, part)
            };
            frames.push(zstd(&errors)?);
        }
        let mut out = Vec::with_capacity(FRAME_TABLE + frames.iter().map(Vec::len).sum::<usize>());
        for f in &frames[..4] {
            out.extend_from_slice(&(f.len() as u32).to_le_bytes());
        }
        for f in &frames {
            out.extend_from_slice(f);
        }
        Ok(out)
    }

    fn decode_whole(bytes: &[u8], size: u32) -> Result<Vec<u8>> {
        Self::decode(bytes, size, WindowPart::Whole)
    }

    /// The centre's frame, then the frames of the ring's parts `part` asks for (all for
    /// the whole window, those meeting a region's rectangle, none for the centre). A
    /// frame that gives more or fewer bytes than its part has is refused.
    fn decode(bytes: &[u8], size: u32, part: WindowPart) -> Result<Vec<u8>> {
        let bad = |e: String| Error::invalid("crop store", format!("its zstd window: {e}"));
        let parts = window_parts(size);
        // The five frames: the table's four byte counts, the last frame the rest.
        let table = bytes.get(..FRAME_TABLE).ok_or_else(|| {
            bad(format!(
                "{} bytes, fewer than its table of frames",
                bytes.len()
            ))
        })?;
        let mut frames: [&[u8]; 5] = [&[]; 5];
        let mut rest = &bytes[FRAME_TABLE..];
        for (i, n) in table.chunks_exact(4).enumerate() {
            let n = u32::from_le_bytes(n.try_into().expect("4 bytes")) as usize;
            if n > rest.len() {
                return Err(bad(format!(
                    "its table counts {n} bytes for frame {i}, past the window's {}",
                    bytes.len()
                )));
            }
            (frames[i], rest) = rest.split_at(n);
        }
        frames[4] = rest;
        const NAMES: [&str; 5] = [
            "centre",
            "band above",
            "left strip",
            "right strip",
            "band below",
        ];
        // Each frame into a buffer of exactly its part's bytes: a frame that would give
        // more is an error, one that gives fewer is refused here.
        let frame = |i: usize| {
            let want = 3 * parts[i].pixels();
            let out = zstd_frame(frames[i], want).map_err(|e| bad(format!("its {}: {e}", NAMES[i])))?;
            if out.len() != want {
                return Err(bad(format!(
                    "its {}: {} bytes, expected {want}",
                    NAMES[i],
                    out.len()
                )));
            }
            Ok(out)
        };
        let centre = parts[0];
        let mut centre_px = frame(0)?;
        if part == WindowPart::Centre {
            unpredict_in_place(&mut centre_px, centre.width, centre.height);
            return Ok(centre_px);
        }
        // The ring's parts to decode: all, or those the region meets.
        let wanted = |r: &PixelRect| match part {
            WindowPart::Region(a) => a.meets(r),
            _ => true,
        };
        let side = window_side(size);
        let n = 3 * side * side;
        // Every byte of the window is written below (the parts cover it: decoded or
        // zero), none read: it is not zeroed first.
        let mut window = Vec::<u8>::with_capacity(n);
        let out = window.as_mut_ptr();
        // SAFETY: `out` has room for the `side x side` window; each part's errors are its
        // own buffer's.
        unsafe { unpredict_rect_raw(&centre_px, centre, out, side) };
        for (i, r) in parts.iter().enumerate().skip(1) {
            if !wanted(r) {
                for y in r.y..r.y + r.height {
                    // SAFETY: the part's row is inside the window.
                    unsafe { out.add(3 * (y * side + r.x)).write_bytes(0, 3 * r.width) };
                }
                continue;
            }
            let errors = frame(i)?;
            if (2..4).contains(&i) {
                // A strip, stored transposed: its row `y` is the window's column `r.x + y`.
                let io = RectIo {
                    src: errors.as_ptr(),
                    src_row: 3 * r.height,
                    // SAFETY: the part's first pixel is inside the window.
                    dst: unsafe { out.add(3 * (r.y * side + r.x)) },
                    dst_row: 3,
                    dst_col: 3 * side,
                    width: r.height,
                    height: r.width,
                };
                // SAFETY: the strip's pixels are inside the window, its errors another
                // buffer.
                unsafe { unpredict_io(io) };
            } else {
                // SAFETY: as above.
                unsafe { unpredict_rect_raw(&errors, *r, out, side) };
            }
        }
        // SAFETY: the parts cover the window, each of its bytes written above.
        unsafe { window.set_len(n) };
        Ok(window)
    }
}

#[cfg(test)]
mod tests {
    use super::super::super::format::margin;
    use super::super::predictor::tests::noise;
    use super::super::predictor::unpredict_rect;
    use super::*;

    /// The store tests' window of crop side 16: smooth bytes, no two rows alike.
    fn smooth_window() -> image::RgbImage {
        let w = window_side(16);
        image::RgbImage::from_raw(
            w as u32,
            w as u32,
            (0..w * w * 3).map(|i| (i * 7 % 251) as u8).collect(),
        )
        .unwrap()
    }

    #[test]
    fn a_predicted_window_round_trips_whole_its_centre_and_its_regions() {
        // Smooth, noisy, saturated and wrapping colour differences (red 255 on green 0,
        // blue 0 on green 255), at several crop sizes.
        let mut next = noise(0x2545_f491);
        for size in [1u32, 2, 3, 5, 8, 9, 16, 40, 192] {
            let side = window_side(size);
            let mut px = Vec::with_capacity(3 * side * side);
            for i in 0..side * side {
                let (y, c) = (i / side, i % side);
                px.extend_from_slice(&match i % 7 {
                    0 => [255, 0, 0],
                    1 => [0, 255, 0],
                    2 => [0, 255, 255],
                    3 => [next(), next(), next()],
                    _ => [(y * 4) as u8, (c * 3 + y) as u8, (200 - c % 200) as u8],
                });
            }
            let window = image::RgbImage::from_raw(side as u32, side as u32, px).unwrap();
            // Each part on its own: predicted and decoded back into the window.
            let mut back = vec![0u8; window.len()];
            for r in window_parts(size) {
                let errors = predict_rect(window.as_raw(), side, r);
                assert_eq!(errors.len(), 3 * r.pixels());
                unpredict_rect(&errors, r, &mut back, side);
            }
            assert_eq!(back, *window.as_raw(), "{size}");
            let stored = PredZstd::encode(&window, size).unwrap();
            let whole = PredZstd::decode(&stored, size, WindowPart::Whole);
            assert_eq!(whole.unwrap(), *window.as_raw(), "{size}");
            // The centre alone: the window's centre rows, from the centre's frame.
            let centre = PredZstd::decode(&stored, size, WindowPart::Centre);
            let (s, m) = (size as usize, margin(size) as usize);
            let mut want = Vec::new();
            for y in m..m + s {
                want.extend_from_slice(
                    &window.as_raw()[3 * (y * side + m)..3 * (y * side + m + s)],
                );
            }
            assert_eq!(centre.unwrap(), want, "{size}");
            // A region: the parts it meets decoded, the others zero, the centre always.
            let parts = window_parts(size);
            let regions = [
                PixelRect {
                    x: 0,
                    y: 0,
                    width: 1,
                    height: 1,
                },
                PixelRect {
                    x: m,
                    y: m,
                    width: s,
                    height: s,
                },
                PixelRect {
                    x: side - 1,
                    y: m,
                    width: 1,
                    height: 2,
                },
                PixelRect {
                    x: 1,
                    y: side - 2,
                    width: side - 2,
                    height: 2,
                },
                PixelRect {
                    x: 0,
                    y: 0,
                    width: 0,
                    height: 0,
                },
            ];
            for region in regions {
                let got = PredZstd::decode(
                    &stored,
                    size,
                    WindowPart::Region(region),
                )
                .unwrap();
                for (i, r) in parts.iter().enumerate() {
                    let meets = i == 0
                        || (region.x < r.x + r.width
                            && r.x < region.x + region.width
                            && region.y < r.y + r.height
                            && r.y < region.y + region.height);
                    for y in r.y..r.y + r.height {
                        let at = 3 * (y * side + r.x)..3 * (y * side + r.x + r.width);
                        if meets {
                            assert_eq!(
                                got[at.clone()],
                                window.as_raw()[at],
                                "{size} {region:?} part {i}"
                            );
                        } else {
                            assert!(
                                got[at].iter().all(|&b| b == 0),
                                "{size} {region:?} part {i}"
                            );
                        }
                    }
                }
            }
            // The other way round: any bytes, read as errors, decode to the image
            // whose prediction errors they are (the decoder and the prediction's
            // per-pixel definition agree on every value, wrapping ones included).
            let noise: Vec<u8> = (0..3 * side * side).map(|_| next()).collect();
            let mut decoded = noise.clone();
            unpredict_in_place(&mut decoded, side, side);
            let all = PixelRect {
                x: 0,
                y: 0,
                width: side,
                height: side,
            };
            assert_eq!(predict_rect(&decoded, side, all), noise, "{size}");
        }
    }

    #[test]
    fn a_predicted_window_cut_damaged_or_of_another_size_is_refused() {
        // A smooth window compresses well below PNG's bytes here.
        let crop = smooth_window();
        let stored = PredZstd::encode(&crop, 16).unwrap();
        assert_eq!(
            PredZstd::decode(&stored, 16, WindowPart::Whole).unwrap(),
            *crop.as_raw()
        );
        assert!(
            stored.len() < crop.len() / 2,
            "{} bytes",
            stored.len()
        );
        // The frames of a larger or a smaller window, cut or damaged bytes, a centre's
        // byte count past the end: refused.
        for other in [15, 17] {
            let w = window_side(other) as u32;
            let bytes =
                PredZstd::encode(&image::RgbImage::new(w, w), other).unwrap();
            for part in [WindowPart::Whole, WindowPart::Centre] {
                let e = PredZstd::decode(&bytes, 16, part).unwrap_err();
                assert!(e.to_string().contains("zstd window"), "{other}: {e}");
            }
        }
        let whole = |b: &[u8]| PredZstd::decode(b, 16, WindowPart::Whole);
        assert!(whole(&stored[..stored.len() - 3]).is_err());
        assert!(whole(&[0x28, 0xb5, 0x2f, 0xfd, 1]).is_err());
        assert!(whole(&[]).is_err());
        assert!(whole(&[1, 0]).is_err());
        // A frame's byte count past the window's end.
        let mut long = stored.clone();
        long[..4].copy_from_slice(&(stored.len() as u32).to_le_bytes());
        let e = whole(&long).unwrap_err().to_string();
        assert!(e.contains("past the window"), "{e}");
        // The centre's and the band above's frames swapped (their counts with them):
        // each gives another count of bytes than its part's.
        let count =
            |i: usize| u32::from_le_bytes(stored[4 * i..4 * i + 4].try_into().unwrap()) as usize;
        let (c, a) = (count(0), count(1));
        let mut swapped = stored.clone();
        swapped[..4].copy_from_slice(&(a as u32).to_le_bytes());
        swapped[4..8].copy_from_slice(&(c as u32).to_le_bytes());
        let frames = &stored[FRAME_TABLE..];
        swapped[FRAME_TABLE..FRAME_TABLE + a].copy_from_slice(&frames[c..c + a]);
        swapped[FRAME_TABLE + a..FRAME_TABLE + a + c].copy_from_slice(&frames[..c]);
        let e = whole(&swapped).unwrap_err().to_string();
        assert!(e.contains("its centre"), "{e}");
    }

}
