//! Rendering the targets of a whole converted dataset, shard by shard: for each
//! `samples/part-K.parquet`, `targets/part-K.parquet` with one row per sample, in the
//! same order. Parallel over samples; deterministic (each sample's points are drawn
//! from `seed` and its position in the dataset); shards already written are kept.
//!
//! A sample that cannot be rendered (a pose the projection cannot use, a mesh of the
//! wrong size, a vertex behind the camera) never stops the run: it gets no targets row,
//! and a row in `targets/errors/part-K.parquet` (the `errors` table of `convert`, with
//! the samples file and the reason), which is written before the shard's targets file,
//! so a shard is finished when both files account for all of its samples. Readers
//! ([`crate::targets_table::read_skipped_keys`]) skip those samples.

use crate::conventions::Pose;
use crate::convert::read_manifest;
use crate::error::{Error, Result};
use crate::raster::VisibilityBuffer;
use crate::render::{CropTransform, FaceRenderer, RasterMode, UvMapper, sample_points};
use crate::samples_table::{self, ErrorRecord};
use crate::targets_table::{self, TargetsRecord};
use nalgebra::Point3;
use rayon::prelude::*;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// What to render.
#[derive(Clone, Debug)]
pub struct RenderOptions {
    /// Crop side in pixels.
    pub size: u32,
    /// UV map side in texels.
    pub uv_size: u32,
    /// Sampled points per sample.
    pub points: usize,
    /// Seed of the point sampling.
    pub seed: u64,
    /// Output folder (`targets/part-K.parquet`).
    pub output: PathBuf,
    /// `(I, N)`: render only the shards `k` with `k % N == I` (job arrays; `(0, 1)`:
    /// all). Parts write disjoint files into the same folder and need no merge: the
    /// sampling seed of each sample follows from its position in the whole dataset, so
    /// the files are those of a single run.
    pub shard: (usize, usize),
    /// Also render the face mask over the whole image (`full_mask_rle`).
    pub full_mask: bool,
}

/// What a run wrote.
#[derive(Clone, Debug, serde::Serialize)]
pub struct RenderSummary {
    /// Samples of the shards this run is responsible for: rendered, kept from an
    /// earlier run, or skipped.
    pub samples: usize,
    /// Shards this run is responsible for (all of them without `--shard`).
    pub shards: usize,
    /// Bytes of the targets files.
    pub bytes: u64,
    /// Bytes per rendered sample.
    pub bytes_per_sample: f64,
    /// Distinct meshes whose UV map was computed.
    pub distinct_meshes: usize,
    /// Samples that could not be rendered (counted in `samples`; no targets row).
    pub skipped: usize,
    /// The first few of them, `key: reason` (all are in `targets/errors/`).
    pub skipped_examples: Vec<String>,
    /// The rasterization rules used.
    pub mode: RasterMode,
}

fn mesh_key(verts: &[f32]) -> Vec<u32> {
    verts.iter().map(|v| v.to_bits()).collect()
}

