//! `augment` over a converted dataset: which samples to enlarge and by how much, the
//! output in the release's download layout, the skip report and the preview.
//!
//! # The rule (the official code's, configurable in [`ProfilingRule`])
//! With the sample's yaw and pitch in degrees:
//! - pitch may be enlarged when `8 <= pitch <= 25` or `-35 <= pitch <= -20`, and
//!   `|yaw| <= 15` (moderately pitched, near-frontal faces);
//! - yaw may be enlarged when `|pitch| <= 25` and `|yaw| >= 20` (already-turned faces);
//! - roll always.
//!
//! Both allowed: pitch, yaw, roll with probabilities 0.4, 0.4, 0.2; only pitch: pitch 0.8,
//! roll 0.2; only yaw: yaw 0.8, roll 0.2; neither: roll 0.4, nothing 0.6. The change is
//! drawn uniformly from 5 to 30 degrees, away from zero (in the sign of the angle; a
//! random sign at exactly zero), and shortened so the new angle stays within
//! `--max-angle` (90 by default); a sample too close to the limit for the 5 degree
//! minimum is skipped with that reason. `--axis yaw|pitch|roll` forces one axis for
//! every sample, ignoring the allowance rule but not the limit.
//!
//! Every draw comes from the sample's own stream of the seed ([`Rng::for_stream`]), so
//! the output does not depend on the number of threads.

use crate::augment::sample::{Axis, FaceImage, Skip};
use crate::mesh::topology::FaceTopology;
use crate::picture::overlay::{MeshStyle, draw_mesh};
use crate::store::dataset::Dataset;
use crate::store::samples_table::SampleRecord;
use arkit_core::NpzCompression;
use arkit_core::Rng;
use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_core::release::{self, InfoAnnotation, ReleaseLayout, SampleKey, Split};
use arkit_core::{Error, Result};
use image::RgbImage;
use nalgebra::{Matrix4, Point3};
use rayon::prelude::*;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// Which samples may be enlarged along which axis, and by how much (degrees).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ProfilingRule {
    /// Yaw is enlarged only when `|yaw| >=` this.
    pub yaw_min_abs: f64,
    /// ... and `|pitch| <=` this.
    pub yaw_max_abs_pitch: f64,
    /// Pitch is enlarged only inside one of these ranges...
    pub pitch_ranges: [(f64, f64); 2],
    /// ... and when `|yaw| <=` this.
    pub pitch_max_abs_yaw: f64,
    /// Smallest change drawn.
    pub min_change: f64,
    /// Largest change drawn.
    pub max_change: f64,
    /// No angle goes past +/- this.
    pub max_angle: f64,
}

impl Default for ProfilingRule {
    fn default() -> Self {
        ProfilingRule {
            yaw_min_abs: 20.0,
            yaw_max_abs_pitch: 25.0,
            pitch_ranges: [(8.0, 25.0), (-35.0, -20.0)],
            pitch_max_abs_yaw: 15.0,
            min_change: 5.0,
            max_change: 30.0,
            max_angle: 90.0,
        }
    }
}

/// How the axis is chosen.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum AxisChoice {
    /// By the rule's probabilities.
    Auto,
    /// Always this axis.
    Fixed(Axis),
}

/// `--axis`'s values: `auto`, or one axis by its name.
#[cfg(feature = "clap")]
impl clap::ValueEnum for AxisChoice {
    fn value_variants<'a>() -> &'a [Self] {
        &[
            AxisChoice::Auto,
            AxisChoice::Fixed(Axis::Yaw),
            AxisChoice::Fixed(Axis::Pitch),
            AxisChoice::Fixed(Axis::Roll),
        ]
    }

    fn to_possible_value(&self) -> Option<clap::builder::PossibleValue> {
        Some(clap::builder::PossibleValue::new(match self {
            AxisChoice::Auto => "auto",
            AxisChoice::Fixed(Axis::Yaw) => "yaw",
            AxisChoice::Fixed(Axis::Pitch) => "pitch",
            AxisChoice::Fixed(Axis::Roll) => "roll",
        }))
    }
}

impl ProfilingRule {
    /// The axes the rule allows for a face at `e` (roll always).
    pub fn allowed(&self, e: &EulerAngles) -> (bool, bool) {
        let (yaw, pitch) = (e.yaw_deg, e.pitch_deg);
        let pitch_ok = self
            .pitch_ranges
            .iter()
            .any(|&(lo, hi)| lo <= pitch && pitch <= hi)
            && yaw.abs() <= self.pitch_max_abs_yaw;
        let yaw_ok = pitch.abs() <= self.yaw_max_abs_pitch && yaw.abs() >= self.yaw_min_abs;
        (yaw_ok, pitch_ok)
    }

