//! `crop_store`: every sample's crop pixels and mesh stored once, so that the loader
//! ([`crate::loader::item::FaceLoader`]) reads one small record instead of decoding the
//! release's JPEG and `_info.npz` for every sample in every epoch.
//!
//! What a record holds, for one sample and one rule set (`exact` or `official`) and crop
//! side `S`: the evaluation crop's box ([`CropTransform`]: the box the loader cuts in
//! `mode="eval"`), the mesh (`V x 3` float32, as `_info.npz` has it), and the crop
//! *window* around that box: crop pixels `-m..S + m` in both axes (`m =`
//! [`margin`]`(S)`), resampled from the full-resolution image by the same formula as
//! the crop ([`CropTransform::crop_window`]). So:
//! - in evaluation the crop is the window's centre `S x S`, bit for bit what decoding
//!   the JPEG and cropping gives;
//! - in training the jittered box (centre moved by up to 0.15 of the landmarks' box
//!   size, side scaled 0.95-1.05) lies inside the window, and is resampled from it
//!   ([`CropTransform::in_window`]): a second bilinear resampling at about the crop's
//!   own scale, so the training crops are slightly smoother than crops from the full
//!   image (measured in docs/python.md), while the box, mask, points and
//!   correspondences are the same.
//!
//! Layout of a store folder (`DATA/crops/<compat>-<S>/` by default): `crops.json`
//! ([`CropStoreManifest`]: the format, the rules, the window codec, `S`, the margin,
//! the vertex count, the key field's width, the dataset's fingerprint, the files, the
//! samples without pixels and why) and, per samples shard `K`, `part-K.bin`: a
//! [`HEADER_BYTES`]-byte header (magic `ARKCROP4`, format, the rules, `S`, `m`, `V`,
//! record count, codec, the shard index `K`, the key field's width, the dataset's
//! fingerprint), one record per row of `samples/part-K.parquet`, in order, the record
//! index (`rows + 1` byte offsets) and a [`FOOTER_BYTES`]-byte footer (magic
//! `ARKCIDX4`, the index's CRC-32). A record: CRC-32 of the rest, status (1: pixels,
//! 0: none), the row, the shard index, the key's length, the dataset's fingerprint,
//! the sample's key (`subject/action/img_id`, zero-padded), the box (four float64),
//! the window's and the mesh's byte counts, the window (`(S + 2m)^2` RGB pixels) as its
//! codec stores it ([`WindowCodec`]: by default its pixels predicted from their
//! neighbours and the errors compressed by zstd, the centre `S x S` and the ring around
//! it, in four parts, in five frames so that evaluation decodes the centre alone and a
//! training crop the parts it reaches ([`window_parts`], [`WindowPart`]); or a PNG, or
//! the raw bytes), then the
//! mesh (`V x 3` float32, by coordinate and byte plane, compressed by zstd: [`encode_mesh`]). All
//! are lossless, so the window read is the window resampled and the mesh the mesh, bit
//! for bit: evaluation crops stay those of the JPEG, and stores of every codec serve the
//! same items in both modes (measured in docs/performance.md: a `pred-zstd` window is
//! about a fifth of the raw bytes, a PNG one a quarter; the mesh 80% of its raw bytes).
//!
//! Nothing read is trusted before it is checked, and nothing is served from another
//! place than the one asked for: [`CropStore::open`] checks the manifest against the
//! dataset (its fingerprint, [`crate::render::dataset::dataset_fingerprint`]: the
//! checksums of its samples shards, so a store of another or a re-converted dataset is
//! refused, never served stale), the rules, `S` and `V` the loader asks for, and every
//! file's header and record index (a part of another store, of another dataset or of
//! another shard, swapped or renamed, is refused by name; a truncated part or a damaged
//! index when the store is opened); [`CropStore::read`] checks each
//! record, in training and in evaluation alike: its CRC, then that it is the record of
//! this dataset, this shard, this row and this sample's key (a comparison of a few
//! dozen bytes, no hashing of the data), then its status, then that the window's and
//! the mesh's lengths fill the record and are within their bounds, and only then decodes
//! the mesh; the window is decoded when the loader knows its crop
//! ([`StoredRecord::crop_pixels`]: the centre alone for the evaluation crop, the parts a
//! training crop reaches for it). Each is decoded into a buffer of its exact size from
//! the manifest, never one a file names: a zstd frame that gives more or fewer bytes, or
//! a PNG of another size or colour type, is refused, the PNG from its header. A record
//! whose sample had no
//! readable image when the store was made has status 0, and reading it is an error
//! naming the sample and the recorded reason. A store of an earlier format is refused
//! with "rerun `arkit-tool crops`". Files are written under a temporary name and
//! renamed; `crops.json` last; `crops` holds the folder's lock while it writes.
//!
//! Tested in `tests/crop_store.rs`: every field of every item equal with and without the
//! store in evaluation (both rule sets), the training items' geometry equal and their
//! pixels close, a truncated file, a flipped byte, a stale dataset, a missing image,
//! part files swapped by hand, a record of another sample, parts of two datasets mixed
//! and a store of an earlier format each refused with the file named, in both modes;
//! `pred-zstd`, PNG and raw stores serving the same items. Here: the codecs' round trips
//! (NaN, -0.0 and denormal vertices; windows with wrapping colour differences, whole and
//! their centres alone; the window's parts covering it once), streams
//! cut, grown or of another size refused, records whose lengths do not add up refused
//! though their CRC matches.

use crate::crop::{CropSampling, CropTransform};
use arkit_core::error::{Error, Result};
use nalgebra::Point3;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::path::{Path, PathBuf};

/// The manifest's file name in a store folder.
pub const MANIFEST_FILE: &str = "crops.json";
/// The store format written and read here (1: before the records carried their
/// dataset, shard and key; 2: fixed-size records of raw windows, before the codecs and
/// the index; 3: raw meshes, before the window moved ahead of a compressed mesh; 4:
/// deflated meshes, before zstd's, which decode in a fifth of the time; 5: a
/// `pred-zstd` window in one frame, before its centre and the four parts of the ring
/// around it had a frame each, so that a crop decodes only what it reaches).
pub const FORMAT: u32 = 6;
/// Bytes of a `part-K.bin` header.
pub const HEADER_BYTES: u64 = 128;
/// Bytes of a `part-K.bin` footer (after the index): its magic, the index's CRC.
pub const FOOTER_BYTES: u64 = 16;
const MAGIC: &[u8; 8] = b"ARKCROP4";
const INDEX_MAGIC: &[u8; 8] = b"ARKCIDX4";
/// Largest `crops.json` read (its list of samples without pixels is what can grow).
const MAX_MANIFEST_BYTES: u64 = 256 << 20;
/// Bytes of a dataset fingerprint (SHA-256, lower-case hex) in headers and records.
pub const FINGERPRINT_BYTES: usize = 64;
/// Widest key field a store has (a key longer than this is refused by `crops`).
pub const MAX_KEY_BYTES: usize = 1024;
/// Where a record's fields start: CRC, status, row, shard, key length, fingerprint, key.
const AT_STATUS: usize = 4;
const AT_ROW: usize = 8;
const AT_SHARD: usize = 16;
const AT_KEY_LEN: usize = 20;
const AT_FINGERPRINT: usize = 24;
const AT_KEY: usize = AT_FINGERPRINT + FINGERPRINT_BYTES;

/// How a record's window is stored. Both are lossless: the window decoded is the
/// window `crops` resampled, byte for byte, so evaluation crops from either are those
/// cut from the decoded JPEG.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WindowCodec {
    /// The `W x W x 3` bytes as they are.
    Raw,
    /// A PNG (8-bit RGB, adaptive filters, zlib's default level).
    Png,
    /// The default: each pixel predicted from its decoded neighbours and the
    /// prediction errors compressed by zstd ([`predict_rect`]): green, then red and
    /// blue less green, each plane by the median edge detector of LOCO-I (JPEG-LS).
    /// The window's five parts ([`window_parts`]: the centre, which is the evaluation
    /// crop, and the four parts of the ring around it) are a zstd frame each, after the
    /// byte counts of the first four (four bytes each, little endian), so that
    /// evaluation decodes the centre alone and a training crop the parts it reaches.
    #[serde(rename = "pred-zstd")]
    PredZstd,
}

impl WindowCodec {
    /// Its name in `crops.json` and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            WindowCodec::Raw => "raw",
            WindowCodec::Png => "png",
            WindowCodec::PredZstd => "pred-zstd",
        }
    }

    fn code(self) -> u32 {
        match self {
            WindowCodec::Raw => 0,
            WindowCodec::Png => 1,
            WindowCodec::PredZstd => 2,
        }
    }
}

/// The bytes `codec` stores for `window`, the `W x W` RGB window of crop side `size`
/// ([`window_side`]).
pub fn encode_window(codec: WindowCodec, window: &image::RgbImage, size: u32) -> Result<Vec<u8>> {
    let w = window_side(size);
    if window.dimensions() != (w as u32, w as u32) {
        return Err(Error::invalid(
            "crop store",
            format!(
                "a {:?} window, crop side {size} has {w}x{w}",
                window.dimensions()
            ),
        ));
    }
    match codec {
        WindowCodec::Raw => Ok(window.as_raw().clone()),
        WindowCodec::Png => {
            use image::ImageEncoder;
            let mut out = Vec::with_capacity(window.len() / 2);
            image::codecs::png::PngEncoder::new_with_quality(
                &mut out,
                image::codecs::png::CompressionType::Default,
                image::codecs::png::FilterType::Adaptive,
            )
            .write_image(
                window.as_raw(),
                window.width(),
                window.height(),
                image::ExtendedColorType::Rgb8,
            )
            .map_err(|e| Error::invalid("crop store", format!("PNG encoding: {e}")))?;
            Ok(out)
        }
        WindowCodec::PredZstd => {
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
            let mut out =
                Vec::with_capacity(FRAME_TABLE + frames.iter().map(Vec::len).sum::<usize>());
            for f in &frames[..4] {
                out.extend_from_slice(&(f.len() as u32).to_le_bytes());
            }
            for f in &frames {
                out.extend_from_slice(f);
            }
            Ok(out)
        }
    }
}

/// zstd's level for [`WindowCodec::PredZstd`]: on the codec bench's windows, level 19
/// is about 1% smaller and takes 2-3x the time to encode (`crops` spends most of its
/// time here); below 15 the windows grow by 5% (level 13) to 15% (level 9).
const ZSTD_LEVEL: i32 = 15;

/// The prediction of a plane's value from the values already decoded: the median edge
/// detector of LOCO-I (JPEG-LS), the median of the left `a`, the above `b` and the
/// plane through them and the above-left `c` (`a + b - c`).
#[inline]
fn med(a: i16, b: i16, c: i16) -> i16 {
    a.min(b).max(a.max(b).min(a + b - c))
}

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

/// A rectangle of an image's pixels: columns `x..x + width` of rows `y..y + height`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PixelRect {
    /// Its first column.
    pub x: usize,
    /// Its first row.
    pub y: usize,
    /// Its columns.
    pub width: usize,
    /// Its rows.
    pub height: usize,
}

impl PixelRect {
    /// Its pixels.
    pub fn pixels(&self) -> usize {
        self.width * self.height
    }

    /// Whether it lies inside an image of `width x height` pixels.
    fn inside(&self, width: usize, height: usize) -> bool {
        self.x + self.width <= width && self.y + self.height <= height
    }

    /// Whether `other` lies inside it.
    pub fn contains(&self, other: &PixelRect) -> bool {
        self.x <= other.x
            && self.y <= other.y
            && other.x + other.width <= self.x + self.width
            && other.y + other.height <= self.y + self.height
    }
}

/// The parts of the window of crop side `size` that a [`WindowCodec::PredZstd`] window
/// stores: the evaluation crop (the window's centre `S x S`) first, then the ring of
/// margin `m` around it, as the band above (`W x m`), the strips left and right of the
/// centre (`m x S` each) and the band below (`W x m`). Each part is a zstd frame of its
/// own, so an evaluation item decodes the centre alone (`S^2` of the window's `W^2`
/// pixels: 62% at `S = 192`) and a training crop the centre and the parts it reaches
/// ([`WindowPart::Region`]). Each part is predicted as an image of its
/// own ([`predict_rect`]), the strips transposed (`S` wide and `m` tall):
/// upright, a strip is so narrow that the decoder's rows would spend half their steps
/// at its edges (1.6 against 0.9 ns a pixel). The parts cover the window, each pixel
/// once (tested).
pub fn window_parts(size: u32) -> [PixelRect; 5] {
    let (s, m) = (size as usize, margin(size) as usize);
    let w = s + 2 * m;
    let rect = |x, y, width, height| PixelRect {
        x,
        y,
        width,
        height,
    };
    [
        rect(m, m, s, s),
        rect(0, 0, w, m),
        rect(0, m, m, s),
        rect(m + s, m, m, s),
        rect(0, m + s, w, m),
    ]
}

