//! `convert`: the release as published into validated, sharded Parquet.
//!
//! Stages: [`discover`] the input layout; [`plan_rows`] from the list CSVs (list order,
//! train before test); cut the rows into shards of `rows_per_shard`; for each shard
//! this process owns (`--shard I/N`: shards `k` with `k % N == I`), validate every
//! sample in parallel ([`validate_sample`]) and write `errors/part-K.parquet` then
//! `samples/part-K.parquet`, each to a temporary name renamed into place. A shard whose
//! two files exist is finished and is kept on a rerun, so an interrupted conversion
//! resumes. Rows keep list order within and across shards, so the output is
//! byte-identical whatever the number of threads. Memory is bounded by one shard.
//!
//! A bad sample never stops the run: it becomes a row of the `errors` table with the
//! file at fault and the reason. Files on disk that no list names, and list rows that
//! repeat a key, are reported in `errors/listing.parquet`.

use crate::conventions::{Camera, Pose};
use crate::error::{Error, Result};
use crate::release::{self, ListRow, SampleKey};
use crate::samples_table::{self, ErrorRecord, SampleRecord};
use crate::topology::FaceTopology;
use nalgebra::{Matrix4, Point3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::{BTreeSet, HashSet};
use std::path::{Path, PathBuf};

/// Which of the two published layouts the input has.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LayoutKind {
    /// `ARKitFace_image_{split}/image/...`, `ARKitFace_info_{split}/info/...`,
    /// `ARKitFace_list/list/ARKitFace_{split}.csv`.
    Download,
    /// `image/...`, `info/...` and list CSV(s) in the root.
    Flat,
}

/// What [`discover`] found.
#[derive(Clone, Debug)]
pub struct DiscoveredInput {
    /// The input root.
    pub root: PathBuf,
    /// The layout.
    pub kind: LayoutKind,
    /// `(split name, list CSV)` pairs, train first.
    pub lists: Vec<(String, PathBuf)>,
}

impl DiscoveredInput {
    /// Image path of a sample, relative to the root.
    pub fn image_relative(&self, split: &str, key: &SampleKey) -> PathBuf {
        self.data_dir(split, "image")
            .join(&key.subject_id)
            .join(&key.facial_action)
            .join(format!("{}_ar.jpg", key.img_id))
    }

    /// Annotation path of a sample, relative to the root.
    pub fn info_relative(&self, split: &str, key: &SampleKey) -> PathBuf {
        self.data_dir(split, "info")
            .join(&key.subject_id)
            .join(&key.facial_action)
            .join(format!("{}_info.npz", key.img_id))
    }

    fn data_dir(&self, split: &str, kind: &str) -> PathBuf {
        match self.kind {
            LayoutKind::Download => PathBuf::from(format!("ARKitFace_{kind}_{split}")).join(kind),
            LayoutKind::Flat => PathBuf::from(kind),
        }
    }

    /// The folders that hold annotations and images (relative), for the orphan scan.
    pub fn data_dirs(&self) -> Vec<PathBuf> {
        let splits: BTreeSet<&str> = self.lists.iter().map(|(s, _)| s.as_str()).collect();
        let mut dirs = Vec::new();
        for s in splits {
            dirs.push(self.data_dir(s, "image"));
            dirs.push(self.data_dir(s, "info"));
        }
        dirs.dedup();
        dirs
    }
}

