//! `convert`: the release as published into validated, sharded Parquet.
//!
//! Stages: [`discover`] the input layout; [`plan_rows`] from the list CSVs (list order,
//! train before test); cut the rows into shards of `rows_per_shard`; for each shard
//! this process owns (`--shard I/N`: shards `k` with `k % N == I`), validate every
//! sample in parallel (`validate_sample_with`) and write `errors/part-K.parquet` then
//! `samples/part-K.parquet`, each to a temporary name renamed into place, then the
//! shard's record `samples/part-K.json` (its [`ShardEntry`]). Rows keep list order
//! within and across shards, so the output is byte-identical whatever the number of
//! threads. Memory is bounded by one shard.
//!
//! Output is what it says. `conversion.json` in the output folder records the
//! conversion's fingerprint (`ConversionFingerprint`: the input root, the list files'
//! contents, the layout, the topology and projection, the shard size, whether images
//! are embedded); a later `convert` into the same folder with another fingerprint is
//! refused (or, with `--overwrite`, replaces the old output). A shard is kept on a
//! rerun, so an interrupted conversion resumes, only when its record exists, its
//! fingerprint (the conversion's, its rows and the size and modification time of each
//! row's files) is the one this run computes, and its files still hash to the record's
//! SHA-256. Each writer holds a lock on its part (`.convert-part-I-of-N.lock`), so a
//! second `convert` of the same part waits for nothing and is refused; stale temporaries
//! of killed runs are removed at the start. Readers ([`crate::store::dataset::Dataset`]) check
//! each shard's size and the SHA-256 of its last 64 KiB (the Parquet footer) against the
//! manifest before using it; [`verify_dataset`] checks the full SHA-256.
//!
//! A bad sample never stops the run: it becomes a row of the `errors` table with the
//! file at fault and the reason. Files on disk that no list names, and list rows that
//! repeat a key, are reported in `errors/listing.parquet`.

use crate::ingest::discover::{
    DiscoveredInput, PlannedRow, discover, find_orphans, plan_rows, relative,
};
use crate::ingest::systematic::{Check, SkipTally};
use crate::mesh::topology::FaceTopology;
use crate::store::manifest::hex;
use crate::store::manifest::{
    LayoutKind, MANIFEST_FILE, Manifest, ShardEntry, read_manifest, sha256_file, tail_sha256,
    topology_digest,
};
use crate::store::parquet;
use crate::store::samples_table::{self, ErrorRecord, SampleRecord};
use arkit_core::atomic_file::FolderLock;
use arkit_core::conventions::{Camera, Pose};
use arkit_core::release::{self};
use arkit_core::{Error, Result};
use nalgebra::{Matrix4, Point3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};

/// What validation needs besides the sample: the camera's projection and the landmarks.
#[derive(Clone, Debug)]
pub struct ValidationContext {
    /// Row-vector projection matrix (the release's unless `--resources` has its own).
    pub projection: Matrix4<f64>,
    /// The topology whose landmark indices and vertex count apply.
    pub topology: FaceTopology,
    /// Keep the JPEG bytes in the table.
    pub embed_images: bool,
}

/// Which per-sample checks run, and the window of the systematic rule
/// ([`crate::ingest::SYSTEMATIC_WINDOW`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ConvertChecks {
    /// Checks turned off (only [`Check::Points2d`] can be).
    pub skip: Vec<Check>,
    /// The systematic rule's window ([`crate::ingest::systematic::SYSTEMATIC_WINDOW`]; 0: the
    /// run never stops, `--allow-systematic-skips`).
    pub window: usize,
}

impl Default for ConvertChecks {
    fn default() -> Self {
        ConvertChecks {
            skip: Vec::new(),
            window: crate::ingest::systematic::SYSTEMATIC_WINDOW,
        }
    }
}

/// The checks `--skip-check` can turn off: those whose failure does not make the sample
/// wrong (the pose and image are still checked against each other without them).
pub(crate) const SKIPPABLE_CHECKS: [Check; 1] = [Check::Points2d];

/// A skipped sample: its error row, and the check (if a named one) that skipped it.
#[derive(Debug)]
pub struct Skip {
    /// The named check, for the systematic rule.
    pub check: Option<Check>,
    /// The `errors` table's row.
    pub record: Box<ErrorRecord>,
}

