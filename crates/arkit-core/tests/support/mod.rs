//! What several of `arkit-core`'s test modules share.

use std::path::PathBuf;

/// The workspace's root, where `fixtures/` and `fuzz/corpus/` are.
pub fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}