/// Finds the layout of `root`.
pub fn discover(root: &Path) -> Result<DiscoveredInput> {
    if !root.is_dir() {
        return Err(Error::format(root, "input folder does not exist"));
    }
    let list_dir = root.join("ARKitFace_list").join("list");
    if list_dir.is_dir() {
        let mut lists = Vec::new();
        for entry in std::fs::read_dir(&list_dir).map_err(|e| Error::io(&list_dir, e))? {
            let path = entry.map_err(|e| Error::io(&list_dir, e))?.path();
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            if let Some(split) = name
                .strip_prefix("ARKitFace_")
                .and_then(|n| n.strip_suffix(".csv"))
            {
                lists.push((split.to_string(), path));
            }
        }
        if lists.is_empty() {
            return Err(Error::format(
                &list_dir,
                "no ARKitFace_<split>.csv list in this folder",
            ));
        }
        // train first, then test, then any other split, by name.
        lists.sort_by_key(|(s, _)| (s != "train", s != "test", s.clone()));
        return Ok(DiscoveredInput {
            root: root.to_path_buf(),
            kind: LayoutKind::Download,
            lists,
        });
    }
    if root.join("image").is_dir() && root.join("info").is_dir() {
        let mut csvs: Vec<PathBuf> = std::fs::read_dir(root)
            .map_err(|e| Error::io(root, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "csv"))
            .collect();
        csvs.sort();
        if csvs.len() != 1 {
            return Err(Error::format(
                root,
                format!(
                    "a flat layout (image/, info/) needs exactly one list CSV in the folder, found {}",
                    csvs.len()
                ),
            ));
        }
        return Ok(DiscoveredInput {
            root: root.to_path_buf(),
            kind: LayoutKind::Flat,
            lists: vec![("all".into(), csvs.remove(0))],
        });
    }
    Err(Error::format(
        root,
        "not an ARKitFace release: expected ARKitFace_list/list/*.csv (download layout) or image/, info/ and one CSV (flat layout)",
    ))
}

/// One row to convert.
#[derive(Clone, Debug)]
pub struct PlannedRow {
    /// Key.
    pub key: SampleKey,
    /// Split name.
    pub split: String,
    /// Image path relative to the root.
    pub image: PathBuf,
    /// Annotation path relative to the root.
    pub info: PathBuf,
}

/// The rows of every list, in order, and the rows that repeat an earlier key.
pub fn plan_rows(input: &DiscoveredInput) -> Result<(Vec<PlannedRow>, Vec<ErrorRecord>)> {
    let mut rows = Vec::new();
    let mut problems = Vec::new();
    let mut seen = HashSet::new();
    for (split, list) in &input.lists {
        for ListRow { key, line } in release::read_list(list)? {
            let rel_list = relative(&input.root, list);
            if !seen.insert(key.clone()) {
                problems.push(ErrorRecord {
                    key: key.clone(),
                    split: split.clone(),
                    file: rel_list.clone(),
                    reason: format!(
                        "line {line}: {key} is listed again; the first listing is converted"
                    ),
                });
                continue;
            }
            rows.push(PlannedRow {
                image: input.image_relative(split, &key),
                info: input.info_relative(split, &key),
                key,
                split: split.clone(),
            });
        }
    }
    Ok((rows, problems))
}

fn relative(root: &Path, path: &Path) -> String {
    let rel = path.strip_prefix(root).unwrap_or(path);
    rel.components()
        .map(|c| c.as_os_str().to_string_lossy())
        .collect::<Vec<_>>()
        .join("/")
}

/// Files under the data folders that no list row names.
pub fn find_orphans(input: &DiscoveredInput, rows: &[PlannedRow]) -> Vec<ErrorRecord> {
    let named: HashSet<PathBuf> = rows
        .iter()
        .flat_map(|r| [r.image.clone(), r.info.clone()])
        .collect();
    let mut out = Vec::new();
    for dir in input.data_dirs() {
        let mut stack = vec![input.root.join(&dir)];
        let mut files = Vec::new();
        while let Some(d) = stack.pop() {
            let Ok(entries) = std::fs::read_dir(&d) else {
                continue;
            };
            for e in entries.flatten() {
                let p = e.path();
                if p.is_dir() {
                    stack.push(p);
                } else {
                    files.push(p);
                }
            }
        }
        files.sort();
        for f in files {
            let rel = f.strip_prefix(&input.root).unwrap_or(&f).to_path_buf();
            if !named.contains(&rel) {
                out.push(ErrorRecord {
                    key: SampleKey {
                        subject_id: String::new(),
                        facial_action: String::new(),
                        img_id: String::new(),
                    },
                    split: String::new(),
                    file: relative(&input.root, &f),
                    reason: "file on disk that no list names".into(),
                });
            }
        }
    }
    out
}

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