impl From<Box<ErrorRecord>> for Skip {
    fn from(record: Box<ErrorRecord>) -> Self {
        Skip {
            check: None,
            record,
        }
    }
}

fn by(check: Check) -> impl FnOnce(Box<ErrorRecord>) -> Skip {
    move |record| Skip {
        check: Some(check),
        record,
    }
}

/// Validates one sample and builds its row with `checks`, or says what is wrong with
/// which file; a skip says which check made it.
fn validate_sample_with(
    root: &Path,
    row: &PlannedRow,
    ctx: &ValidationContext,
    checks: &ConvertChecks,
) -> std::result::Result<SampleRecord, Skip> {
    let fail = |file: &Path, reason: String| {
        Box::new(ErrorRecord {
            key: row.key.clone(),
            split: row.split.clone(),
            file: relative(root, &root.join(file)),
            reason,
        })
    };
    let strip = |e: Error| -> String { e.reason() };
    let info_path = root.join(&row.info);
    let info = release::read_info_with_vertex_count(&info_path, ctx.topology.vertex_count)
        .map_err(|e| fail(&row.info, strip(e)))?;
    if info.verts.len() != ctx.topology.vertex_count {
        return Err(fail(
            &row.info,
            format!(
                "{} vertices, the topology has {}",
                info.verts.len(),
                ctx.topology.vertex_count
            ),
        )
        .into());
    }
    let pose =
        Pose::from_release_rt(&info.rt).map_err(|e| by(Check::Pose)(fail(&row.info, strip(e))))?;
    let image_path = root.join(&row.image);
    let bytes = crate::picture::image_decode::read_image_file(&image_path)
        .map_err(|e| fail(&row.image, e.reason()))?;
    crate::picture::check_jpeg_framing(&bytes).map_err(|m| fail(&row.image, m))?;
    // The size from the header, checked before any pixel is decoded; the decode then
    // proves the JPEG whole.
    let (width, height) = crate::picture::image_decode::decode_rgb8_checked(&bytes, &image_path, |h| {
        let (width, height) = (h.width, h.height);
        if width > arkit_core::MAX_VIEWPORT || height > arkit_core::MAX_VIEWPORT {
            return Err(Error::format(
                &image_path,
                format!(
                    "the image is {width}x{height}: larger than the {} pixels a side the renderer takes",
                    arkit_core::MAX_VIEWPORT
                ),
            ));
        }
        if width < MIN_IMAGE_SIDE || height < MIN_IMAGE_SIDE {
            return Err(Error::format(
                &image_path,
                format!(
                    "the image is {width}x{height}: too small for a face crop (at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE})"
                ),
            ));
        }
        Ok(())
    })
    .map_err(|e| fail(&row.image, e.reason()))?
    .dimensions();
    let camera =
        Camera::new(ctx.projection, width, height).map_err(|e| fail(&row.info, strip(e)))?;
    let verts64: Vec<Point3<f64>> = info.verts.iter().map(|p| p.cast()).collect();
    camera
        .check_projectable(&pose, &verts64)
        .map_err(|e| by(Check::Projection)(fail(&row.info, strip(e))))?;
    let mut landmarks_2d = Vec::with_capacity(136);
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for (k, &v) in ctx.topology.landmarks.iter().enumerate() {
        let p = camera.project(&pose, &verts64[v as usize]);
        if !(0.0..=width as f64).contains(&p.u) || !(0.0..=height as f64).contains(&p.v) {
            return Err(by(Check::Projection)(fail(
                &row.info,
                format!(
                    "landmark {k} projects to ({:.1}, {:.1}), outside the {width}x{height} image: annotation and image do not match",
                    p.u, p.v
                ),
            )));
        }
        landmarks_2d.extend([p.u as f32, p.v as f32]);
        x0 = x0.min(p.u);
        y0 = y0.min(p.v);
        x1 = x1.max(p.u);
        y1 = y1.max(p.v);
    }
    if x1 - x0 < MIN_FACE_SPAN_PX || y1 - y0 < MIN_FACE_SPAN_PX {
        return Err(by(Check::Projection)(fail(
            &row.info,
            format!(
                "the 68 landmarks span {:.1}x{:.1} pixels (at least {MIN_FACE_SPAN_PX} each way): a collapsed or all-zero mesh",
                x1 - x0,
                y1 - y0
            ),
        )));
    }
    if let Some(points2d) = info
        .points2d
        .as_ref()
        .filter(|_| !checks.skip.contains(&Check::Points2d))
    {
        let mut off: Vec<f64> = verts64
            .iter()
            .zip(points2d)
            .map(|(v, q)| {
                let p = camera.project(&pose, v);
                (p.u - q[0]).hypot(p.v - q[1])
            })
            .collect();
        off.sort_by(f64::total_cmp);
        let median = off[off.len() / 2];
        let tolerance =
            POINTS2D_TOLERANCE_PX.max(POINTS2D_TOLERANCE_FRACTION * width.max(height) as f64);
        if median > tolerance {
            return Err(by(Check::Points2d)(fail(
                &row.image,
                format!(
                    "the annotation's points2d lie a median {median:.1} px from its verts at R_t projected into this {width}x{height} image (tolerance {tolerance:.1} px): the image is not the one the annotation was made for (resized or another sample's)"
                ),
            )));
        }
    }
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let half = 0.75 * (x1 - x0).max(y1 - y0);
    let e = pose.euler();
    let t = pose.translation_m();
    Ok(SampleRecord {
        key: row.key.clone(),
        split: row.split.clone(),
        image_path: relative(root, &image_path),
        image_width: width,
        image_height: height,
        jpeg: ctx.embed_images.then_some(bytes),
        verts: info.verts.iter().flat_map(|p| [p.x, p.y, p.z]).collect(),
        rt: info.rt,
        yaw_deg: e.yaw_deg,
        pitch_deg: e.pitch_deg,
        roll_deg: e.roll_deg,
        translation_m: [t.x, t.y, t.z],
        landmarks_2d,
        face_box: [cx - half, cy - half, cx + half, cy + half],
    })
}

