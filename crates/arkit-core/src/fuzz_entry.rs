//! The entry points of the fuzz targets in `fuzz/`, shared with the test that replays
//! the committed seed corpus on stable (`tests/fuzz_corpus.rs`).
//!
//! Each takes arbitrary bytes, runs one reader of untrusted files on them and returns
//! whether the input was accepted. A reader must return `Ok` or `Err`, never panic,
//! abort or allocate without bound (the fuzzer runs with an RSS limit). When the input
//! is accepted, the entry also checks a property of the codec (re-encoding round trips,
//! validation agreeing with use) and panics if it fails: those assertions are on our
//! own invariants, so a panic here is a bug found, not a rejected input.

use crate::conventions::Pose;
use crate::{npy, predictions_csv, release, target_codec, torch_pickle};
use std::path::Path;

/// `.npy` bytes through [`npy::parse_npy`]; an accepted array written back and read
/// again writes the same bytes.
pub fn npy(data: &[u8]) -> bool {
    let Ok(a) = npy::parse_npy(data, Path::new("fuzz.npy")) else {
        return false;
    };
    let mut once = Vec::new();
    if npy::write_npy(&mut once, &a).is_err() {
        panic!("an accepted array cannot be written");
    }
    let again = match npy::parse_npy(&once, Path::new("again.npy")) {
        Ok(b) => b,
        Err(e) => panic!("our own output is refused: {e}"),
    };
    let mut twice = Vec::new();
    if npy::write_npy(&mut twice, &again).is_err() {
        panic!("a re-read array cannot be written");
    }
    assert!(once == twice, "write(read(write(a))) differs from write(a)");
    true
}

/// `.npz` bytes through [`npy::parse_npz`]; an accepted archive written back (stored)
/// reads back with the same keys and shapes.
pub fn npz(data: &[u8]) -> bool {
    let Ok(z) = npy::parse_npz(data, Path::new("fuzz.npz")) else {
        return false;
    };
    let keys: Vec<String> = z.keys().map(str::to_string).collect();
    let members: Vec<(&str, &npy::NpyArray)> = keys
        .iter()
        .filter_map(|k| z.get(k).map(|a| (k.as_str(), a)))
        .collect();
    let mut cur = std::io::Cursor::new(Vec::new());
    // Duplicate names (possible in a zip) are refused by the writer; nothing to compare.
    if npy::write_npz(&mut cur, &members, npy::NpzCompression::Stored).is_err() {
        return true;
    }
    match npy::parse_npz(cur.get_ref(), Path::new("again.npz")) {
        Ok(back) => {
            for (k, a) in &members {
                let shape = back.get(k).map(|b| b.shape().to_vec());
                assert!(shape.as_deref() == Some(a.shape()), "member {k} changed");
            }
        }
        Err(e) => panic!("our own archive is refused: {e}"),
    }
    true
}

/// `_info.npz` bytes: [`npy::parse_npz`], then `release::InfoAnnotation::from_npz`,
/// and [`Pose::from_release_rt`] of any 4x4 finite `R_t` present. An annotation that
/// validates has a usable pose (validation and use agree).
pub fn info_npz(data: &[u8]) -> bool {
    let path = Path::new("fuzz_info.npz");
    let Ok(z) = npy::parse_npz(data, path) else {
        return false;
    };
    if let Ok(v) = z.require_finite_f64("R_t", &[4, 4]) {
        let mut rt = [0.0; 16];
        rt.copy_from_slice(&v);
        let _ = Pose::from_release_rt(&rt);
    }
    match release::InfoAnnotation::from_npz(&z, path) {
        Ok(info) => {
            if let Err(e) = info.pose() {
                panic!("a validated R_t gives no pose: {e}");
            }
            assert!(info.verts.len() == release::ARKIT_VERTEX_COUNT);
            true
        }
        Err(_) => false,
    }
}

/// List CSV text through `release::parse_list`; accepted keys are plain, non-empty
/// names, and a list of accepted keys written by [`release::list_csv_text`] (when no key
/// needs quoting) reads back the same.
pub fn list_csv(data: &[u8]) -> bool {
    let Ok(text) = std::str::from_utf8(data) else {
        return false;
    };
    let Ok(rows) = release::parse_list(text, Path::new("fuzz.csv")) else {
        return false;
    };
    let keys: Vec<release::SampleKey> = rows.into_iter().map(|r| r.key).collect();
    for k in &keys {
        for v in [&k.subject_id, &k.facial_action, &k.img_id] {
            assert!(!v.is_empty() && !v.contains('/') && !v.contains('\\'));
        }
    }
    let plain = |v: &str| !v.contains([',', '"', '\n', '\r', '\u{feff}']) && v.trim() == v;
    if keys
        .iter()
        .all(|k| plain(&k.subject_id) && plain(&k.facial_action) && plain(&k.img_id))
    {
        match release::parse_list(&release::list_csv_text(&keys), Path::new("again.csv")) {
            Ok(back) => {
                let back: Vec<_> = back.into_iter().map(|r| r.key).collect();
                assert!(back == keys, "list CSV round trip changed the keys");
            }
            Err(e) => panic!("our own list is refused: {e}"),
        }
    }
    true
}

