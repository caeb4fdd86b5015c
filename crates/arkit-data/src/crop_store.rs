//! `crop_store`: every sample's crop pixels and mesh stored once, so that the loader
//! ([`crate::loader::FaceLoader`]) reads one fixed-size record instead of decoding the
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
//! ([`CropStoreManifest`]: the rules, `S`, the margin, the vertex count, the dataset's
//! fingerprint, the files, the samples without pixels and why) and, per samples shard
//! `K`, `part-K.bin`: a 64-byte header (magic `ARKCROP1`, format, the rules, `S`, `m`,
//! `V`, record count, record size) and one record per row of `samples/part-K.parquet`,
//! in order, all of one size: CRC-32 of the rest, status (1: pixels, 0: none), the row,
//! the box (four float64), the mesh, the window (`(S + 2m)^2 x 3` bytes, RGB). Fixed
//! records need no index: record `r` is at `64 + r * size`.
//!
//! Nothing read is trusted before it is checked: [`CropStore::open`] checks the
//! manifest against the dataset (its fingerprint: a store of another or a re-converted
//! dataset is refused, never served stale), the rules, `S` and `V` the loader asks for,
//! and every file's header and length; [`CropStore::read`] checks each record's CRC,
//! status and row. A record whose sample had no readable image when the store was made
//! has status 0, and reading it is an error naming the sample and the recorded reason.
//! Files are written under a temporary name and renamed; `crops.json` last.
//!
//! Tested in `tests/crop_store.rs`: every field of every item equal with and without the
//! store in evaluation (both rule sets), the training items' geometry equal and their
//! pixels close, a truncated file, a flipped byte, a stale dataset and a missing image
//! each refused with the file named.

use crate::crop::{CropSampling, CropTransform};
use crate::error::{Error, Result};
use nalgebra::Point3;
use serde::{Deserialize, Serialize};
use std::fs::File;
use std::path::{Path, PathBuf};

/// The manifest's file name in a store folder.
pub const MANIFEST_FILE: &str = "crops.json";
/// The store format written here.
pub const FORMAT: u32 = 1;
/// Bytes of a `part-K.bin` header.
pub const HEADER_BYTES: u64 = 64;
const MAGIC: &[u8; 8] = b"ARKCROP1";
/// Largest `crops.json` read (its list of samples without pixels is what can grow).
const MAX_MANIFEST_BYTES: u64 = 256 << 20;
/// Bytes of a record before the mesh: CRC, status, row, the box.
const RECORD_PREFIX: usize = 4 + 4 + 8 + 4 * 8;

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

/// Bytes of one record for crop side `size` and `vertex_count` vertices.
pub fn record_bytes(size: u32, vertex_count: usize) -> u64 {
    let w = window_side(size) as u64;
    RECORD_PREFIX as u64 + 12 * vertex_count as u64 + 3 * w * w
}

/// `crops.json`: what a store holds and what it was made from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CropStoreManifest {
    /// [`FORMAT`].
    pub format: u32,
    /// The rules the boxes and windows follow: `"exact"` or `"official"`.
    pub compat: String,
    /// Crop side `S`.
    pub img_size: u32,
    /// [`margin`]`(S)`.
    pub margin: u32,
    /// Vertices per mesh.
    pub vertex_count: usize,
    /// [`crate::render_dataset::dataset_fingerprint`] of the dataset stored.
    pub dataset_fingerprint: String,
    /// [`record_bytes`].
    pub record_bytes: u64,
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

/// One sample's stored values.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredCrop {
    /// The evaluation crop's box.
    pub eval_crop: CropTransform,
    /// The mesh.
    pub verts: Vec<Point3<f32>>,
    /// The window, `W x W` RGB (`W =` [`window_side`]).
    pub window: image::RgbImage,
}

impl StoredCrop {
    /// The first crop pixel of the window along each axis (`-m`).
    pub fn first(&self) -> i64 {
        -(margin(self.eval_crop.size) as i64)
    }

    /// The window's side.
    pub fn side(&self) -> usize {
        window_side(self.eval_crop.size)
    }

    /// The evaluation crop: the window's centre `S x S` (RGB bytes, row-major).
    pub fn centre(&self) -> Vec<u8> {
        let (s, w, m) = (
            self.eval_crop.size as usize,
            self.side(),
            margin(self.eval_crop.size) as usize,
        );
        let mut out = Vec::with_capacity(s * s * 3);
        for r in m..m + s {
            out.extend_from_slice(&self.window.as_raw()[3 * (r * w + m)..3 * (r * w + m + s)]);
        }
        out
    }

