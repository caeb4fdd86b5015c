//! Rendering the targets of a whole converted dataset, shard by shard: for each
//! `samples/part-K.parquet`, `targets/part-K.parquet` with one row per sample, in the
//! same order. Parallel over samples; deterministic (each sample's points are drawn
//! from `seed` and its position in the dataset); shards already written are kept.
//!
//! What was kept is known to be right: `targets/render.json` records the options, the
//! topology and a fingerprint of the dataset's samples ([`dataset_fingerprint`]), and is
//! written, after the options are checked, before any shard. A rerun whose
//! `render.json` would differ is refused while `targets/` holds any shard file (remove
//! them, choose another output, or use [`render_dataset_replacing`]); a failed run that
//! wrote no shard does not block a rerun with other options.
//!
//! A sample that cannot be rendered (a pose the projection cannot use, a mesh of the
//! wrong size, a vertex behind the camera) never stops the run: it gets no targets row,
//! and a row in `targets/errors/part-K.parquet` (the `errors` table of `convert`, with
//! the samples file and the reason), which is written before the shard's targets file,
//! so a shard is finished when both files account for all of its samples. Readers
//! ([`crate::store::targets_table::read_skipped_keys`]) skip those samples.

use crate::crop::RuleSet;
use crate::render::face::{FaceRenderer, sample_points};
use crate::render::uv_map::UvMapper;
use crate::store::manifest::dataset_fingerprint;
use crate::store::parquet;
use crate::store::samples_table::{self, ErrorRecord};
use crate::store::targets_table::{self, TargetsRecord};
use arkit_core::VisibilityBuffer;
use arkit_core::conventions::Pose;
use arkit_core::{Error, Result};
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

impl RenderOptions {
    /// Crop sides accepted (`--size`).
    pub(crate) const SIZE: std::ops::RangeInclusive<u32> = 16..=1024;
    /// UV map sides accepted (`--uv-size`).
    pub(crate) const UV_SIZE: std::ops::RangeInclusive<u32> = 16..=512;
    /// Points per sample accepted (`--points`; also at most `size * size`).
    pub(crate) const POINTS: std::ops::RangeInclusive<usize> = 1..=65_536;

    /// Checks every option, naming the command-line option in the error.
    pub fn validate(&self) -> Result<()> {
        if !Self::SIZE.contains(&self.size) {
            return Err(Error::invalid(
                "--size",
                format!("{} is not in {:?} pixels", self.size, Self::SIZE),
            ));
        }
        if !Self::UV_SIZE.contains(&self.uv_size) {
            return Err(Error::invalid(
                "--uv-size",
                format!("{} is not in {:?} texels", self.uv_size, Self::UV_SIZE),
            ));
        }
        if !Self::POINTS.contains(&self.points) {
            return Err(Error::invalid(
                "--points",
                format!("{} is not in {:?}", self.points, Self::POINTS),
            ));
        }
        let pixels = self.size as usize * self.size as usize;
        if self.points > pixels {
            return Err(Error::invalid(
                "--points",
                format!(
                    "{} is more than the {pixels} pixels of a --size {} crop",
                    self.points, self.size
                ),
            ));
        }
        let (part, parts) = self.shard;
        if parts == 0 || part >= parts {
            return Err(Error::invalid(
                "--shard",
                format!("{part}/{parts}: need 0 <= I < N"),
            ));
        }
        Ok(())
    }
}

/// Refuses to render a dataset with another topology than it was converted with (the
/// one check every stage uses).
use crate::store::manifest::check_topology;

/// Whether `targets/` under `output` holds any shard file (targets or errors).
fn has_shard_files(output: &Path) -> Result<bool> {
    Ok(!shard_files(output)?.is_empty())
}

/// The shard files (`part-*.parquet`) in `output/targets` and `output/targets/errors`.
fn shard_files(output: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for dir in [
        output.join("targets"),
        output.join("targets").join("errors"),
    ] {
        let entries = match std::fs::read_dir(&dir) {
            Ok(e) => e,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(Error::io(&dir, e)),
        };
        for e in entries {
            let e = e.map_err(|e| Error::io(&dir, e))?;
            let name = e.file_name();
            let name = name.to_string_lossy();
            if name.starts_with("part-") && name.ends_with(".parquet") {
                files.push(e.path());
            }
        }
    }
    files.sort();
    Ok(files)
}

