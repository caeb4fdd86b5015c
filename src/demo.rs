//! The whole pipeline on data it makes itself: synth -> convert -> split -> render ->
//! augment -> train -> predict (the model, the shipped model and the mean-pose
//! baseline) -> eval -> report. Each stage calls the same library function as its command, so the demo
//! checks the commands' code, not a copy of it.
//!
//! Output folder layout:
//! - `release/`: the synthetic release (download layout, `_info.npz`, list CSVs);
//! - `dataset/`: `convert`'s Parquet, `split`'s lists, `render`'s targets;
//! - `augmented/`: profiled samples in the release layout;
//! - `model/`: the checkpoint (`perspnet.json`, `model.safetensors`, `loss.csv`);
//! - `predictions.parquet`, `shipped.parquet`, `baseline.parquet`: the predictions of
//!   the model trained here, of the shipped model ([`arkit_perspnet::SHIPPED_MODEL_DIR`],
//!   compiled into the binary; left out for another topology than the built-in face's)
//!   and of the mean pose;
//! - `report/index.html` and its pictures; `demo.json`: timings and eval summaries.

use crate::report::{self, Figure, Page, StageTiming};
use arkit_core::PredictionRecord;
use arkit_core::conventions::Camera;
use arkit_core::{Error, Result};
use arkit_data::augment::{AugmentOptions, AxisChoice, ProfilingRule};
use arkit_data::eval::Summary;
use arkit_data::eval::{EvalOptions, Evaluation, ReportFiles};
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
use arkit_data::ingest::{self, ConvertOptions, HoldOut, ValidationContext};
use arkit_data::mesh::FaceTopology;
use arkit_data::pose::RansacParams;
use arkit_data::render::FaceRenderer;
use arkit_data::render::RenderOptions;
use arkit_data::store::Manifest;
use arkit_data::store::write_predictions;
use arkit_perspnet::{Augmentation, TrainOptions};
use arkit_perspnet::{Checkpoint, PerspNetConfig, StepLoss};
use image::RgbImage;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Sizes of a demo run.
#[derive(Clone, Debug, Serialize)]
pub struct DemoPlan {
    /// Synthetic subjects.
    pub subjects: usize,
    /// Images per subject.
    pub images_per_subject: usize,
    /// Image side in pixels (square images).
    pub image_size: u32,
    /// Subjects held out for test.
    pub test_subjects: usize,
    /// Network input (crop) side.
    pub crop: u32,
    /// Points per sample.
    pub points: usize,
    /// UV map side.
    pub uv_size: u32,
    /// Training epochs (the `tiny` network).
    pub epochs: usize,
    /// Batch size.
    pub batch: usize,
    /// Learning rate.
    pub learning_rate: f64,
    /// Seed of everything.
    pub seed: u64,
}

impl DemoPlan {
    /// `demo --quick`: 192 images, a short training run; about two minutes on two
    /// cores.
    pub fn quick(seed: u64) -> Self {
        DemoPlan {
            subjects: 16,
            images_per_subject: 12,
            image_size: 256,
            test_subjects: 4,
            crop: 64,
            points: 256,
            uv_size: 32,
            epochs: 4,
            batch: 8,
            learning_rate: 2e-3,
            seed,
        }
    }

    /// `demo`: 960 images and a longer training run (about ten minutes on two cores).
    pub fn full(seed: u64) -> Self {
        DemoPlan {
            subjects: 40,
            images_per_subject: 24,
            test_subjects: 8,
            epochs: 8,
            ..DemoPlan::quick(seed)
        }
    }

    /// The smallest run that still exercises every stage (tests).
    pub fn smoke(seed: u64) -> Self {
        DemoPlan {
            subjects: 4,
            images_per_subject: 4,
            image_size: 160,
            test_subjects: 1,
            epochs: 1,
            batch: 4,
            ..DemoPlan::quick(seed)
        }
    }

    /// Images in all.
    pub fn images(&self) -> usize {
        self.subjects * self.images_per_subject
    }

    /// Training steps.
    pub fn train_steps(&self) -> usize {
        let train = (self.subjects - self.test_subjects) * self.images_per_subject;
        arkit_perspnet::total_steps(train, self.epochs, self.batch)
    }

    /// Work units of the whole run for one progress display: a sample per stage that
    /// goes through samples, a step per training step, one for each small stage.
    pub fn units(&self) -> u64 {
        let n = self.images() as u64;
        let test = (self.test_subjects * self.images_per_subject) as u64;
        // synth, convert, render, augment; split; train; predict (two models); eval,
        // report.
        4 * n + 1 + self.train_steps() as u64 + 2 * test + 2
    }