/// Predictions CSV text through [`predictions_csv::parse_csv`]; every accepted pose has
/// 16 values (by type) and no mask.
pub fn predictions_csv(data: &[u8]) -> bool {
    let Ok(text) = std::str::from_utf8(data) else {
        return false;
    };
    match predictions_csv::parse_csv(text, Path::new("fuzz_pred.csv")) {
        Ok(rows) => {
            assert!(rows.iter().all(|r| r.mask_rle.is_none()));
            true
        }
        Err(_) => false,
    }
}

/// The `targets` blob decoders, with every size taken from the input: bytes 0..4 are
/// the mask's pixel count (u32 LE), 4..6 the UV side (u16 LE, so above
/// [`crate::limits::MAX_UV_SIZE`] too), 6..8 a split point; the rest is the blob(s).
/// Runs the mask decoder on the u32s before the split, the UV decoder on the whole
/// rest, and the correspondence decoder on the two parts. Accepted blobs round-trip.
pub fn targets_blobs(data: &[u8]) -> bool {
    if data.len() < 8 {
        return false;
    }
    let len = u32::from_le_bytes([data[0], data[1], data[2], data[3]]) as usize;
    let uv_size = u16::from_le_bytes([data[4], data[5]]) as u32;
    let rest = &data[8..];
    let split = (u16::from_le_bytes([data[6], data[7]]) as usize).min(rest.len());
    let (a, b) = rest.split_at(split);
    let mut accepted = false;
    let _ = target_codec::mask_len(data[0] as u32 * 256, data[1] as u32 * 256, "mask");
    if let Ok(runs) = target_codec::unpack_u32_le(a, "mask_rle")
        && let Ok(mask) = target_codec::rle_decode(&runs, len)
    {
        let again = target_codec::rle_decode(&target_codec::rle_encode(&mask), len);
        assert!(again.ok().as_ref() == Some(&mask), "RLE round trip");
        accepted = true;
    }
    if let Ok(bits) = target_codec::decode_uv_map(rest, uv_size) {
        assert!(
            target_codec::encode_uv_map(&bits, uv_size) == rest,
            "UV map round trip"
        );
        accepted = true;
    }
    if let Ok((ids, ws)) = target_codec::decode_correspondences(a, b) {
        let (va, wb) = target_codec::encode_correspondences(&ids, &ws);
        assert!(va == a && wb == b, "correspondence round trip");
        accepted = true;
    }
    accepted
}

/// A `torch.save` archive (input starting with `PK`) through
/// [`torch_pickle::TorchZip::new`], every tensor then read; or else the bytes as a
/// bare `data.pkl` through `torch_pickle::parse_state_dict_pickle`. An accepted
/// tensor lies in its storage, and its data read is exactly `numel` elements.
pub fn torch_pickle(data: &[u8]) -> bool {
    if data.starts_with(b"PK") {
        let Ok(mut z) =
            torch_pickle::TorchZip::new(std::io::Cursor::new(data), Path::new("fuzz.pth"))
        else {
            return false;
        };
        for i in 0..z.tensors().len() {
            let t = z.tensors()[i].clone();
            match z.read(i) {
                Ok(b) => assert!(
                    b.len() == t.numel() * t.dtype.size(),
                    "{}: wrong length",
                    t.name
                ),
                Err(_) => return false,
            }
        }
        return true;
    }
    let Ok(tensors) = torch_pickle::parse_state_dict_pickle(data, Path::new("data.pkl")) else {
        return false;
    };
    for t in &tensors {
        assert!(t.shape.len() == t.stride.len());
        if t.numel() > 0 {
            let last = t.offset as u64
                + t.shape
                    .iter()
                    .zip(&t.stride)
                    .map(|(&n, &s)| (n as u64 - 1) * s as u64)
                    .sum::<u64>();
            assert!(
                last < t.storage_numel,
                "{} reaches beyond its storage",
                t.name
            );
        }
    }
    true
}
