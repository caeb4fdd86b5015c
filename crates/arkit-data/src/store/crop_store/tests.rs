//! The store's tests across its files: records written by the writer and read back by
//! the reader in every codec (the `cfg(test)` codec `xor` included), and records
//! that are not the one asked for, or whose lengths do not add up, refused. Nothing
//! imports this file.

use super::codec::{WindowCodec, encode_window};
use super::format::{
    AT_KEY, FOOTER_BYTES, FORMAT, WindowPart, key_field_bytes, margin, raw_record_bytes,
    record_prefix, window_side,
};
use super::manifest::CropStoreManifest;
use super::mesh_codec::encode_mesh;
use super::reader::CropStore;
use super::records::{StoredCrop, encode_record};
use super::writer::write_shard_file;
use crate::crop::{CropTransform, RuleSet};
use arkit_core::Result;
use nalgebra::Point3;
use std::path::Path;

fn manifest() -> CropStoreManifest {
    CropStoreManifest {
        format: FORMAT,
        rules: RuleSet::Official,
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
            rules: RuleSet::Official,
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
    CropStore::of_part(dir, m, &dir.join("part-0.bin"), 0, n).unwrap()
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
    // Every codec of the table, `xor` (the tests' own, registered by its file and one
    // line) among them: written by the writer, its header checked and its records read
    // back by the reader.
    assert!(WindowCodec::ALL.contains(&WindowCodec::Xor));
    for &codec in WindowCodec::ALL {
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
        let e = CropStore::of_part(dir.path(), &m, &path, 0, 6).unwrap_err();
        assert!(e.to_string().contains("index's CRC"), "{e}");
    }
}

/// `store` with its part file opened again from `path`.
fn store_of_file(store: &CropStore, path: &Path) -> CropStore {
    CropStore::of_part(store.dir(), store.manifest(), path, 0, 6).unwrap()
}

#[test]
fn a_record_of_another_sample_row_shard_or_dataset_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let (m, crop) = (manifest(), crop());
    let store = store_of(dir.path(), &m, six(&m, &crop));
    // Asked as another sample: the key differs.
    let e = whole(&store, 0, 5, "s/a/6").unwrap_err().to_string();
    assert!(
        e.contains("part-0.bin") && e.contains("should be sample s/a/6, but it holds sample s/a/5"),
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
