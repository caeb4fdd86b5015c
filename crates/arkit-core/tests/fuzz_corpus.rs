//! Replays every file of the committed fuzz seed corpus (`fuzz/corpus/<target>/`)
//! through the same entry points as the fuzz targets (`arkit_core::fuzz_entry`), on
//! stable, so `cargo test` catches a regression on any input the fuzzer once found
//! interesting. Each entry must return (accepted or refused) without panicking; the
//! test fails if a target's folder is missing or holds fewer seeds than expected, and
//! checks that the valid seeds written by our own writers are accepted.

use arkit_core::fuzz_entry;
use std::path::PathBuf;

type Entry = fn(&[u8]) -> bool;

fn replay(target: &str, entry: Entry, min_files: usize, min_accepted: usize) {
    let dir = crate::support::workspace().join("fuzz/corpus").join(target);
    let entries = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("seed corpus {} missing: {e}", dir.display()));
    let mut files: Vec<PathBuf> = entries
        .map(|e| e.expect("directory entry").path())
        .filter(|p| p.is_file())
        .collect();
    files.sort();
    assert!(
        files.len() >= min_files,
        "{target}: {} seed files, expected at least {min_files}",
        files.len()
    );
    let mut accepted = 0;
    for f in &files {
        let bytes = std::fs::read(f).expect("read seed");
        let ok = std::panic::catch_unwind(|| entry(&bytes))
            .unwrap_or_else(|_| panic!("{target}: {} panicked", f.display()));
        accepted += ok as usize;
    }
    assert!(
        accepted >= min_accepted,
        "{target}: {accepted} of {} seeds accepted, expected at least {min_accepted}",
        files.len()
    );
}

#[test]
fn npy_corpus() {
    replay("npy", fuzz_entry::npy, 21, 20);
}

#[test]
fn npz_corpus() {
    replay("npz", fuzz_entry::npz, 5, 5);
}

#[test]
fn info_npz_corpus() {
    replay("info_npz", fuzz_entry::info_npz, 3, 2);
}

#[test]
fn list_csv_corpus() {
    replay("list_csv", fuzz_entry::list_csv, 4, 3);
}

#[test]
fn predictions_csv_corpus() {
    replay("predictions_csv", fuzz_entry::predictions_csv, 3, 2);
}

#[test]
fn targets_blobs_corpus() {
    replay("targets_blobs", fuzz_entry::targets_blobs, 4, 3);
}

#[test]
fn torch_pickle_corpus() {
    replay("torch_pickle", fuzz_entry::torch_pickle, 10, 3);
}