    fn check(&self) -> Result<()> {
        if self.subjects < 2 || self.test_subjects == 0 || self.test_subjects >= self.subjects {
            return Err(Error::invalid(
                "demo",
                "needs at least two subjects and 1..subjects-1 held out",
            ));
        }
        if self.images_per_subject == 0 || self.epochs == 0 || self.batch == 0 {
            return Err(Error::invalid(
                "demo",
                "images per subject, epochs and batch must be positive",
            ));
        }
        Ok(())
    }
}

/// Progress of a demo run: stage changes and work done (see [`DemoPlan::units`]).
pub trait DemoProgress: Sync {
    /// Stage `index` (1-based) of [`STAGES`] starts.
    fn stage(&self, index: usize, name: &str);
    /// `units` of work are done.
    fn advance(&self, units: u64);
}

/// The stages, in order.
pub const STAGES: [&str; 9] = [
    "synth", "convert", "split", "render", "augment", "train", "predict", "eval", "report",
];

/// What a demo run did.
#[derive(Clone, Debug, Serialize)]
pub struct DemoSummary {
    /// The sizes used.
    pub plan: DemoPlan,
    /// Wall time per stage.
    pub stages: Vec<StageTiming>,
    /// The model trained by this run on the held-out subjects.
    pub model: Summary,
    /// Its training steps.
    pub trained_steps: usize,
    /// The shipped model ([`arkit_perspnet::SHIPPED_MODEL_DIR`]) on the same samples (none
    /// with another topology than the built-in face's, on which it was trained).
    pub shipped: Option<Summary>,
    /// Training steps of the shipped model.
    pub shipped_steps: usize,
    /// The mean-pose baseline on the same samples.
    pub baseline: Summary,
    /// Training loss of the first and last step.
    pub loss: [f32; 2],
    /// The report page.
    pub report: PathBuf,
}

struct Clock<'a> {
    progress: &'a dyn DemoProgress,
    stages: Vec<StageTiming>,
    started: Instant,
}

impl<'a> Clock<'a> {
    fn start(&mut self, name: &str) {
        let index = STAGES.iter().position(|s| *s == name).map_or(0, |i| i + 1);
        self.progress.stage(index, name);
        self.started = Instant::now();
    }

    /// The progress callback the stages hand to the library: it advances the bar, and
    /// holds the bar, not the clock (which the stage goes on timing).
    fn ticker(&self) -> impl Fn(usize) + Sync + 'a {
        let progress = self.progress;
        move |n: usize| progress.advance(n as u64)
    }

    fn done(&mut self, name: &str, detail: String) {
        self.stages.push(StageTiming {
            stage: name.to_string(),
            seconds: self.started.elapsed().as_secs_f64(),
            detail,
        });
    }
}

/// The folders of a demo run (module docs).
struct Folders {
    output: PathBuf,
    release: PathBuf,
    dataset: PathBuf,
    augmented: PathBuf,
    model: PathBuf,
    report: PathBuf,
}

/// What `predict` made: the trained model's, the shipped model's (none for another
/// topology) and the mean pose's predictions of the test split.
struct Predictions {
    rows: Vec<PredictionRecord>,
    shipped_rows: Option<Vec<PredictionRecord>>,
    baseline_rows: Vec<PredictionRecord>,
    shipped_checkpoint: Checkpoint,
}

/// What `eval` made of the [`Predictions`].
struct Evaluations {
    model: Evaluation,
    baseline: Evaluation,
    shipped: Option<Summary>,
    report: ReportFiles,
}