/// The differences between two `render.json` values, for the refusal message.
fn differences(old: &serde_json::Value, new: &serde_json::Value) -> String {
    let keys: std::collections::BTreeSet<&String> = [old, new]
        .iter()
        .filter_map(|v| v.as_object())
        .flat_map(|o| o.keys())
        .collect();
    let mut out = Vec::new();
    for k in keys {
        let (a, b) = (&old[k.as_str()], &new[k.as_str()]);
        if a != b {
            out.push(if k == "dataset" {
                "made from another dataset (or before render.json recorded one)".to_string()
            } else {
                format!("{k} {a} there, {b} now")
            });
        }
    }
    if out.is_empty() {
        "render.json is not one this version writes".into()
    } else {
        out.join(", ")
    }
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
    /// The rasterization rules used (`"mode"` in `--json`, as `render.json` names it).
    #[serde(rename = "mode")]
    pub rules: RuleSet,
}

fn mesh_key(verts: &[f32]) -> Vec<u32> {
    verts.iter().map(|v| v.to_bits()).collect()
}

/// Renders every shard of the converted dataset in `dataset`, keeping the shards an
/// earlier run with the same options finished; refuses when `targets/` holds shards
/// made with other options, another topology or from another dataset.
pub fn render_dataset(
    dataset: &Path,
    renderer: &FaceRenderer,
    options: &RenderOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<RenderSummary> {
    let _writers = hold_folders(dataset, options)?;
    render(dataset, renderer, options, false, progress)
}

/// [`render_dataset`], but shards made with other options, another topology or from
/// another dataset are deleted (every `targets/part-*.parquet` and
/// `targets/errors/part-*.parquet`) and rendered again instead of refused; shards made
/// with the same ones are still kept. Not with a `shard` part other than `(0, 1)`: other
/// parts may be writing into the same folder.
pub fn render_dataset_replacing(
    dataset: &Path,
    renderer: &FaceRenderer,
    options: &RenderOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<RenderSummary> {
    if options.shard.1 != 1 {
        return Err(Error::invalid(
            "--overwrite",
            "not with --shard (other parts may be writing there): remove the targets folder before starting the parts instead",
        ));
    }
    let _writers = hold_folders(dataset, options)?;
    render(dataset, renderer, options, true, progress)
}

/// The writers' lock (`.convert.lock`, shared) of the dataset read and, when the
/// targets go elsewhere (`--output`), of that folder too (made if needed): a
/// `convert --overwrite` of either is refused while this render runs, and this render
/// is refused while one removes there.
fn hold_folders(
    dataset: &Path,
    options: &RenderOptions,
) -> Result<Vec<arkit_core::atomic_file::FolderLock>> {
    // Nothing is made for options that are refused or a folder that is no dataset:
    // those are refused before the output folder is created for its lock.
    options.validate()?;
    let mut held: Vec<_> = crate::ingest::convert::hold_against_overwrite(dataset)?
        .into_iter()
        .collect();
    let same = match (dataset.canonicalize(), options.output.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => dataset == options.output,
    };
    let is_dataset = dataset
        .join(crate::store::manifest::MANIFEST_FILE)
        .is_file();
    if !same && is_dataset {
        std::fs::create_dir_all(&options.output).map_err(|e| Error::io(&options.output, e))?;
        held.extend(crate::ingest::convert::hold_against_overwrite(
            &options.output,
        )?);
    }
    Ok(held)
}

fn render(
    dataset: &Path,
    renderer: &FaceRenderer,
    options: &RenderOptions,
    replace: bool,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<RenderSummary> {
    // Everything is checked before anything is written.
    options.validate()?;
    let data = crate::store::dataset::Dataset::open(dataset)?;
    let manifest = data.manifest().clone();
    check_topology(&manifest, renderer.topology())?;
    let (part, parts) = options.shard;
    let uv = UvMapper::derive(renderer.topology())?;
    // The layout's rasterization, once: a mesh's map is then three weighted positions
    // per texel.
    let uv_texels = uv.texels(options.uv_size);
    let settings = render_settings(renderer, options, &manifest);
    let targets_dir = options.output.join("targets");
    // Parts of one render take the settings check in turn; a second render of the same
    // part is refused while the first runs; killed runs' temporaries go.
    let settings_lock = arkit_core::atomic_file::FolderLock::wait(&targets_dir, "render-settings")?;
    let _part_lock = arkit_core::atomic_file::FolderLock::acquire(
        &targets_dir,
        &format!("render-part-{part}-of-{parts}"),
        "render of this part",
    )?;
    arkit_core::atomic_file::remove_stale_temporaries(&targets_dir, true)?;
    claim_targets(options, &settings, replace)?;
    drop(settings_lock);
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
            if shard_finished(&out, &errors_path, shard.rows)? {
                let n = parquet::parquet_row_count(&errors_path)?;
                if n > 0 && skipped.examples.len() < SkipTally::EXAMPLES {
                    skipped.add(&samples_table::read_errors(&errors_path)?);
                } else {
                    skipped.count += n;
                }
                progress(shard.rows);
            } else {
                let rows = samples_table::read_samples(&data.samples_path(shard)?)?;
                let (results, meshes) =
                    render_rows(&rows, renderer, options, &uv, &uv_texels, offset, progress);
                distinct += meshes;
                let (records, bad) = sort_results(&rows, results, &shard.samples_file);
                if let Some(h) = pending.take() {
                    join_writer(h)?;
                }
                // Errors first: a targets file without its errors file is never
                // "finished".
                parquet::write_parquet(&errors_path, &mut samples_table::errors_frame(&bad)?)?;
                skipped.add(&bad);
                let path = out.clone();
                pending = Some(scope.spawn(move || {
                    parquet::write_parquet(&path, &mut targets_table::targets_frame(&records)?)
                }));
            }
            samples += shard.rows;
            offset += shard.rows as u64;
            outputs.push(out);
        }
        if let Some(h) = pending.take() {
            join_writer(h)?;
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
        rules: renderer.rules(),
        skipped: skipped.count,
        skipped_examples: skipped.examples,
    })
}

/// What `render.json` records: the options, the topology and the dataset's fingerprint
/// (shards are kept on a rerun only if they were made with the same options, the same
/// topology and from the same samples).
fn render_settings(
    renderer: &FaceRenderer,
    options: &RenderOptions,
    manifest: &crate::store::manifest::Manifest,
) -> serde_json::Value {
    serde_json::json!({
        "size": options.size, "uv_size": options.uv_size, "points": options.points, "seed": options.seed,
        "mode": renderer.rules(), "topology": renderer.topology().source, "full_mask": options.full_mask,
        "dataset": dataset_fingerprint(manifest),
    })
}

/// Compares `settings` with the `targets/render.json` there: when they differ, shards
/// made otherwise are refused (or deleted when `replace`) and `render.json` is written.
/// Runs under the settings lock.
fn claim_targets(
    options: &RenderOptions,
    settings: &serde_json::Value,
    replace: bool,
) -> Result<()> {
    let targets_dir = options.output.join("targets");
    let settings_path = targets_dir.join("render.json");
    let old: Option<serde_json::Value> = match std::fs::read_to_string(&settings_path) {
        Ok(text) => Some(
            // Unreadable as JSON counts as different settings.
            serde_json::from_str(&text).unwrap_or(serde_json::Value::Null),
        ),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
        Err(e) => return Err(Error::io(&settings_path, e)),
    };
    if old.as_ref() != Some(settings) {
        if has_shard_files(&options.output)? {
            if !replace {
                let why = match &old {
                    Some(old) => differences(old, settings),
                    None => "no render.json says how they were made".into(),
                };
                return Err(Error::format(
                    &settings_path,
                    format!(
                        "the targets in {} were made otherwise ({why}); remove that folder, choose another --output, or pass --overwrite to replace them",
                        options.output.join("targets").display()
                    ),
                ));
            }
            // render.json first: a reader never finds the old one beside shards that
            // are going (RenderedTargets), then the shards.
            match std::fs::remove_file(&settings_path) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(Error::io(&settings_path, e)),
            }
            for f in shard_files(&options.output)? {
                std::fs::remove_file(&f).map_err(|e| Error::io(&f, e))?;
            }
        }
        // No shard there: whatever wrote render.json rendered nothing that could be kept.
        std::fs::create_dir_all(options.output.join("targets"))
            .map_err(|e| Error::io(&options.output, e))?;
        arkit_core::atomic_file::write_bytes(&settings_path, format!("{settings:#}\n").as_bytes())?;
    }
    Ok(())
}