/// Renders every shard of the converted dataset in `dataset`.
pub fn render_dataset(
    dataset: &Path,
    renderer: &FaceRenderer,
    options: &RenderOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<RenderSummary> {
    let manifest = read_manifest(&dataset.join("dataset.json"))?;
    let (part, parts) = options.shard;
    if parts == 0 || part >= parts {
        return Err(Error::invalid(
            "--shard",
            format!("{part}/{parts}: need 0 <= I < N"),
        ));
    }
    let uv = UvMapper::derive(renderer.topology())?;
    // The layout's rasterization, once: a mesh's map is then three weighted positions
    // per texel.
    let uv_texels = uv.texels(options.uv_size);
    std::fs::create_dir_all(options.output.join("targets"))
        .map_err(|e| Error::io(&options.output, e))?;
    // Shards are kept on a rerun only if they were made with the same options.
    let settings = serde_json::json!({
        "size": options.size, "uv_size": options.uv_size, "points": options.points, "seed": options.seed,
        "mode": renderer.mode, "topology": renderer.topology().source, "full_mask": options.full_mask,
    });
    let settings_path = options.output.join("targets").join("render.json");
    if settings_path.exists() {
        let text =
            std::fs::read_to_string(&settings_path).map_err(|e| Error::io(&settings_path, e))?;
        let old: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Error::format(&settings_path, e.to_string()))?;
        if old != settings {
            return Err(Error::format(
                &settings_path,
                format!(
                    "the targets here were made with other options ({old}); remove the targets folder or choose another --output"
                ),
            ));
        }
    } else {
        crate::atomic_file::write_bytes(&settings_path, format!("{settings:#}\n").as_bytes())?;
    }
    std::fs::create_dir_all(options.output.join("targets").join("errors"))
        .map_err(|e| Error::io(&options.output, e))?;
    let (mut samples, mut bytes, mut distinct) = (0usize, 0u64, 0usize);
    let mut skipped = SkipTally::default();
    let mut offset = 0u64;
    // Encoding and writing shard k (one thread) overlaps reading and rendering shard
    // k+1 (rayon), so the sequential Parquet work does not leave a core idle.
    let mut outputs = Vec::new();
    std::thread::scope(|scope| -> Result<()> {
        let mut pending: Option<std::thread::ScopedJoinHandle<'_, Result<()>>> = None;
        for shard in &manifest.shards {
            if shard.index % parts != part {
                offset += shard.rows as u64;
                continue;
            }
            let out = targets_table::shard_path(&options.output, shard.index);
            let errors_path = targets_table::errors_path(&options.output, shard.index);
            if out.exists()
                && errors_path.exists()
                && samples_table::parquet_row_count(&out)?
                    + samples_table::parquet_row_count(&errors_path)?
                    == shard.rows
            {
                let n = samples_table::parquet_row_count(&errors_path)?;
                if n > 0 && skipped.examples.len() < SkipTally::EXAMPLES {
                    skipped.add(&samples_table::read_errors(&errors_path)?);
                } else {
                    skipped.count += n;
                }
                progress(shard.rows);
            } else {
                let rows = samples_table::read_samples(&dataset.join(&shard.samples_file))?;
                // UV maps depend only on the mesh: one per distinct mesh.
                let mut uv_maps: HashMap<Vec<u32>, usize> = HashMap::new();
                let mut unique: Vec<&[f32]> = Vec::new();
                let index: Vec<usize> = rows
                    .iter()
                    .map(|r| {
                        *uv_maps.entry(mesh_key(&r.verts)).or_insert_with(|| {
                            unique.push(&r.verts);
                            unique.len() - 1
                        })
                    })
                    .collect();
                distinct += unique.len();
                let maps: Vec<Vec<[f32; 3]>> = unique
                    .par_iter()
                    .map(|v| {
                        let pts: Vec<Point3<f32>> =
                            v.chunks(3).map(|c| Point3::new(c[0], c[1], c[2])).collect();
                        uv_texels.position_map(&uv.extended_positions(&pts))
                    })
                    .collect();
                let results: Vec<Result<TargetsRecord>> = rows
                    .par_iter()
                    .enumerate()
                    .map_init(
                        || {
                            let crop = VisibilityBuffer::new(options.size, options.size);
                            (crop, VisibilityBuffer::new(1, 1))
                        },
                        |(buffer, full), (i, r)| -> Result<TargetsRecord> {
                            progress(1);
                            let verts: Vec<Point3<f32>> = r
                                .verts
                                .chunks(3)
                                .map(|c| Point3::new(c[0], c[1], c[2]))
                                .collect();
                            let pose = Pose::from_release_rt(&r.rt)?;
                            let crop = match renderer.mode {
                                RasterMode::Exact => {
                                    CropTransform::around_landmarks(&r.landmarks_2d, options.size)
                                }
                                RasterMode::Official => renderer.official_crop(
                                    &verts,
                                    &pose,
                                    r.image_width,
                                    r.image_height,
                                    options.size,
                                )?,
                            };
                            let t = renderer.render(
                                &verts,
                                &pose,
                                r.image_width,
                                r.image_height,
                                &crop,
                                buffer,
                            )?;
                            let seed = options.seed
                                ^ (offset + i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                            let points = sample_points(t.corr_vertices.len(), options.points, seed);
                            let full_mask =
                                if options.full_mask && renderer.mode == RasterMode::Official {
                                    // The official pipeline rendered the whole image already.
                                    Some(renderer.face_pixels(buffer))
                                } else if options.full_mask {
                                    Some(renderer.render_full_mask(
                                        &verts,
                                        &pose,
                                        r.image_width,
                                        r.image_height,
                                        full,
                                    )?)
                                } else {
                                    None
                                };
                            Ok(TargetsRecord::new(
                                r.key.clone(),
                                &t,
                                points,
                                options.uv_size,
                                &maps[index[i]],
                            )
                            .with_image(
                                r.image_width,
                                r.image_height,
                                full_mask.as_deref(),
                            ))
                        },
                    )
                    .collect();
                let mut records = Vec::with_capacity(rows.len());
                let mut bad = Vec::new();
                for (r, result) in rows.iter().zip(results) {
                    match result {
                        Ok(t) => records.push(t),
                        Err(e) => bad.push(ErrorRecord {
                            key: r.key.clone(),
                            split: r.split.clone(),
                            file: shard.samples_file.clone(),
                            reason: e.to_string(),
                        }),
                    }
                }
                if let Some(h) = pending.take() {
                    h.join().expect("writer thread")?;
                }
                // Errors first: a targets file without its errors file is never
                // "finished".
                samples_table::write_parquet(
                    &errors_path,
                    &mut samples_table::errors_frame(&bad)?,
                )?;
                skipped.add(&bad);
                let path = out.clone();
                pending = Some(scope.spawn(move || {
                    samples_table::write_parquet(
                        &path,
                        &mut targets_table::targets_frame(&records)?,
                    )
                }));
            }
            samples += shard.rows;
            offset += shard.rows as u64;
            outputs.push(out);
        }
        if let Some(h) = pending.take() {
            h.join().expect("writer thread")?;
        }
        Ok(())
    })?;
    for out in &outputs {
        bytes += std::fs::metadata(out).map_err(|e| Error::io(out, e))?.len();
    }
    Ok(RenderSummary {
        samples,
        shards: outputs.len(),
        bytes,
        bytes_per_sample: bytes as f64 / (samples - skipped.count).max(1) as f64,
        distinct_meshes: distinct,
        mode: renderer.mode,
        skipped: skipped.count,
        skipped_examples: skipped.examples,
    })
}

/// The samples a run skipped: how many, and the first few reasons (the full list
/// is in the errors files; a run over millions of samples keeps only these).
#[derive(Debug, Default)]
struct SkipTally {
    count: usize,
    examples: Vec<String>,
}

impl SkipTally {
    /// Reasons kept for the summary.
    const EXAMPLES: usize = 10;

    fn add(&mut self, records: &[ErrorRecord]) {
        self.count += records.len();
        let room = Self::EXAMPLES.saturating_sub(self.examples.len());
        self.examples.extend(
            records
                .iter()
                .take(room)
                .map(|e| format!("{}: {}", e.key, e.reason)),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::release::SampleKey;

    fn records(range: std::ops::Range<usize>) -> Vec<ErrorRecord> {
        range
            .map(|i| ErrorRecord {
                key: SampleKey {
                    subject_id: "1".into(),
                    facial_action: "a".into(),
                    img_id: i.to_string(),
                },
                split: "train".into(),
                file: "f".into(),
                reason: format!("reason {i}"),
            })
            .collect()
    }

    #[test]
    fn skip_tally_counts_everything_and_keeps_the_first_ten_reasons() {
        let mut tally = SkipTally::default();
        tally.add(&records(0..7));
        tally.add(&[]);
        tally.add(&records(7..15));
        assert_eq!(tally.count, 15);
        assert_eq!(tally.examples.len(), SkipTally::EXAMPLES);
        assert!(tally.examples[0].ends_with(": reason 0"));
        assert!(tally.examples[9].ends_with(": reason 9"));
    }
}