/// Runs the whole pipeline into `output` (which must be absent or empty) with the
/// built-in face or the given topology: one function per group of stages below, each
/// timed by the `Clock`.
pub fn run_demo(
    output: &Path,
    plan: &DemoPlan,
    topology: &FaceTopology,
    progress: &dyn DemoProgress,
) -> Result<DemoSummary> {
    plan.check()?;
    if output.exists()
        && std::fs::read_dir(output)
            .map_err(|e| Error::io(output, e))?
            .next()
            .is_some()
    {
        return Err(Error::invalid(
            "--output",
            format!(
                "{} is not empty: the demo writes a fresh folder (remove it or choose another)",
                output.display()
            ),
        ));
    }
    let f = Folders {
        output: output.to_path_buf(),
        release: output.join("release"),
        dataset: output.join("dataset"),
        augmented: output.join("augmented"),
        model: output.join("model"),
        report: output.join("report"),
    };
    std::fs::create_dir_all(&f.report).map_err(|e| Error::io(&f.report, e))?;
    let mut clock = Clock {
        progress,
        stages: Vec::new(),
        started: Instant::now(),
    };
    let manifest = make_dataset(&f, plan, topology, &mut clock)?;
    let previews = render_and_augment(&f, plan, topology, &mut clock)?;
    let (checkpoint, log) = train_model(&f, plan, topology, &mut clock)?;
    let predictions = predict_test_split(&f, plan, topology, &mut clock)?;
    let evaluations = evaluate_predictions(&f, topology, &predictions, &mut clock)?;
    let page_path = write_report_page(
        &f,
        plan,
        &manifest,
        previews,
        &log,
        &checkpoint,
        &predictions,
        &evaluations,
        &mut clock,
    )?;
    progress.advance(1);
    let summary = DemoSummary {
        plan: plan.clone(),
        stages: clock.stages,
        model: evaluations.model.summary,
        trained_steps: checkpoint.steps,
        shipped: evaluations.shipped,
        shipped_steps: predictions.shipped_checkpoint.steps,
        baseline: evaluations.baseline.summary,
        loss: [checkpoint.first_loss, checkpoint.last_loss],
        report: page_path,
    };
    arkit_core::atomic_file::write_bytes(
        &output.join("demo.json"),
        serde_json::to_string_pretty(&summary)
            .expect("json")
            .as_bytes(),
    )?;
    Ok(summary)
}

/// `synth`, `convert` and `split`: the synthetic release, its Parquet and the
/// subject-disjoint split; returns the dataset's manifest.
fn make_dataset(
    f: &Folders,
    plan: &DemoPlan,
    topology: &FaceTopology,
    clock: &mut Clock<'_>,
) -> Result<Manifest> {
    let tick = clock.ticker();
    let (release, dataset) = (&f.release, &f.dataset);
    clock.start("synth");
    let source = FaceSource::new(topology.clone())?;
    let synth_options = SynthOptions {
        subjects: plan.subjects,
        images_per_subject: plan.images_per_subject,
        width: plan.image_size,
        height: plan.image_size,
        seed: plan.seed,
        ..SynthOptions::default()
    };
    synth_options.check()?;
    let made = synth::generate(&source, &synth_options, release, &|| tick(1))?;
    clock.done(
        "synth",
        format!(
            "{} images of {} subjects, {}x{}, release layout",
            made.train_samples + made.test_samples,
            made.subjects,
            plan.image_size,
            plan.image_size
        ),
    );

    clock.start("convert");
    let convert_options = ConvertOptions {
        input: release.clone(),
        output: dataset.clone(),
        resources: None,
        rows_per_shard: 64,
        embed_images: false,
        shard_index: 0,
        shard_count: 1,
        overwrite: true,
    };
    let ctx = ValidationContext {
        projection: Camera::release_projection(),
        topology: topology.clone(),
        embed_images: false,
    };
    let manifest = ingest::convert(&convert_options, &ctx, &tick)?;
    clock.done(
        "convert",
        format!(
            "{} samples validated into {} Parquet shards, {} skipped",
            manifest.converted,
            manifest.shards.len(),
            manifest.skipped
        ),
    );

    clock.start("split");
    let counts = ingest::split_dataset(
        dataset,
        Some(HoldOut::Subjects(plan.test_subjects)),
        0,
        plan.seed,
        &dataset.join("splits"),
    )?;
    tick(1);
    let count = |s: &str| {
        counts.get(s).copied().unwrap_or(ingest::SplitCount {
            subjects: 0,
            images: 0,
        })
    };
    clock.done(
        "split",
        format!(
            "subject-disjoint: train {} subjects / {} images, test {} / {}",
            count("train").subjects,
            count("train").images,
            count("test").subjects,
            count("test").images
        ),
    );

    Ok(manifest)
}

