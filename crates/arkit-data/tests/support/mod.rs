//! What several of `arkit-data`'s test modules share.

#![allow(dead_code)]

pub mod converted;

use std::path::PathBuf;

/// The workspace's root, where `schemas/` and `fixtures/` are.
pub fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The real ARKit topology and face (`ARKIT_RESOURCES`, default `../shared/arkitface-resources`
/// beside the workspace), or `None` when it is absent (the caller says SKIPPED).
pub fn resources() -> Option<PathBuf> {
    let dir = std::env::var_os("ARKIT_RESOURCES")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join("../shared/arkitface-resources"));
    dir.join("triangles.npy").exists().then_some(dir)
}
