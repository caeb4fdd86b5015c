//! The entry points of the fuzz targets of `arkit-perspnet`'s readers
//! (`fuzz/fuzz_targets`), shared with the test that replays the committed seed corpus on
//! stable (this module's tests) and its seeded mutation loop (`ARKIT_FUZZ_ITERS`). Not
//! part of the API; see `arkit_data::fuzz_entry` for the rules every entry follows.

use crate::training::checkpoint::{
    CHECKPOINT_FILES, CHECKPOINT_RECORD, Checkpoint, read_checkpoint_info, verify_checkpoint,
};
use std::path::PathBuf;

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
        let dir = std::env::temp_dir().join(format!("arkit-fuzz-pn-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("a scratch folder for the fuzz entries");
        Scratch(dir)
    };
}

/// The contents the [`checkpoint_json`] entry gives each file of the checkpoint folder
/// (small and fixed: the record is what is fuzzed).
pub fn checkpoint_file_bytes(name: &str) -> Vec<u8> {
    format!("the fuzz entry's {name}\n").into_bytes()
}

/// `checkpoint.json` through [`verify_checkpoint`], in a folder whose four checkpoint
/// files hold [`checkpoint_file_bytes`]. Accepted when it verifies; then the record
/// lists each file with its size.
pub fn checkpoint_json(data: &[u8]) -> bool {
    let dir = SCRATCH.with(|s| s.0.clone());
    for name in CHECKPOINT_FILES {
        std::fs::write(dir.join(name), checkpoint_file_bytes(name)).expect("scratch folder");
    }
    std::fs::write(dir.join(CHECKPOINT_RECORD), data).expect("scratch folder");
    if verify_checkpoint(&dir).is_err() {
        return false;
    }
    let record: serde_json::Value = serde_json::from_slice(data).expect("a verified record");
    for name in CHECKPOINT_FILES {
        let listed = record["files"]
            .as_array()
            .and_then(|f| f.iter().find(|f| f["name"] == name))
            .and_then(|f| f["bytes"].as_u64());
        assert!(
            listed == Some(checkpoint_file_bytes(name).len() as u64),
            "{name} verified with another size"
        );
    }
    true
}

/// A checkpoint's `perspnet.json` through the reader [`crate::load`] uses (parsed, its
/// network config validated). Accepted when it reads; then written again it reads back
/// the same JSON.
pub fn perspnet_json(data: &[u8]) -> bool {
    let path = SCRATCH.with(|s| s.0.join("perspnet.json"));
    std::fs::write(&path, data).expect("scratch folder");
    let Ok(c) = read_checkpoint_info(&path) else {
        return false;
    };
    let text = serde_json::to_string(&c).expect("a checkpoint serialises");
    let back: Checkpoint = serde_json::from_str(&text).expect("our own perspnet.json parses");
    let value = |c: &Checkpoint| serde_json::to_value(c).expect("serialises");
    assert!(
        value(&back) == value(&c),
        "perspnet.json round trip changed it"
    );
    true
}

#[cfg(test)]
mod tests;