/// Options of a conversion.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ConvertOptions {
    /// Input root.
    pub input: PathBuf,
    /// Output folder.
    pub output: PathBuf,
    /// Resource folder (topology, landmarks, projection), if given.
    pub resources: Option<PathBuf>,
    /// Rows per shard.
    pub rows_per_shard: usize,
    /// Keep JPEG bytes in the table.
    pub embed_images: bool,
    /// This process converts shards `k` with `k % shard_count == shard_index`.
    pub shard_index: usize,
    /// Number of processes sharing the conversion.
    pub shard_count: usize,
    /// Replace the output of another conversion found in the output folder instead of
    /// refusing.
    #[serde(default)]
    pub overwrite: bool,
}

use arkit_core::limits::{MIN_FACE_SPAN_PX, MIN_IMAGE_SIDE};

/// The annotation's own `points2d`, when present, must lie within this many pixels
/// (median over the vertices) of `verts` at `R_t` projected into the image, or this
/// fraction of the image's larger side, whichever is larger; further, the image is not
/// the one the annotation was made for (another size, another sample).
pub(crate) const POINTS2D_TOLERANCE_PX: f64 = 8.0;
/// See [`POINTS2D_TOLERANCE_PX`].
pub(crate) const POINTS2D_TOLERANCE_FRACTION: f64 = 0.02;

/// Progress callback: called with the number of samples just finished.
pub type Progress<'a> = &'a (dyn Fn(usize) + Sync);

/// What a conversion is made from; two runs with the same fingerprint write the same
/// bytes. The shard count (`--shard I/N`) is not part of it: parts of one conversion
/// share it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ConversionFingerprint {
    /// The input root, absolute.
    pub input_root: String,
    /// The layout found.
    pub layout: LayoutKind,
    /// `(list file relative to the root, SHA-256 of its bytes)`.
    pub lists: Vec<(String, String)>,
    /// Where the topology came from.
    pub topology: String,
    /// `store::manifest::topology_digest` of the topology.
    pub topology_sha256: String,
    /// The projection matrix, row-major.
    pub projection: Vec<f64>,
    /// Rows per shard.
    pub rows_per_shard: usize,
    /// Whether JPEG bytes are embedded.
    pub embed_images: bool,
    /// The tool's version.
    pub version: String,
    /// [`samples_table::SAMPLES_FORMAT`] (0 in records written before it was recorded,
    /// whose shards are format 1): an output of another format is another conversion,
    /// so one dataset never mixes formats.
    #[serde(default)]
    pub samples_format: u32,
    /// The per-sample checks turned off (`--skip-check`), sorted: a conversion with a
    /// check off converts other samples, so it is another conversion. Absent when none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub skipped_checks: Vec<String>,
}