    /// Draws the axis and signed change for a face at `e`; `Ok(None)` when the rule
    /// picks nothing, `Err` when the face is too close to the limit.
    pub fn choose(
        &self,
        e: &EulerAngles,
        choice: AxisChoice,
        rng: &mut Rng,
    ) -> std::result::Result<Option<(Axis, f64)>, Skip> {
        let axis = match choice {
            AxisChoice::Fixed(a) => a,
            AxisChoice::Auto => {
                let (yaw_ok, pitch_ok) = self.allowed(e);
                let x = rng.next_f64();
                match (yaw_ok, pitch_ok) {
                    (true, true) if x < 0.4 => Axis::Pitch,
                    (true, true) if x < 0.8 => Axis::Yaw,
                    (true, false) | (false, true) if x < 0.8 => {
                        if yaw_ok {
                            Axis::Yaw
                        } else {
                            Axis::Pitch
                        }
                    }
                    (false, false) if x >= 0.4 => return Ok(None),
                    _ => Axis::Roll,
                }
            }
        };
        let angle = match axis {
            Axis::Yaw => e.yaw_deg,
            Axis::Pitch => e.pitch_deg,
            Axis::Roll => e.roll_deg,
        };
        // Away from zero; a random direction at exactly zero.
        let positive = if angle == 0.0 {
            rng.next_f64() >= 0.5
        } else {
            angle > 0.0
        };
        let sign = if positive { 1.0 } else { -1.0 };
        let room = self.max_angle - angle.abs();
        if room < self.min_change {
            return Err(Skip::AngleLimit(format!(
                "{axis:?} is already {angle:.1} degrees: less than {} degrees to the +/-{} limit",
                self.min_change, self.max_angle
            )));
        }
        let change = rng.uniform(self.min_change, self.max_change).min(room);
        Ok(Some((axis, sign * change)))
    }
}

/// Options of [`augment_dataset`].
#[derive(Clone, Debug)]
pub struct AugmentOptions {
    /// Output root (the release's download layout is written under it).
    pub output: PathBuf,
    /// Axis choice.
    pub axis: AxisChoice,
    /// The rule.
    pub rule: ProfilingRule,
    /// Augmentations per sample.
    pub per_sample: usize,
    /// Also write a mirrored copy of every sample.
    pub flip: bool,
    /// Also write the original samples, so the output is a complete training set.
    pub with_originals: bool,
    /// Seed.
    pub seed: u64,
    /// JPEG quality of the written images.
    pub jpeg_quality: u8,
    /// Keep this many (original, augmented) pairs for a preview.
    pub preview_pairs: usize,
}

impl AugmentOptions {
    /// Checks what the options cannot be, before anything is read or written: a JPEG
    /// quality in 1..=100, `0 <= min_change <= max_change`, `min_change <= max_angle`
    /// (or no sample could change), `max_angle` in (0, 90], and something to write
    /// (`per_sample > 0`, `flip` or `with_originals`). The CLI calls it after parsing.
    pub fn validate(&self) -> Result<()> {
        let r = &self.rule;
        let bad = |what: &str, why: String| Err(Error::invalid(what, why));
        if !(1..=100).contains(&self.jpeg_quality) {
            return bad(
                "--jpeg-quality",
                format!("{} is not in 1..=100", self.jpeg_quality),
            );
        }
        if !(r.max_angle > 0.0 && r.max_angle <= 90.0) {
            return bad(
                "--max-angle",
                format!("{} degrees is not in (0, 90]", r.max_angle),
            );
        }
        if r.min_change.is_nan() || r.min_change < 0.0 {
            return bad(
                "--min-change",
                format!("{} degrees is not a non-negative angle", r.min_change),
            );
        }
        if r.min_change > r.max_change {
            return bad(
                "--min-change",
                format!(
                    "{} degrees is more than --max-change {}",
                    r.min_change, r.max_change
                ),
            );
        }
        if r.min_change > r.max_angle {
            return bad(
                "--min-change",
                format!(
                    "{} degrees is more than --max-angle {}: no sample could change",
                    r.min_change, r.max_angle
                ),
            );
        }
        if self.per_sample == 0 && !self.flip && !self.with_originals {
            return bad(
                "--per-sample",
                "0 with neither --flip nor --with-originals would write nothing".into(),
            );
        }
        Ok(())
    }
}