/// `rect` of the RGB image `image` (`image_width` pixels wide) transposed: an RGB
/// image `rect.height` wide and `rect.width` tall, whose pixel `(y, x)` is the image's
/// pixel at row `rect.y + x`, column `rect.x + y`.
fn transposed(image: &[u8], image_width: usize, rect: PixelRect) -> Vec<u8> {
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
unsafe fn unpredict_rect_raw(errors: &[u8], rect: PixelRect, image: *mut u8, image_width: usize) {
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

/// The bytes one decoding of prediction errors reads and writes: `height` rows of
/// `width` pixels, pixel `(y, x)`'s errors at `src + y * src_row + 3 x`, its RGB bytes
/// written at `dst + y * dst_row + x * dst_col` (`dst_col` 3 for an image written as
/// it was predicted, or a row's bytes for one written transposed).
///
/// Its users' safety contract: every pixel's three error bytes are readable at its
/// `src` address (and, but for the last pixel of each row, the byte after them), its
/// three bytes writable at its `dst` address; the two are either the same bytes (`src
/// == dst`, `src_row == dst_row`, `dst_col == 3`: in place) or do not overlap.
#[derive(Clone, Copy)]
struct RectIo {
    src: *const u8,
    src_row: usize,
    dst: *mut u8,
    dst_row: usize,
    dst_col: usize,
    width: usize,
    height: usize,
}

impl RectIo {
    /// Pixel `(y, x)`'s errors.
    ///
    /// # Safety
    ///
    /// The pixel is inside the rectangle.
    #[inline(always)]
    unsafe fn src_at(&self, y: usize, x: usize) -> *const u8 {
        // SAFETY: the caller's.
        unsafe { self.src.add(y * self.src_row + 3 * x) }
    }

    /// Where pixel `(y, x)`'s RGB bytes go.
    ///
    /// # Safety
    ///
    /// The pixel is inside the rectangle.
    #[inline(always)]
    unsafe fn dst_at(&self, y: usize, x: usize) -> *mut u8 {
        // SAFETY: the caller's.
        unsafe { self.dst.add(y * self.dst_row + x * self.dst_col) }
    }
}

/// Decodes the prediction errors `io` names, pixel by pixel the same arithmetic as the
/// prediction. On x86-64 a pixel's three planes are decoded together in SSE2 lanes (part
/// of the baseline; VEX-encoded where the CPU has AVX2) and four rows at once, each a
/// pixel behind the one above it ([`unpredict_rows_sse2`]): a pixel needs its left
/// neighbour (the decoder's one serial dependency) and the row above's pixel and the one
/// before it, so the four rows' chains run side by side. Elsewhere one pixel at a time
/// ([`unpredict_scalar`]). Both are tested against the prediction's own per-pixel
/// definition, and each other.
///
/// # Safety
///
/// [`RectIo`]'s contract.
unsafe fn unpredict_io(io: RectIo) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 was detected; the bytes are the caller's.
        unsafe { unpredict_rows_vex(io) };
    } else {
        // SAFETY: SSE2 is part of the x86-64 baseline; the bytes are the caller's.
        unsafe { unpredict_rows_sse2::<false>(io) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    // SAFETY: the caller's.
    unsafe {
        unpredict_scalar(io)
    };
}

/// [`unpredict_io`] one pixel at a time: the first row and column apart, so the inner
/// loop has no case to choose, and the row above's plane values kept beside the row
/// being decoded.
///
/// # Safety
///
/// [`RectIo`]'s contract.
#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
unsafe fn unpredict_scalar(io: RectIo) {
    if io.width == 0 {
        return;
    }
    // Each decoded pixel's bytes from its plane predictions and its errors; returns
    // its plane values (green, red less green, blue less green).
    #[inline(always)]
    unsafe fn decode(io: &RectIo, y: usize, x: usize, p: [i16; 3]) -> [i16; 3] {
        // SAFETY: the pixel is inside the rectangle (the caller's); its errors are
        // read before its bytes are written.
        unsafe {
            let e = io.src_at(y, x);
            let [e0, e1, e2] = [e.read(), e.add(1).read(), e.add(2).read()];
            let g = (p[0] as u8).wrapping_add(e0);
            let r = (p[1] as u8).wrapping_add(e1).wrapping_add(g);
            let b = (p[2] as u8).wrapping_add(e2).wrapping_add(g);
            let d = io.dst_at(y, x);
            d.write(r);
            d.add(1).write(g);
            d.add(2).write(b);
            let g = g as i16;
            [g, r as i16 - g, b as i16 - g]
        }
    }
    let (mut prev, mut cur) = (vec![[0i16; 3]; io.width], vec![[0i16; 3]; io.width]);
    for y in 0..io.height {
        // SAFETY (every `decode` below): pixel (y, x) is inside the rectangle.
        // The first pixel: none (top-left) or the one above.
        let mut left = unsafe { decode(&io, y, 0, if y == 0 { [0; 3] } else { prev[0] }) };
        cur[0] = left;
        for x in 1..io.width {
            let p = if y == 0 {
                // The first row: the left neighbour.
                left
            } else {
                let (c, b) = (prev[x - 1], prev[x]);
                [
                    med(left[0], b[0], c[0]),
                    med(left[1], b[1], c[1]),
                    med(left[2], b[2], c[2]),
                ]
            };
            left = unsafe { decode(&io, y, x, p) };
            cur[x] = left;
        }
        std::mem::swap(&mut prev, &mut cur);
    }
}

/// [`unpredict_rows_sse2`] compiled for a CPU with AVX2: the same operations in the
/// three-operand (VEX) encodings, which spare the register copies of SSE2's two-operand
/// ones, and bands of [`WIDE_WAVEFRONT`] rows whose steps away from the window's edges
/// run in two registers of four rows ([`band_middle_avx2`]): 51 against 80 us a
/// 244x244 window (bands of four rows in one register, alternated, one core; 123 us
/// with a register per row).
///
/// # Safety
///
/// The CPU has AVX2; [`RectIo`]'s contract.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn unpredict_rows_vex(io: RectIo) {
    // SAFETY: the caller's.
    unsafe { unpredict_rows_sse2::<true>(io) }
}

/// [`unpredict_io`] in SSE2: a pixel's planes (green, red less green, blue
/// less green) in the first three `i16` lanes of a register, [`med`] lane by lane, and
/// rows decoded [`WAVEFRONT`] at a time, row `k` of a group at column `t - k` in step
/// `t`, so that every pixel's left, above and above-left neighbours are decoded before
/// it (the above ones by the row before in an earlier step) and the rows' dependency
/// chains overlap. With `WIDE` (only inlined into [`unpredict_rows_vex`], on a CPU with
/// AVX2) the steps away from the edges run in [`band_middle_avx2`].
///
/// # Safety
///
/// [`RectIo`]'s contract.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn unpredict_rows_sse2<const WIDE: bool>(io: RectIo) {
    // SAFETY: SSE2 is part of the x86-64 baseline (these run on every x86-64 CPU,
    // inlined into the AVX2 entry on CPUs that have it); the pointers are the caller's.
    unsafe {
        use std::arch::x86_64::*;
        let (width, height) = (io.width, io.height);
        if width == 0 || height == 0 {
            return;
        }
        let zero = _mm_setzero_si128();
        // The planes of the row above the rows being decoded, and the last of those rows'.
        let (mut above, mut below) = (vec![zero; width], vec![zero; width]);
        // The wide bands' staging ([`BandState::stage`]).
        let mut stage = if WIDE {
            vec![[0u64; 4]; width]
        } else {
            Vec::new()
        };
        // The first row: the left neighbour predicts (none for the first pixel).
        let mut left = zero;
        for (x, out) in above.iter_mut().enumerate() {
            // SAFETY: pixel (0, x) is inside the rectangle.
            left = decode_pixel_sse2(&io, 0, x, left);
            *out = left;
        }
        let mut y = 1;
        if WIDE {
            while y + WIDE_WAVEFRONT <= height {
                // SAFETY: rows y..y + WIDE_WAVEFRONT are inside the rectangle.
                unpredict_band_sse2::<WIDE_WAVEFRONT, true>(&io, y, &above, &mut below, &mut stage);
                std::mem::swap(&mut above, &mut below);
                y += WIDE_WAVEFRONT;
            }
        }
        while y + WAVEFRONT <= height {
            // SAFETY: rows y..y + WAVEFRONT are inside the rectangle.
            unpredict_band_sse2::<WAVEFRONT, false>(&io, y, &above, &mut below, &mut []);
            std::mem::swap(&mut above, &mut below);
            y += WAVEFRONT;
        }
        // The last one to three rows as one band, their chains side by side too.
        // SAFETY: rows y..height are inside the rectangle.
        match height - y {
            3 => unpredict_band_sse2::<3, false>(&io, y, &above, &mut below, &mut []),
            2 => unpredict_band_sse2::<2, false>(&io, y, &above, &mut below, &mut []),
            1 => unpredict_band_sse2::<1, false>(&io, y, &above, &mut below, &mut []),
            _ => {}
        }
    }
}

/// The rows [`unpredict_rows_sse2`] decodes side by side (a row's state in a register
/// of its own).
#[cfg(target_arch = "x86_64")]
const WAVEFRONT: usize = 4;

/// The rows [`unpredict_rows_vex`] decodes side by side: two registers of four rows
/// ([`band_middle_avx2`]).
#[cfg(target_arch = "x86_64")]
const WIDE_WAVEFRONT: usize = 8;

/// Rows `y0..y0 + K` of [`unpredict_rows_sse2`] (`y0 >= 1`, all inside the rectangle):
/// `above` holds row `y0 - 1`'s planes, `below` gets row `y0 + K - 1`'s. The steps
/// where every row is past its first column and before its last run without a case to
/// choose, so the rows' state stays in registers.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn unpredict_band_sse2<const K: usize, const WIDE: bool>(
    io: &RectIo,
    y0: usize,
    above: &[std::arch::x86_64::__m128i],
    below: &mut [std::arch::x86_64::__m128i],
    stage: &mut [[u64; 4]],
) {
    // SAFETY: SSE2 is part of the x86-64 baseline (these run on every x86-64 CPU,
    // inlined into the AVX2 entry on CPUs that have it); the pointers are the caller's.
    unsafe {
        use std::arch::x86_64::*;
        // Row k's planes at its last decoded column and at the one before.
        let mut last = [_mm_setzero_si128(); K];
        let mut before = [_mm_setzero_si128(); K];
        let width = io.width;
        let end = width + K - 1;
        // Steps t in inner..outer: every row k at a column t - k in 1..width - 1.
        let (inner, outer) = if width > K + 1 {
            (K, width - 1)
        } else {
            (end, end)
        };
        let mut band = BandState {
            io,
            y0,
            above,
            below,
            stage,
        };
        for t in 0..inner {
            // SAFETY: rows y0..y0 + K are inside the rectangle (the caller's).
            band_step::<K, true>(&mut band, t, &mut last, &mut before);
        }
        if let (true, Ok(last), Ok(before)) = (
            WIDE,
            <&mut [__m128i; WIDE_WAVEFRONT]>::try_from(&mut last[..]),
            <&mut [__m128i; WIDE_WAVEFRONT]>::try_from(&mut before[..]),
        ) {
            // SAFETY: WIDE runs only on a CPU with AVX2 ([`unpredict_rows_vex`]); the
            // steps are the band's inner ones.
            band_middle_avx2(&mut band, inner..outer, last, before);
        } else {
            for t in inner..outer {
                // SAFETY: as above.
                band_step::<K, false>(&mut band, t, &mut last, &mut before);
            }
        }
        for t in outer..end {
            // SAFETY: as above.
            band_step::<K, true>(&mut band, t, &mut last, &mut before);
        }
    }
}

/// What every step of [`unpredict_band_sse2`] reads or writes besides the rows' state.
#[cfg(target_arch = "x86_64")]
struct BandState<'a> {
    io: &'a RectIo,
    y0: usize,
    above: &'a [std::arch::x86_64::__m128i],
    below: &'a mut [std::arch::x86_64::__m128i],
    /// [`band_middle_avx2`]'s second register per column (`width` of them; empty
    /// elsewhere), whose last row becomes `below` after the steps.
    stage: &'a mut [[u64; 4]],
}

