//! `arkit-tool inspect`.

use arkit_core::Result;
use arkit_data::store::{f64_values, read_parquet_columns, str_values};
use clap::Args;
use std::collections::BTreeSet;
use std::path::PathBuf;
use std::process::ExitCode;

/// Summarise a converted dataset: the state of each output (samples, targets/, crop
/// stores, temporaries left by killed runs), subjects, images, actions, errors, and the
/// pose distributions (yaw, pitch, roll, distance) as histograms.
///
/// An output an interrupted run left unfinished is named with the command that
/// completes it (for example "targets: 7 of 30 shards, rerun `arkit-tool render ...`");
/// a folder whose samples are unfinished (no dataset.json) gets the state alone and
/// exit status 1.
///
/// Example: arkit-tool inspect --dataset data/parquet --plot poses.svg
#[derive(Args, Debug)]
pub struct InspectArgs {
    /// A folder written by `convert` (with dataset.json). Or a dataset published with `arkit-tool push`: s3://BUCKET/PREFIX (its tables
    /// are mirrored in the cache folder, $ARKIT_CACHE_DIR or ~/.cache/arkit-tool).
    #[arg(long)]
    dataset: PathBuf,
    /// Also draw the four histograms as a chart into this SVG file (titled axes with
    /// tick values and units; open it in a browser). For a PNG, convert it, e.g.
    /// `rsvg-convert -o poses.png poses.svg` (Debian: librsvg2-bin).
    #[arg(long, value_name = "FILE.svg")]
    plot: Option<PathBuf>,
    /// First check every file the manifest names against its full SHA-256 (every other
    /// command checks each shard's size and footer only); exits 1 on a mismatch.
    #[arg(long)]
    verify: bool,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(mut a: InspectArgs) -> Result<ExitCode> {
    let (dir, remote) = super::remote::dataset_folder(&a.dataset)?;
    // What the user named: the folder, or the URL (never the mirror's folder).
    let shown = a.dataset.display().to_string();
    a.dataset = dir;
    if let Some(path) = &a.plot
        && !path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("svg"))
    {
        return Err(arkit_core::Error::invalid(
            "--plot",
            format!(
                "{}: the chart is written as SVG; name the file .svg (for a PNG, convert it: rsvg-convert -o poses.png poses.svg)",
                path.display()
            ),
        ));
    }
    let state = match &remote {
        Some(r) => arkit_tool::folder_state::published_folder_state(&a.dataset, r.publication()),
        None => arkit_tool::folder_state::folder_state(&a.dataset),
    };
    if state.samples.state != arkit_tool::folder_state::State::Complete {
        // Nothing else can be read: the state, and the way out, alone.
        if a.json {
            println!(
                "{}",
                serde_json::to_string_pretty(&serde_json::json!({"state": state})).expect("json")
            );
        } else {
            println!("{shown}");
            for line in state.lines() {
                println!("  {line}");
            }
        }
        return Err(arkit_core::Error::format(
            &a.dataset,
            state.samples.message.clone(),
        ));
    }
    let data = arkit_data::store::Dataset::open(&a.dataset)?;
    if a.verify {
        let n = arkit_data::ingest::verify_dataset(&a.dataset)?;
        eprintln!("verified {n} files against the SHA-256 in dataset.json");
    }
    let m = data.manifest().clone();
    let (mut yaw, mut pitch, mut roll, mut dist) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut subjects, mut actions) = (BTreeSet::new(), BTreeSet::new());
    let mut official_failures = 0usize;
    for s in &m.shards {
        let path = data.samples_path(s)?;
        let df = read_parquet_columns(
            &path,
            &[
                "subject_id",
                "facial_action",
                "yaw_deg",
                "pitch_deg",
                "roll_deg",
                "tz_m",
                "face_box_x0",
                "face_box_y0",
            ],
        )?;
        // The official loader fails where int() of its box's left or top edge is
        // negative (the slice from a negative index is empty): docs/python.md.
        let x0 = f64_values(&df, "face_box_x0", &path)?;
        let y0 = f64_values(&df, "face_box_y0", &path)?;
        official_failures += x0
            .iter()
            .zip(&y0)
            .filter(|&(x, y)| x.trunc() < 0.0 || y.trunc() < 0.0)
            .count();
        subjects.extend(str_values(&df, "subject_id", &path)?);
        actions.extend(str_values(&df, "facial_action", &path)?);
        yaw.extend(f64_values(&df, "yaw_deg", &path)?);
        pitch.extend(f64_values(&df, "pitch_deg", &path)?);
        roll.extend(f64_values(&df, "roll_deg", &path)?);
        dist.extend(f64_values(&df, "tz_m", &path)?.into_iter().map(|z| -z));
    }
    let hists = arkit_tool::report::pose_histograms(&yaw, &pitch, &roll, &dist);
    if a.json {
        let h: Vec<serde_json::Value> = hists
            .iter()
            .map(|(n, h)| serde_json::json!({"name": n, "lo": h.lo, "hi": h.hi, "counts": h.counts, "outside": h.outside}))
            .collect();
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "subjects": subjects.len(), "images": yaw.len(), "facial_actions": actions.len(),
                "skipped": m.skipped, "listing_problems": m.listing_problems, "shards": m.shards.len(),
                "official_loader_failures": official_failures,
                "histograms": h,
                "state": state,
            }))
            .expect("json")
        );
    } else {
        println!("{shown}");
        for line in state.lines() {
            println!("  {line}");
        }
        println!(
            "  {} subjects, {} images, {} facial actions, {} shards",
            subjects.len(),
            yaw.len(),
            actions.len(),
            m.shards.len()
        );
        println!(
            "  {} samples skipped, {} listing problems (see errors/)",
            m.skipped, m.listing_problems
        );
        println!(
            "  {official_failures} samples the official loader fails on (its crop box leaves the image's top or left edge; docs/python.md)"
        );
        for (name, h) in &hists {
            println!("\n{name}");
            for line in h.text_lines(40) {
                println!("  {line}");
            }
            if h.outside > 0 {
                println!("  ({} outside the range)", h.outside);
            }
        }
    }
    if let Some(path) = &a.plot {
        let title = format!("Poses of {shown}");
        let svg = arkit_tool::report::pose_chart(&title, &hists);
        arkit_core::atomic_file::write_bytes(path, svg.as_bytes())?;
        if a.json {
            eprintln!("plot: {}", path.display());
        } else {
            println!("plot: {}", path.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}