/// One sample written.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AugmentedRecord {
    /// The source sample.
    pub source: SampleKey,
    /// The new sample's key.
    pub key: SampleKey,
    /// Its split (that of its source).
    pub split: String,
    /// What was done: `original`, `flip`, or `yaw`/`pitch`/`roll` with the change.
    pub operation: String,
    /// Signed change in degrees (0 for original and flip).
    pub change_deg: f64,
}

/// What [`augment_dataset`] did.
#[derive(Clone, Debug, Default, Serialize)]
pub struct AugmentSummary {
    /// Source samples read.
    pub sources: usize,
    /// Samples written.
    pub written: Vec<AugmentedRecord>,
    /// Samples (or augmentations) skipped, with the reason.
    pub skipped: Vec<(SampleKey, String)>,
    /// Augmentations the rule chose not to make.
    pub not_chosen: usize,
    /// Source samples whose image or annotation could not be read (file and reason):
    /// nothing was written for them.
    pub unreadable: Vec<(SampleKey, String)>,
}

fn split_of(s: &str) -> Split {
    if s == "test" {
        Split::Test
    } else {
        Split::Train
    }
}

fn face_of(r: &SampleRecord, dataset: &Dataset) -> Result<FaceImage> {
    let image = dataset.image(r)?;
    Ok(FaceImage {
        image,
        verts: r
            .verts
            .chunks_exact(3)
            .map(|c| Point3::new(c[0], c[1], c[2]))
            .collect(),
        pose: Pose::from_release_rt(&r.rt)?,
    })
}

fn write_sample(
    layout: &ReleaseLayout,
    split: Split,
    key: &SampleKey,
    face: &FaceImage,
    quality: u8,
) -> Result<()> {
    let (w, h) = face.image.dimensions();
    let camera = Camera::release(w, h);
    let info =
        InfoAnnotation::complete(face.verts.clone(), &face.pose, &camera, Matrix4::identity());
    arkit_core::atomic_file::write_bytes(
        &layout.image_path(split, key),
        &crate::picture::encode::jpeg_bytes(&face.image, quality)?,
    )?;
    release::write_info(
        &layout.info_path(split, key),
        &info,
        NpzCompression::Deflated,
    )
}

/// Copies an original sample unchanged: its JPEG bytes as they are and its `R_t`
/// exactly (the other keys derived from it).
fn write_original(
    layout: &ReleaseLayout,
    split: Split,
    r: &SampleRecord,
    face: &FaceImage,
    dataset: &Dataset,
) -> Result<()> {
    let bytes = match &r.jpeg {
        Some(b) => b.clone(),
        None => {
            let p = dataset.image_root().join(&r.image_path);
            std::fs::read(&p).map_err(|e| Error::io(&p, e))?
        }
    };
    let (w, h) = face.image.dimensions();
    let mut info = InfoAnnotation::complete(
        face.verts.clone(),
        &face.pose,
        &Camera::release(w, h),
        Matrix4::identity(),
    );
    info.rt = r.rt;
    info.face_anchor_transform = Some(r.rt);
    arkit_core::atomic_file::write_bytes(&layout.image_path(split, &r.key), &bytes)?;
    release::write_info(
        &layout.info_path(split, &r.key),
        &info,
        NpzCompression::Deflated,
    )
}

/// A picture of a face with its mesh drawn (for previews).
pub fn drawn(face: &FaceImage, topology: &FaceTopology) -> Result<RgbImage> {
    let mut img = face.image.clone();
    let pts: Vec<Point3<f64>> = face.verts.iter().map(|p| p.cast()).collect();
    draw_mesh(&mut img, topology, &pts, &face.pose, &MeshStyle::ANNOTATION)?;
    Ok(img)
}