impl ConversionFingerprint {
    /// The fingerprint of converting `input` with `options` and `ctx`.
    pub fn new(
        input: &DiscoveredInput,
        options: &ConvertOptions,
        ctx: &ValidationContext,
    ) -> Result<Self> {
        let input_root = absolute_root(&input.root)?;
        let mut lists = Vec::new();
        for (_, p) in &input.lists {
            lists.push((relative(&input.root, p), sha256_file(p)?));
        }
        Ok(Self {
            input_root: input_root.display().to_string(),
            layout: input.kind,
            lists,
            topology: ctx.topology.source.clone(),
            topology_sha256: topology_digest(&ctx.topology),
            projection: ctx.projection.transpose().iter().copied().collect(),
            rows_per_shard: options.rows_per_shard,
            embed_images: options.embed_images,
            version: env!("CARGO_PKG_VERSION").into(),
            samples_format: samples_table::SAMPLES_FORMAT,
            skipped_checks: Vec::new(),
        })
    }

    /// SHA-256 of the fingerprint's JSON, hex.
    pub fn digest(&self) -> String {
        hex(&Sha256::digest(
            serde_json::to_vec(self).unwrap_or_default().as_slice(),
        ))
    }
}

/// `root` as an absolute, canonical path (symbolic links resolved).
fn absolute_root(root: &Path) -> Result<PathBuf> {
    std::fs::canonicalize(root).map_err(|e| Error::io(root, e))
}

/// The fingerprint of one shard: the conversion's, then each row's key, split and files
/// with their size and modification time (a file changed in place changes it).
fn shard_fingerprint(conversion: &str, root: &Path, rows: &[PlannedRow]) -> String {
    let mut h = Sha256::new();
    h.update(conversion.as_bytes());
    for r in rows {
        h.update(format!("\n{}\t{}", r.key, r.split).as_bytes());
        for f in [&r.image, &r.info] {
            h.update(b"\t");
            h.update(f.to_string_lossy().as_bytes());
            match std::fs::metadata(root.join(f)) {
                Ok(m) => {
                    h.update(m.len().to_le_bytes());
                    let t = m
                        .modified()
                        .ok()
                        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                        .map_or(0, |d| d.as_nanos());
                    h.update(t.to_le_bytes());
                }
                Err(_) => h.update(b"missing"),
            }
        }
    }
    hex(&h.finalize())
}

/// The name of the conversion record in an output folder.
pub const CONVERSION_FILE: &str = "conversion.json";