/// Step `t` of [`unpredict_band_sse2`]: row `k` decodes column `t - k`, from the last
/// row up, so that row `k` reads row `k - 1`'s last two pixels before row `k - 1`
/// moves on. With `EDGE` false every row is at a column in `1..width - 1` (no first
/// column, no row end), and the cases are compiled out.
///
/// # Safety
///
/// Rows `y0..y0 + K` are inside the rectangle of `band.io` ([`RectIo`]'s contract).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn band_step<const K: usize, const EDGE: bool>(
    band: &mut BandState<'_>,
    t: usize,
    last: &mut [std::arch::x86_64::__m128i; K],
    before: &mut [std::arch::x86_64::__m128i; K],
) {
    // SAFETY: SSE2 is part of the x86-64 baseline (these run on every x86-64 CPU,
    // inlined into the AVX2 entry on CPUs that have it); the pointers are the caller's.
    unsafe {
        use std::arch::x86_64::*;
        let med = |a: __m128i, b: __m128i, c: __m128i| {
            let plane = _mm_sub_epi16(_mm_add_epi16(a, b), c);
            _mm_max_epi16(
                _mm_min_epi16(a, b),
                _mm_min_epi16(_mm_max_epi16(a, b), plane),
            )
        };
        let io = band.io;
        for k in (0..K).rev() {
            let x = t.wrapping_sub(k);
            if EDGE && x >= io.width {
                continue;
            }
            let (b, c) = match k {
                0 if EDGE && x == 0 => (band.above[0], band.above[0]),
                0 => (band.above[x], band.above[x - 1]),
                _ => (last[k - 1], before[k - 1]),
            };
            // The first column: the pixel above predicts.
            let p = if EDGE && x == 0 {
                b
            } else {
                med(last[k], b, c)
            };
            let y = band.y0 + k;
            let planes = if EDGE {
                // SAFETY: pixel (y, x) is inside the rectangle.
                decode_pixel_sse2(io, y, x, p)
            } else {
                // SAFETY: as above, and x + 1 < width: the fourth byte is the next
                // pixel's.
                decode_inner_pixel_sse2(io.src_at(y, x), io.dst_at(y, x), p)
            };
            before[k] = last[k];
            last[k] = planes;
            if k == K - 1 {
                band.below[x] = planes;
            }
        }
    }
}

/// The inner steps `steps` of a band of eight rows ([`unpredict_band_sse2`]) in two
/// AVX2 registers of four rows, row `k`'s planes in 64-bit lane `k % 4` (`i16` lanes
/// `4 (k % 4)..4 (k % 4) + 3`, the fourth zero) of register `k / 4`, where
/// [`band_step`] does each row in a register of its own. Per step and register one
/// median and one decode; the rows above move one row down by a lane permute (the
/// first register's lane 3 into the second's lane 0). The two registers' dependency
/// chains overlap: the second reads only the first's values of the step before. The
/// same arithmetic lane by lane, so the same bytes (tested against the scalar
/// decoder). `last` and `before` hold the rows' state as [`band_step`] keeps it, on
/// entry and on return.
///
/// # Safety
///
/// The CPU has AVX2; `band`'s eight rows are inside its rectangle ([`RectIo`]'s
/// contract), and every step is an inner one: each row at a column in `1..width - 1`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn band_middle_avx2(
    band: &mut BandState<'_>,
    steps: std::ops::Range<usize>,
    last: &mut [std::arch::x86_64::__m128i; WIDE_WAVEFRONT],
    before: &mut [std::arch::x86_64::__m128i; WIDE_WAVEFRONT],
) {
    use std::arch::x86_64::*;
    let io = *band.io;
    if steps.is_empty() {
        return;
    }
    assert!(
        steps.start >= WIDE_WAVEFRONT
            && steps.end < io.width
            && band.y0 + WIDE_WAVEFRONT <= io.height
            && band.stage.len() == io.width
            && band.below.len() == io.width,
        "inner steps of a band inside the rectangle"
    );
    let zero = _mm_setzero_si128();
    // Four rows' xmm state (planes in lanes 0-2) to and from the 64-bit lanes of one
    // register.
    let join = |r: &[__m128i]| {
        _mm256_set_m128i(
            _mm_unpacklo_epi64(r[2], r[3]),
            _mm_unpacklo_epi64(r[0], r[1]),
        )
    };
    let split = |v: __m256i, r: &mut [__m128i]| {
        let (lo, hi) = (_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
        r[0] = _mm_move_epi64(lo);
        r[1] = _mm_unpackhi_epi64(lo, zero);
        r[2] = _mm_move_epi64(hi);
        r[3] = _mm_unpackhi_epi64(hi, zero);
    };
    // Lanes 0-2 of every row.
    let planes_mask = _mm256_set1_epi64x(0x0000_00ff_00ff_00ff);
    // Green modulo 256 (the low byte of the row's lane 0) into its lanes 1 and 2, lanes
    // 0 and 3 zero.
    let green_of = _mm256_setr_epi8(
        -128, -128, 0, -128, 0, -128, -128, -128, -128, -128, 8, -128, 8, -128, -128, -128, -128,
        -128, 0, -128, 0, -128, -128, -128, -128, -128, 8, -128, 8, -128, -128, -128,
    );
    // A row's red, green and blue (lanes 1, 0, 2) as its first three bytes.
    let rgb_of = _mm256_setr_epi8(
        2, 0, 4, -128, 10, 8, 12, -128, -128, -128, -128, -128, -128, -128, -128, -128, 2, 0, 4,
        -128, 10, 8, 12, -128, -128, -128, -128, -128, -128, -128, -128, -128,
    );
    // Rows 0-3 (`_a`) and 4-7 (`_b`): planes at the last decoded column and the one before.
    let (mut last_a, mut before_a) = (join(&last[..4]), join(&before[..4]));
    let (mut last_b, mut before_b) = (join(&last[4..]), join(&before[4..]));
    // Row k's pixel of step t is a row down and a pixel left of row k - 1's: its errors
    // `src_step` bytes after, its bytes `dst_step` after (before, for a transposed
    // destination), offsets computed one by one (an array of them would be built in
    // vector lanes and each taken out again).
    let src_step = io.src_row - 3;
    let dst_step = io.dst_row as isize - io.dst_col as isize;
    // One register's rows `k0..k0 + 4` of a step whose row 0 pixel goes to `dst0`,
    // from their left `a`, above `b` and above-left `c` planes and their errors: writes
    // each row's pixel and returns the rows' planes.
    let decode = |a: __m256i, b: __m256i, c: __m256i, errors: __m256i, dst0: *mut u8, k0: usize| {
        let plane = _mm256_sub_epi16(_mm256_add_epi16(a, b), c);
        let p = _mm256_max_epi16(
            _mm256_min_epi16(a, b),
            _mm256_min_epi16(_mm256_max_epi16(a, b), plane),
        );
        // Green, red less green and blue less green, modulo 256 once masked.
        let sums = _mm256_add_epi16(p, errors);
        let green = _mm256_shuffle_epi8(sums, green_of);
        let grb = _mm256_and_si256(_mm256_add_epi16(sums, green), planes_mask);
        // Each half's low 64 bits (two rows' bytes, `rgb_of`) moved to a general
        // register, then stored from there: lane extracts into memory would each take
        // the shuffle unit, which is what a step waits on.
        let rgb = _mm256_shuffle_epi8(grb, rgb_of);
        let (mut lo, mut hi) = (
            _mm_cvtsi128_si64(_mm256_castsi256_si128(rgb)) as u64,
            _mm_cvtsi128_si64(_mm256_extracti128_si256::<1>(rgb)) as u64,
        );
        // SAFETY: an empty instruction: the values stay in general registers (else
        // the compiler folds the moves and shifts back into lane extracts).
        unsafe {
            std::arch::asm!("/* {0} {1} */", inout(reg) lo, inout(reg) hi, options(pure, nomem, nostack))
        };
        let out = [lo as u32, (lo >> 32) as u32, hi as u32, (hi >> 32) as u32];
        for (k, &o) in (k0..k0 + 4).zip(&out) {
            // SAFETY: the caller's (below): the pixel is inside the rectangle.
            // Three bytes (two and one), as `decode_inner_pixel_sse2` writes them.
            unsafe {
                let ptr = dst0.offset(k as isize * dst_step);
                ptr.cast::<u16>().write_unaligned(o as u16);
                ptr.add(2).write((o >> 16) as u8);
            }
        }
        _mm256_sub_epi16(grb, green)
    };
    // Above: row k - 1's last pixel, row 0's from the band above, row 4's from row 3
    // (the first register's lane 3). Above-left: the pixel before those, which is the
    // step before's above.
    let down = |v: __m256i| _mm256_permute4x64_epi64::<0b10_01_00_00>(v);
    let down_from = |a: __m256i, b: __m256i| {
        _mm256_alignr_epi8::<8>(b, _mm256_permute2x128_si256::<0x21>(a, b))
    };
    // SAFETY: `above` holds a value for every column, and `steps.start >= 1`.
    let above = |x: usize| unsafe { _mm256_castsi128_si256(*band.above.get_unchecked(x)) };
    let mut c_a = _mm256_blend_epi32::<0b11>(down(before_a), above(steps.start - 1));
    let mut c_b = down_from(before_a, before_b);
    let first = steps.start;
    let stage = band.stage.as_mut_ptr();
    for t in steps.clone() {
        // SAFETY: every row's pixel t - k is an inner one (the caller's), so its four
        // error bytes (its three and the next pixel's first) are readable and its
        // three bytes writable ([`RectIo`]); `stage` holds a value for every column
        // (asserted above).
        unsafe {
            let (src0, dst0) = (io.src_at(band.y0, t), io.dst_at(band.y0, t));
            let read = |k: usize| src0.add(k * src_step).cast::<i32>().read_unaligned();
            // Lane 3 of each row gets the next pixel's first byte: it never reaches a
            // result (green is taken from lane 0, the sums are masked to lanes 0-2).
            let errors = |k: usize| {
                _mm256_cvtepu8_epi16(_mm_setr_epi32(
                    read(k),
                    read(k + 1),
                    read(k + 2),
                    read(k + 3),
                ))
            };
            let b_a = _mm256_blend_epi32::<0b11>(down(last_a), above(t));
            let b_b = down_from(last_a, last_b);
            let new_a = decode(last_a, b_a, c_a, errors(0), dst0, 0);
            let new_b = decode(last_b, b_b, c_b, errors(4), dst0, 4);
            (before_a, last_a, c_a) = (last_a, new_a, b_a);
            (before_b, last_b, c_b) = (last_b, new_b, b_b);
            // The whole register kept (a plain store), its last row taken out below.
            _mm256_storeu_si256(stage.add(t - (WIDE_WAVEFRONT - 1)).cast(), last_b);
        }
    }
    for x in first - (WIDE_WAVEFRONT - 1)..steps.end - (WIDE_WAVEFRONT - 1) {
        // Row 7's planes: the register's lane 3, the upper half zero.
        // SAFETY: SSE2 is part of the x86-64 baseline; the eight bytes are `stage[x][3]`.
        band.below[x] = unsafe { _mm_loadl_epi64(band.stage[x][3..].as_ptr().cast()) };
    }
    split(last_a, &mut last[..4]);
    split(last_b, &mut last[4..]);
    split(before_a, &mut before[..4]);
    split(before_b, &mut before[4..]);
}

/// Decodes pixel `(y, x)` of `io`'s rectangle from its plane predictions `p` (lanes
/// 0-2; lane 3 and up zero): its three error bytes give its RGB bytes, and its planes
/// come back in lanes 0-2 (the others zero). Reads and writes the pixel's three bytes
/// only (for the rectangle's last pixels, where no fourth byte follows).
///
/// # Safety
///
/// `(y, x)` is inside the rectangle ([`RectIo`]'s contract).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn decode_pixel_sse2(
    io: &RectIo,
    y: usize,
    x: usize,
    p: std::arch::x86_64::__m128i,
) -> std::arch::x86_64::__m128i {
    debug_assert!(y < io.height && x < io.width);
    let mut four = [0u8; 4];
    // SAFETY: the pixel's three bytes are readable and writable (the caller's); `four`
    // holds four bytes.
    unsafe {
        std::ptr::copy_nonoverlapping(io.src_at(y, x), four.as_mut_ptr(), 3);
        decode_inner_pixel_sse2(four.as_ptr(), io.dst_at(y, x), p)
    }
}