/// `render` and `augment`; returns the augmentation's preview pairs.
fn render_and_augment(
    f: &Folders,
    plan: &DemoPlan,
    topology: &FaceTopology,
    clock: &mut Clock<'_>,
) -> Result<Vec<(RgbImage, RgbImage)>> {
    let tick = clock.ticker();
    let (dataset, augmented) = (&f.dataset, &f.augmented);
    clock.start("render");
    let renderer = FaceRenderer::new(topology.clone(), Camera::release_projection())?;
    let rendered = arkit_data::render::render_dataset(
        dataset,
        &renderer,
        &RenderOptions {
            size: plan.crop,
            uv_size: plan.uv_size,
            points: plan.points,
            seed: plan.seed,
            shard: (0, 1),
            full_mask: false,
            output: dataset.clone(),
        },
        &tick,
    )?;
    clock.done(
        "render",
        format!(
            "{}x{} crops, masks, correspondences, {}x{} UV maps, {} points: {:.1} KiB per sample",
            plan.crop,
            plan.crop,
            plan.uv_size,
            plan.uv_size,
            plan.points,
            rendered.bytes_per_sample / 1024.0
        ),
    );

    clock.start("augment");
    let (aug, previews) = arkit_data::augment::augment_dataset(
        dataset,
        topology,
        &AugmentOptions {
            output: augmented.clone(),
            axis: AxisChoice::Auto,
            rule: ProfilingRule::default(),
            per_sample: 1,
            flip: false,
            with_originals: false,
            seed: plan.seed,
            jpeg_quality: 90,
            preview_pairs: 6,
        },
        &tick,
    )?;
    clock.done(
        "augment",
        format!(
            "{} profiled or rolled samples written in the release layout ({} skipped, {} left alone by the official rule)",
            aug.written.len(),
            aug.skipped.len(),
            aug.not_chosen
        ),
    );

    Ok(previews)
}

/// `train`: the tiny network on the train split; its checkpoint and loss log.
fn train_model(
    f: &Folders,
    plan: &DemoPlan,
    topology: &FaceTopology,
    clock: &mut Clock<'_>,
) -> Result<(Checkpoint, Vec<StepLoss>)> {
    let tick = clock.ticker();
    let (dataset, model_dir) = (&f.dataset, &f.model);
    clock.start("train");
    let config = PerspNetConfig {
        input_size: plan.crop as usize,
        points: plan.points,
        ..PerspNetConfig::tiny()
    };
    let examples = arkit_perspnet::read_examples(dataset, dataset, &config, Some("train"))?;
    let (checkpoint, log) = arkit_perspnet::train(
        &examples,
        topology,
        &TrainOptions {
            config,
            epochs: plan.epochs,
            max_steps: None,
            batch: plan.batch,
            learning_rate: plan.learning_rate,
            lr_hold: 0.5,
            augmentation: Augmentation::DEFAULT,
            seed: plan.seed,
            resume: false,
            lowered_start: false,
            output: model_dir.clone(),
        },
        &|_| tick(1),
    )?;
    drop(examples);
    clock.done(
        "train",
        format!(
            "tiny PerspNet, {} steps of {} on {} samples: loss {:.3} -> {:.3}",
            checkpoint.steps,
            plan.batch,
            checkpoint.examples,
            checkpoint.first_loss,
            checkpoint.last_loss
        ),
    );

    Ok((checkpoint, log))
}

/// `predict`: the test split through the model trained here, the shipped model and
/// the mean pose, each written beside the report.
fn predict_test_split(
    f: &Folders,
    plan: &DemoPlan,
    topology: &FaceTopology,
    clock: &mut Clock<'_>,
) -> Result<Predictions> {
    let tick = clock.ticker();
    let (output, dataset, model_dir) = (&f.output, &f.dataset, &f.model);
    clock.start("predict");
    // The test split through a network and PnP, as `predict --model` does.
    let predict_test = |model| {
        arkit_perspnet::model_predictions(
            dataset,
            model,
            Some("test"),
            arkit_data::crop::RuleSet::Exact,
            None,
            plan.seed,
            &RansacParams::default(),
            &tick,
        )
    };
    let model = arkit_perspnet::load(model_dir, topology)?;
    let (rows, predicted) = predict_test(&model)?;
    write_predictions(&output.join("predictions.parquet"), &rows)?;
    let shipped_checkpoint = arkit_perspnet::shipped_checkpoint()?;
    let shipped_rows = if shipped_checkpoint.topology == topology.source {
        let shipped = arkit_perspnet::shipped_model(topology)?;
        let (shipped_rows, _) = predict_test(&shipped)?;
        write_predictions(&output.join("shipped.parquet"), &shipped_rows)?;
        Some(shipped_rows)
    } else {
        tick(predicted.samples);
        None
    };
    let (baseline_rows, mean) =
        arkit_data::pose::mean_pose_predictions(dataset, Some("train"), Some("test"))?;
    write_predictions(&output.join("baseline.parquet"), &baseline_rows)?;
    clock.done(
        "predict",
        format!(
            "{} test samples: network + PnP ({} failures); mean pose of {} training samples",
            predicted.samples, predicted.failures, mean.fitted_on
        ),
    );

    Ok(Predictions {
        rows,
        shipped_rows,
        baseline_rows,
        shipped_checkpoint,
    })
}