/// The conversion record at `path` (`conversion.json`), or `None` when there is none.
/// Errors name the file: unreadable, or not a record.
pub fn read_conversion_record(path: &Path) -> Result<Option<ConversionFingerprint>> {
    match std::fs::read_to_string(path) {
        Ok(text) => serde_json::from_str(&text)
            .map(Some)
            .map_err(|e| Error::format(path, format!("not a conversion record: {e}"))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(Error::io(path, e)),
    }
}

/// The record of a finished shard, beside its samples file.
fn shard_record_name(index: usize) -> String {
    format!("samples/part-{index:05}.json")
}

/// Reads the conversion record of `output`, takes the folder for this conversion and
/// removes stale temporaries. Refuses a folder that holds another conversion (or
/// samples without a record) unless `overwrite`, which removes that output first, and
/// only when no other writer of the folder is running ([`WRITERS_LOCK`]). Returns that
/// lock, held shared for the rest of the run.
/// The lock file (`.convert.lock`) that every writer of a converted folder (each part
/// of `convert`, `merge`, `split`, `render`) holds shared for its whole run, and that
/// `convert --overwrite` takes exclusively before it removes another conversion: so an
/// overwrite is refused while any of them still writes there, and they are refused
/// while an overwrite removes.
pub(crate) const WRITERS_LOCK: &str = "convert";

/// Takes [`WRITERS_LOCK`] shared in `dataset` for a writer of it, `None` when there is
/// no such folder (the writer then refuses it with its own error). Refused while a
/// `convert --overwrite` removes the folder's conversion.
pub(crate) fn hold_against_overwrite(dataset: &Path) -> Result<Option<FolderLock>> {
    if !dataset.is_dir() {
        return Ok(None);
    }
    FolderLock::acquire_shared(dataset, WRITERS_LOCK, "convert --overwrite").map(Some)
}

fn claim_output(
    output: &Path,
    fingerprint: &ConversionFingerprint,
    overwrite: bool,
) -> Result<FolderLock> {
    // Parts of one conversion starting together take this in turn (it is held for
    // the check and the record only).
    let _guard = arkit_core::atomic_file::FolderLock::wait(output, "conversion")?;
    let record = output.join(CONVERSION_FILE);
    let existing = read_conversion_record(&record)?;
    let has_output = ["samples", "errors", "manifest"]
        .iter()
        .any(|d| std::fs::read_dir(output.join(d)).is_ok_and(|mut r| r.next().is_some()))
        || output.join(MANIFEST_FILE).exists();
    let conflict = match &existing {
        Some(e) => e != fingerprint,
        None => has_output,
    };
    if conflict {
        if !overwrite {
            let what = match &existing {
                Some(e) if e.input_root != fingerprint.input_root => {
                    format!("a conversion of {}", e.input_root)
                }
                Some(e) if e.lists != fingerprint.lists => {
                    "a conversion of other list files".to_string()
                }
                Some(e) if e.topology_sha256 != fingerprint.topology_sha256 => {
                    format!("a conversion with another topology ({})", e.topology)
                }
                Some(e) if e.samples_format != fingerprint.samples_format => format!(
                    "a conversion in samples format {} (this version writes format {})",
                    e.samples_format.max(1),
                    fingerprint.samples_format
                ),
                Some(e) if e.skipped_checks != fingerprint.skipped_checks => format!(
                    "a conversion with other checks turned off (--skip-check: [{}] there, [{}] now)",
                    e.skipped_checks.join(", "),
                    fingerprint.skipped_checks.join(", ")
                ),
                Some(_) => "a conversion with other options or another version".to_string(),
                None => "samples without a conversion record".to_string(),
            };
            return Err(Error::format(
                output,
                format!(
                    "holds {what}: made from other input or options; choose another --output, remove the folder, or pass --overwrite"
                ),
            ));
        }
        // Nothing is removed while another writer of the folder still runs.
        let writers = FolderLock::acquire(output, WRITERS_LOCK, "convert, merge, split or render")?;
        // dataset.json first (and written last): a reader that finds it unchanged after
        // reading the folder read one generation (`Dataset::confirm_unchanged`).
        let p = output.join(MANIFEST_FILE);
        if p.exists() {
            std::fs::remove_file(&p).map_err(|e| Error::io(&p, e))?;
        }
        for d in ["samples", "errors", "manifest", "splits", "targets"] {
            let p = output.join(d);
            if p.exists() {
                std::fs::remove_dir_all(&p).map_err(|e| Error::io(&p, e))?;
            }
        }
        write_conversion_record(&record, fingerprint)?;
        arkit_core::atomic_file::remove_stale_temporaries(output, true)?;
        return writers.into_shared();
    }
    // Taken under the guard, before the record: an overwrite (which needs the guard)
    // cannot slip in between.
    let writers = FolderLock::acquire_shared(output, WRITERS_LOCK, "convert --overwrite")?;
    if existing.as_ref() != Some(fingerprint) {
        write_conversion_record(&record, fingerprint)?;
    }
    arkit_core::atomic_file::remove_stale_temporaries(output, true)?;
    Ok(writers)
}

/// Writes the conversion record `record` (`conversion.json`) atomically.
fn write_conversion_record(record: &Path, fingerprint: &ConversionFingerprint) -> Result<()> {
    let text = serde_json::to_string_pretty(fingerprint)
        .map_err(|e| Error::invalid("conversion record", e.to_string()))?;
    arkit_core::atomic_file::write_bytes(record, format!("{text}\n").as_bytes())
}

/// A finished shard from an earlier run, if it was made from exactly these rows of this
/// conversion and its files still hash to its record.
fn finished_shard(out: &Path, index: usize, fingerprint: &str) -> Result<Option<ShardEntry>> {
    let record = out.join(shard_record_name(index));
    let Ok(text) = std::fs::read_to_string(&record) else {
        return Ok(None);
    };
    let Ok(entry) = serde_json::from_str::<ShardEntry>(&text) else {
        return Ok(None);
    };
    if entry.index != index || entry.fingerprint != fingerprint {
        return Ok(None);
    }
    let (samples, errors) = (out.join(&entry.samples_file), out.join(&entry.errors_file));
    if !samples.exists() || !errors.exists() {
        return Ok(None);
    }
    if sha256_file(&samples)? != entry.sha256 || sha256_file(&errors)? != entry.errors_sha256 {
        return Ok(None);
    }
    Ok(Some(entry))
}

/// The manifest's file name for a part.
pub fn manifest_name(index: usize, count: usize) -> String {
    if count == 1 {
        MANIFEST_FILE.into()
    } else {
        format!("manifest/part-{index:04}-of-{count:04}.json")
    }
}

/// Runs a conversion (or this process's part of it); returns its manifest.
pub fn convert(
    options: &ConvertOptions,
    ctx: &ValidationContext,
    progress: Progress,
) -> Result<Manifest> {
    let input = discover(&options.input)?;
    let plan = plan_rows(&input)?;
    convert_planned(options, ctx, &input, plan, progress)
}

/// [`convert`] for an input already discovered and planned (so a caller that reports
/// what it found reads the lists once).
fn convert_planned(
    options: &ConvertOptions,
    ctx: &ValidationContext,
    input: &DiscoveredInput,
    plan: (Vec<PlannedRow>, Vec<ErrorRecord>),
    progress: Progress,
) -> Result<Manifest> {
    convert_planned_with(
        options,
        ctx,
        &ConvertChecks::default(),
        input,
        plan,
        progress,
    )
}

/// `convert_planned` with `checks` (checks turned off, the systematic rule's
/// window). A run that the systematic rule stops ([`crate::ingest::SYSTEMATIC_WINDOW`]) returns its
/// message as the error; the shards finished before it stay (a rerun with the check
/// turned off is another conversion and replaces them with `--overwrite`).
pub fn convert_planned_with(
    options: &ConvertOptions,
    ctx: &ValidationContext,
    checks: &ConvertChecks,
    input: &DiscoveredInput,
    plan: (Vec<PlannedRow>, Vec<ErrorRecord>),
    progress: Progress,
) -> Result<Manifest> {
    check_convert_options(options, checks)?;
    let (rows, mut listing) = plan;
    let out = &options.output;
    let mut fingerprint = ConversionFingerprint::new(input, options, ctx)?;
    let mut skipped: Vec<String> = checks.skip.iter().map(|c| c.name().to_string()).collect();
    skipped.sort();
    skipped.dedup();
    fingerprint.skipped_checks = skipped;
    let conversion = fingerprint.digest();
    let _writers = claim_output(out, &fingerprint, options.overwrite)?;
    let _part_lock = arkit_core::atomic_file::FolderLock::acquire(
        out,
        &format!(
            "convert-part-{}-of-{}",
            options.shard_index, options.shard_count
        ),
        "convert of this part",
    )?;
    std::fs::create_dir_all(out.join("samples")).map_err(|e| Error::io(out, e))?;
    std::fs::create_dir_all(out.join("errors")).map_err(|e| Error::io(out, e))?;
    let mut listing_problems = 0;
    if options.shard_index == 0 {
        listing.extend(find_orphans(input, &rows));
        listing_problems = listing.len();
        parquet::write_parquet(
            &out.join("errors").join("listing.parquet"),
            &mut samples_table::errors_frame(&listing)?,
        )?;
    }
    let mut shards = Vec::new();
    let vertices = ctx.topology.vertex_count;
    let mut tally = SkipTally::new(checks.window);
    // Validation of shard k+1 (rayon) overlaps the writing of shard k (one writer
    // thread), so the sequential Parquet encoding does not leave a core idle.
    std::thread::scope(|scope| -> Result<()> {
        let mut pending: Option<std::thread::ScopedJoinHandle<'_, Result<ShardEntry>>> = None;
        let join = |h: std::thread::ScopedJoinHandle<'_, Result<ShardEntry>>| {
            h.join()
                .unwrap_or_else(|_| Err(Error::invalid("convert", "the shard writer panicked")))
        };
        for (index, chunk) in rows.chunks(options.rows_per_shard).enumerate() {
            if index % options.shard_count != options.shard_index {
                continue;
            }
            let shard_fp = shard_fingerprint(&conversion, &input.root, chunk);
            if let Some(entry) = finished_shard(out, index, &shard_fp)? {
                // Finished by an earlier run of this conversion, from the same files.
                progress(chunk.len());
                shards.push(entry);
                continue;
            }
            let files = ShardFiles::new(out, index);
            // A record that no longer matches goes first: an interruption from here on
            // leaves a shard that the next run redoes.
            if files.record_path.exists() {
                std::fs::remove_file(&files.record_path)
                    .map_err(|e| Error::io(&files.record_path, e))?;
            }
            let (good, bad) =
                validate_shard(chunk, &input.root, ctx, checks, &mut tally, progress)?;
            if let Some(h) = pending.take() {
                shards.push(join(h)?);
            }
            pending = Some(
                scope.spawn(move || write_shard(files, index, &good, &bad, vertices, shard_fp)),
            );
        }
        if let Some(h) = pending.take() {
            shards.push(join(h)?);
        }
        Ok(())
    })?;
    shards.sort_by_key(|s| s.index);
    let converted = shards.iter().map(|s| s.rows).sum();
    let skipped = shards.iter().map(|s| s.error_rows).sum();
    let manifest = Manifest {
        tool: "arkit-tool".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        input: options.input.display().to_string(),
        input_root: fingerprint.input_root.clone(),
        fingerprint: conversion,
        topology_sha256: fingerprint.topology_sha256.clone(),
        layout: input.kind,
        lists: input
            .lists
            .iter()
            .map(|(_, p)| relative(&input.root, p))
            .collect(),
        topology: ctx.topology.source.clone(),
        rows_per_shard: options.rows_per_shard,
        embed_images: options.embed_images,
        part: [options.shard_index, options.shard_count],
        listed: rows.len(),
        converted,
        skipped,
        listing_problems,
        shards,
    };
    write_manifest(
        &out.join(manifest_name(options.shard_index, options.shard_count)),
        &manifest,
    )?;
    Ok(manifest)
}