/// Checks that `bytes` look like a complete JPEG: the start-of-image marker, and an
/// end-of-image marker near the end (inside entropy-coded data 0xFF is always
/// followed by 0x00 or a restart marker, so `FF D9` there is a real end marker).
pub fn check_jpeg_framing(bytes: &[u8]) -> std::result::Result<(), String> {
    if bytes.len() < 4 || bytes[..3] != [0xFF, 0xD8, 0xFF] {
        return Err("not a JPEG file (no start-of-image marker)".into());
    }
    let tail = &bytes[bytes.len().saturating_sub(64)..];
    if !tail.windows(2).any(|w| w == [0xFF, 0xD9]) {
        return Err("truncated JPEG (no end-of-image marker)".into());
    }
    Ok(())
}

/// Validates one sample and builds its row, or says what is wrong with which file.
pub fn validate_sample(
    root: &Path,
    row: &PlannedRow,
    ctx: &ValidationContext,
) -> std::result::Result<SampleRecord, Box<ErrorRecord>> {
    let fail = |file: &Path, reason: String| {
        Box::new(ErrorRecord {
            key: row.key.clone(),
            split: row.split.clone(),
            file: relative(root, &root.join(file)),
            reason,
        })
    };
    let strip = |e: Error| -> String {
        match e {
            Error::Format { message, .. } => message,
            Error::Io { source, .. } => source.to_string(),
            Error::Invalid { what, message } => format!("{what}: {message}"),
        }
    };
    let info_path = root.join(&row.info);
    let info = release::read_info(&info_path).map_err(|e| fail(&row.info, strip(e)))?;
    if info.verts.len() != ctx.topology.vertex_count {
        return Err(fail(
            &row.info,
            format!(
                "{} vertices, the topology has {}",
                info.verts.len(),
                ctx.topology.vertex_count
            ),
        ));
    }
    let pose = Pose::from_release_rt(&info.rt).map_err(|e| fail(&row.info, strip(e)))?;
    let image_path = root.join(&row.image);
    let bytes = std::fs::read(&image_path).map_err(|e| fail(&row.image, e.to_string()))?;
    check_jpeg_framing(&bytes).map_err(|m| fail(&row.image, m))?;
    let image = image::load_from_memory_with_format(&bytes, image::ImageFormat::Jpeg)
        .map_err(|e| fail(&row.image, format!("JPEG does not decode: {e}")))?;
    let (width, height) = (image.width(), image.height());
    drop(image);
    let camera =
        Camera::new(ctx.projection, width, height).map_err(|e| fail(&row.info, strip(e)))?;
    let verts64: Vec<Point3<f64>> = info.verts.iter().map(|p| p.cast()).collect();
    camera
        .check_projectable(&pose, &verts64)
        .map_err(|e| fail(&row.info, strip(e)))?;
    let mut landmarks_2d = Vec::with_capacity(136);
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for (k, &v) in ctx.topology.landmarks.iter().enumerate() {
        let p = camera.project(&pose, &verts64[v as usize]);
        if !(0.0..=width as f64).contains(&p.u) || !(0.0..=height as f64).contains(&p.v) {
            return Err(fail(
                &row.info,
                format!(
                    "landmark {k} projects to ({:.1}, {:.1}), outside the {width}x{height} image: annotation and image do not match",
                    p.u, p.v
                ),
            ));
        }
        landmarks_2d.extend([p.u as f32, p.v as f32]);
        x0 = x0.min(p.u);
        y0 = y0.min(p.v);
        x1 = x1.max(p.u);
        y1 = y1.max(p.v);
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
}

/// One finished shard in the manifest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShardEntry {
    /// Shard number.
    pub index: usize,
    /// `samples/part-K.parquet`, relative to the output.
    pub samples_file: String,
    /// Rows in it.
    pub rows: usize,
    /// SHA-256 of the file.
    pub sha256: String,
    /// `errors/part-K.parquet`.
    pub errors_file: String,
    /// Rows in it (samples skipped in this shard).
    pub error_rows: usize,
    /// SHA-256 of the errors file.
    pub errors_sha256: String,
}

