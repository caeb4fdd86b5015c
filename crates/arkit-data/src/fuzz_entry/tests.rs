//! The committed seed corpus (`fuzz/corpus/<target>/`) replayed through the entries, on
//! stable: each target's folder must hold at least so many seeds, each must return
//! without panicking, and at least so many (the valid files the tool wrote) must be
//! accepted. Then the seeded mutation loop over the same seeds ([`harness`]):
//! `ARKIT_FUZZ_ITERS` mutated inputs per target (300 by default, about a second;
//! docs/testing.md, "Fuzzing"), none of which may panic.

use super::harness::{self, Entry, corpus_root};
use super::*;

fn replay(target: &str, entry: Entry, min_files: usize, min_accepted: usize) -> Vec<Vec<u8>> {
    let corpus = corpus_root(env!("CARGO_MANIFEST_DIR"));
    harness::replay(&corpus, target, entry, min_files, min_accepted)
}

fn refused(target: &str, entry: Entry, damaged: &[&str], but: &[&str]) {
    let corpus = corpus_root(env!("CARGO_MANIFEST_DIR"));
    harness::refused(&corpus, target, entry, damaged, but);
}

#[test]
fn crop_part_corpus() {
    replay("crop_part", crop_part, 21, 6);
    let damaged = ["truncated", "no_footer", "crc_flipped", "window_flipped"];
    refused("crop_part", crop_part, &damaged, &["resealed"]);
}

#[test]
fn crop_window_corpus() {
    replay("crop_window", crop_window, 9, 3);
    refused("crop_window", crop_window, &["truncated"], &[]);
}

#[test]
fn mesh_corpus() {
    replay("mesh", mesh, 5, 2);
    // (A flipped bit can decode to other values of the right size: the mesh has no
    // checksum of its own, the record's CRC covers it.)
    refused("mesh", mesh, &["truncated", "one_vertex_more"], &[]);
}

#[test]
fn crops_json_corpus() {
    replay("crops_json", crops_json, 7, 3);
    refused(
        "crops_json",
        crops_json,
        &["truncated", "format_5", "huge", "webp"],
        &[],
    );
}

#[test]
fn dataset_json_corpus() {
    replay("dataset_json", dataset_json, 9, 3);
    let hostile = ["truncated", "absolute", "dotdot", "huge", "past_count"];
    refused("dataset_json", dataset_json, &hostile, &[]);
}

#[test]
fn conversion_json_corpus() {
    replay("conversion_json", conversion_json, 3, 1);
    refused(
        "conversion_json",
        conversion_json,
        &["truncated", "negative"],
        &[],
    );
}

/// The test codec (`xor`, registered under `cfg(test)` only, so the tool cannot write
/// its seeds): every accepted `raw` window seed, stored again by it, is accepted.
#[test]
fn the_test_codec_takes_the_raw_seeds() {
    let raw = WindowCodec::ALL.iter().find(|c| c.name() == "raw").unwrap();
    let xor = WindowCodec::ALL.iter().find(|c| c.name() == "xor").unwrap();
    let mut n = 0;
    for s in replay("crop_window", crop_window, 1, 0) {
        if s[0] as u32 != raw.code() {
            continue;
        }
        let size = s[1] as u32;
        let w = window_side(size) as u32;
        let img = image::RgbImage::from_raw(w, w, s[2..].to_vec()).unwrap();
        let mut again = vec![xor.code() as u8, s[1]];
        again.extend(encode_window(*xor, &img, size).unwrap());
        assert!(crop_window(&again), "an xor window refused");
        n += 1;
    }
    assert!(n >= 1, "no raw window seed");
}

#[test]
fn mutated_seeds_never_panic() {
    let targets: [(&str, Entry); 6] = [
        ("crop_part", crop_part),
        ("crop_window", crop_window),
        ("mesh", mesh),
        ("crops_json", crops_json),
        ("dataset_json", dataset_json),
        ("conversion_json", conversion_json),
    ];
    harness::mutation_loop(&corpus_root(env!("CARGO_MANIFEST_DIR")), &targets, 300);
}