/// Whether a shard's targets and errors files are both there and account for all of its
/// `rows` samples (an earlier run finished it).
fn shard_finished(out: &Path, errors_path: &Path, rows: usize) -> Result<bool> {
    Ok(out.exists()
        && errors_path.exists()
        && parquet::parquet_row_count(out)? + parquet::parquet_row_count(errors_path)? == rows)
}

/// Renders the targets of a shard's `rows` (the first at `offset` in the dataset), in
/// parallel; returns each row's result and the number of distinct meshes (one UV map
/// each).
fn render_rows(
    rows: &[samples_table::SampleRecord],
    renderer: &FaceRenderer,
    options: &RenderOptions,
    uv: &UvMapper,
    uv_texels: &crate::render::uv_map::UvTexels,
    offset: u64,
    progress: &(dyn Fn(usize) + Sync),
) -> (Vec<Result<TargetsRecord>>, usize) {
    // UV maps depend only on the mesh: one per distinct mesh.
    let mut uv_maps: HashMap<Vec<u32>, usize> = HashMap::new();
    let mut unique: Vec<&[f32]> = Vec::new();
    let vertex_count = renderer.topology().vertex_count;
    // A row that cannot be rendered gets no map (and an errors row below).
    let index: Vec<Option<usize>> = rows
        .iter()
        .map(|r| {
            check_row(r, vertex_count).ok()?;
            Some(*uv_maps.entry(mesh_key(&r.verts)).or_insert_with(|| {
                unique.push(&r.verts);
                unique.len() - 1
            }))
        })
        .collect();
    let distinct = unique.len();
    let maps: Vec<Vec<[f32; 3]>> = unique
        .par_iter()
        .map(|v| {
            let pts: Vec<Point3<f32>> =
                v.chunks(3).map(|c| Point3::new(c[0], c[1], c[2])).collect();
            uv_texels.position_map(&uv.extended_positions(&pts))
        })
        .collect();
    let results = rows
        .par_iter()
        .enumerate()
        .map_init(
            || {
                let crop = VisibilityBuffer::new(options.size, options.size);
                (crop, VisibilityBuffer::new(1, 1))
            },
            |(buffer, full), (i, r)| -> Result<TargetsRecord> {
                progress(1);
                check_row(r, vertex_count)?;
                let map = index[i].ok_or_else(|| {
                    Error::invalid("verts", "no UV map (the row failed its checks)")
                })?;
                let seed = options.seed ^ (offset + i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                render_row(renderer, options, r, &maps[map], seed, buffer, full)
            },
        )
        .collect();
    (results, distinct)
}

/// One row's targets: its crop, the rendered correspondences, `options.points` points
/// drawn from `seed`, its UV map `map` and (with `options.full_mask`) the whole image's
/// face mask; `buffer` and `full` are the thread's crop and full-image buffers.
fn render_row(
    renderer: &FaceRenderer,
    options: &RenderOptions,
    r: &samples_table::SampleRecord,
    map: &[[f32; 3]],
    seed: u64,
    buffer: &mut VisibilityBuffer,
    full: &mut VisibilityBuffer,
) -> Result<TargetsRecord> {
    let verts: Vec<Point3<f32>> = r
        .verts
        .chunks(3)
        .map(|c| Point3::new(c[0], c[1], c[2]))
        .collect();
    let pose = Pose::from_release_rt(&r.rt)?;
    let crop = renderer.crop_of(
        &verts,
        &pose,
        (r.image_width, r.image_height),
        &r.landmarks_2d,
        options.size,
    )?;
    let t = renderer.render(&verts, &pose, r.image_width, r.image_height, &crop, buffer)?;
    let points = sample_points(t.corr_vertices.len(), options.points, seed);
    let full_mask = if options.full_mask && renderer.renders_whole_image() {
        // The official pipeline rendered the whole image already.
        Some(renderer.face_pixels(buffer))
    } else if options.full_mask {
        Some(renderer.render_full_mask(&verts, &pose, r.image_width, r.image_height, full)?)
    } else {
        None
    };
    Ok(
        TargetsRecord::new(r.key.clone(), &t, points, options.uv_size, map).with_image(
            r.image_width,
            r.image_height,
            full_mask.as_deref(),
        ),
    )
}

/// Splits a shard's results into the targets records and the errors rows (which name the
/// shard's `samples_file`), in row order.
fn sort_results(
    rows: &[samples_table::SampleRecord],
    results: Vec<Result<TargetsRecord>>,
    samples_file: &str,
) -> (Vec<TargetsRecord>, Vec<ErrorRecord>) {
    let mut records = Vec::with_capacity(rows.len());
    let mut bad = Vec::new();
    for (r, result) in rows.iter().zip(results) {
        match result {
            Ok(t) => records.push(t),
            Err(e) => bad.push(ErrorRecord {
                key: r.key.clone(),
                split: r.split.clone(),
                file: samples_file.to_string(),
                reason: e.to_string(),
            }),
        }
    }
    (records, bad)
}

/// Waits for the thread writing a targets file; its panic (a bug, not an input) becomes
/// an error instead of a second panic.
fn join_writer(h: std::thread::ScopedJoinHandle<'_, Result<()>>) -> Result<()> {
    h.join().unwrap_or_else(|_| {
        Err(Error::invalid(
            "render",
            "the targets writer thread panicked",
        ))
    })
}

/// The checks of one samples row that rendering relies on (the samples file may come
/// from elsewhere than `convert`): the mesh's size, finite even landmarks, and an image
/// size the rasterizer takes. A failed row is skipped with this reason.
fn check_row(r: &samples_table::SampleRecord, vertex_count: usize) -> Result<()> {
    if r.verts.len() != 3 * vertex_count {
        return Err(Error::invalid(
            "verts",
            format!(
                "{} values, expected {} (3 per vertex of the topology)",
                r.verts.len(),
                3 * vertex_count
            ),
        ));
    }
    let lm = &r.landmarks_2d;
    if lm.is_empty() || !lm.len().is_multiple_of(2) || lm.iter().any(|v| !v.is_finite()) {
        return Err(Error::invalid(
            "landmarks_2d",
            format!(
                "{} values: need a non-empty, even number of finite values",
                lm.len()
            ),
        ));
    }
    let max = arkit_core::MAX_VIEWPORT;
    if !(1..=max).contains(&r.image_width) || !(1..=max).contains(&r.image_height) {
        return Err(Error::invalid(
            "image size",
            format!(
                "{}x{}: each side must be 1..={max} pixels",
                r.image_width, r.image_height
            ),
        ));
    }
    Ok(())
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
    use crate::store::manifest::Manifest;
    use arkit_core::SampleKey;

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

    fn options(size: u32, uv_size: u32, points: usize) -> RenderOptions {
        RenderOptions {
            size,
            uv_size,
            points,
            seed: 0,
            output: PathBuf::from("/nonexistent"),
            shard: (0, 1),
            full_mask: false,
        }
    }

    fn invalid_option(o: &RenderOptions) -> String {
        match o.validate() {
            Err(Error::Invalid { what, .. }) => what,
            other => panic!("{o:?}: {other:?}"),
        }
    }

    #[test]
    fn render_options_are_checked_and_the_error_names_the_option() {
        assert!(options(192, 192, 1024).validate().is_ok());
        // The edges of every range are accepted...
        assert!(options(16, 16, 256).validate().is_ok());
        assert!(options(1024, 512, 65_536).validate().is_ok());
        // ... and one past them is not.
        assert_eq!(invalid_option(&options(15, 16, 1)), "--size");
        assert_eq!(invalid_option(&options(1025, 16, 1)), "--size");
        assert_eq!(invalid_option(&options(20_000, 16, 1)), "--size");
        assert_eq!(invalid_option(&options(16, 15, 1)), "--uv-size");
        assert_eq!(invalid_option(&options(16, 513, 1)), "--uv-size");
        assert_eq!(invalid_option(&options(16, 16, 0)), "--points");
        assert_eq!(invalid_option(&options(16, 16, 257)), "--points");
        assert_eq!(invalid_option(&options(1024, 16, 65_537)), "--points");
        let mut o = options(16, 16, 1);
        o.shard = (2, 2);
        assert_eq!(invalid_option(&o), "--shard");
        o.shard = (0, 0);
        assert_eq!(invalid_option(&o), "--shard");
    }

    fn manifest() -> Manifest {
        let shard = |index: usize| crate::store::manifest::ShardEntry {
            index,
            samples_file: format!("samples/part-{index:05}.parquet"),
            rows: 4,
            sha256: format!("{index:064}"),
            errors_file: format!("errors/part-{index:05}.parquet"),
            error_rows: 0,
            errors_sha256: "e".repeat(64),
            bytes: 0,
            tail_sha256: String::new(),
            fingerprint: String::new(),
        };
        Manifest {
            tool: "arkit-tool".into(),
            version: "0".into(),
            input: "data/a".into(),
            input_root: String::new(),
            fingerprint: String::new(),
            topology_sha256: String::new(),
            layout: crate::store::manifest::LayoutKind::Download,
            lists: vec![],
            topology: crate::mesh::synthetic_face::builtin()
                .topology
                .source
                .clone(),
            rows_per_shard: 4,
            embed_images: false,
            part: [0, 1],
            listed: 8,
            converted: 8,
            skipped: 0,
            listing_problems: 0,
            shards: vec![shard(0), shard(1)],
        }
    }

    #[test]
    fn the_dataset_fingerprint_follows_the_samples_not_the_paths() {
        let m = manifest();
        let f = dataset_fingerprint(&m);
        assert_eq!(f.len(), 64);
        // The same samples converted from elsewhere, by another version: the same.
        let mut same = m.clone();
        (same.input, same.version) = ("/elsewhere".into(), "9".into());
        assert_eq!(dataset_fingerprint(&same), f);
        // Another samples file, another row count (the seeds of later shards move),
        // another topology: different.
        let mut other = m.clone();
        other.shards[1].sha256 = "f".repeat(64);
        assert_ne!(dataset_fingerprint(&other), f);
        let mut other = m.clone();
        other.shards[0].rows = 3;
        assert_ne!(dataset_fingerprint(&other), f);
        let mut other = m.clone();
        other.topology = "/data/resources".into();
        assert_ne!(dataset_fingerprint(&other), f);
    }

    #[test]
    fn the_topology_must_be_the_one_the_dataset_was_converted_with() {
        let builtin = crate::mesh::synthetic_face::builtin().topology.clone();
        let mut m = manifest();
        assert!(check_topology(&m, &builtin).is_ok());
        m.topology = "/data/resources".into();
        let e = check_topology(&m, &builtin).unwrap_err().to_string();
        assert!(
            e.contains("--resources") && e.contains("/data/resources"),
            "{e}"
        );
        // A resources folder given for a dataset converted with the built-in face.
        let mut real = builtin.clone();
        real.source = "/data/resources".into();
        assert!(check_topology(&m, &real).is_ok());
        let e = check_topology(&manifest(), &real).unwrap_err().to_string();
        assert!(e.contains("leave --resources out"), "{e}");
    }

    #[test]
    fn the_refusal_names_what_differs() {
        let old = serde_json::json!({"size": 64, "seed": 0, "dataset": "a"});
        let new = serde_json::json!({"size": 64, "seed": 7, "dataset": "b", "full_mask": false});
        let d = differences(&old, &new);
        assert!(d.contains("seed 0 there, 7 now"), "{d}");
        assert!(d.contains("another dataset"), "{d}");
        assert!(d.contains("full_mask null there, false now"), "{d}");
        assert!(!d.contains("size"), "{d}");
    }
}