/// [`decode_pixel_sse2`] of the pixel whose errors start at `src`, with a fourth byte
/// after them (read with them, and left as it was), its RGB bytes written at `dst`.
///
/// # Safety
///
/// Four bytes are readable at `src`, three writable at `dst`; if the two overlap, they
/// are the same address.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn decode_inner_pixel_sse2(
    src: *const u8,
    dst: *mut u8,
    p: std::arch::x86_64::__m128i,
) -> std::arch::x86_64::__m128i {
    // SAFETY: SSE2 is part of the x86-64 baseline (these run on every x86-64 CPU,
    // inlined into the AVX2 entry on CPUs that have it); the pointers are the caller's.
    unsafe {
        use std::arch::x86_64::*;
        let read = src.cast::<u32>().read_unaligned();
        let zero = _mm_setzero_si128();
        let low_byte = _mm_set1_epi16(0xff);
        let errors = _mm_unpacklo_epi8(_mm_cvtsi32_si128(read as i32), zero);
        // Green, and red and blue less green, each modulo 256.
        let sums = _mm_and_si128(_mm_add_epi16(p, errors), low_byte);
        // Green in lanes 1 and 2: red and blue are their planes plus green, modulo 256.
        let green = _mm_and_si128(
            _mm_shufflelo_epi16::<0>(sums),
            _mm_setr_epi16(0, -1, -1, 0, 0, 0, 0, 0),
        );
        let grb = _mm_and_si128(
            _mm_add_epi16(sums, green),
            _mm_setr_epi16(0xff, 0xff, 0xff, 0, 0, 0, 0, 0),
        );
        // Lanes red, green, blue, packed to bytes.
        let rgb = _mm_packus_epi16(_mm_shufflelo_epi16::<0b11_10_00_01>(grb), zero);
        let out = _mm_cvtsi128_si32(rgb) as u32;
        // Three bytes written (two and one): in place, a four-byte store would overlap
        // the next pixel's four-byte read, which the CPU could then not forward from
        // the store; elsewhere, it would write past the pixel.
        dst.cast::<u16>().write_unaligned(out as u16);
        dst.add(2).write((out >> 16) as u8);
        _mm_sub_epi16(grb, green)
    }
}

/// Bytes before a [`WindowCodec::PredZstd`] window's frames: the byte counts of its
/// first four.
const FRAME_TABLE: usize = 16;

/// What of a stored window [`decode_window`] and [`StoredRecord::decode`] decode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WindowPart {
    /// The whole `W x W` window.
    Whole,
    /// Its centre `S x S`, the evaluation crop: with [`WindowCodec::PredZstd`] the
    /// ring's frames are not decoded.
    Centre,
    /// The `W x W` window with at least the pixels of this rectangle of it decoded
    /// (what a training crop reaches, [`crate::crop::CropTransform::window_reach`]):
    /// with [`WindowCodec::PredZstd`] the parts of the ring it does not meet are not
    /// decoded, and their pixels are zero.
    Region(PixelRect),
}

/// The pixels `bytes` (stored by `codec`) hold of the window of crop side `size`: the
/// `W x W x 3` window (for a region, with the parts it does not meet zero where the
/// codec stores parts) or its centre's `S x S x 3` bytes, as `part` asks. Bounded: the
/// output is allocated from `size` (the store's, checked against its manifest), never
/// from a size read from `bytes`; a zstd frame that gives more or fewer bytes than its
/// part has is refused, and a PNG whose header is not `W x W` 8-bit RGB is refused
/// before any pixel is decoded.
pub fn decode_window(
    codec: WindowCodec,
    bytes: &[u8],
    size: u32,
    part: WindowPart,
) -> Result<Vec<u8>> {
    let side = window_side(size);
    let want = 3 * side * side;
    let whole = match codec {
        WindowCodec::Raw => {
            if bytes.len() != want {
                return Err(Error::invalid(
                    "crop store",
                    format!("a raw window of {} bytes, expected {want}", bytes.len()),
                ));
            }
            bytes.to_vec()
        }
        WindowCodec::Png => {
            use image::ImageDecoder;
            let bad = |e: String| Error::invalid("crop store", format!("its PNG window: {e}"));
            let mut decoder = image::codecs::png::PngDecoder::new(std::io::Cursor::new(bytes))
                .map_err(|e| bad(e.to_string()))?;
            let mut limits = image::Limits::default();
            limits.max_image_width = Some(side as u32);
            limits.max_image_height = Some(side as u32);
            limits.max_alloc = Some(2 * want as u64 + (1 << 16));
            decoder.set_limits(limits).map_err(|e| bad(e.to_string()))?;
            if decoder.dimensions() != (side as u32, side as u32)
                || decoder.color_type() != image::ColorType::Rgb8
                || decoder.total_bytes() != want as u64
            {
                return Err(bad(format!(
                    "{:?} {:?}, expected {side}x{side} Rgb8",
                    decoder.dimensions(),
                    decoder.color_type()
                )));
            }
            let mut out = vec![0u8; want];
            decoder
                .read_image(&mut out)
                .map_err(|e| bad(e.to_string()))?;
            out
        }
        WindowCodec::PredZstd => return decode_pred_zstd(bytes, size, part),
    };
    Ok(match part {
        WindowPart::Whole | WindowPart::Region(_) => whole,
        WindowPart::Centre => window_centre(&whole, size),
    })
}

/// The centre `S x S x 3` bytes of the `W x W x 3` window `window` of crop side `size`.
fn window_centre(window: &[u8], size: u32) -> Vec<u8> {
    let (s, w, m) = (size as usize, window_side(size), margin(size) as usize);
    let mut out = Vec::with_capacity(3 * s * s);
    for r in m..m + s {
        out.extend_from_slice(&window[3 * (r * w + m)..3 * (r * w + m + s)]);
    }
    out
}

/// [`decode_window`] of a [`WindowCodec::PredZstd`] window: the centre's frame, then
/// the frames of the ring's parts `part` asks for (all for the whole window, those
/// meeting a region's rectangle, none for the centre).
fn decode_pred_zstd(bytes: &[u8], size: u32, part: WindowPart) -> Result<Vec<u8>> {
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
        WindowPart::Region(a) => {
            a.x < r.x + r.width
                && r.x < a.x + a.width
                && a.y < r.y + r.height
                && r.y < a.y + a.height
        }
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

/// `bytes` decoded as zstd frames into a new buffer of room for `most` bytes, never
/// more (a frame that would give more is an error; one that gives fewer returns them,
/// for the caller to refuse): the buffer is not zeroed first, and the decompression
/// context is one the thread keeps.
fn zstd_frame(bytes: &[u8], most: usize) -> std::io::Result<Vec<u8>> {
    thread_local! {
        static CONTEXT: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
            const { std::cell::RefCell::new(None) };
    }
    CONTEXT.with_borrow_mut(|context| {
        let d = match context {
            Some(d) => d,
            None => context.insert(zstd::bulk::Decompressor::new()?),
        };
        let mut out = Vec::with_capacity(most);
        // Into the buffer's capacity: `most` bytes, or more if the allocator gave more,
        // which the callers' length checks refuse.
        d.decompress_to_buffer(bytes, &mut out)?;
        Ok(out)
    })
}

/// The bytes a record stores for `verts`: their float32 bits, coordinate by coordinate
/// (every x, then every y, then every z) and byte plane by byte plane (the lowest byte
/// of each value, then the next, ...), compressed by zstd (one frame, level 19). The
/// planes put the values' sign and exponent bytes, which vary little from one vertex to
/// the next, side by side, where zstd finds them; the bits are kept, NaN, -0.0 and
/// denormals included. (Deflate at its best level gives 1-2% more bytes and inflates
/// in about five times zstd's time.)
pub fn encode_mesh(verts: &[Point3<f32>]) -> Vec<u8> {
    let n = verts.len();
    let mut planes = vec![0u8; 12 * n];
    for (i, p) in verts.iter().enumerate() {
        for (c, v) in [p.x, p.y, p.z].into_iter().enumerate() {
            for (k, b) in v.to_bits().to_le_bytes().into_iter().enumerate() {
                planes[(4 * c + k) * n + i] = b;
            }
        }
    }
    zstd::bulk::compress(&planes, MESH_LEVEL).expect("zstd compresses any bytes into a Vec")
}

/// zstd's level for meshes: its slowest, written once; its decoding is as fast as at
/// any other level.
const MESH_LEVEL: i32 = 19;

/// The most bytes a stored mesh of `vertex_count` vertices can take: zstd's bound for
/// its `12 V` bytes (stored blocks and the frame's header).
pub fn max_mesh_bytes(vertex_count: usize) -> usize {
    zstd::zstd_safe::compress_bound(12 * vertex_count)
}

/// The `vertex_count` vertices that `bytes` ([`encode_mesh`]) hold. Bounded: the frame
/// is decoded into a buffer of exactly `12 V` bytes, and one that would give more or
/// fewer, or is not a zstd frame, is refused.
pub fn decode_mesh(bytes: &[u8], vertex_count: usize) -> Result<Vec<Point3<f32>>> {
    let n = vertex_count;
    let want = 12 * n;
    let bad = |why: String| Error::invalid("crop store", format!("its mesh: {why}"));
    let planes = zstd_frame(bytes, want).map_err(|e| {
        bad(format!(
            "not a zstd frame of at most the {want} bytes of {n} vertices ({e})"
        ))
    })?;
    if planes.len() != want {
        return Err(bad(format!(
            "{} bytes, expected the {want} of {n} vertices",
            planes.len()
        )));
    }
    let value = |i: usize, c: usize| {
        let b = |k: usize| planes[(4 * c + k) * n + i];
        f32::from_bits(u32::from_le_bytes([b(0), b(1), b(2), b(3)]))
    };
    Ok((0..n)
        .map(|i| Point3::new(value(i, 0), value(i, 1), value(i, 2)))
        .collect())
}

/// Bytes of a record before the window: CRC, status, row, shard, key length, fingerprint,
/// the key field (`key_bytes` wide), the box, the window's and the mesh's lengths.
fn record_prefix(key_bytes: usize) -> usize {
    AT_KEY + key_bytes + 4 * 8 + 8
}

/// The key field's width for a dataset whose longest key has `longest` bytes: a
/// multiple of 8, at least 8.
pub fn key_field_bytes(longest: usize) -> usize {
    longest.max(1).div_ceil(8) * 8
}

/// Crop pixels kept beyond each edge of an `S`-pixel evaluation crop: the training
/// jitter moves the box centre by up to 0.15 of the landmarks' box size (0.1 of the
/// crop's side, whose half is 0.75 of that size) and scales its half-side by up to
/// 1.05 (0.025 of the side more), so a jittered box reaches `0.125 S` past the
/// evaluation crop; two pixels more cover the bilinear taps and the official box's
/// integer rounding.
pub fn margin(size: u32) -> u32 {
    size.div_ceil(8) + 2
}

/// Side of a stored window for crop side `size`.
pub fn window_side(size: u32) -> usize {
    (size + 2 * margin(size)) as usize
}

/// Bytes of one record with raw pixels for crop side `size`, a stored mesh of
/// `mesh_bytes` ([`encode_mesh`]) and a key field of `key_bytes` ([`key_field_bytes`]).
pub fn raw_record_bytes(size: u32, mesh_bytes: usize, key_bytes: usize) -> u64 {
    let w = window_side(size) as u64;
    record_prefix(key_bytes) as u64 + mesh_bytes as u64 + 3 * w * w
}

/// The largest window a store accepts: the raw bytes, plus room for a compressed one
/// that does not compress (a PNG's filter bytes, chunks and deflate's stored blocks, a
/// WebP's headers: well under this).
fn max_window_bytes(size: u32) -> usize {
    let w = window_side(size);
    3 * w * w + 3 * w * w / 8 + 4096
}

/// The largest record a store accepts: the largest window and the largest mesh.
fn max_record_bytes(size: u32, vertex_count: usize, key_bytes: usize) -> u64 {
    (record_prefix(key_bytes) + max_window_bytes(size) + max_mesh_bytes(vertex_count)) as u64
}

/// `crops.json`: what a store holds and what it was made from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CropStoreManifest {
    /// [`FORMAT`].
    pub format: u32,
    /// The rules the boxes and windows follow: `"exact"` or `"official"`.
    pub compat: String,
    /// How the windows are stored.
    pub codec: WindowCodec,
    /// Crop side `S`.
    pub img_size: u32,
    /// [`margin`]`(S)`.
    pub margin: u32,
    /// Vertices per mesh.
    pub vertex_count: usize,
    /// Width of each record's key field ([`key_field_bytes`] of the longest key).
    pub key_bytes: usize,
    /// [`crate::render::dataset::dataset_fingerprint`] of the dataset stored.
    pub dataset_fingerprint: String,
    /// One entry per samples shard, by index.
    pub shards: Vec<CropShard>,
    /// The samples stored without pixels, and why.
    pub missing: Vec<MissingCrop>,
}

/// One `part-K.bin`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CropShard {
    /// The samples shard `K`.
    pub index: usize,
    /// `part-K.bin`, relative to the store folder.
    pub file: String,
    /// Records (the shard's rows).
    pub records: usize,
    /// The file's bytes (header, records, index, footer).
    pub bytes: u64,
}

/// A sample stored without pixels.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MissingCrop {
    /// Its samples shard.
    pub shard: usize,
    /// Its row there.
    pub row: usize,
    /// `subject/action/img_id`.
    pub key: String,
    /// Why (the error, naming the file).
    pub reason: String,
}

/// One sample's stored values, its window decoded.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredCrop {
    /// The evaluation crop's box.
    pub eval_crop: CropTransform,
    /// The mesh.
    pub verts: Vec<Point3<f32>>,
    /// The window, `W x W` RGB (`W =` [`window_side`]); or, decoded as
    /// [`WindowPart::Centre`], its centre `S x S` only.
    pub window: image::RgbImage,
    /// What of its window `window` holds.
    pub part: WindowPart,
}

