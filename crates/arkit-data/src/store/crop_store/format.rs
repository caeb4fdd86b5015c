//! `format`: the bytes of a store on disk, and the window's geometry they follow.
//!
//! A store folder (`DATA/crops/<compat>-<S>/` by default) holds [`MANIFEST_FILE`]
//! (`crops.json`, [`super::manifest::CropStoreManifest`]) and, per samples shard `K`,
//! `part-K.bin` ([`shard_file_name`]):
//!
//! - a [`HEADER_BYTES`]-byte header ([`PartHeader`]): magic `ARKCROP4`, format, the
//!   rules, `S`, `m`, `V`, record count, codec, the shard index `K`, the key field's
//!   width, the dataset's fingerprint;
//! - one record per row of `samples/part-K.parquet`, in order: CRC-32 of the rest,
//!   status (1: pixels, 0: none), the row, the shard index, the key's length, the
//!   dataset's fingerprint, the sample's key (`subject/action/img_id`, zero-padded to
//!   the key field's width), the evaluation crop's box (four float64), the window's and
//!   the mesh's byte counts ([`record_prefix`] bytes so far), then the window as its
//!   codec stores it and the mesh ([`super::mesh_codec`]);
//! - the record index (`rows + 1` byte offsets, little endian) and a
//!   [`FOOTER_BYTES`]-byte footer (magic `ARKCIDX4`, the index's CRC-32).
//!
//! The window of crop side `S` is crop pixels `-m..S + m` in both axes (`m =`
//! [`margin`]`(S)`, side [`window_side`]); its centre `S x S` is the evaluation crop,
//! and [`window_parts`] cuts it into the centre and the four parts of the ring around
//! it. Every number is little endian. A leaf: it imports no other file of the store.

use arkit_core::{Error, Result};
use std::path::Path;

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
pub(super) const FOOTER_BYTES: u64 = 16;
const MAGIC: &[u8; 8] = b"ARKCROP4";
pub(super) const INDEX_MAGIC: &[u8; 8] = b"ARKCIDX4";
/// Bytes of a dataset fingerprint (SHA-256, lower-case hex) in headers and records.
pub(super) const FINGERPRINT_BYTES: usize = 64;
/// Widest key field a store has (a key longer than this is refused by `crops`).
pub(crate) const MAX_KEY_BYTES: usize = 1024;
/// Where a record's fields start: CRC, status, row, shard, key length, fingerprint, key.
pub(super) const AT_STATUS: usize = 4;
pub(super) const AT_ROW: usize = 8;
pub(super) const AT_SHARD: usize = 16;
pub(super) const AT_KEY_LEN: usize = 20;
pub(super) const AT_FINGERPRINT: usize = 24;
pub(super) const AT_KEY: usize = AT_FINGERPRINT + FINGERPRINT_BYTES;

/// Bytes of a record before the window: CRC, status, row, shard, key length, fingerprint,
/// the key field (`key_bytes` wide), the box, the window's and the mesh's lengths.
pub(super) fn record_prefix(key_bytes: usize) -> usize {
    AT_KEY + key_bytes + 4 * 8 + 8
}

/// The key field's width for a dataset whose longest key has `longest` bytes: a
/// multiple of 8, at least 8.
pub(crate) fn key_field_bytes(longest: usize) -> usize {
    longest.max(1).div_ceil(8) * 8
}

