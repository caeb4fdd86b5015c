//! The entry points of the fuzz targets of `arkit-data`'s readers (`fuzz/fuzz_targets`),
//! shared with the test that replays the committed seed corpus on stable (this module's
//! tests) and its seeded mutation loop (`ARKIT_FUZZ_ITERS`). Not part of the API.
//!
//! Each takes arbitrary bytes, runs one reader of untrusted files on them and returns
//! whether the input was accepted. A reader must return `Ok` or `Err`, never panic,
//! abort or allocate without bound. When the input is accepted, the entry also checks a
//! property of the format (two ways of reading agree, a re-encoding round trips) and
//! panics if it fails: those are our own invariants, so a panic is a bug found.
//!
//! The readers take paths: the entries write the input into a scratch folder of their
//! own (one per thread, under the system's temporary folder, removed when the thread
//! ends) and read it from there, as the tool does.
//!
//! Inputs that are more than one file (a crop store part with its manifest) are laid
//! out as [`container`] says; `examples/data_fuzz_seeds.rs` writes the seeds so.

use crate::ingest::convert::{CONVERSION_FILE, ConversionFingerprint, read_conversion_record};
use crate::store::crop_store::{
    self, CropStore, CropStoreManifest, WindowCodec, WindowPart, check_for_loader, decode_mesh,
    decode_window, encode_mesh, encode_window, read_manifest, reseal_part, window_parts,
    window_side,
};
use crate::store::dataset::Dataset;
use crate::store::manifest::{MANIFEST_FILE, MAX_SHARDS, Manifest, dataset_fingerprint};
use std::path::PathBuf;

/// The largest crop side the entries pass to the readers (a caller's choice, not the
/// file's: the loader passes its own `S`).
pub const MAX_FUZZ_SIZE: u32 = 96;
/// The most vertices the entries pass to the readers (the caller's `V`).
pub const MAX_FUZZ_VERTICES: usize = 4096;
/// The most records (rows) of a crop store part the entries read (the dataset's rows).
pub const MAX_FUZZ_RECORDS: usize = 256;

/// A folder of this thread's, removed when the thread ends.
struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