/// Augments every sample of `dataset` (a `convert` output) into `options.output`.
/// Returns the summary and up to `preview_pairs` (original, augmented) pictures.
pub fn augment_dataset(
    dataset: &Path,
    topology: &FaceTopology,
    options: &AugmentOptions,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<(AugmentSummary, Vec<(RgbImage, RgbImage)>)> {
    options.validate()?;
    let data = Dataset::open(dataset)?;
    let layout = ReleaseLayout::new(&options.output);
    let _lock =
        arkit_core::atomic_file::FolderLock::acquire(&options.output, "augment", "augment")?;
    arkit_core::atomic_file::remove_stale_temporaries(&options.output, true)?;
    let mirror_map = if options.flip {
        Some(topology.mirror_map()?)
    } else {
        None
    };
    let run = AugmentRun {
        data: &data,
        topology,
        options,
        layout,
        mirror_map,
        summary: Mutex::new(AugmentSummary::default()),
        previews: Mutex::new(Vec::new()),
    };
    let mut row_offset = 0u64;
    for shard in data.shards() {
        let rows = data.read_samples(shard)?;
        let base = row_offset;
        row_offset += rows.len() as u64;
        rows.par_iter()
            .enumerate()
            .try_for_each(|(i, r)| augment_row(&run, base + i as u64, r, progress))?;
    }
    let AugmentRun {
        layout,
        summary,
        previews,
        ..
    } = run;
    let mut summary = summary.into_inner().expect("summary lock");
    summary.written.sort_by(|a, b| a.key.cmp(&b.key));
    summary.skipped.sort();
    summary.unreadable.sort();
    write_augment_lists(&layout, &summary)?;
    if summary.written.is_empty() {
        return Err(nothing_written(&summary));
    }
    let previews = previews
        .into_inner()
        .expect("preview lock")
        .into_iter()
        .map(|(_, a, b)| (a, b))
        .collect();
    Ok((summary, previews))
}

/// What every sample of an augmentation shares, and what the samples gather.
struct AugmentRun<'a> {
    /// The dataset read.
    data: &'a Dataset,
    /// Its topology.
    topology: &'a FaceTopology,
    /// The options.
    options: &'a AugmentOptions,
    /// The output's release layout.
    layout: ReleaseLayout,
    /// With `flip`: the topology's mirror map.
    mirror_map: Option<Vec<u32>>,
    /// The summary so far.
    summary: Mutex<AugmentSummary>,
    /// The preview pairs so far, by dataset row (at most `preview_pairs`, the first rows).
    previews: Mutex<Vec<(usize, RgbImage, RgbImage)>>,
}

/// Augments one sample (dataset row `row`): its original (with `with_originals`), its
/// `per_sample` profiled views and its mirror (with `flip`); what was written, skipped
/// or not chosen goes into the summary. A sample whose image cannot be read is reported
/// and skipped, never replaced by a placeholder.
fn augment_row(
    run: &AugmentRun<'_>,
    row: u64,
    r: &SampleRecord,
    progress: &(dyn Fn(usize) + Sync),
) -> Result<()> {
    let options = run.options;
    let split = split_of(&r.split);
    let face = match face_of(r, run.data) {
        Ok(f) => f,
        Err(e) => {
            let mut s = run.summary.lock().expect("summary lock");
            s.sources += 1;
            s.unreadable.push((r.key.clone(), e.to_string()));
            drop(s);
            progress(1);
            return Ok(());
        }
    };
    let mut written = Vec::new();
    let mut skipped = Vec::new();
    if options.with_originals {
        write_original(&run.layout, split, r, &face, run.data)?;
        written.push(AugmentedRecord {
            source: r.key.clone(),
            key: r.key.clone(),
            split: split.name().to_string(),
            operation: "original".into(),
            change_deg: 0.0,
        });
    }
    let not_chosen = profile_views(run, row, r, split, &face, &mut written, &mut skipped)?;
    if let Some(map) = &run.mirror_map {
        match crate::augment::sample::mirror(&face, map) {
            Ok(out) => {
                let key = SampleKey {
                    img_id: format!("{}_flip", r.key.img_id),
                    ..r.key.clone()
                };
                write_sample(&run.layout, split, &key, &out, options.jpeg_quality)?;
                written.push(AugmentedRecord {
                    source: r.key.clone(),
                    key,
                    split: split.name().to_string(),
                    operation: "flip".into(),
                    change_deg: 0.0,
                });
            }
            Err(why) => skipped.push((r.key.clone(), why.to_string())),
        }
    }
    let mut s = run.summary.lock().expect("summary lock");
    s.sources += 1;
    s.written.extend(written);
    s.skipped.extend(skipped);
    s.not_chosen += not_chosen;
    drop(s);
    progress(1);
    Ok(())
}