impl StoredCrop {
    /// The evaluation crop: the window's centre `S x S` (RGB bytes, row-major).
    pub fn centre(&self) -> Vec<u8> {
        match self.part {
            WindowPart::Centre => self.window.as_raw().clone(),
            _ => window_centre(self.window.as_raw(), self.eval_crop.size),
        }
    }

    /// The pixels of `crop` (a box in the same image, of the same sampling and size):
    /// the centre when it is the evaluation crop, else resampled from the window. A
    /// crop that reaches pixels of the window not decoded (read as its centre, or as a
    /// region the crop reaches past) is an error.
    pub fn crop_pixels(&self, crop: &CropTransform) -> Result<Vec<u8>> {
        if *crop == self.eval_crop {
            return Ok(self.centre());
        }
        let in_window = crop.in_window(&self.eval_crop, window_first(self.eval_crop.size));
        let decoded = match self.part {
            WindowPart::Whole => true,
            WindowPart::Centre => false,
            WindowPart::Region(r) => reach_in_window(&in_window, self.window.width())
                .is_none_or(|reach| r.contains(&reach)),
        };
        if !decoded {
            return Err(Error::invalid(
                "crop store",
                format!(
                    "a crop reaching pixels of the window that were not decoded (decoded: {:?})",
                    self.part
                ),
            ));
        }
        Ok(in_window.crop_window(&self.window, 0, crop.size as usize))
    }
}

/// The first pixel of the window of crop side `size` in the evaluation crop's pixel
/// grid, along each axis: `-m`.
fn window_first(size: u32) -> i64 {
    -(margin(size) as i64)
}

/// The pixels of a `side x side` window that the crop `in_window` (in the window's pixel
/// grid) reaches, clipped to the window; `None` when it reaches none.
fn reach_in_window(in_window: &CropTransform, side: u32) -> Option<PixelRect> {
    let [(x0, x1), (y0, y1)] = in_window.window_reach(0, in_window.size as usize)?;
    let clip = |lo: i64, hi: i64| {
        let (lo, hi) = (lo.max(0), hi.min(side as i64 - 1));
        (lo <= hi).then_some((lo as usize, (hi - lo + 1) as usize))
    };
    let ((x, width), (y, height)) = (clip(x0, x1)?, clip(y0, y1)?);
    Some(PixelRect {
        x,
        y,
        width,
        height,
    })
}

/// A record read and checked ([`CropStore::read`]): its box and mesh decoded, its window
/// as stored, decoded when asked for, as much of it as is asked for.
#[derive(Clone, Debug)]
pub struct StoredRecord {
    /// The evaluation crop's box.
    pub eval_crop: CropTransform,
    /// The mesh.
    pub verts: Vec<Point3<f32>>,
    window: StoredWindow,
    codec: WindowCodec,
    /// The part file and the row, which errors name.
    path: PathBuf,
    row: usize,
}

/// A record's window as read.
#[derive(Clone, Debug)]
enum StoredWindow {
    /// A raw window: its pixels.
    Raw(image::RgbImage),
    /// Any other codec's bytes.
    Encoded(Vec<u8>),
}

impl StoredRecord {
    /// Its window's `part` decoded ([`decode_window`]). An error names the part file
    /// and the record.
    pub fn decode(&self, part: WindowPart) -> Result<StoredCrop> {
        let size = self.eval_crop.size;
        let pixels = match (&self.window, part) {
            (StoredWindow::Raw(w), WindowPart::Centre) => window_centre(w.as_raw(), size),
            (StoredWindow::Raw(w), _) => w.as_raw().clone(),
            (StoredWindow::Encoded(bytes), part) => decode_window(self.codec, bytes, size, part)
                .map_err(|e| {
                    Error::format(
                        &self.path,
                        format!("record {}: {e}; run `arkit-tool crops` again", self.row),
                    )
                })?,
        };
        let w = match part {
            WindowPart::Centre => size,
            _ => window_side(size) as u32,
        };
        let window = image::RgbImage::from_raw(w, w, pixels).ok_or_else(|| {
            Error::format(
                &self.path,
                format!("record {}: a window of another size than {w}x{w}", self.row),
            )
        })?;
        Ok(StoredCrop {
            eval_crop: self.eval_crop,
            verts: self.verts.clone(),
            window,
            part,
        })
    }

    /// The pixels of `crop` (a box in the same image, of the same sampling and size,
    /// as [`StoredCrop::crop_pixels`]), decoding only what it needs: the centre for the
    /// evaluation crop, else the parts of the window the crop reaches
    /// ([`WindowPart::Region`]).
    pub fn crop_pixels(&self, crop: &CropTransform) -> Result<Vec<u8>> {
        let first = window_first(self.eval_crop.size);
        if let StoredWindow::Raw(window) = &self.window {
            // Raw pixels are resampled where they were read.
            return Ok(if *crop == self.eval_crop {
                window_centre(window.as_raw(), self.eval_crop.size)
            } else {
                crop.in_window(&self.eval_crop, first)
                    .crop_window(window, 0, crop.size as usize)
            });
        }
        let part = if *crop == self.eval_crop {
            WindowPart::Centre
        } else {
            let side = window_side(self.eval_crop.size) as u32;
            let reach = reach_in_window(&crop.in_window(&self.eval_crop, first), side);
            WindowPart::Region(reach.unwrap_or(PixelRect {
                x: 0,
                y: 0,
                width: 0,
                height: 0,
            }))
        };
        let decoded = self.decode(part)?;
        if part == WindowPart::Centre {
            return Ok(decoded.window.into_raw());
        }
        decoded.crop_pixels(crop)
    }
}

/// The sampling a rule set's crops use.
fn sampling_of(compat: &str) -> Result<CropSampling> {
    match compat {
        "exact" => Ok(CropSampling::Centres),
        "official" => Ok(CropSampling::Corners),
        other => Err(Error::invalid(
            "compat",
            format!("'{other}': expected 'exact' or 'official'"),
        )),
    }
}

fn compat_code(compat: &str) -> Result<u32> {
    Ok(match sampling_of(compat)? {
        CropSampling::Centres => 0,
        CropSampling::Corners => 1,
    })
}

/// The header of the `part-K.bin` of samples shard `index`, with `records` records.
fn header(manifest: &CropStoreManifest, index: usize, records: usize) -> Result<[u8; 128]> {
    let fingerprint = manifest.dataset_fingerprint.as_bytes();
    if fingerprint.len() != FINGERPRINT_BYTES {
        return Err(Error::invalid(
            "crop store",
            format!(
                "dataset fingerprint '{}' is not {FINGERPRINT_BYTES} hex digits",
                manifest.dataset_fingerprint
            ),
        ));
    }
    let mut h = [0u8; HEADER_BYTES as usize];
    h[..8].copy_from_slice(MAGIC);
    let fields = [
        manifest.format,
        compat_code(&manifest.compat)?,
        manifest.img_size,
        manifest.margin,
        manifest.vertex_count as u32,
    ];
    for (i, f) in fields.iter().enumerate() {
        h[8 + 4 * i..12 + 4 * i].copy_from_slice(&f.to_le_bytes());
    }
    h[28..36].copy_from_slice(&(records as u64).to_le_bytes());
    h[36..40].copy_from_slice(&manifest.codec.code().to_le_bytes());
    h[44..48].copy_from_slice(&(index as u32).to_le_bytes());
    h[48..52].copy_from_slice(&(manifest.key_bytes as u32).to_le_bytes());
    h[52..52 + FINGERPRINT_BYTES].copy_from_slice(fingerprint);
    Ok(h)
}

/// Why the header `found` of `path` is not `want` (the header [`header`] gives for it),
/// most telling difference first.
fn header_mismatch(path: &Path, found: &[u8], want: &[u8], manifest: &CropStoreManifest) -> Error {
    let u32_at = |h: &[u8], i: usize| u32::from_le_bytes(h[i..i + 4].try_into().expect("4 bytes"));
    let fp_end = 52 + FINGERPRINT_BYTES;
    let why = if &found[..7] == b"ARKCROP" && found[7] != MAGIC[7] {
        format!(
            "a part of a store of format {}, which this version no longer reads: rerun `arkit-tool crops`",
            found[7] as char
        )
    } else if found[..8] != want[..8] {
        format!(
            "not a crop store part (its first bytes are not {})",
            String::from_utf8_lossy(MAGIC)
        )
    } else if found[52..fp_end] != want[52..fp_end] {
        format!(
            "made from another dataset than {MANIFEST_FILE} says (its fingerprint {}, {MANIFEST_FILE}'s {}): parts of two stores were mixed in this folder; rerun `arkit-tool crops`",
            String::from_utf8_lossy(&found[52..fp_end]),
            manifest.dataset_fingerprint
        )
    } else if found[44..48] != want[44..48] {
        format!(
            "holds the records of samples shard {}, but {MANIFEST_FILE} names it for shard {}: part files were swapped or renamed; rerun `arkit-tool crops`",
            u32_at(found, 44),
            u32_at(want, 44)
        )
    } else {
        format!(
            "its header does not match {MANIFEST_FILE} (format, rules, codec, size, margin, vertices, records, key width): the file is not this store's; rerun `arkit-tool crops`"
        )
    };
    Error::format(path, why)
}

/// One record's bytes: row `row` of samples shard `shard`, sample `key`; a stored crop
/// (its window stored by the manifest's codec), or `None` for a sample without pixels
/// (status 0). A key wider than the manifest's key field is an error.
pub fn encode_record(
    manifest: &CropStoreManifest,
    shard: usize,
    row: usize,
    key: &str,
    crop: Option<&StoredCrop>,
) -> Result<Vec<u8>> {
    let fingerprint = manifest.dataset_fingerprint.as_bytes();
    if key.len() > manifest.key_bytes || fingerprint.len() != FINGERPRINT_BYTES {
        return Err(Error::invalid(
            "crop store",
            format!(
                "{key}: a key of {} bytes does not fit the store's {}-byte key field (or the fingerprint is not {FINGERPRINT_BYTES} hex digits)",
                key.len(),
                manifest.key_bytes
            ),
        ));
    }
    let prefix = record_prefix(manifest.key_bytes);
    let mut r = vec![0u8; prefix];
    r[AT_ROW..AT_ROW + 8].copy_from_slice(&(row as u64).to_le_bytes());
    r[AT_SHARD..AT_SHARD + 4].copy_from_slice(&(shard as u32).to_le_bytes());
    r[AT_KEY_LEN..AT_KEY_LEN + 4].copy_from_slice(&(key.len() as u32).to_le_bytes());
    r[AT_FINGERPRINT..AT_KEY].copy_from_slice(fingerprint);
    r[AT_KEY..AT_KEY + key.len()].copy_from_slice(key.as_bytes());
    if let Some(c) = crop {
        let w = window_side(manifest.img_size);
        if c.verts.len() != manifest.vertex_count
            || c.part != WindowPart::Whole
            || c.window.dimensions() != (w as u32, w as u32)
        {
            return Err(Error::invalid(
                "crop store",
                format!(
                    "{key}: {} vertices and a {:?} window, the store holds {} and {w}x{w}",
                    c.verts.len(),
                    c.window.dimensions(),
                    manifest.vertex_count
                ),
            ));
        }
        r[AT_STATUS..AT_STATUS + 4].copy_from_slice(&1u32.to_le_bytes());
        let b = &c.eval_crop;
        let at_box = AT_KEY + manifest.key_bytes;
        for (i, v) in [b.x0, b.y0, b.side, b.side_y].iter().enumerate() {
            r[at_box + 8 * i..at_box + 8 * (i + 1)].copy_from_slice(&v.to_le_bytes());
        }
        let window = encode_window(manifest.codec, &c.window, manifest.img_size)?;
        let mesh = encode_mesh(&c.verts);
        let at_lens = at_box + 32;
        r[at_lens..at_lens + 4].copy_from_slice(&(window.len() as u32).to_le_bytes());
        r[at_lens + 4..at_lens + 8].copy_from_slice(&(mesh.len() as u32).to_le_bytes());
        r.reserve(window.len() + mesh.len());
        r.extend_from_slice(&window);
        r.extend_from_slice(&mesh);
    }
    let crc = crc32fast::hash(&r[4..]);
    r[..4].copy_from_slice(&crc.to_le_bytes());
    Ok(r)
}

