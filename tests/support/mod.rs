//! What several of the end-to-end test modules share: the command, the conversion's
//! options, and writers of synthetic (and hostile) input.

#![allow(dead_code)]

pub mod biwi_writer;
pub mod png_bomb;

use arkit_core::conventions::Camera;
use arkit_data::ingest::{ConvertOptions, ValidationContext};
use std::path::Path;
use std::process::Command;

/// The `arkit-tool` binary this test run built.
pub fn tool() -> Command {
    Command::new(env!("CARGO_BIN_EXE_arkit-tool"))
}

/// The tiny PerspNet shipped with arkit-tool (for the built-in synthetic face).
pub const TINY_MODEL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/models/tiny-synthetic");

/// Runs `arkit-tool ARGS`: its exit code, standard output and standard error.
pub fn run_tool(args: &[&str]) -> (Option<i32>, String, String) {
    let out = tool().args(args).output().unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).to_string(),
        String::from_utf8_lossy(&out.stderr).to_string(),
    )
}

/// Runs `arkit-tool ARGS`, which must succeed; its standard output.
pub fn tool_ok(args: &[&str]) -> String {
    let (code, stdout, stderr) = run_tool(args);
    assert_eq!(code, Some(0), "{args:?}: {stdout}{stderr}");
    stdout
}

/// What `convert` checks samples against: the release's camera and the built-in face.
pub fn convert_context() -> ValidationContext {
    ValidationContext {
        projection: Camera::release_projection(),
        topology: arkit_data::mesh::builtin().topology.clone(),
        embed_images: false,
    }
}

/// `convert`'s options for one machine: `input` into `output`, `rows_per_shard` rows
/// per shard, images not embedded.
pub fn convert_options(input: &Path, output: &Path, rows_per_shard: usize) -> ConvertOptions {
    ConvertOptions {
        input: input.to_path_buf(),
        output: output.to_path_buf(),
        resources: None,
        rows_per_shard,
        embed_images: false,
        shard_index: 0,
        shard_count: 1,
        overwrite: false,
    }
}

/// A synthetic release of `subjects x images` images of `size x size` pixels (`seed`)
/// in `release`, converted into `dir` with four rows per shard, by the command itself.
pub fn converted_by_the_command(
    release: &Path,
    dir: &Path,
    subjects: usize,
    images: usize,
    size: u32,
    seed: u64,
) {
    let run = |command: &mut Command| {
        let out = command.output().unwrap();
        assert!(
            out.status.success(),
            "{command:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    };
    let (subjects, images, seed) = (subjects.to_string(), images.to_string(), seed.to_string());
    run(tool().arg("synth").arg("--output").arg(release).args([
        "--subjects",
        &subjects,
        "--images-per-subject",
        &images,
        "--size",
        &format!("{size}x{size}"),
        "--seed",
        &seed,
    ]));
    run(tool()
        .args(["convert", "--input"])
        .arg(release)
        .arg("--output")
        .arg(dir)
        .args(["--rows-per-shard", "4"]));
}