/// Writes the `per_sample` profiled views of `face` (row `row`) that the rule chooses,
/// each from its own random stream, keeping preview pairs of the first rows; returns how
/// many draws the rule did not choose.
fn profile_views(
    run: &AugmentRun<'_>,
    row: u64,
    r: &SampleRecord,
    split: Split,
    face: &FaceImage,
    written: &mut Vec<AugmentedRecord>,
    skipped: &mut Vec<(SampleKey, String)>,
) -> Result<usize> {
    let (options, topology) = (run.options, run.topology);
    let mut not_chosen = 0;
    for k in 0..options.per_sample {
        let mut rng = Rng::for_stream(options.seed, row << 8 | k as u64);
        let choice = options
            .rule
            .choose(&face.pose.euler(), options.axis, &mut rng);
        let (axis, change) = match choice {
            Ok(Some(c)) => c,
            Ok(None) => {
                not_chosen += 1;
                continue;
            }
            Err(why) => {
                skipped.push((r.key.clone(), why.to_string()));
                continue;
            }
        };
        match crate::augment::sample::profile(topology, face, axis, change) {
            Ok(out) => {
                let key = SampleKey {
                    img_id: format!("{}_aug{k}", r.key.img_id),
                    ..r.key.clone()
                };
                write_sample(&run.layout, split, &key, &out, options.jpeg_quality)?;
                let mut p = run.previews.lock().expect("preview lock");
                if p.len() < options.preview_pairs || p.iter().any(|q| q.0 > row as usize) {
                    p.push((row as usize, drawn(face, topology)?, drawn(&out, topology)?));
                    p.sort_by_key(|q| q.0);
                    p.truncate(options.preview_pairs);
                }
                written.push(AugmentedRecord {
                    source: r.key.clone(),
                    key,
                    split: split.name().to_string(),
                    operation: format!("{axis:?}").to_lowercase(),
                    change_deg: change,
                });
            }
            Err(why) => skipped.push((r.key.clone(), why.to_string())),
        }
    }
    Ok(not_chosen)
}

/// The list CSVs: every written sample, by its source's split; all at once (none when
/// nothing was written).
fn write_augment_lists(layout: &ReleaseLayout, summary: &AugmentSummary) -> Result<()> {
    let lists: Vec<(&str, Vec<SampleKey>)> = [Split::Train, Split::Test]
        .into_iter()
        .map(|split| {
            let keys = summary
                .written
                .iter()
                .filter(|w| w.split == split.name())
                .map(|w| w.key.clone())
                .collect();
            (split.name(), keys)
        })
        .filter(|(_, keys): &(&str, Vec<SampleKey>)| !keys.is_empty())
        .collect();
    if !lists.is_empty() {
        let lists: Vec<(&str, &[SampleKey])> =
            lists.iter().map(|(s, k)| (*s, k.as_slice())).collect();
        release::write_lists(&layout.root, &lists)?;
    }
    Ok(())
}

/// The error of a run that wrote nothing: its counts and the first unreadable image's
/// reason.
fn nothing_written(summary: &AugmentSummary) -> Error {
    Error::invalid(
        "augment",
        format!(
            "nothing was written ({} sources, {} unreadable, {} skipped, {} not chosen by the rule){}",
            summary.sources,
            summary.unreadable.len(),
            summary.skipped.len(),
            summary.not_chosen,
            summary
                .unreadable
                .first()
                .map(|(_, why)| format!("; first unreadable: {why}"))
                .unwrap_or_default()
        ),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rule_allows_as_documented() {
        let r = ProfilingRule::default();
        let e = |yaw, pitch| EulerAngles::new(yaw, pitch, 0.0);
        assert_eq!(r.allowed(&e(30.0, 10.0)), (true, false));
        assert_eq!(r.allowed(&e(5.0, 10.0)), (false, true));
        assert_eq!(r.allowed(&e(5.0, -30.0)), (false, true));
        assert_eq!(r.allowed(&e(5.0, 0.0)), (false, false));
        assert_eq!(r.allowed(&e(30.0, 40.0)), (false, false));
    }

    #[test]
    fn changes_go_away_from_zero_and_stop_at_the_limit() {
        let r = ProfilingRule::default();
        let mut rng = Rng::new(3);
        for _ in 0..200 {
            let (axis, d) = r
                .choose(
                    &EulerAngles::new(-70.0, 0.0, 0.0),
                    AxisChoice::Fixed(Axis::Yaw),
                    &mut rng,
                )
                .unwrap()
                .unwrap();
            assert_eq!(axis, Axis::Yaw);
            assert!((-20.0..=-5.0).contains(&d), "{d}");
        }
        let near = r.choose(
            &EulerAngles::new(88.0, 0.0, 0.0),
            AxisChoice::Fixed(Axis::Yaw),
            &mut rng,
        );
        assert!(matches!(near, Err(Skip::AngleLimit(_))));
        // Neither axis allowed: roll 40% of the time, nothing otherwise.
        let mut rolls = 0;
        for _ in 0..2000 {
            if let Ok(Some((Axis::Roll, _))) =
                r.choose(&EulerAngles::new(0.0, 0.0, 3.0), AxisChoice::Auto, &mut rng)
            {
                rolls += 1;
            }
        }
        assert!((700..900).contains(&rolls), "{rolls}");
    }
}