thread_local! {
    static SCRATCH: Scratch = {
        static NEXT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("arkit-fuzz-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("a scratch folder for the fuzz entries");
        Scratch(dir)
    };
}

/// This thread's scratch folder, emptied of the files `names`.
fn scratch(names: &[&str]) -> PathBuf {
    SCRATCH.with(|s| {
        for n in names {
            let _ = std::fs::remove_file(s.0.join(n));
        }
        s.0.clone()
    })
}

/// The inputs of more than one part: each part but the last as a `u32` little-endian
/// byte count and its bytes, then the last part (the rest).
pub mod container {
    /// The `n` parts of `data` ([`self`]), or `None` when a count runs past its end.
    pub fn split(data: &[u8], n: usize) -> Option<Vec<&[u8]>> {
        let mut parts = Vec::with_capacity(n);
        let mut rest = data;
        for _ in 1..n {
            let (len, tail) = rest.split_first_chunk::<4>()?;
            let len = u32::from_le_bytes(*len) as usize;
            if len > tail.len() {
                return None;
            }
            let (part, tail) = tail.split_at(len);
            parts.push(part);
            rest = tail;
        }
        parts.push(rest);
        Some(parts)
    }

    /// The bytes of `parts` laid out as [`split`] reads them.
    pub fn join(parts: &[&[u8]]) -> Vec<u8> {
        let mut out = Vec::new();
        for (i, p) in parts.iter().enumerate() {
            if i + 1 < parts.len() {
                out.extend_from_slice(&(p.len() as u32).to_le_bytes());
            }
            out.extend_from_slice(p);
        }
        out
    }
}

/// A crop store part file with its manifest, read as the loader reads it: the input is
/// a [`container`] of `crops.json`, the keys of the shard's rows (one a line, as the
/// dataset gives them), a flags byte and the shard index (`u32` LE) and `part-K.bin`.
/// Flag bit 0: recompute the records' and the index's CRCs first (`crop_store::reseal_part`),
/// to reach the checks and decoders behind them (a hostile file can carry valid CRCs).
/// The manifest is read ([`read_manifest`]) and checked as [`CropStore::open`] checks
/// it for a loader of its own rules, side (at most [`MAX_FUZZ_SIZE`]) and vertex count
/// (at most [`MAX_FUZZ_VERTICES`]); the part is opened (header and index) and each
/// record read with its key. Accepted when every record reads; then each record's
/// window decoded whole, as its centre and as each part of the ring agree pixel for
/// pixel, and its evaluation crop is the centre.
pub fn crop_part(data: &[u8]) -> bool {
    let Some([json, keys, head, part]) =
        container::split(data, 4).map(|p| [p[0], p[1], p[2], p[3]])
    else {
        return false;
    };
    let Ok(keys) = std::str::from_utf8(keys) else {
        return false;
    };
    let keys: Vec<&str> = if keys.is_empty() {
        Vec::new()
    } else {
        keys.split('\n').collect()
    };
    if keys.len() > MAX_FUZZ_RECORDS || head.len() != 5 {
        return false;
    }
    let shard = u32::from_le_bytes([head[1], head[2], head[3], head[4]]) as usize;
    if shard >= 64 {
        return false;
    }
    let dir = scratch(&[crop_store::MANIFEST_FILE, "part.bin"]);
    let mut part = part.to_vec();
    if head[0] & 1 == 1 {
        reseal_part(&mut part, keys.len());
    }
    let path = dir.join("part.bin");
    let written = std::fs::write(dir.join(crop_store::MANIFEST_FILE), json)
        .and_then(|_| std::fs::write(&path, &part));
    written.expect("the scratch folder takes the input");
    let Ok(m) = read_manifest(&dir) else {
        return false;
    };
    if m.img_size == 0 || m.img_size > MAX_FUZZ_SIZE || m.vertex_count > MAX_FUZZ_VERTICES {
        return false;
    }
    if !loader_takes(&m, &dir.join(crop_store::MANIFEST_FILE)) {
        return false;
    }
    let Ok(store) = CropStore::of_part(&dir, &m, &path, shard, keys.len()) else {
        return false;
    };
    for (row, key) in keys.iter().enumerate() {
        let Ok(rec) = store.read(shard, row, key) else {
            return false;
        };
        assert!(rec.verts.len() == m.vertex_count, "a mesh of another size");
        let Ok(whole) = rec.decode(WindowPart::Whole) else {
            return false;
        };
        check_window_parts(&whole.window.clone().into_raw(), m.img_size, &|p| {
            rec.decode(p).map(|c| c.window.into_raw()).ok()
        });
        let centre = rec.crop_pixels(&rec.eval_crop);
        assert!(
            centre.ok().as_ref() == Some(&whole.centre()),
            "the evaluation crop is not the window's centre"
        );
    }
    true
}

/// Whether a loader of the manifest's own rules (a `crops.json` naming other rules does
/// not parse), side and vertex count takes the store manifest `m` (read from `path`):
/// [`check_for_loader`].
fn loader_takes(m: &CropStoreManifest, path: &std::path::Path) -> bool {
    check_for_loader(m, path, m.rules, m.img_size, m.vertex_count).is_ok()
}

/// Checks that the window `whole` (`W x W x 3`, crop side `size`) agrees with the
/// decodings `decode` gives of its centre and of each part of its ring: the centre's
/// pixels, and each part's pixels inside the whole window's. A decoding that fails
/// after the whole window decoded is a bug.
fn check_window_parts(whole: &[u8], size: u32, decode: &dyn Fn(WindowPart) -> Option<Vec<u8>>) {
    let w = window_side(size);
    let parts = window_parts(size);
    let rect_of = |img: &[u8], r: &crop_store::PixelRect, side: usize| -> Vec<u8> {
        (r.y..r.y + r.height)
            .flat_map(|y| img[3 * (y * side + r.x)..3 * (y * side + r.x + r.width)].to_vec())
            .collect()
    };
    let centre = decode(WindowPart::Centre).expect("the centre decodes when the whole does");
    assert!(
        centre == rect_of(whole, &parts[0], w),
        "the centre decoded alone differs from the whole window's"
    );
    for r in parts {
        let region = decode(WindowPart::Region(r)).expect("a region decodes when the whole does");
        assert!(
            rect_of(&region, &r, w) == rect_of(whole, &r, w),
            "region {r:?} decoded differs from the whole window's"
        );
    }
}

/// The code of `codec` in a part file's header (byte 0 of a [`crop_window`] input).
pub fn codec_code(codec: WindowCodec) -> u32 {
    codec.code()
}

/// A stored window through the codecs' decoder ([`decode_window`]): byte 0 is the
/// codec's code in a part file's header, byte 1 the crop side `S` (the store's, from
/// its manifest; 1..=[`MAX_FUZZ_SIZE`]), the rest the window's stored bytes. Accepted
/// when the whole window decodes; then its centre and each part of its ring decoded
/// alone agree with it, and the window encoded again by the codec decodes to it.
pub fn crop_window(data: &[u8]) -> bool {
    let [code, size, ref bytes @ ..] = *data else {
        return false;
    };
    let Some(codec) = WindowCodec::ALL
        .iter()
        .copied()
        .find(|c| c.code() == code as u32)
    else {
        return false;
    };
    let size = size as u32;
    if size == 0 || size > MAX_FUZZ_SIZE {
        return false;
    }
    let Ok(whole) = decode_window(codec, bytes, size, WindowPart::Whole) else {
        return false;
    };
    check_window_parts(&whole, size, &|p| decode_window(codec, bytes, size, p).ok());
    let w = window_side(size) as u32;
    let img = image::RgbImage::from_raw(w, w, whole.clone()).expect("W x W x 3 bytes");
    let again = encode_window(codec, &img, size).expect("a decoded window encodes");
    assert!(
        decode_window(codec, &again, size, WindowPart::Whole).ok() == Some(whole),
        "{}: the window encoded again decodes to other pixels",
        codec.name()
    );
    true
}

/// A stored mesh through [`decode_mesh`]: bytes 0..2 are the vertex count `V` (`u16`
/// LE: the store's, from its manifest), the rest the mesh's stored bytes. Accepted when
/// it decodes; then encoding the vertices again ([`encode_mesh`]) and decoding gives
/// the same bits.
pub fn mesh(data: &[u8]) -> bool {
    let [a, b, ref bytes @ ..] = *data else {
        return false;
    };
    let v = u16::from_le_bytes([a, b]) as usize;
    let Ok(verts) = decode_mesh(bytes, v) else {
        return false;
    };
    assert!(verts.len() == v, "{} vertices, asked for {v}", verts.len());
    let bits = |p: &[nalgebra::Point3<f32>]| -> Vec<u32> {
        p.iter()
            .flat_map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
            .collect()
    };
    let again = decode_mesh(&encode_mesh(&verts), v).expect("our own mesh decodes");
    assert!(bits(&again) == bits(&verts), "mesh round trip changed bits");
    true
}

/// `crops.json` through [`read_manifest`] and the loader's checks of it
/// (`crop_store::check_for_loader`, for its own rules, side and vertex count). Accepted when both
/// pass; then the manifest written again reads back equal, and each shard's part
/// header follows from it.
pub fn crops_json(data: &[u8]) -> bool {
    let dir = scratch(&[crop_store::MANIFEST_FILE]);
    let path = dir.join(crop_store::MANIFEST_FILE);
    std::fs::write(&path, data).expect("the scratch folder takes the input");
    let Ok(m) = read_manifest(&dir) else {
        return false;
    };
    if !loader_takes(&m, &path) {
        return false;
    }
    let text = serde_json::to_string(&m).expect("a manifest serialises");
    let back: CropStoreManifest = serde_json::from_str(&text).expect("our own manifest parses");
    assert!(back == m, "crops.json round trip changed it");
    for s in &m.shards {
        if s.index < MAX_SHARDS {
            assert!(
                m.part_header(s.index, s.records).is_ok(),
                "a checked manifest gives no part header"
            );
        }
    }
    true
}

/// `dataset.json` through [`Dataset::open`] (which reads and checks it,
/// [`Manifest::check`]). Accepted when it opens; then every shard's files lie inside
/// the dataset's folder, the manifest written again reads back equal, and its
/// fingerprint is computed.
pub fn dataset_json(data: &[u8]) -> bool {
    let dir = scratch(&[MANIFEST_FILE]);
    std::fs::write(dir.join(MANIFEST_FILE), data).expect("the scratch folder takes the input");
    let Ok(ds) = Dataset::open(&dir) else {
        return false;
    };
    let m = ds.manifest();
    for s in ds.shards() {
        assert!(s.index < MAX_SHARDS, "shard index {} unbounded", s.index);
        for f in [&s.samples_file, &s.errors_file] {
            let up = std::path::Path::new(f)
                .components()
                .any(|c| matches!(c, std::path::Component::ParentDir));
            assert!(
                dir.join(f).starts_with(&dir) && !up,
                "{f} is outside the dataset"
            );
        }
    }
    let text = serde_json::to_string(m).expect("a manifest serialises");
    let back: Manifest = serde_json::from_str(&text).expect("our own manifest parses");
    assert!(&back == m, "dataset.json round trip changed it");
    assert!(dataset_fingerprint(m).len() == 64);
    true
}

/// `conversion.json` through [`read_conversion_record`]. Accepted when it reads; then
/// the record written again reads back equal, with the same digest.
pub fn conversion_json(data: &[u8]) -> bool {
    let dir = scratch(&[CONVERSION_FILE]);
    let path = dir.join(CONVERSION_FILE);
    std::fs::write(&path, data).expect("the scratch folder takes the input");
    let Ok(Some(c)) = read_conversion_record(&path) else {
        return false;
    };
    let text = serde_json::to_string(&c).expect("a record serialises");
    let back: ConversionFingerprint = serde_json::from_str(&text).expect("our own record parses");
    assert!(back == c, "conversion.json round trip changed it");
    assert!(back.digest() == c.digest());
    true
}

pub mod harness;

#[cfg(test)]
mod tests;