/// Refuses checks that cannot be turned off, an empty shard size and a part `I/N` with
/// `I >= N`.
fn check_convert_options(options: &ConvertOptions, checks: &ConvertChecks) -> Result<()> {
    if let Some(c) = checks.skip.iter().find(|c| !SKIPPABLE_CHECKS.contains(c)) {
        return Err(Error::invalid(
            "--skip-check",
            format!(
                "the '{}' check cannot be turned off (a sample that fails it would be wrong); only {} can",
                c.name(),
                SKIPPABLE_CHECKS.map(|c| c.name()).join(", ")
            ),
        ));
    }
    if options.rows_per_shard == 0 {
        return Err(Error::invalid("--rows-per-shard", "must be at least 1"));
    }
    if options.shard_count == 0 || options.shard_index >= options.shard_count {
        return Err(Error::invalid(
            "--shard",
            format!(
                "{}/{} is not I/N with I < N",
                options.shard_index, options.shard_count
            ),
        ));
    }
    Ok(())
}

/// The files of shard `index` of a conversion into `out`: samples, errors (relative to
/// `out` and in it) and the shard's record.
struct ShardFiles {
    /// `samples/part-KKKKK.parquet`.
    samples_rel: String,
    /// `errors/part-KKKKK.parquet`.
    errors_rel: String,
    /// The samples file.
    samples_path: PathBuf,
    /// The errors file.
    errors_path: PathBuf,
    /// The shard's record, written last.
    record_path: PathBuf,
}