/// Writes `dir/part-K.bin` (atomically) from its records, in row order: the header,
/// the records, their index (`records + 1` offsets from the file's start, the last
/// the index's own) and the footer (its magic and the index's CRC).
pub fn write_shard_file(
    dir: &Path,
    manifest: &CropStoreManifest,
    index: usize,
    records: &mut dyn Iterator<Item = Result<Vec<u8>>>,
    count: usize,
) -> Result<CropShard> {
    let file = shard_file_name(index);
    let path = dir.join(&file);
    let head = header(manifest, index, count)?;
    let mut total = 0;
    arkit_core::atomic_file::write_atomically(&path, |w| {
        w.write_all(&head).map_err(|e| Error::io(&path, e))?;
        let mut offsets = Vec::with_capacity(count + 1);
        let mut at = HEADER_BYTES;
        for r in records {
            let r = r?;
            offsets.push(at);
            at += r.len() as u64;
            w.write_all(&r).map_err(|e| Error::io(&path, e))?;
        }
        if offsets.len() != count {
            return Err(Error::invalid(
                "crop store",
                format!(
                    "{}: {} records for {count} rows",
                    path.display(),
                    offsets.len()
                ),
            ));
        }
        offsets.push(at);
        let index: Vec<u8> = offsets.iter().flat_map(|o| o.to_le_bytes()).collect();
        let mut footer = [0u8; FOOTER_BYTES as usize];
        footer[..8].copy_from_slice(INDEX_MAGIC);
        footer[8..12].copy_from_slice(&crc32fast::hash(&index).to_le_bytes());
        w.write_all(&index).map_err(|e| Error::io(&path, e))?;
        w.write_all(&footer).map_err(|e| Error::io(&path, e))?;
        total = at + index.len() as u64 + FOOTER_BYTES;
        Ok(())
    })?;
    Ok(CropShard {
        index,
        file,
        records: count,
        bytes: total,
    })
}

/// The file name of samples shard `index`'s records: `part-K.bin`.
fn shard_file_name(index: usize) -> String {
    format!("part-{index}.bin")
}

/// Writes `crops.json` (atomically; last, after every shard file).
pub fn write_manifest(dir: &Path, manifest: &CropStoreManifest) -> Result<()> {
    let text = serde_json::to_string_pretty(manifest).expect("manifest serialises");
    arkit_core::atomic_file::write_bytes(&dir.join(MANIFEST_FILE), text.as_bytes())
}

/// Reads and parses `dir/crops.json`; a store of another format is refused first, with
/// what to do.
pub fn read_manifest(dir: &Path) -> Result<CropStoreManifest> {
    let path = dir.join(MANIFEST_FILE);
    let meta = std::fs::metadata(&path).map_err(|e| {
        Error::format(
            dir,
            format!("not a crop store ({MANIFEST_FILE}: {e}); make one with `arkit-tool crops`"),
        )
    })?;
    if meta.len() > MAX_MANIFEST_BYTES {
        return Err(Error::format(
            &path,
            format!("{} bytes, more than a manifest can be", meta.len()),
        ));
    }
    let text = std::fs::read_to_string(&path).map_err(|e| Error::io(&path, e))?;
    let value: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::format(&path, format!("not a crop store manifest: {e}")))?;
    match value.get("format").and_then(|f| f.as_u64()) {
        Some(f) if f == FORMAT as u64 => {}
        Some(f) => {
            return Err(Error::format(
                &path,
                format!(
                    "a crop store of format {f}; this version reads format {FORMAT} (compressed windows whose centre is decoded alone, zstd meshes, an index per part): rerun `arkit-tool crops`"
                ),
            ));
        }
        None => {
            return Err(Error::format(
                &path,
                "not a crop store manifest: no format number",
            ));
        }
    }
    serde_json::from_value(value)
        .map_err(|e| Error::format(&path, format!("not a crop store manifest: {e}")))
}

/// An opened store (see the module docs).
#[derive(Debug)]
pub struct CropStore {
    dir: PathBuf,
    manifest: CropStoreManifest,
    /// Per samples shard index, its file, path and record offsets (`records + 1`).
    files: Vec<Option<PartFile>>,
}

#[derive(Debug)]
struct PartFile {
    file: File,
    path: PathBuf,
    offsets: Vec<u64>,
}

/// The record offsets of the part file `path` (`len` bytes, `records` records, of the
/// store `manifest`), read from its index and checked: the footer's magic and the
/// index's CRC, offsets that start after the header, increase by at least a record's
/// prefix and at most [`max_record_bytes`], and end where the index starts.
fn read_index(
    file: &File,
    path: &Path,
    len: u64,
    records: usize,
    manifest: &CropStoreManifest,
) -> Result<Vec<u64>> {
    let index_bytes = 8 * (records as u64 + 1);
    let truncated = |what: &str| {
        Error::format(
            path,
            format!(
                "{len} bytes: {what}; the file is truncated or not this store's (rerun `arkit-tool crops`)"
            ),
        )
    };
    if len < HEADER_BYTES + index_bytes + FOOTER_BYTES {
        return Err(truncated("too short for its header, index and footer"));
    }
    let mut footer = [0u8; FOOTER_BYTES as usize];
    read_exact_at(file, &mut footer, len - FOOTER_BYTES).map_err(|e| Error::io(path, e))?;
    if &footer[..8] != INDEX_MAGIC {
        return Err(truncated("no index footer at its end"));
    }
    let index_at = len - FOOTER_BYTES - index_bytes;
    let mut index = vec![0u8; index_bytes as usize];
    read_exact_at(file, &mut index, index_at).map_err(|e| Error::io(path, e))?;
    if crc32fast::hash(&index).to_le_bytes() != footer[8..12] {
        return Err(Error::format(
            path,
            "its record index's CRC does not match (the file is damaged); rerun `arkit-tool crops`",
        ));
    }
    let offsets: Vec<u64> = index
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
        .collect();
    let (least, most) = (
        record_prefix(manifest.key_bytes) as u64,
        max_record_bytes(manifest.img_size, manifest.vertex_count, manifest.key_bytes),
    );
    let ok = offsets[0] == HEADER_BYTES
        && offsets[records] == index_at
        && offsets
            .windows(2)
            .all(|p| p[1] >= p[0] + least && p[1] - p[0] <= most);
    if !ok {
        return Err(Error::format(
            path,
            format!(
                "its record index does not fit the file (records of {least}..={most} bytes from byte {HEADER_BYTES} to the index at {index_at}); rerun `arkit-tool crops`"
            ),
        ));
    }
    Ok(offsets)
}

impl CropStore {
    /// Opens the store in `dir` for `dataset`, crops of rules `compat` and side
    /// `img_size`, meshes of `vertex_count` vertices; every check of the module docs
    /// but the records'.
    pub fn open(
        dir: &Path,
        dataset: &crate::store::dataset::Dataset,
        compat: &str,
        img_size: u32,
        vertex_count: usize,
    ) -> Result<Self> {
        let manifest = read_manifest(dir)?;
        let mpath = dir.join(MANIFEST_FILE);
        let expect = |what: &str, found: String, want: String| -> Result<()> {
            if found == want {
                Ok(())
            } else {
                Err(Error::format(
                    &mpath,
                    format!(
                        "{what} is {found}, the loader needs {want}: make a store for it with `arkit-tool crops`"
                    ),
                ))
            }
        };
        expect("compat", manifest.compat.clone(), compat.to_string())?;
        expect(
            "img_size",
            manifest.img_size.to_string(),
            img_size.to_string(),
        )?;
        expect(
            "margin",
            manifest.margin.to_string(),
            margin(img_size).to_string(),
        )?;
        expect(
            "vertex_count",
            manifest.vertex_count.to_string(),
            vertex_count.to_string(),
        )?;
        if manifest.key_bytes == 0
            || manifest.key_bytes > MAX_KEY_BYTES
            || !manifest.key_bytes.is_multiple_of(8)
        {
            return Err(Error::format(
                &mpath,
                format!(
                    "key_bytes is {}, not a multiple of 8 in 8..={MAX_KEY_BYTES}",
                    manifest.key_bytes
                ),
            ));
        }
        let fingerprint = crate::render::dataset::dataset_fingerprint(dataset.manifest());
        if manifest.dataset_fingerprint != fingerprint {
            return Err(Error::format(
                &mpath,
                format!(
                    "made from another dataset than {} (or before it was converted again): run `arkit-tool crops` again",
                    dataset.dir().display()
                ),
            ));
        }
        let shards = dataset.shards();
        let mut files: Vec<Option<PartFile>> =
            (0..shards.iter().map(|s| s.index + 1).max().unwrap_or(0))
                .map(|_| None)
                .collect();
        for s in shards {
            let entry = manifest
                .shards
                .iter()
                .find(|c| c.index == s.index)
                .ok_or_else(|| {
                    Error::format(&mpath, format!("no file for samples shard {}", s.index))
                })?;
            if entry.records != s.rows || entry.file != shard_file_name(s.index) {
                return Err(Error::format(
                    &mpath,
                    format!(
                        "shard {}: {} records in '{}', the dataset has {} rows",
                        s.index, entry.records, entry.file, s.rows
                    ),
                ));
            }
            let path = dir.join(&entry.file);
            let file = File::open(&path).map_err(|e| Error::io(&path, e))?;
            let len = file.metadata().map_err(|e| Error::io(&path, e))?.len();
            let mut head = [0u8; HEADER_BYTES as usize];
            if len >= HEADER_BYTES {
                read_exact_at(&file, &mut head, 0).map_err(|e| Error::io(&path, e))?;
            }
            let want_head = header(&manifest, s.index, entry.records)?;
            // The header first: a file of another store, dataset or shard is named as
            // such, whatever its length.
            if len >= HEADER_BYTES && head != want_head {
                return Err(header_mismatch(&path, &head, &want_head, &manifest));
            }
            if len < HEADER_BYTES {
                return Err(Error::format(
                    &path,
                    format!(
                        "{len} bytes, shorter than a header: the file is truncated or not this store's"
                    ),
                ));
            }
            let offsets = read_index(&file, &path, len, entry.records, &manifest)?;
            files[s.index] = Some(PartFile {
                file,
                path,
                offsets,
            });
        }
        Ok(CropStore {
            dir: dir.to_path_buf(),
            manifest,
            files,
        })
    }

    /// The store folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Its manifest.
    pub fn manifest(&self) -> &CropStoreManifest {
        &self.manifest
    }

    /// Where the record of row `row` of samples shard `shard` lies in its part file:
    /// its first byte and its length.
    pub fn record_span(&self, shard: usize, row: usize) -> Option<(u64, u64)> {
        let o = &self.files.get(shard)?.as_ref()?.offsets;
        (row + 1 < o.len()).then(|| (o[row], o[row + 1] - o[row]))
    }