/// `eval`: each prediction set scored, and the trained model's report pictures.
fn evaluate_predictions(
    f: &Folders,
    topology: &FaceTopology,
    p: &Predictions,
    clock: &mut Clock<'_>,
) -> Result<Evaluations> {
    let tick = clock.ticker();
    let (dataset, report_dir) = (&f.dataset, &f.report);
    clock.start("eval");
    let options = EvalOptions {
        split: Some("test".into()),
        targets: Some(dataset.clone()),
        keep_worst: 8,
        ..EvalOptions::default()
    };
    let ev = arkit_data::eval::evaluate(dataset, &p.rows, &options)?;
    let base = arkit_data::eval::evaluate(dataset, &p.baseline_rows, &options)?;
    let shipped = p
        .shipped_rows
        .as_ref()
        .map(|r| arkit_data::eval::evaluate(dataset, r, &options).map(|e| e.summary))
        .transpose()?;
    let eval_report = arkit_data::eval::write_report(report_dir, &ev, topology)?;
    tick(1);
    clock.done(
        "eval",
        format!(
            "MAE_r {:.2} deg, ADD {:.1} mm ({}mean pose: {:.2} deg, {:.1} mm)",
            ev.summary.mae_r_deg,
            ev.summary.add_mm,
            shipped.as_ref().map_or(String::new(), |s| format!(
                "shipped model: {:.2} deg, {:.1} mm; ",
                s.mae_r_deg, s.add_mm
            )),
            base.summary.mae_r_deg,
            base.summary.add_mm
        ),
    );

    Ok(Evaluations {
        model: ev,
        baseline: base,
        shipped,
        report: eval_report,
    })
}

/// The report page: the figures of every stage and the results table.
#[allow(clippy::too_many_arguments)]
fn write_report_page(
    f: &Folders,
    plan: &DemoPlan,
    manifest: &Manifest,
    previews: Vec<(RgbImage, RgbImage)>,
    log: &[StepLoss],
    checkpoint: &Checkpoint,
    p: &Predictions,
    e: &Evaluations,
    clock: &mut Clock<'_>,
) -> Result<PathBuf> {
    let (dataset, report_dir) = (&f.dataset, &f.report);
    clock.start("report");
    let mut figures = Vec::new();
    let samples = arkit_data::store::Dataset::open(dataset)?.read_samples(&manifest.shards[0])?;
    figures.push(report::write_chart(
        report_dir,
        "poses.svg",
        report::pose_svg(&samples),
        "Poses of the synthetic dataset",
        "Histograms of yaw, pitch and roll (degrees) and camera distance (metres) of the \
         first shard's samples, as `arkit-tool inspect --plot` draws them.",
    )?);
    figures.push(report::write_figure(
        report_dir,
        "targets.png",
        &targets_sheet(dataset, manifest.shards[0].index, &samples)?,
        "What render stores for each sample",
        "Per row, one sample: the network's input crop; the face mask (green; eye and mouth \
         openings are not face); each face pixel coloured by the canonical 3D point it shows \
         (x, y, z as red, green, blue: the correspondences); the UV position map coloured \
         the same way.",
    )?);
    if !previews.is_empty() {
        let cells: Vec<RgbImage> = previews.into_iter().flat_map(|(o, n)| [o, n]).collect();
        figures.push(report::write_figure(
            report_dir,
            "augmented.png",
            &arkit_data::picture::contact_sheet(&cells, 4, 240),
            "Face profiling",
            "Pairs of original and augmented images: the face turned out of plane through its \
             mesh (yaw or pitch) or rotated about the camera axis (roll), as `augment` writes \
             them.",
        )?);
    }
    figures.push(report::write_chart(
        report_dir,
        "loss.svg",
        report::loss_svg(log),
        "Training loss",
        "The weighted loss terms per step (log scale): correspondence smooth L1, shape L1, \
         KL to the barycentric rows, segmentation cross-entropy, and their total.",
    )?);
    let errors_svg = report_dir.join("errors_by_pose.svg");
    figures.push(Figure {
        file: "errors_by_pose.svg".into(),
        title: "Errors by pose".into(),
        caption: "Mean geodesic rotation error per |yaw| and |pitch| bin, and mean translation \
                  error per distance bin, on the held-out subjects (as `eval --report` \
                  draws them; an empty bin has no bar)."
            .into(),
        svg: Some(std::fs::read_to_string(&errors_svg).map_err(|e| Error::io(&errors_svg, e))?),
        overlay: None,
    });
    if e.report.worst_labels.is_some() {
        figures.push(Figure {
            file: "worst.png".into(),
            title: "The worst predictions".into(),
            caption: "The held-out samples with the largest rotation errors: true mesh in \
                      green, predicted pose in red; each labelled with its key and error."
                .into(),
            svg: None,
            overlay: e.report.worst_labels.clone(),
        });
    }
    let title = "arkit-tool demo";
    let intro = format!(
        "The whole pipeline on {} synthetic images of {} subjects ({} held out), made by \
         `arkit-tool synth` with seed {}: convert, a subject-disjoint split, render, \
         augment, a tiny PerspNet trained for {} steps on the CPU, predict with PnP, \
         and eval against the mean-pose baseline and the tiny PerspNet shipped with \
         arkit-tool (trained for longer on other synthetic subjects).",
        plan.images(),
        plan.subjects,
        plan.test_subjects,
        plan.seed,
        checkpoint.steps
    );
    let shipped_name = format!(
        "tiny PerspNet, shipped ({} steps)",
        p.shipped_checkpoint.steps
    );
    let trained_name = format!("tiny PerspNet, trained here ({} steps)", checkpoint.steps);
    let mut results: Vec<(&str, &Summary)> = Vec::new();
    if let Some(s) = &e.shipped {
        results.push((&shipped_name, s));
    }
    results.push((&trained_name, &e.model.summary));
    results.push(("mean pose", &e.baseline.summary));
    clock.done("report", "this page and its pictures".into());
    let page_path = report::write_page(
        report_dir,
        &Page {
            title,
            intro: &intro,
            stages: &clock.stages,
            results: &results,
            figures: &figures,
        },
    )?;
    Ok(page_path)
}