    /// The pixels of `crop` (a box in the same image, of the same sampling and size):
    /// the centre when it is the evaluation crop, else resampled from the window.
    pub fn crop_pixels(&self, crop: &CropTransform) -> Vec<u8> {
        if *crop == self.eval_crop {
            return self.centre();
        }
        crop.in_window(&self.eval_crop, self.first()).crop_window(
            &self.window,
            0,
            crop.size as usize,
        )
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

/// The 64-byte header of a `part-K.bin` with `records` records.
fn header(manifest: &CropStoreManifest, records: usize) -> Result<[u8; 64]> {
    let mut h = [0u8; 64];
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
    h[36..44].copy_from_slice(&manifest.record_bytes.to_le_bytes());
    Ok(h)
}

/// One record's bytes: a stored crop, or `None` for a sample without pixels (status 0).
pub fn encode_record(
    manifest: &CropStoreManifest,
    row: usize,
    crop: Option<&StoredCrop>,
) -> Vec<u8> {
    let mut r = vec![0u8; manifest.record_bytes as usize];
    r[8..16].copy_from_slice(&(row as u64).to_le_bytes());
    if let Some(c) = crop {
        r[4..8].copy_from_slice(&1u32.to_le_bytes());
        let b = &c.eval_crop;
        for (i, v) in [b.x0, b.y0, b.side, b.side_y].iter().enumerate() {
            r[16 + 8 * i..24 + 8 * i].copy_from_slice(&v.to_le_bytes());
        }
        let mut at = RECORD_PREFIX;
        for p in &c.verts {
            for v in [p.x, p.y, p.z] {
                r[at..at + 4].copy_from_slice(&v.to_le_bytes());
                at += 4;
            }
        }
        r[at..at + c.window.len()].copy_from_slice(c.window.as_raw());
    }
    let crc = crc32fast::hash(&r[4..]);
    r[..4].copy_from_slice(&crc.to_le_bytes());
    r
}

/// Writes `dir/part-K.bin` (atomically) from its records, in row order.
pub fn write_shard_file(
    dir: &Path,
    manifest: &CropStoreManifest,
    index: usize,
    records: &mut dyn Iterator<Item = Vec<u8>>,
    count: usize,
) -> Result<CropShard> {
    let file = format!("part-{index}.bin");
    let path = dir.join(&file);
    let head = header(manifest, count)?;
    crate::atomic_file::write_atomically(&path, |w| {
        w.write_all(&head).map_err(|e| Error::io(&path, e))?;
        let mut written = 0;
        for r in records {
            w.write_all(&r).map_err(|e| Error::io(&path, e))?;
            written += 1;
        }
        if written != count {
            return Err(Error::invalid(
                "crop store",
                format!("{}: {written} records for {count} rows", path.display()),
            ));
        }
        Ok(())
    })?;
    Ok(CropShard {
        index,
        file,
        records: count,
    })
}

/// Writes `crops.json` (atomically; last, after every shard file).
pub fn write_manifest(dir: &Path, manifest: &CropStoreManifest) -> Result<()> {
    let text = serde_json::to_string_pretty(manifest).expect("manifest serialises");
    crate::atomic_file::write_bytes(&dir.join(MANIFEST_FILE), text.as_bytes())
}

/// Reads and parses `dir/crops.json`.
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
    serde_json::from_str(&text)
        .map_err(|e| Error::format(&path, format!("not a crop store manifest: {e}")))
}

/// An opened store (see the module docs).
#[derive(Debug)]
pub struct CropStore {
    dir: PathBuf,
    manifest: CropStoreManifest,
    /// Per samples shard index, its file and path.
    files: Vec<Option<(File, PathBuf)>>,
}

impl CropStore {
    /// Opens the store in `dir` for `dataset`, crops of rules `compat` and side
    /// `img_size`, meshes of `vertex_count` vertices; every check of the module docs
    /// but the records'.
    pub fn open(
        dir: &Path,
        dataset: &crate::dataset::Dataset,
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
        expect("format", manifest.format.to_string(), FORMAT.to_string())?;
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
        expect(
            "record_bytes",
            manifest.record_bytes.to_string(),
            record_bytes(img_size, vertex_count).to_string(),
        )?;
        let fingerprint = crate::render_dataset::dataset_fingerprint(dataset.manifest());
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
        let mut files: Vec<Option<(File, PathBuf)>> =
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
            if entry.records != s.rows || entry.file != format!("part-{}.bin", s.index) {
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
            let want = HEADER_BYTES + entry.records as u64 * manifest.record_bytes;
            if len != want {
                return Err(Error::format(
                    &path,
                    format!(
                        "{len} bytes, expected {want} (a header and {} records): the file is truncated or not this store's",
                        entry.records
                    ),
                ));
            }
            let mut head = [0u8; 64];
            read_exact_at(&file, &mut head, 0).map_err(|e| Error::io(&path, e))?;
            if head != header(&manifest, entry.records)? {
                return Err(Error::format(
                    &path,
                    "its header does not match crops.json (magic, format, rules, size, margin, vertices, records)",
                ));
            }
            files[s.index] = Some((file, path));
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

    /// The record of row `row` of samples shard `shard`.
    pub fn read(&self, shard: usize, row: usize) -> Result<StoredCrop> {
        let (file, path) = self
            .files
            .get(shard)
            .and_then(|f| f.as_ref())
            .ok_or_else(|| Error::invalid("crop store", format!("no samples shard {shard}")))?;
        let m = &self.manifest;
        // The head (CRC to mesh) and the window read into their own buffers, so the
        // window is returned as read, not moved out of the record.
        let verts_end = RECORD_PREFIX + 12 * m.vertex_count;
        let at = HEADER_BYTES + row as u64 * m.record_bytes;
        let mut r = vec![0u8; verts_end];
        let mut window = vec![0u8; m.record_bytes as usize - verts_end];
        read_exact_at(file, &mut r, at).map_err(|e| Error::io(path, e))?;
        read_exact_at(file, &mut window, at + verts_end as u64).map_err(|e| Error::io(path, e))?;
        let u32_at = |i: usize| u32::from_le_bytes(r[i..i + 4].try_into().expect("4 bytes"));
        let mut crc = crc32fast::Hasher::new();
        crc.update(&r[4..]);
        crc.update(&window);
        if crc.finalize() != u32_at(0) {
            return Err(Error::format(
                path,
                format!(
                    "record {row}: its CRC does not match (the file is damaged); run `arkit-tool crops` again"
                ),
            ));
        }
        let stored_row = u64::from_le_bytes(r[8..16].try_into().expect("8 bytes"));
        if stored_row != row as u64 {
            return Err(Error::format(
                path,
                format!("record {row} says it is row {stored_row}"),
            ));
        }
        if u32_at(4) != 1 {
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
        let f64_at = |i: usize| f64::from_le_bytes(r[i..i + 8].try_into().expect("8 bytes"));
        let eval_crop = CropTransform {
            x0: f64_at(16),
            y0: f64_at(24),
            side: f64_at(32),
            side_y: f64_at(40),
            size: m.img_size,
            sampling: sampling_of(&m.compat)?,
        };
        let verts = r[RECORD_PREFIX..verts_end]
            .chunks_exact(12)
            .map(|c| {
                let f = |k: usize| f32::from_le_bytes(c[k..k + 4].try_into().expect("4 bytes"));
                Point3::new(f(0), f(4), f(8))
            })
            .collect();
        let w = window_side(m.img_size) as u32;
        Ok(StoredCrop {
            eval_crop,
            verts,
            window: image::RgbImage::from_raw(w, w, window).expect("the record's window size"),
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

    #[test]
    fn a_record_round_trips_and_its_crc_catches_a_flipped_byte() {
        let m = CropStoreManifest {
            format: FORMAT,
            compat: "official".into(),
            img_size: 16,
            margin: margin(16),
            vertex_count: 2,
            dataset_fingerprint: String::new(),
            record_bytes: record_bytes(16, 2),
            shards: Vec::new(),
            missing: Vec::new(),
        };
        let w = window_side(16);
        let crop = StoredCrop {
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
        };
        let bytes = encode_record(&m, 5, Some(&crop));
        assert_eq!(bytes.len() as u64, m.record_bytes);
        assert_eq!(crc32fast::hash(&bytes[4..]).to_le_bytes(), bytes[..4]);
        // Decode through a one-shard store file.
        let dir = tempfile::tempdir().unwrap();
        let mut records = (0..6).map(|r| {
            if r == 5 {
                bytes.clone()
            } else {
                encode_record(&m, r, None)
            }
        });
        write_shard_file(dir.path(), &m, 0, &mut records, 6).unwrap();
        let path = dir.path().join("part-0.bin");
        let file = File::open(&path).unwrap();
        let store = CropStore {
            dir: dir.path().to_path_buf(),
            manifest: m.clone(),
            files: vec![Some((file, path.clone()))],
        };
        assert_eq!(store.read(0, 5).unwrap(), crop);
        let e = store.read(0, 2).unwrap_err().to_string();
        assert!(e.contains("part-0.bin") && e.contains("no pixels"), "{e}");
        // One byte of the window flipped: refused, naming the file.
        let mut all = std::fs::read(&path).unwrap();
        let at = (HEADER_BYTES + 5 * m.record_bytes) as usize + 100;
        all[at] ^= 1;
        std::fs::write(&path, &all).unwrap();
        let store = CropStore {
            files: vec![Some((File::open(&path).unwrap(), path.clone()))],
            ..store
        };
        let e = store.read(0, 5).unwrap_err().to_string();
        assert!(e.contains("part-0.bin") && e.contains("CRC"), "{e}");
    }
}