impl ShardFiles {
    /// Shard `index`'s files in `out`.
    fn new(out: &Path, index: usize) -> Self {
        let samples_rel = format!("samples/part-{index:05}.parquet");
        let errors_rel = format!("errors/part-{index:05}.parquet");
        let (samples_path, errors_path) = (out.join(&samples_rel), out.join(&errors_rel));
        let record_path = out.join(shard_record_name(index));
        ShardFiles {
            samples_rel,
            errors_rel,
            samples_path,
            errors_path,
            record_path,
        }
    }
}

/// Validates a shard's rows (in parallel), split into the good samples and the errors
/// rows. The first samples of the run (up to the systematic rule's window, counted in
/// `tally`) are validated first, and the rule applied, before the rest of the shard.
fn validate_shard(
    chunk: &[PlannedRow],
    root: &Path,
    ctx: &ValidationContext,
    checks: &ConvertChecks,
    tally: &mut SkipTally,
    progress: Progress,
) -> Result<(Vec<SampleRecord>, Vec<ErrorRecord>)> {
    let validate = |rows: &[PlannedRow]| -> Vec<std::result::Result<SampleRecord, Skip>> {
        rows.par_iter()
            .map(|row| {
                let r = validate_sample_with(root, row, ctx, checks);
                progress(1);
                r
            })
            .collect()
    };
    let first = tally.remaining().min(chunk.len());
    let mut results = validate(&chunk[..first]);
    for r in &results {
        tally.record(r.as_ref().err().and_then(|s| {
            s.check
                .map(|c| (c, format!("{}: {}", s.record.file, s.record.reason)))
        }));
    }
    if let Some((_, message)) = tally.verdict("samples") {
        return Err(Error::invalid("convert", message));
    }
    results.extend(validate(&chunk[first..]));
    let (mut good, mut bad) = (Vec::new(), Vec::new());
    for r in results {
        match r {
            Ok(s) => good.push(s),
            Err(e) => bad.push(*e.record),
        }
    }
    Ok((good, bad))
}