/// Eval summaries as one aligned table: a header of the paper's columns (as
/// [`Summary::columns`]), then one row per named summary, with the PnP failures.
pub fn results_table(rows: &[(&str, &Summary)]) -> String {
    let name_w = rows.iter().map(|(n, _)| n.len()).max().unwrap_or(0);
    let cols: Vec<_> = rows.iter().map(|(_, s)| s.columns()).collect();
    let Some(first) = cols.first() else {
        return String::new();
    };
    let widths: Vec<usize> = (0..first.len())
        .map(|i| {
            cols.iter()
                .map(|c| c[i].0.len().max(c[i].1.len()))
                .max()
                .unwrap_or(0)
        })
        .collect();
    let mut out = format!("{:name_w$}", "");
    for (c, w) in first.iter().zip(&widths) {
        out += &format!("  {:>w$}", c.0);
    }
    out += "  PnP failures\n";
    for ((name, s), c) in rows.iter().zip(&cols) {
        out += &format!("{name:name_w$}");
        for (v, w) in c.iter().zip(&widths) {
            out += &format!("  {:>w$}", v.1);
        }
        out += &format!("  {:>12}\n", s.pose_failures);
    }
    out
}

/// The targets of four samples of shard `shard` (whose `samples` rows are given) as
/// rows of four panels.
fn targets_sheet(
    dataset: &Path,
    shard: usize,
    samples: &[arkit_data::store::SampleRecord],
) -> Result<RgbImage> {
    let data = arkit_data::store::Dataset::open(dataset)?;
    let targets = arkit_data::store::read_targets(
        &dataset
            .join("targets")
            .join(format!("part-{shard:05}.parquet")),
    )?;
    let cell = 192;
    let up = |img: &RgbImage| {
        image::imageops::resize(img, cell, cell, image::imageops::FilterType::Nearest)
    };
    let mut cells = Vec::new();
    let step = (samples.len() / 4).max(1);
    for (s, t) in samples.iter().zip(&targets).step_by(step).take(4) {
        let image = data.image(s)?;
        let p = report::target_panels(s, t, &image)?;
        cells.extend([
            up(&p.crop),
            up(&p.mask),
            up(&p.correspondences),
            up(&p.uv_map),
        ]);
    }
    Ok(arkit_data::picture::contact_sheet(&cells, 4, cell))
}