/// `dataset.json` (or one part of it for `--shard I/N`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// `arkit-tool`.
    pub tool: String,
    /// The tool's version.
    pub version: String,
    /// Input root as given.
    pub input: String,
    /// Layout found.
    pub layout: LayoutKind,
    /// The lists read.
    pub lists: Vec<String>,
    /// Where the topology and landmarks came from.
    pub topology: String,
    /// The conversion's arguments.
    pub rows_per_shard: usize,
    /// Whether JPEG bytes are embedded.
    pub embed_images: bool,
    /// Which part this is (`[I, N]`); `[0, 1]` for a whole dataset.
    pub part: [usize; 2],
    /// Rows listed (all shards of the dataset).
    pub listed: usize,
    /// Samples converted (in the shards of this manifest).
    pub converted: usize,
    /// Samples skipped (in the shards of this manifest).
    pub skipped: usize,
    /// Listing problems (orphan files, repeated rows), when this part reports them.
    pub listing_problems: usize,
    /// Shards, by index.
    pub shards: Vec<ShardEntry>,
}

/// Progress callback: called with the number of samples just finished.
pub type Progress<'a> = &'a (dyn Fn(usize) + Sync);

fn sha256_file(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    Ok(Sha256::digest(&bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect())
}

/// The manifest's file name for a part.
pub fn manifest_name(index: usize, count: usize) -> String {
    if count == 1 {
        "dataset.json".into()
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
pub fn convert_planned(
    options: &ConvertOptions,
    ctx: &ValidationContext,
    input: &DiscoveredInput,
    plan: (Vec<PlannedRow>, Vec<ErrorRecord>),
    progress: Progress,
) -> Result<Manifest> {
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
    let (rows, mut listing) = plan;
    let out = &options.output;
    std::fs::create_dir_all(out.join("samples")).map_err(|e| Error::io(out, e))?;
    std::fs::create_dir_all(out.join("errors")).map_err(|e| Error::io(out, e))?;
    let mut listing_problems = 0;
    if options.shard_index == 0 {
        listing.extend(find_orphans(input, &rows));
        listing_problems = listing.len();
        samples_table::write_parquet(
            &out.join("errors").join("listing.parquet"),
            &mut samples_table::errors_frame(&listing)?,
        )?;
    }
    let mut shards = Vec::new();
    // Validation of shard k+1 (rayon) overlaps the writing of shard k (one writer
    // thread), so the sequential Parquet encoding does not leave a core idle.
    std::thread::scope(|scope| -> Result<()> {
        let mut pending: Option<std::thread::ScopedJoinHandle<'_, Result<ShardEntry>>> = None;
        for (index, chunk) in rows.chunks(options.rows_per_shard).enumerate() {
            if index % options.shard_count != options.shard_index {
                continue;
            }
            let samples_rel = format!("samples/part-{index:05}.parquet");
            let errors_rel = format!("errors/part-{index:05}.parquet");
            let (samples_path, errors_path) = (out.join(&samples_rel), out.join(&errors_rel));
            if samples_path.exists() && errors_path.exists() {
                // Finished by an earlier run: keep it.
                let counts = (
                    samples_table::parquet_row_count(&samples_path)?,
                    samples_table::parquet_row_count(&errors_path)?,
                );
                if counts.0 + counts.1 != chunk.len() {
                    return Err(Error::format(
                        &samples_path,
                        format!(
                            "holds {} + {} error rows but this shard has {} listed rows: it was made from other input or options; remove the output folder",
                            counts.0,
                            counts.1,
                            chunk.len()
                        ),
                    ));
                }
                progress(chunk.len());
                shards.push(ShardEntry {
                    index,
                    samples_file: samples_rel,
                    rows: counts.0,
                    sha256: sha256_file(&samples_path)?,
                    errors_file: errors_rel,
                    error_rows: counts.1,
                    errors_sha256: sha256_file(&errors_path)?,
                });
                continue;
            }
            let results: Vec<std::result::Result<SampleRecord, Box<ErrorRecord>>> = chunk
                .par_iter()
                .map(|row| {
                    let r = validate_sample(&input.root, row, ctx);
                    progress(1);
                    r
                })
                .collect();
            let (mut good, mut bad) = (Vec::new(), Vec::new());
            for r in results {
                match r {
                    Ok(s) => good.push(s),
                    Err(e) => bad.push(*e),
                }
            }
            if let Some(h) = pending.take() {
                shards.push(h.join().expect("writer thread")?);
            }
            pending = Some(scope.spawn(move || {
                // Errors first: a samples file without its errors file is never "finished".
                samples_table::write_parquet(
                    &errors_path,
                    &mut samples_table::errors_frame(&bad)?,
                )?;
                samples_table::write_parquet(
                    &samples_path,
                    &mut samples_table::samples_frame(&good)?,
                )?;
                Ok(ShardEntry {
                    index,
                    samples_file: samples_rel,
                    rows: good.len(),
                    sha256: sha256_file(&samples_path)?,
                    errors_file: errors_rel,
                    error_rows: bad.len(),
                    errors_sha256: sha256_file(&errors_path)?,
                })
            }));
        }
        if let Some(h) = pending.take() {
            shards.push(h.join().expect("writer thread")?);
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

fn write_manifest(path: &Path, m: &Manifest) -> Result<()> {
    let text =
        serde_json::to_string_pretty(m).map_err(|e| Error::invalid("manifest", e.to_string()))?;
    crate::atomic_file::write_bytes(path, format!("{text}\n").as_bytes())
}

/// Reads a manifest.
pub fn read_manifest(path: &Path) -> Result<Manifest> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| Error::format(path, format!("not a manifest: {e}")))
}

/// Joins the parts of a `--shard I/N` conversion into `dataset.json`. Errors if a part
/// is missing or the parts disagree.
pub fn merge(dataset: &Path) -> Result<Manifest> {
    let dir = dataset.join("manifest");
    let mut parts: Vec<Manifest> = Vec::new();
    let entries = std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))?;
    let mut paths: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    paths.sort();
    for p in &paths {
        parts.push(read_manifest(p)?);
    }
    let first = parts
        .first()
        .ok_or_else(|| Error::format(&dir, "no manifest parts to merge"))?
        .clone();
    let n = first.part[1];
    let have: BTreeSet<usize> = parts.iter().map(|p| p.part[0]).collect();
    if let Some(missing) = (0..n).find(|i| !have.contains(i)) {
        return Err(Error::format(
            &dir,
            format!("part {missing} of {n} is missing: run `convert --shard {missing}/{n}`"),
        ));
    }
    for (p, path) in parts.iter().zip(&paths) {
        if p.part[1] != n
            || p.listed != first.listed
            || p.rows_per_shard != first.rows_per_shard
            || p.input != first.input
        {
            return Err(Error::format(
                path,
                "this part comes from a different conversion (input, shard count or shard size differ)",
            ));
        }
    }
    let mut shards: Vec<ShardEntry> = parts.iter().flat_map(|p| p.shards.clone()).collect();
    shards.sort_by_key(|s| s.index);
    let merged = Manifest {
        part: [0, 1],
        converted: parts.iter().map(|p| p.converted).sum(),
        skipped: parts.iter().map(|p| p.skipped).sum(),
        listing_problems: parts.iter().map(|p| p.listing_problems).sum(),
        shards,
        ..first
    };
    write_manifest(&dataset.join("dataset.json"), &merged)?;
    Ok(merged)
}

/// Reads every `samples` shard of a converted dataset named by its `dataset.json`.
pub fn read_dataset_samples(dataset: &Path) -> Result<Vec<SampleRecord>> {
    let m = read_manifest(&dataset.join("dataset.json"))?;
    let mut out = Vec::new();
    for s in &m.shards {
        out.extend(samples_table::read_samples(&dataset.join(&s.samples_file))?);
    }
    Ok(out)
}
