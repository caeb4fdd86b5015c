//! Embeds the face detector's model (SeetaFace's frontal cascade, BSD-2-Clause) that the
//! `rustface` crate ships in its package on crates.io (`model/seeta_fd_frontal_v1.0.bin`),
//! so that `predict --image` finds faces with no download at run time.
//!
//! The file is looked up in Cargo's registry sources (`$CARGO_HOME/registry/src/*/`) and in
//! a vendored copy (`vendor/rustface*` beside the workspace); `ARKIT_FACE_MODEL` names it
//! directly. Its size is checked against the released file's.

use std::path::{Path, PathBuf};

/// The rustface release whose model is embedded (the workspace pins it).
const RUSTFACE: &str = "rustface-0.1.7";
const MODEL: &str = "model/seeta_fd_frontal_v1.0.bin";
/// Bytes of `seeta_fd_frontal_v1.0.bin` in rustface 0.1.7.
const MODEL_BYTES: u64 = 1_209_904;

fn candidates() -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Some(p) = std::env::var_os("ARKIT_FACE_MODEL") {
        out.push(PathBuf::from(p));
    }
    let cargo_home = std::env::var_os("CARGO_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cargo")));
    if let Some(Ok(indexes)) =
        cargo_home.map(|home| std::fs::read_dir(home.join("registry").join("src")))
    {
        let mut dirs: Vec<PathBuf> = indexes.flatten().map(|e| e.path()).collect();
        dirs.sort();
        out.extend(dirs.into_iter().map(|d| d.join(RUSTFACE).join(MODEL)));
    }
    if let Some(manifest) = std::env::var_os("CARGO_MANIFEST_DIR") {
        let workspace = Path::new(&manifest).join("..").join("..");
        out.push(workspace.join("vendor").join("rustface").join(MODEL));
        out.push(workspace.join("vendor").join(RUSTFACE).join(MODEL));
    }
    out
}

fn main() {
    println!("cargo:rerun-if-env-changed=ARKIT_FACE_MODEL");
    println!("cargo:rerun-if-changed=build.rs");
    let tried = candidates();
    let found = tried
        .iter()
        .find(|p| std::fs::metadata(p).is_ok_and(|m| m.len() == MODEL_BYTES));
    let Some(model) = found else {
        let list: Vec<String> = tried.iter().map(|p| p.display().to_string()).collect();
        panic!(
            "the face detector's model ({MODEL} of {RUSTFACE}, {MODEL_BYTES} bytes) was not found; \
             looked in: {}. Run `cargo fetch`, or set ARKIT_FACE_MODEL to the file",
            list.join(", ")
        );
    };
    let out =
        PathBuf::from(std::env::var_os("OUT_DIR").expect("OUT_DIR")).join("seeta_fd_frontal.bin");
    std::fs::copy(model, &out).expect("copy the face detector's model into OUT_DIR");
    // The detector's own test photo (a group photo in rustface's package), for the tests.
    let package = model
        .parent()
        .and_then(Path::parent)
        .expect("the package folder");
    println!(
        "cargo:rustc-env=ARKIT_RUSTFACE_PACKAGE={}",
        package.display()
    );
    println!("cargo:rerun-if-changed={}", model.display());
}