    /// The record of row `row` of samples shard `shard`, which must be that of sample
    /// `key` (`subject/action/img_id`) of this store's dataset: checked, with the
    /// record's CRC, before anything of it is decoded or returned. Its mesh is decoded
    /// here, its window when asked for ([`StoredRecord::crop_pixels`],
    /// [`StoredRecord::decode`]).
    pub fn read(&self, shard: usize, row: usize, key: &str) -> Result<StoredRecord> {
        let part = self
            .files
            .get(shard)
            .and_then(|f| f.as_ref())
            .ok_or_else(|| Error::invalid("crop store", format!("no samples shard {shard}")))?;
        let path = &part.path;
        let (at, len) = self.record_span(shard, row).ok_or_else(|| {
            Error::invalid("crop store", format!("{}: no record {row}", path.display()))
        })?;
        let m = &self.manifest;
        // `len` was bounded when the index was read. The head (CRC to the lengths) and
        // the rest (the window, then the mesh) read into their own buffers, so a raw
        // window is returned as read, not moved out of the record.
        let prefix = record_prefix(m.key_bytes);
        let head_len = (len as usize).min(prefix);
        let mut r = vec![0u8; head_len];
        let mut tail = vec![0u8; len as usize - head_len];
        read_exact_at(&part.file, &mut r, at).map_err(|e| Error::io(path, e))?;
        read_exact_at(&part.file, &mut tail, at + head_len as u64)
            .map_err(|e| Error::io(path, e))?;
        let u32_at = |i: usize| u32::from_le_bytes(r[i..i + 4].try_into().expect("4 bytes"));
        let mut crc = crc32fast::Hasher::new();
        crc.update(&r[4..]);
        crc.update(&tail);
        if crc.finalize() != u32_at(0) {
            return Err(Error::format(
                path,
                format!(
                    "record {row}: its CRC does not match (the file is damaged); run `arkit-tool crops` again"
                ),
            ));
        }
        // Whose record it is: this dataset's, this shard's, this row's, this sample's.
        let stored_row = u64::from_le_bytes(r[AT_ROW..AT_ROW + 8].try_into().expect("8 bytes"));
        let stored_shard = u32_at(AT_SHARD) as u64;
        let key_len = (u32_at(AT_KEY_LEN) as usize).min(m.key_bytes);
        let stored_key = &r[AT_KEY..AT_KEY + key_len];
        let stored_fingerprint = &r[AT_FINGERPRINT..AT_KEY];
        if stored_row != row as u64
            || stored_shard != shard as u64
            || stored_key != key.as_bytes()
            || stored_fingerprint != m.dataset_fingerprint.as_bytes()
        {
            let other_dataset = if stored_fingerprint != m.dataset_fingerprint.as_bytes() {
                format!(
                    " of another dataset (fingerprint {})",
                    String::from_utf8_lossy(stored_fingerprint)
                )
            } else {
                String::new()
            };
            return Err(Error::format(
                path,
                format!(
                    "record {row} of shard {shard} should be sample {key}, but it holds sample {} (row {stored_row} of shard {stored_shard}{other_dataset}): the store's files were mixed, swapped or edited; run `arkit-tool crops` again",
                    String::from_utf8_lossy(stored_key)
                ),
            ));
        }
        if u32_at(AT_STATUS) != 1 {
            let why = m
                .missing
                .iter()
                .find(|x| x.shard == shard && x.row == row)
                .map(|x| format!("{}: {}", x.key, x.reason))
                .unwrap_or_else(|| "no reason recorded".into());
            return Err(Error::format(
                path,
                format!(
                    "record {row} has no pixels: its sample could not be read when the store was made ({why})"
                ),
            ));
        }
        let at_box = AT_KEY + m.key_bytes;
        let (window_len, mesh_len) = (u32_at(at_box + 32) as usize, u32_at(at_box + 36) as usize);
        if head_len != prefix
            || window_len > max_window_bytes(m.img_size)
            || mesh_len > max_mesh_bytes(m.vertex_count)
            || window_len + mesh_len != tail.len()
        {
            return Err(Error::format(
                path,
                format!(
                    "record {row}: a window of {window_len} bytes and a mesh of {mesh_len} in a record of {len}: the file is not this store's; run `arkit-tool crops` again"
                ),
            ));
        }
        let f64_at = |i: usize| f64::from_le_bytes(r[i..i + 8].try_into().expect("8 bytes"));
        let eval_crop = CropTransform {
            x0: f64_at(at_box),
            y0: f64_at(at_box + 8),
            side: f64_at(at_box + 16),
            side_y: f64_at(at_box + 24),
            size: m.img_size,
            sampling: sampling_of(&m.compat)?,
        };
        let in_record = |e: Error| {
            Error::format(
                path,
                format!("record {row}: {e}; run `arkit-tool crops` again"),
            )
        };
        let verts = decode_mesh(&tail[window_len..], m.vertex_count).map_err(in_record)?;
        // The window kept in the buffer it was read into, the mesh cut off.
        tail.truncate(window_len);
        let window = match m.codec {
            WindowCodec::Raw => {
                let w = window_side(m.img_size) as u32;
                let len = tail.len();
                let bad = || {
                    Error::format(
                        path,
                        format!(
                            "record {row}: a raw window of {len} bytes, expected {}",
                            3 * w * w
                        ),
                    )
                };
                if len != 3 * (w * w) as usize {
                    return Err(bad());
                }
                StoredWindow::Raw(image::RgbImage::from_raw(w, w, tail).ok_or_else(bad)?)
            }
            _ => StoredWindow::Encoded(tail),
        };
        Ok(StoredRecord {
            eval_crop,
            verts,
            window,
            codec: m.codec,
            path: path.clone(),
            row,
        })
    }
}