/// The file name of samples shard `index`'s records: `part-K.bin`.
pub(super) fn shard_file_name(index: usize) -> String {
    format!("part-{index}.bin")
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

/// The first pixel of the window of crop side `size` in the evaluation crop's pixel
/// grid, along each axis: `-m`.
pub(super) fn window_first(size: u32) -> i64 {
    -(margin(size) as i64)
}

/// Bytes of one record with raw pixels for crop side `size`, a stored mesh of
/// `mesh_bytes` ([`super::mesh_codec::encode_mesh`]) and a key field of `key_bytes`
/// ([`key_field_bytes`]).
#[cfg(test)]
pub(super) fn raw_record_bytes(size: u32, mesh_bytes: usize, key_bytes: usize) -> u64 {
    let w = window_side(size) as u64;
    record_prefix(key_bytes) as u64 + mesh_bytes as u64 + 3 * w * w
}

/// The largest window a store accepts: the raw bytes, plus room for a compressed one
/// that does not compress (a PNG's filter bytes, chunks and deflate's stored blocks, a
/// WebP's headers: well under this).
pub(super) fn max_window_bytes(size: u32) -> usize {
    let w = window_side(size);
    3 * w * w + 3 * w * w / 8 + 4096
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
    pub(super) fn inside(&self, width: usize, height: usize) -> bool {
        self.x + self.width <= width && self.y + self.height <= height
    }

    /// Whether `other` lies inside it.
    pub fn contains(&self, other: &PixelRect) -> bool {
        self.x <= other.x
            && self.y <= other.y
            && other.x + other.width <= self.x + self.width
            && other.y + other.height <= self.y + self.height
    }

    /// Whether it and `other` share a pixel.
    pub(super) fn meets(&self, other: &PixelRect) -> bool {
        self.x < other.x + other.width
            && other.x < self.x + self.width
            && self.y < other.y + other.height
            && other.y < self.y + self.height
    }
}

/// The parts of the window of crop side `size`: the evaluation crop (the window's centre
/// `S x S`) first, then the ring of margin `m` around it, as the band above (`W x m`),
/// the strips left and right of the centre (`m x S` each) and the band below (`W x m`).
/// A codec that stores them apart (`pred-zstd`: a zstd frame each) lets an evaluation
/// item decode the centre alone (`S^2` of the window's `W^2` pixels: 62% at `S = 192`)
/// and a training crop the centre and the parts it reaches ([`WindowPart::Region`]).
/// The parts cover the window, each pixel once (tested).
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

/// What of a stored window is decoded ([`super::codec::decode_window`],
/// [`super::records::StoredRecord::decode`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WindowPart {
    /// The whole `W x W` window.
    Whole,
    /// Its centre `S x S`, the evaluation crop: with a codec that stores the window's
    /// parts apart (`pred-zstd`) the ring's are not decoded.
    Centre,
    /// The `W x W` window with at least the pixels of this rectangle of it decoded
    /// (what a training crop reaches, `crate::crop::CropTransform::window_reach`):
    /// with a codec that stores the window's parts apart (`pred-zstd`) the parts of the
    /// ring it does not meet are not decoded, and their pixels are zero.
    Region(PixelRect),
}

/// The centre `S x S x 3` bytes of the `W x W x 3` window `window` of crop side `size`.
pub(super) fn window_centre(window: &[u8], size: u32) -> Vec<u8> {
    let (s, w, m) = (size as usize, window_side(size), margin(size) as usize);
    let mut out = Vec::with_capacity(3 * s * s);
    for r in m..m + s {
        out.extend_from_slice(&window[3 * (r * w + m)..3 * (r * w + m + s)]);
    }
    out
}

/// The fields of a `part-K.bin` header, as [`PartHeader::bytes`] lays them out.
pub(super) struct PartHeader<'a> {
    /// [`FORMAT`].
    pub format: u32,
    /// The rules' code: 0 `exact`, 1 `official`.
    pub rules: u32,
    /// Crop side `S`.
    pub img_size: u32,
    /// [`margin`]`(S)`.
    pub margin: u32,
    /// Vertices per mesh.
    pub vertex_count: u32,
    /// Records in the file.
    pub records: u64,
    /// The window codec's code.
    pub codec: u32,
    /// The samples shard `K`.
    pub shard: u32,
    /// Width of each record's key field.
    pub key_bytes: u32,
    /// The dataset's fingerprint ([`FINGERPRINT_BYTES`] hex digits).
    pub fingerprint: &'a str,
}

impl PartHeader<'_> {
    /// The header's [`HEADER_BYTES`] bytes; a fingerprint of another length is an error.
    pub fn bytes(&self) -> Result<[u8; HEADER_BYTES as usize]> {
        let fingerprint = self.fingerprint.as_bytes();
        if fingerprint.len() != FINGERPRINT_BYTES {
            return Err(Error::invalid(
                "crop store",
                format!(
                    "dataset fingerprint '{}' is not {FINGERPRINT_BYTES} hex digits",
                    self.fingerprint
                ),
            ));
        }
        let mut h = [0u8; HEADER_BYTES as usize];
        h[..8].copy_from_slice(MAGIC);
        let fields = [
            self.format,
            self.rules,
            self.img_size,
            self.margin,
            self.vertex_count,
        ];
        for (i, f) in fields.iter().enumerate() {
            h[8 + 4 * i..12 + 4 * i].copy_from_slice(&f.to_le_bytes());
        }
        h[28..36].copy_from_slice(&self.records.to_le_bytes());
        h[36..40].copy_from_slice(&self.codec.to_le_bytes());
        h[44..48].copy_from_slice(&self.shard.to_le_bytes());
        h[48..52].copy_from_slice(&self.key_bytes.to_le_bytes());
        h[52..52 + FINGERPRINT_BYTES].copy_from_slice(fingerprint);
        Ok(h)
    }
}

/// Why the header `found` of `path` is not `want` (the header the manifest gives for
/// it; `fingerprint` the manifest's dataset fingerprint), most telling difference first.
pub(super) fn header_mismatch(path: &Path, found: &[u8], want: &[u8], fingerprint: &str) -> Error {
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
            fingerprint
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
}
