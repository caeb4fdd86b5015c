//! `records`: one sample's record in its bytes ([`encode_record`]) and back
//! ([`StoredRecord::from_bytes`], every check of a record's bytes); the values a record
//! holds ([`StoredRecord`]: the box and mesh decoded, the window as stored) and a crop's
//! pixels from them, decoding only what the crop reaches ([`StoredCrop`]). The layout
//! is [`super::format`]'s. Uses `format`, `codec`, `mesh_codec` and `manifest`.

use super::codec::{WindowCodec, decode_window, encode_window};
use super::format::{
    AT_FINGERPRINT, AT_KEY, AT_KEY_LEN, AT_ROW, AT_SHARD, AT_STATUS, FINGERPRINT_BYTES, PixelRect,
    WindowPart, max_window_bytes, record_prefix, window_centre, window_first, window_side,
};
use super::manifest::CropStoreManifest;
use super::mesh_codec::{decode_mesh, encode_mesh, max_mesh_bytes};
use crate::crop::CropTransform;
use arkit_core::{Error, Result};
use nalgebra::Point3;
use std::path::{Path, PathBuf};

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
    pub(crate) fn crop_pixels(&self, crop: &CropTransform) -> Result<Vec<u8>> {
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

/// A record read and checked ([`super::CropStore::read`]): its box and mesh decoded, its window
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
    /// The pixels as read, of a codec that stores them as they are (`raw`).
    Pixels(image::RgbImage),
    /// Any other codec's bytes, decoded when asked for.
    Encoded(Vec<u8>),
}

impl StoredRecord {
    /// Its window's `part` decoded ([`decode_window`]). An error names the part file
    /// and the record.
    pub fn decode(&self, part: WindowPart) -> Result<StoredCrop> {
        let size = self.eval_crop.size;
        let pixels = match (&self.window, part) {
            (StoredWindow::Pixels(w), WindowPart::Centre) => window_centre(w.as_raw(), size),
            (StoredWindow::Pixels(w), _) => w.as_raw().clone(),
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
    pub(crate) fn crop_pixels(&self, crop: &CropTransform) -> Result<Vec<u8>> {
        let first = window_first(self.eval_crop.size);
        if let StoredWindow::Pixels(window) = &self.window {
            // Pixels as stored are resampled where they were read.
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

/// One record's bytes: row `row` of samples shard `shard`, sample `key`; a stored crop
/// (its window stored by the manifest's codec), or `None` for a sample without pixels
/// (status 0). A key wider than the manifest's key field is an error.
pub(crate) fn encode_record(
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

impl StoredRecord {
    /// The record of row `row` of samples shard `shard` of the store `m`, read from the
    /// part file `path` as `r` (its first [`record_prefix`] bytes, or all of a shorter
    /// record) and `tail` (the rest: the window, then the mesh): checked, in this order,
    /// its CRC, that it is the record of this dataset, this shard, this row and the
    /// sample `key` (a comparison of a few dozen bytes, no hashing of the data), its
    /// status, and that the window's and the mesh's lengths fill the record and are
    /// within their bounds; only then is the mesh decoded. The window is kept as read
    /// (the buffer `tail`, the mesh cut off). Errors name the file and the record.
    pub(super) fn from_bytes(
        m: &CropStoreManifest,
        path: &Path,
        (shard, row, key): (usize, usize, &str),
        r: Vec<u8>,
        mut tail: Vec<u8>,
    ) -> Result<StoredRecord> {
        let len = r.len() + tail.len();
        let prefix = record_prefix(m.key_bytes);
        let head_len = r.len();
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
            rules: m.rules,
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
        let window = if m.codec.stores_pixels() {
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
            StoredWindow::Pixels(image::RgbImage::from_raw(w, w, tail).ok_or_else(bad)?)
        } else {
            StoredWindow::Encoded(tail)
        };
        Ok(StoredRecord {
            eval_crop,
            verts,
            window,
            codec: m.codec,
            path: path.to_path_buf(),
            row,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::crop::RuleSet;

    #[test]
    fn a_records_training_crops_decode_only_what_they_reach_and_equal_the_whole_windows() {
        let mut x = 0x0bad_cafe_u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as u8
        };
        for &rules in RuleSet::ALL {
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
                rules,
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
                    "{rules:?} {dx} {dy} {scale}"
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
}