/// `pread` of exactly `buf.len()` bytes at `offset` (positional: safe to share the file
/// between threads and forked processes).
fn read_exact_at(file: &File, buf: &mut [u8], offset: u64) -> std::io::Result<()> {
    #[cfg(unix)]
    {
        std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
    }
    #[cfg(windows)]
    {
        let mut done = 0;
        while done < buf.len() {
            let n = std::os::windows::fs::FileExt::seek_read(
                file,
                &mut buf[done..],
                offset + done as u64,
            )?;
            if n == 0 {
                return Err(std::io::ErrorKind::UnexpectedEof.into());
            }
            done += n;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_margin_covers_the_largest_training_jitter() {
        // Landmarks' box size d: the crop's half-side is 0.75 d = S / 2 crop pixels, so
        // one d is 2S/3 crop pixels. The largest jitter: centre 0.15 d, half-side
        // 0.75 d * 1.05: 0.9375 d from the centre, 0.1875 d = S / 8 past the crop.
        for s in [16u32, 64, 192, 193, 1024] {
            let d = 2.0 * s as f64 / 3.0;
            let reach = 0.15 * d + 0.75 * d * 1.05 - s as f64 / 2.0;
            assert!((reach - s as f64 / 8.0).abs() < 1e-9);
            assert!(margin(s) as f64 >= reach + 2.0 - 1e-9, "{s}");
        }
        assert_eq!(window_side(192), 192 + 2 * 26);
    }

    fn manifest() -> CropStoreManifest {
        CropStoreManifest {
            format: FORMAT,
            compat: "official".into(),
            codec: WindowCodec::Png,
            img_size: 16,
            margin: margin(16),
            vertex_count: 2,
            key_bytes: key_field_bytes(5),
            dataset_fingerprint: "ab".repeat(32),
            shards: Vec::new(),
            missing: Vec::new(),
        }
    }

    /// The record of row `row` of shard `shard` of `store`, its window decoded whole.
    fn whole(store: &CropStore, shard: usize, row: usize, key: &str) -> Result<StoredCrop> {
        store.read(shard, row, key)?.decode(WindowPart::Whole)
    }

    fn crop() -> StoredCrop {
        let w = window_side(16);
        StoredCrop {
            eval_crop: CropTransform {
                x0: 1.5,
                y0: -2.25,
                side: 30.0,
                side_y: 31.0,
                size: 16,
                sampling: CropSampling::Corners,
            },
            verts: vec![Point3::new(0.1, -0.2, 0.3), Point3::new(1.0, 2.0, 3.0)],
            window: image::RgbImage::from_raw(
                w as u32,
                w as u32,
                (0..w * w * 3).map(|i| (i * 7 % 251) as u8).collect(),
            )
            .unwrap(),
            part: WindowPart::Whole,
        }
    }

    /// `dir/part-0.bin` of six records, row `r` holding `records[r]`, opened.
    fn store_of(dir: &Path, m: &CropStoreManifest, records: Vec<Vec<u8>>) -> CropStore {
        let n = records.len();
        write_shard_file(dir, m, 0, &mut records.into_iter().map(Ok), n).unwrap();
        let path = dir.join("part-0.bin");
        let file = File::open(&path).unwrap();
        let len = file.metadata().unwrap().len();
        let offsets = read_index(&file, &path, len, n, m).unwrap();
        CropStore {
            dir: dir.to_path_buf(),
            manifest: m.clone(),
            files: vec![Some(PartFile {
                file,
                path,
                offsets,
            })],
        }
    }

    /// The records of samples `s/a/<row>`, row 5 with `crop`'s pixels, the others without.
    fn six(m: &CropStoreManifest, crop: &StoredCrop) -> Vec<Vec<u8>> {
        (0..6)
            .map(|r| {
                let key = format!("s/a/{r}");
                encode_record(m, 0, r, &key, (r == 5).then_some(crop)).unwrap()
            })
            .collect()
    }

    #[test]
    fn a_record_round_trips_in_each_codec_and_its_crc_catches_a_flipped_byte() {
        for codec in [WindowCodec::Raw, WindowCodec::Png, WindowCodec::PredZstd] {
            let dir = tempfile::tempdir().unwrap();
            let m = CropStoreManifest {
                codec,
                ..manifest()
            };
            let crop = crop();
            let records = six(&m, &crop);
            let bytes = &records[5];
            assert_eq!(crc32fast::hash(&bytes[4..]).to_le_bytes(), bytes[..4]);
            if codec == WindowCodec::Raw {
                let mesh = encode_mesh(&crop.verts).len();
                assert_eq!(bytes.len() as u64, raw_record_bytes(16, mesh, m.key_bytes));
            }
            let store = store_of(dir.path(), &m, records);
            assert_eq!(whole(&store, 0, 5, "s/a/5").unwrap(), crop);
            let e = whole(&store, 0, 2, "s/a/2").unwrap_err().to_string();
            assert!(e.contains("part-0.bin") && e.contains("no pixels"), "{e}");
            // One byte of the window flipped: refused by the CRC before it is decoded,
            // naming the file.
            let path = dir.path().join("part-0.bin");
            let mut all = std::fs::read(&path).unwrap();
            let (at, len) = store.record_span(0, 5).unwrap();
            let in_window = at as usize + record_prefix(m.key_bytes) + 10;
            assert!(in_window + encode_mesh(&crop.verts).len() < (at + len) as usize);
            all[in_window] ^= 1;
            std::fs::write(&path, &all).unwrap();
            let e = whole(&store_of_file(&store, &path), 0, 5, "s/a/5").unwrap_err();
            assert!(
                e.to_string().contains("part-0.bin") && e.to_string().contains("CRC"),
                "{e}"
            );
            // The index damaged: refused when the part is opened.
            all[in_window] ^= 1;
            let n = all.len();
            all[n - FOOTER_BYTES as usize - 3] ^= 1;
            std::fs::write(&path, &all).unwrap();
            let file = File::open(&path).unwrap();
            let e = read_index(&file, &path, n as u64, 6, &m).unwrap_err();
            assert!(e.to_string().contains("index's CRC"), "{e}");
        }
    }

    /// `store` with its part file opened again from `path`.
    fn store_of_file(store: &CropStore, path: &Path) -> CropStore {
        let file = File::open(path).unwrap();
        let len = file.metadata().unwrap().len();
        let offsets = read_index(&file, path, len, 6, &store.manifest).unwrap();
        CropStore {
            dir: store.dir.clone(),
            manifest: store.manifest.clone(),
            files: vec![Some(PartFile {
                file,
                path: path.to_path_buf(),
                offsets,
            })],
        }
    }

    #[test]
    fn a_record_of_another_sample_row_shard_or_dataset_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (m, crop) = (manifest(), crop());
        let store = store_of(dir.path(), &m, six(&m, &crop));
        // Asked as another sample: the key differs.
        let e = whole(&store, 0, 5, "s/a/6").unwrap_err().to_string();
        assert!(
            e.contains("part-0.bin")
                && e.contains("should be sample s/a/6, but it holds sample s/a/5"),
            "{e}"
        );
        // Record 5 in row 3's place (each CRC and the index intact): row 3 is refused,
        // with what it holds; the other records are still served.
        let mut records = six(&m, &crop);
        records[3] = records[5].clone();
        let store = store_of(dir.path(), &m, records);
        let e = whole(&store, 0, 3, "s/a/3").unwrap_err().to_string();
        assert!(e.contains("holds sample s/a/5 (row 5 of shard 0)"), "{e}");
        assert_eq!(whole(&store, 0, 5, "s/a/5").unwrap(), crop);
        // Another shard's or another dataset's record of the same row and key.
        for (shard, fingerprint, says) in [
            (1, "ab".repeat(32), "row 5 of shard 1)"),
            (
                0,
                "cd".repeat(32),
                &*format!("of another dataset (fingerprint {})", "cd".repeat(32)),
            ),
        ] {
            let other = CropStoreManifest {
                dataset_fingerprint: fingerprint,
                ..m.clone()
            };
            let mut records = six(&m, &crop);
            records[5] = encode_record(&other, shard, 5, "s/a/5", Some(&crop)).unwrap();
            let store = store_of(dir.path(), &m, records);
            let e = whole(&store, 0, 5, "s/a/5").unwrap_err().to_string();
            assert!(e.contains("part-0.bin") && e.contains(says), "{e}");
        }
        // A key longer than the key field is refused when written, never cut.
        let e = encode_record(&m, 0, 0, "s/a/123456", None).unwrap_err();
        assert!(e.to_string().contains("does not fit"), "{e}");
    }

    /// The bits of `verts`, for comparisons that tell NaNs and -0.0 apart.
    fn bits(verts: &[Point3<f32>]) -> Vec<u32> {
        verts
            .iter()
            .flat_map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
            .collect()
    }

    #[test]
    fn a_mesh_round_trips_bit_for_bit_nans_zeros_and_denormals_included() {
        let odd = [
            f32::NAN,
            f32::from_bits(0x7fc0_1234),
            f32::from_bits(0xffbf_ffff),
            -0.0,
            0.0,
            f32::from_bits(1),
            -f32::from_bits(0x007f_ffff),
            f32::MIN_POSITIVE,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MAX,
            -1.5e-3,
        ];
        // A face-like mesh (smooth, centimetres in metres) with the odd values in it.
        let mut verts: Vec<Point3<f32>> = (0..1220)
            .map(|i| {
                let t = i as f32 * 0.013;
                Point3::new(
                    0.08 * t.sin(),
                    0.09 * (0.7 * t).cos(),
                    0.02 + 0.03 * t.cos(),
                )
            })
            .collect();
        for (i, v) in odd.iter().enumerate() {
            verts[37 * i].x = *v;
            verts[37 * i + 5].y = *v;
            verts[37 * i + 11].z = -*v;
        }
        let stored = encode_mesh(&verts);
        assert!(stored.len() < 12 * verts.len(), "{} bytes", stored.len());
        assert!(stored.len() <= max_mesh_bytes(verts.len()));
        assert_eq!(
            bits(&decode_mesh(&stored, verts.len()).unwrap()),
            bits(&verts)
        );
        // Every value alone, and no vertices at all.
        let each: Vec<Point3<f32>> = odd.iter().map(|&v| Point3::new(v, -v, v)).collect();
        let back = decode_mesh(&encode_mesh(&each), each.len()).unwrap();
        assert_eq!(bits(&back), bits(&each));
        assert!(decode_mesh(&encode_mesh(&[]), 0).unwrap().is_empty());
        // Random bits (nothing to compress): still within the bound, still exact.
        let mut x = 0x9e37_79b9_u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            f32::from_bits(x)
        };
        let noise: Vec<Point3<f32>> = (0..1220)
            .map(|_| Point3::new(next(), next(), next()))
            .collect();
        let stored = encode_mesh(&noise);
        assert!(
            stored.len() <= max_mesh_bytes(noise.len()),
            "{}",
            stored.len()
        );
        assert_eq!(
            bits(&decode_mesh(&stored, noise.len()).unwrap()),
            bits(&noise)
        );
    }

    #[test]
    fn a_record_whose_mesh_or_lengths_do_not_fit_is_refused_though_its_crc_matches() {
        let dir = tempfile::tempdir().unwrap();
        let (m, crop) = (manifest(), crop());
        let at_lens = AT_KEY + m.key_bytes + 32;
        // Record 5 with its mesh replaced by `mesh` and its lengths by `lens`, CRC
        // recomputed: what a writer with a bug (or an editor) could leave.
        let forged = |mesh: &[u8], lens: Option<(u32, u32)>| {
            let mut records = six(&m, &crop);
            let r = &mut records[5];
            let window_len = u32::from_le_bytes(r[at_lens..at_lens + 4].try_into().unwrap());
            r.truncate(record_prefix(m.key_bytes) + window_len as usize);
            r.extend_from_slice(mesh);
            let (w, n) = lens.unwrap_or((window_len, mesh.len() as u32));
            r[at_lens..at_lens + 4].copy_from_slice(&w.to_le_bytes());
            r[at_lens + 4..at_lens + 8].copy_from_slice(&n.to_le_bytes());
            let crc = crc32fast::hash(&r[4..]);
            r[..4].copy_from_slice(&crc.to_le_bytes());
            whole(&store_of(dir.path(), &m, records), 0, 5, "s/a/5")
        };
        let good = encode_mesh(&crop.verts);
        assert_eq!(forged(&good, None).unwrap(), crop);
        // A mesh of three vertices in a store of two.
        let three = encode_mesh(&[crop.verts[0], crop.verts[1], crop.verts[0]]);
        let e = forged(&three, None).unwrap_err().to_string();
        assert!(
            e.contains("part-0.bin") && e.contains("record 5") && e.contains("its mesh"),
            "{e}"
        );
        // Lengths that do not add up to the record's, or a mesh longer than any can be.
        let window_len = encode_window(m.codec, &crop.window, 16).unwrap().len() as u32;
        for lens in [
            (window_len + 1, good.len() as u32),
            (window_len - 1, good.len() as u32),
            (0, window_len + good.len() as u32),
        ] {
            let e = forged(&good, Some(lens)).unwrap_err().to_string();
            assert!(
                e.contains("record 5") && e.contains("not this store's"),
                "{lens:?}: {e}"
            );
        }
        // The mesh counted into the window: no mesh left to decode.
        let e = forged(&good, Some((window_len + good.len() as u32, 0)))
            .unwrap_err()
            .to_string();
        assert!(e.contains("record 5") && e.contains("its mesh"), "{e}");
    }

    #[test]
    fn a_mesh_stream_cut_short_grown_or_of_another_size_is_refused() {
        let verts = crop().verts;
        let stored = encode_mesh(&verts);
        // Cut: every shorter frame refused.
        for cut in 0..stored.len() {
            assert!(decode_mesh(&stored[..cut], 2).is_err(), "cut to {cut}");
        }
        // Bytes after the frame's end.
        let mut more = stored.clone();
        more.push(0);
        let e = decode_mesh(&more, 2).unwrap_err().to_string();
        assert!(e.contains("its mesh: not a zstd frame"), "{e}");
        // The frame of a larger mesh, read as two vertices: it gives more than 24 bytes.
        let three = [verts[0], verts[1], verts[0]];
        let e = decode_mesh(&encode_mesh(&three), 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("at most the 24 bytes of 2 vertices"), "{e}");
        // The frame of a smaller mesh: it gives fewer.
        let e = decode_mesh(&encode_mesh(&verts[..1]), 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("12 bytes, expected the 24"), "{e}");
        // Not zstd at all.
        assert!(decode_mesh(&[0xff; 40], 2).is_err());
    }

    /// A xorshift stream of bytes for the codec tests.
    fn noise(seed: u32) -> impl FnMut() -> u8 {
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
        unsafe { unpredict_scalar(io) };
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
                // The SSE2 encoding too, where the dispatch took the VEX one.
                #[cfg(target_arch = "x86_64")]
                {
                    let mut sse2 = errors;
                    let p = sse2.as_mut_ptr();
                    let io = RectIo {
                        src: p,
                        src_row: 3 * width,
                        dst: p,
                        dst_row: 3 * width,
                        dst_col: 3,
                        width,
                        height,
                    };
                    // SAFETY: SSE2 is part of the x86-64 baseline; in place, a whole
                    // image.
                    unsafe { unpredict_rows_sse2::<false>(io) };
                    assert_eq!(sse2, scalar, "SSE2, {width}x{height}");
                }
            }
        }
    }

    #[test]
    fn the_window_parts_cover_the_window_once_with_the_centre_first() {
        for size in [1u32, 2, 7, 8, 9, 16, 64, 192, 224, 256] {
            let (s, m, w) = (size as usize, margin(size) as usize, window_side(size));
            let parts = window_parts(size);
            assert_eq!(
                parts[0],
                PixelRect {
                    x: m,
                    y: m,
                    width: s,
                    height: s
                }
            );
            let mut hits = vec![0u8; w * w];
            for r in parts {
                assert!(r.inside(w, w), "{size}: {r:?}");
                for y in r.y..r.y + r.height {
                    for x in r.x..r.x + r.width {
                        hits[y * w + x] += 1;
                    }
                }
            }
            assert!(hits.iter().all(|&h| h == 1), "{size}");
        }
    }

    #[test]
    fn a_predicted_window_round_trips_whole_and_centre_and_a_frame_of_another_size_is_refused() {
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
            let stored = encode_window(WindowCodec::PredZstd, &window, size).unwrap();
            let whole = decode_window(WindowCodec::PredZstd, &stored, size, WindowPart::Whole);
            assert_eq!(whole.unwrap(), *window.as_raw(), "{size}");
            // The centre alone: the window's centre rows, from the centre's frame.
            let centre = decode_window(WindowCodec::PredZstd, &stored, size, WindowPart::Centre);
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
                let got = decode_window(
                    WindowCodec::PredZstd,
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
        // A smooth window compresses well below PNG's bytes here.
        let crop = crop();
        let stored = encode_window(WindowCodec::PredZstd, &crop.window, 16).unwrap();
        assert_eq!(
            decode_window(WindowCodec::PredZstd, &stored, 16, WindowPart::Whole).unwrap(),
            *crop.window.as_raw()
        );
        assert!(
            stored.len() < crop.window.len() / 2,
            "{} bytes",
            stored.len()
        );
        // The frames of a larger or a smaller window, cut or damaged bytes, a centre's
        // byte count past the end: refused.
        for other in [15, 17] {
            let w = window_side(other) as u32;
            let bytes =
                encode_window(WindowCodec::PredZstd, &image::RgbImage::new(w, w), other).unwrap();
            for part in [WindowPart::Whole, WindowPart::Centre] {
                let e = decode_window(WindowCodec::PredZstd, &bytes, 16, part).unwrap_err();
                assert!(e.to_string().contains("zstd window"), "{other}: {e}");
            }
        }
        let whole = |b: &[u8]| decode_window(WindowCodec::PredZstd, b, 16, WindowPart::Whole);
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

    #[test]
    fn a_records_training_crops_decode_only_what_they_reach_and_equal_the_whole_windows() {
        let mut next = noise(0x0bad_cafe);
        for sampling in [CropSampling::Centres, CropSampling::Corners] {
            let size = 32u32;
            let side = window_side(size);
            let window = image::RgbImage::from_fn(side as u32, side as u32, |x, y| {
                image::Rgb([(x * 5 + y) as u8, next(), (y * 3) as u8])
            });
            let eval_crop = CropTransform {
                x0: 100.25,
                y0: 80.5,
                side: 60.0,
                side_y: 61.0,
                size,
                sampling,
            };
            let whole = StoredCrop {
                eval_crop,
                verts: Vec::new(),
                window: window.clone(),
                part: WindowPart::Whole,
            };
            let record = StoredRecord {
                eval_crop,
                verts: Vec::new(),
                window: StoredWindow::Encoded(
                    encode_window(WindowCodec::PredZstd, &window, size).unwrap(),
                ),
                codec: WindowCodec::PredZstd,
                path: PathBuf::from("part-0.bin"),
                row: 3,
            };
            assert_eq!(record.crop_pixels(&eval_crop).unwrap(), whole.centre());
            // Boxes moved and scaled as far as the training jitter goes, and past the
            // window (where the crop reads zero).
            for (dx, dy, scale) in [
                (0.1, 0.1, 1.05),
                (-0.1, 0.1, 0.95),
                (0.1, -0.1, 1.0),
                (-0.1, -0.1, 1.05),
                (0.0, 0.0, 1.05),
                (0.02, -0.01, 0.95),
                (0.3, 0.0, 1.0),
            ] {
                let crop = CropTransform {
                    x0: eval_crop.x0 + dx * 60.0 - (scale - 1.0) * 30.0,
                    y0: eval_crop.y0 + dy * 61.0 - (scale - 1.0) * 30.5,
                    side: 60.0 * scale,
                    side_y: 61.0 * scale,
                    ..eval_crop
                };
                assert_eq!(
                    record.crop_pixels(&crop).unwrap(),
                    whole.crop_pixels(&crop).unwrap(),
                    "{sampling:?} {dx} {dy} {scale}"
                );
            }
            // A window decoded for a small region refuses a crop reaching past it.
            let small = record
                .decode(WindowPart::Region(PixelRect {
                    x: 20,
                    y: 20,
                    width: 4,
                    height: 4,
                }))
                .unwrap();
            let moved = CropTransform {
                x0: eval_crop.x0 - 6.0,
                ..eval_crop
            };
            let e = small.crop_pixels(&moved).unwrap_err().to_string();
            assert!(e.contains("not decoded"), "{e}");
        }
    }

    #[test]
    fn a_png_window_of_another_size_or_colour_is_refused_before_decoding() {
        use image::ImageEncoder;
        let crop = crop();
        let side = crop.window.width();
        let png = encode_window(WindowCodec::Png, &crop.window, 16).unwrap();
        let decode = |b: &[u8], part| decode_window(WindowCodec::Png, b, 16, part);
        assert_eq!(
            decode(&png, WindowPart::Whole).unwrap(),
            *crop.window.as_raw()
        );
        assert_eq!(decode(&png, WindowPart::Centre).unwrap(), crop.centre());
        assert!(png.len() < crop.window.len(), "{} bytes", png.len());
        // A PNG of a larger side than the store's: refused from its header.
        let mut big = Vec::new();
        image::codecs::png::PngEncoder::new(&mut big)
            .write_image(
                &vec![0u8; 3 * 1024 * 1024],
                1024,
                1024,
                image::ExtendedColorType::Rgb8,
            )
            .unwrap();
        let e = decode(&big, WindowPart::Whole).unwrap_err();
        assert!(e.to_string().contains("PNG window"), "{e}");
        // Grey instead of RGB, of the right side.
        let mut grey = Vec::new();
        image::codecs::png::PngEncoder::new(&mut grey)
            .write_image(
                &vec![9u8; (side * side) as usize],
                side,
                side,
                image::ExtendedColorType::L8,
            )
            .unwrap();
        let e = decode(&grey, WindowPart::Whole).unwrap_err();
        assert!(e.to_string().contains("expected"), "{e}");
        // Raw bytes of the wrong length; damaged PNG bytes; a window of another side.
        assert!(decode_window(WindowCodec::Raw, &[0; 10], 16, WindowPart::Centre).is_err());
        assert!(decode(&png[..png.len() / 2], WindowPart::Whole).is_err());
        assert!(encode_window(WindowCodec::Png, &crop.window, 17).is_err());
    }
}
