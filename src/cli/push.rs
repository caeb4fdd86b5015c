//! `arkit-tool push`.

use arkit_core::Result;
use arkit_data::storage::{DatasetLocation, PushOptions, push};
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Publish a converted dataset to object storage (S3, or S3-compatible: MinIO, Ceph),
/// with what its folder holds: samples, splits, targets, crop stores.
///
/// Every file goes up with its SHA-256 as metadata (files of 16 MiB and more as
/// multipart uploads), then `arkit-publication.json` last, naming every object with its
/// size and SHA-256: a reader never opens a half-published dataset, and checks each
/// object it reads against that record. A push killed and run again uploads only what
/// is missing or different. A push over a dataset of another fingerprint is refused
/// without --overwrite.
///
/// Credentials and endpoint come from the environment and the AWS config files:
/// AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_SESSION_TOKEN, AWS_REGION,
/// AWS_ENDPOINT_URL (e.g. http://127.0.0.1:9000 for a MinIO), AWS_PROFILE. No secret
/// is ever printed.
///
/// Then read it where a dataset folder is read: `arkit-tool inspect --dataset
/// s3://bucket/arkit`, `ARKitFaceDataset("s3://bucket/arkit", ...)`. See docs/cloud.md.
///
/// Example: arkit-tool push data/arkit s3://my-bucket/arkit
#[derive(Args, Debug)]
pub struct PushArgs {
    /// A folder written by `convert` (with dataset.json).
    dataset: PathBuf,
    /// Where to publish it: s3://BUCKET/PREFIX.
    url: String,
    /// Replace a dataset of another fingerprint published at the URL.
    #[arg(long)]
    overwrite: bool,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: PushArgs) -> Result<ExitCode> {
    let url = match DatasetLocation::parse(&a.url)? {
        DatasetLocation::Remote(u) => u,
        DatasetLocation::Local(p) => {
            return Err(arkit_core::Error::invalid(
                "URL",
                format!(
                    "{}: not an object-store URL; push publishes to s3://BUCKET/PREFIX (copy a folder with cp or rsync)",
                    p.display()
                ),
            ));
        }
    };
    let options = PushOptions {
        overwrite: a.overwrite,
        ..Default::default()
    };
    let bar = indicatif::ProgressBar::hidden();
    if !a.json {
        bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
    }
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "push {bar:30} {bytes}/{total_bytes} {bytes_per_sec} eta {eta}",
        )
        .expect("template"),
    );
    let summary = push(
        &a.dataset,
        &url,
        &options,
        &|total| bar.set_length(total),
        &|n| bar.inc(n),
    )?;
    bar.finish_and_clear();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
    } else {
        println!(
            "published {} objects ({} bytes) to {}: {} uploaded ({} bytes, {} multipart), {} already there",
            summary.objects,
            summary.bytes,
            summary.url,
            summary.uploaded,
            summary.uploaded_bytes,
            summary.multipart,
            summary.unchanged
        );
    }
    Ok(ExitCode::SUCCESS)
}