/// Writes shard `index`: its errors file, its samples file, then its record (a shard is
/// finished only once the record exists); returns the record.
fn write_shard(
    files: ShardFiles,
    index: usize,
    good: &[SampleRecord],
    bad: &[ErrorRecord],
    vertices: usize,
    fingerprint: String,
) -> Result<ShardEntry> {
    let ShardFiles {
        samples_rel,
        errors_rel,
        samples_path,
        errors_path,
        record_path,
    } = files;
    parquet::write_parquet(&errors_path, &mut samples_table::errors_frame(bad)?)?;
    samples_table::write_samples(&samples_path, good, vertices)?;
    let entry = ShardEntry {
        index,
        samples_file: samples_rel,
        rows: good.len(),
        sha256: sha256_file(&samples_path)?,
        errors_file: errors_rel,
        error_rows: bad.len(),
        errors_sha256: sha256_file(&errors_path)?,
        bytes: std::fs::metadata(&samples_path)
            .map_err(|e| Error::io(&samples_path, e))?
            .len(),
        tail_sha256: tail_sha256(&samples_path)?,
        fingerprint,
    };
    // The record last: a shard is finished only once it exists.
    let text = serde_json::to_string_pretty(&entry)
        .map_err(|e| Error::invalid("shard record", e.to_string()))?;
    arkit_core::atomic_file::write_bytes(&record_path, format!("{text}\n").as_bytes())?;
    Ok(entry)
}

pub(super) fn write_manifest(path: &Path, m: &Manifest) -> Result<()> {
    let text =
        serde_json::to_string_pretty(m).map_err(|e| Error::invalid("manifest", e.to_string()))?;
    arkit_core::atomic_file::write_bytes(path, format!("{text}\n").as_bytes())
}

/// Reads every `samples` shard of a converted dataset named by its `dataset.json`, each
/// checked against the manifest first.
pub fn read_dataset_samples(dataset: &Path) -> Result<Vec<SampleRecord>> {
    crate::store::dataset::Dataset::open(dataset)?.read_all_samples()
}

/// Checks every file the manifest of `dataset` names against its full SHA-256; returns
/// the number of files checked, or the first file that differs.
pub fn verify_dataset(dataset: &Path) -> Result<usize> {
    let m = read_manifest(&dataset.join(MANIFEST_FILE))?;
    let mut checked = 0;
    for s in &m.shards {
        for (file, sha) in [
            (&s.samples_file, &s.sha256),
            (&s.errors_file, &s.errors_sha256),
        ] {
            let path = dataset.join(file);
            if &sha256_file(&path)? != sha {
                return Err(Error::format(
                    &path,
                    "its SHA-256 differs from the manifest's: the file changed after convert wrote it; rerun `arkit-tool convert`",
                ));
            }
            checked += 1;
        }
    }
    Ok(checked)
}
