//! `arkit-tool import-arkit`.

use arkit_core::Error;
use arkit_core::{ReleaseLayout, Split};
use arkit_data::ingest::{self, ImportOptions};

use arkit_core::Result;
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Turn your own ARKit face captures into a release-layout dataset.
///
/// CAPTURE is a folder of frames (or of sub-folders of frames, each sub-folder one
/// facial action): per frame a JSON with ARKit's values and the captured image
/// (NAME.json next to NAME.png or NAME.jpg). The JSON keys, with matrices as ARKit gives
/// them (simd: column-major, each inner array one column):
///   face_anchor_transform  ARFaceAnchor.transform, 4 columns of 4
///   camera_transform       ARCamera.transform, 4 columns of 4
///   camera_intrinsics      ARCamera.intrinsics, 3 columns of 3 (pixels)
///   image_resolution       ARCamera.imageResolution, [width, height]
///   interface_orientation  "portrait", "portraitUpsideDown", "landscapeLeft", "landscapeRight"
///   vertices               ARFaceAnchor.geometry.vertices, 1220 of [x, y, z]
///   image                  (optional) the image's file name
///
/// Each frame becomes a release sample: R_t = (inv(C O) A)^T in the release's row-vector
/// form (so faceAnchortransform = R_t @ cameratransform, as in the release), the image
/// turned to the interface orientation and resampled into the release's camera
/// (square, f = 1.57443701 NDC, centred), and an _info.npz with verts, R_t, verts_gt,
/// faceAnchortransform, cameratransform, projectionMatrix, euler_angles, translation and
/// points2d. `convert` reads the output as it reads the release. A bad frame (missing
/// key, wrong vertex count, non-rigid transform, unreadable or resized image, face out
/// of view) is reported with its file and reason and skipped; the others are written.
/// When one check skips more than half of the first 1,000 frames, the import stops
/// with the check and what to do, and leaves no output (--allow-systematic-skips
/// skips them one by one instead). Derivation: docs/import-arkit.md.
///
/// Example: arkit-tool import-arkit --input my_capture --output my_release --preview check.png
#[derive(Args, Debug)]
pub struct ImportArkitArgs {
    /// The capture folder.
    #[arg(long)]
    input: PathBuf,
    /// Output folder, written in the release's download layout.
    #[arg(long)]
    output: PathBuf,
    /// Subject id of every frame (default: the capture folder's name).
    #[arg(long)]
    subject: Option<String>,
    /// Which list names the frames: test (to evaluate on them) or train.
    #[arg(long, value_enum, default_value = "test")]
    split: Split,
    /// Side of the written square images, 32..=16384 pixels (default: the side that
    /// keeps the capture's focal length in pixels, round(2 fx / 1.57443701)).
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(32..=16384))]
    size: Option<u32>,
    /// JPEG quality of the written images, 1..=100.
    #[arg(long, allow_negative_numbers = true, default_value_t = 95, value_parser = clap::value_parser!(u8).range(1..=100))]
    jpeg_quality: u8,
    /// Replace a release layout already in --output.
    #[arg(long)]
    overwrite: bool,
    /// Release resource folder (triangles.npy, kpt_ind.npy, ...), for --preview's mesh
    /// outline (without it the built-in stand-in face's topology is drawn).
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Also write a PNG grid of the first written frames, each beside a copy with its
    /// mesh projected over it (to check that the meshes land on the faces).
    #[arg(long, value_name = "FILE.png")]
    preview: Option<PathBuf>,
    /// Exit with status 1 if any frame was skipped (after writing the others).
    #[arg(long)]
    strict: bool,
    /// Worker threads, 1..=1024 (default: all cores).
    #[arg(long, allow_negative_numbers = true, value_parser = super::values::jobs)]
    jobs: Option<usize>,
    /// Do not stop when one check skips more than half of the first 1,000 frames (the
    /// sign of a capture app writing another convention: row-major matrices, images
    /// turned or resized; the message names the check and what to do): skip them one
    /// by one, each reported. Captures of fewer than 1,000 frames are never stopped.
    #[arg(long)]
    allow_systematic_skips: bool,
    /// The systematic rule's window (tests).
    #[arg(long, hide = true, default_value_t = arkit_data::ingest::SYSTEMATIC_WINDOW)]
    systematic_window: usize,
    /// Print a JSON summary instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(a: ImportArkitArgs) -> Result<ExitCode> {
    let split = a.split;
    let options = ImportOptions {
        input: a.input.clone(),
        output: a.output.clone(),
        subject: a.subject.clone(),
        split,
        size: a.size,
        jpeg_quality: a.jpeg_quality,
        overwrite: a.overwrite,
        systematic_window: if a.allow_systematic_skips {
            0
        } else {
            a.systematic_window
        },
    };
    let subject_guess = a.subject.clone().unwrap_or_default();
    let total = ingest::find_frames(&a.input, &subject_guess)?.len();
    let bar = super::console::progress_bar(total as u64, "import-arkit", "frames");
    let pool = super::setup::thread_pool(a.jobs)?;
    let summary = pool.install(|| ingest::import_capture(&options, &|| bar.inc(1)))?;
    bar.finish_and_clear();
    if let Some(path) = &a.preview {
        write_preview(&a, split, path)?;
    }
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&summary).expect("serialisable")
        );
    } else {
        for p in summary.skipped.iter().take(20) {
            eprintln!("skipped {}: {}", p.file, p.reason);
        }
        if summary.skipped.len() > 20 {
            eprintln!("... and {} more", summary.skipped.len() - 20);
        }
        println!(
            "imported {} of {} frames of subject {} into the {} list of {} (skipped {})",
            summary.imported,
            summary.frames_found,
            summary.subject_id,
            summary.split,
            summary.output.display(),
            summary.skipped.len()
        );
        if let Some(p) = &a.preview {
            println!("preview: {}", p.display());
        }
    }
    if a.strict && !summary.skipped.is_empty() {
        return Ok(ExitCode::from(1));
    }
    Ok(ExitCode::SUCCESS)
}

/// The first six written frames, each as written and with its mesh drawn over it.
fn write_preview(a: &ImportArkitArgs, split: Split, path: &std::path::Path) -> Result<()> {
    let topology = super::setup::load_topology(a.resources.as_deref())?;
    let layout = ReleaseLayout::new(&a.output);
    let keys = arkit_core::release::read_list(&layout.list_path(split))?;
    let mut images = Vec::new();
    for row in keys.iter().take(6) {
        let img_path = layout.image_path(split, &row.key);
        let image = arkit_data::picture::read_rgb8_checked(&img_path, |_| Ok(()))?;
        let info = arkit_core::release::read_info(&layout.info_path(split, &row.key))?;
        let mut drawn = image.clone();
        arkit_data::ingest::synth::draw_overlay(&mut drawn, &topology, &info)?;
        images.push(image);
        images.push(drawn);
    }
    let sheet = arkit_data::picture::contact_sheet(&images, 4, 320);
    let mut bytes = std::io::Cursor::new(Vec::new());
    sheet
        .write_to(&mut bytes, image::ImageFormat::Png)
        .map_err(|e| Error::invalid("preview", e.to_string()))?;
    arkit_core::atomic_file::write_bytes(path, bytes.get_ref())
}
