//! A small synthetic release, converted: the dataset most loader tests start from.

use arkit_core::conventions::Camera;
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
use arkit_data::ingest::{self, ConvertOptions, ValidationContext};
use std::path::Path;

/// A synthetic release of `subjects x images` images of `size x size` pixels (built-in
/// face, `seed`) in `release`, converted into `dir` with four rows per shard and the
/// images not embedded (so loaders read the release's files, as the official loader
/// does).
pub fn converted_synthetic(
    release: &Path,
    dir: &Path,
    subjects: usize,
    images: usize,
    size: u32,
    seed: u64,
) {
    let options = SynthOptions {
        subjects,
        images_per_subject: images,
        width: size,
        height: size,
        seed,
        ..SynthOptions::default()
    };
    synth::generate(&FaceSource::builtin(), &options, release, &|| {}).unwrap();
    let ctx = ValidationContext {
        projection: Camera::release_projection(),
        topology: arkit_data::mesh::builtin().topology.clone(),
        embed_images: false,
    };
    let copts = ConvertOptions {
        input: release.to_path_buf(),
        output: dir.to_path_buf(),
        resources: None,
        rows_per_shard: 4,
        embed_images: false,
        shard_index: 0,
        shard_count: 1,
        overwrite: false,
    };
    ingest::convert(&copts, &ctx, &|_| {}).unwrap();
}
