//! `arkit-tool demo`.

use arkit_core::Result;
use arkit_tool::demo::{self, DemoPlan, DemoProgress, STAGES};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Run the whole pipeline on synthetic data and write a report to look at.
///
/// synth -> convert -> split -> render -> augment -> train (tiny PerspNet) -> predict
/// (the network with PnP, the tiny PerspNet shipped with arkit-tool, and the mean-pose
/// baseline) -> eval -> report, each stage the library code of its own command. Ends
/// with the eval table of the three and OUTPUT/report/index.html:
/// pose histograms, crops with their masks, correspondences and UV maps, augmented
/// samples, the loss curve, errors by pose and the worst predictions drawn. The page
/// works offline.
///
/// --quick: 192 images and a short training run (about 20 s on two idle cores);
/// without it, 960 images and a longer run (about ten minutes). The same --seed gives
/// the same data, the same weights and the same table.
///
/// Example: arkit-tool demo --quick --output demo/   (then open demo/report/index.html)
#[derive(Args, Debug)]
pub struct DemoArgs {
    /// The folder to write (must be absent or empty).
    #[arg(long, default_value = "arkit-demo")]
    output: PathBuf,
    /// A smaller, faster run.
    #[arg(long)]
    quick: bool,
    /// Seed of the data, the split, the weights and the sampling.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Worker threads, 1..=1024 (default: all cores).
    #[arg(long, allow_negative_numbers = true, value_parser = super::values::jobs)]
    jobs: Option<usize>,
    /// Print the summary (timings, both eval summaries) as JSON.
    #[arg(long)]
    json: bool,
}

struct Bar(indicatif::ProgressBar);

impl DemoProgress for Bar {
    fn stage(&self, index: usize, name: &str) {
        self.0
            .set_prefix(format!("[{index}/{}] {name:<8}", STAGES.len()));
    }
    fn advance(&self, units: u64) {
        self.0.inc(units);
    }
}

pub fn run(a: DemoArgs) -> Result<ExitCode> {
    let plan = if a.quick {
        DemoPlan::quick(a.seed)
    } else {
        DemoPlan::full(a.seed)
    };
    let topology = super::setup::load_topology(None)?;
    let bar = indicatif::ProgressBar::new(plan.units()).with_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} demo {prefix} [{bar:30}] {percent}% elapsed {elapsed}",
        )
        .expect("valid progress template")
        .progress_chars("=> "),
    );
    let progress = Bar(bar);
    let pool = super::setup::thread_pool(a.jobs)?;
    let summary = pool.install(|| demo::run_demo(&a.output, &plan, &topology, &progress))?;
    progress.0.finish_and_clear();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
        return Ok(ExitCode::SUCCESS);
    }
    println!("{:<8} {:>8}  what it did", "stage", "seconds");
    for s in &summary.stages {
        println!("{:<8} {:>8.1}  {}", s.stage, s.seconds, s.detail);
    }
    let total: f64 = summary.stages.iter().map(|s| s.seconds).sum();
    println!("{:<8} {:>8.1}\n", "total", total);
    let shipped_name = format!("tiny PerspNet, shipped ({} steps)", summary.shipped_steps);
    let trained_name = format!(
        "tiny PerspNet, trained here ({} steps)",
        summary.trained_steps
    );
    let mut rows = Vec::new();
    if let Some(s) = &summary.shipped {
        rows.push((shipped_name.as_str(), s));
    }
    rows.push((trained_name.as_str(), &summary.model));
    rows.push(("mean pose", &summary.baseline));
    println!(
        "on the {} images of the held-out subjects (angles in degrees, distances in mm, rates in %):",
        summary.model.samples
    );
    print!("{}", demo::results_table(&rows));
    if summary.shipped.is_some() {
        println!(
            "the shipped model is {} (trained by `arkit-tool train` on other synthetic \
             subjects, see docs/train.md); the other was trained by this run.",
            arkit_perspnet::SHIPPED_MODEL_DIR
        );
    }
    println!("\nreport: {}", summary.report.display());
    Ok(ExitCode::SUCCESS)
}
