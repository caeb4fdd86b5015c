//! The committed seed corpus of perspnet's targets replayed through the entries, then
//! the seeded mutation loop (`ARKIT_FUZZ_ITERS`, 300 by default), as in
//! `arkit_data::fuzz_entry`'s tests.

use super::*;
use arkit_data::fuzz_entry::harness::{self, Entry, corpus_root};

fn replay(target: &str, entry: Entry, min_files: usize, min_accepted: usize) {
    let corpus = corpus_root(env!("CARGO_MANIFEST_DIR"));
    harness::replay(&corpus, target, entry, min_files, min_accepted);
}

fn refused(target: &str, entry: Entry, damaged: &[&str]) {
    let corpus = corpus_root(env!("CARGO_MANIFEST_DIR"));
    harness::refused(&corpus, target, entry, damaged, &[]);
}

#[test]
fn checkpoint_json_corpus() {
    replay("checkpoint_json", checkpoint_json, 7, 1);
    let damaged = [
        "as_written",
        "truncated",
        "unlisted",
        "off_by_one",
        "sha_other",
        "huge",
    ];
    refused("checkpoint_json", checkpoint_json, &damaged);
}

#[test]
fn perspnet_json_corpus() {
    replay("perspnet_json", perspnet_json, 7, 3);
    refused(
        "perspnet_json",
        perspnet_json,
        &["truncated", "huge", "dropout_one", "zero"],
    );
}

#[test]
fn mutated_seeds_never_panic() {
    let targets: [(&str, Entry); 2] = [
        ("checkpoint_json", checkpoint_json),
        ("perspnet_json", perspnet_json),
    ];
    harness::mutation_loop(&corpus_root(env!("CARGO_MANIFEST_DIR")), &targets, 300);
}
