//! `arkit-tool synth`.

use arkit_core::Error;
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};

use arkit_core::Result;
use clap::Args;
use std::path::PathBuf;
use std::process::ExitCode;

/// Write a synthetic dataset in the release's exact download layout.
///
/// Images are JPEGs of a shaded, textured face (skin, brows, eyes, lips) on a varied
/// background; each has an `_info.npz` with `verts`, `R_t` and the optional keys
/// (`verts_gt`, `faceAnchortransform`, `cameratransform`, `projectionMatrix`,
/// `euler_angles`, `translation`, `points2d`), all consistent with the image. Poses
/// cover the paper's ranges (yaw -78..77, pitch -64..51, roll -90..63 degrees,
/// distance 0.3..0.9 m). The same seed gives byte-identical output.
///
/// --group-photo FILE.jpg instead writes one photo of several faces side by side, at
/// several distances, in a camera with square pixels (`1.57443701 x max(W, H) / 2` px:
/// padded and resized to 800 px, the official demo's camera), for `predict --image`;
/// beside it FILE.boxes.json (the faces' landmark boxes, for --boxes) and
/// FILE.truth.json (each face's box, R_t, yaw/pitch/roll and translation).
///
/// Example: arkit-tool synth --output data/synth --subjects 10 --images-per-subject 20
///          arkit-tool synth --group-photo group.jpg --faces 3 --size 1280x720
#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Folder to write (`ARKitFace_image_train/`, `ARKitFace_info_train/`, ..., `ARKitFace_list/`).
    #[arg(long, required_unless_present = "group_photo")]
    output: Option<PathBuf>,
    /// Write a group photo (JPEG) instead of a dataset (see above); --size is the
    /// photo's (e.g. 1280x720).
    #[arg(long, value_name = "FILE.jpg", conflicts_with = "output")]
    group_photo: Option<PathBuf>,
    /// With --group-photo: how many faces, 1..=8.
    #[arg(long, default_value_t = 3)]
    faces: usize,
    /// Number of subjects (identities), 1..=100000.
    #[arg(long, allow_negative_numbers = true, default_value_t = 10,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=100_000))]
    subjects: usize,
    /// Images per subject, 1..=100000.
    #[arg(long, allow_negative_numbers = true, default_value_t = 20,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=100_000))]
    images_per_subject: usize,
    /// Image size as WIDTHxHEIGHT, each side 32..=8192 (the official evaluation uses
    /// 800x800).
    #[arg(long, default_value = "800x800", value_parser = super::parse_size)]
    size: (u32, u32),
    /// Seed of every random choice.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Fraction of subjects put in the test split, in [0, 1].
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.2, value_parser = super::unit_interval)]
    test_fraction: f64,
    /// JPEG quality, 1..=100.
    #[arg(long, allow_negative_numbers = true, default_value_t = 90, value_parser = clap::value_parser!(u8).range(1..=100))]
    jpeg_quality: u8,
    /// Use the real ARKit topology and template face from this folder (the release's
    /// `.npy` files: triangles.npy, uv_coords_std_202109.npy, kpt_ind.npy,
    /// template_verts.npy) instead of the built-in stand-in face.
    #[arg(long)]
    resources: Option<PathBuf>,
    /// Also write a PNG grid of the first samples, each beside a copy with its annotation
    /// (outline, eye and mouth openings, landmarks) projected over it.
    #[arg(long, value_name = "FILE.png")]
    preview: Option<PathBuf>,
    /// Print a JSON summary instead of text.
    #[arg(long)]
    json: bool,
}

pub fn run(a: SynthArgs) -> Result<ExitCode> {
    let options = SynthOptions {
        subjects: a.subjects,
        images_per_subject: a.images_per_subject,
        width: a.size.0,
        height: a.size.1,
        seed: a.seed,
        test_fraction: a.test_fraction,
        jpeg_quality: a.jpeg_quality,
    };
    options.check()?;
    let source = match &a.resources {
        Some(dir) => FaceSource::new(arkit_data::mesh::FaceTopology::from_resources(dir)?)?,
        None => FaceSource::builtin(),
    };
    if let Some(path) = &a.group_photo {
        return group_photo(&source, &options, a.faces, path, a.json);
    }
    let output = a.output.clone().expect("clap: --output or --group-photo");
    let total = (options.subjects * options.images_per_subject) as u64;
    let bar = super::progress_bar(total, "synth", "samples");
    let summary = synth::generate(&source, &options, &output, &|| bar.inc(1))?;
    bar.finish_and_clear();
    if let Some(path) = &a.preview {
        // Each sample twice: as written, and with its annotation drawn over it.
        let samples: Vec<_> = synth::plan(&options).into_iter().take(6).collect();
        let mut images = Vec::new();
        for s in &samples {
            let sample = synth::render_sample(&source, &options, s)?;
            let mut drawn = sample.image.clone();
            synth::draw_overlay(&mut drawn, &source.topology, &sample.info)?;
            images.push(sample.image);
            images.push(drawn);
        }
        let sheet = arkit_data::picture::contact_sheet(&images, 4, 320);
        let mut bytes = std::io::Cursor::new(Vec::new());
        sheet
            .write_to(&mut bytes, image::ImageFormat::Png)
            .map_err(|e| Error::invalid("preview", e.to_string()))?;
        arkit_core::atomic_file::write_bytes(path, bytes.get_ref())?;
    }
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&summary).expect("serialisable")
        );
    } else {
        println!(
            "wrote {} train + {} test samples of {} subjects ({}x{}, seed {}, {}) to {}",
            summary.train_samples,
            summary.test_samples,
            summary.subjects,
            summary.width,
            summary.height,
            summary.seed,
            summary.topology,
            summary.output.display()
        );
        if let Some(p) = &a.preview {
            println!("preview: {}", p.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `synth --group-photo`: the photo, its boxes and its truth.
fn group_photo(
    source: &FaceSource,
    options: &SynthOptions,
    faces: usize,
    path: &std::path::Path,
    json: bool,
) -> Result<ExitCode> {
    let photo = synth::group_photo(source, options, faces)?;
    let beside = |suffix: &str| {
        let stem = path
            .file_stem()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_default();
        path.with_file_name(format!("{stem}.{suffix}"))
    };
    let boxes: Vec<[f64; 4]> = photo.faces.iter().map(|f| f.bbox).collect();
    let truth = serde_json::json!({
        "photo": path.display().to_string(),
        "width": options.width,
        "height": options.height,
        "focal_px": photo.focal_px,
        "seed": options.seed,
        "faces": photo.faces.iter().map(|f| {
            let rt = f.pose.to_release_rt();
            let e = f.pose.euler();
            let t = f.pose.translation_m();
            serde_json::json!({
                "box": f.bbox,
                "R_t": [[rt[0], rt[1], rt[2], rt[3]], [rt[4], rt[5], rt[6], rt[7]],
                        [rt[8], rt[9], rt[10], rt[11]], [rt[12], rt[13], rt[14], rt[15]]],
                "angles": {"yaw": e.yaw_deg, "pitch": e.pitch_deg, "roll": e.roll_deg},
                "translation_m": [t.x, t.y, t.z],
            })
        }).collect::<Vec<_>>(),
    });
    let (boxes_path, truth_path) = (beside("boxes.json"), beside("truth.json"));
    arkit_core::atomic_file::write_bytes(
        path,
        &arkit_data::picture::jpeg_bytes(&photo.image, options.jpeg_quality)?,
    )?;
    arkit_core::atomic_file::write_bytes(
        &boxes_path,
        serde_json::to_string_pretty(&boxes)
            .expect("json")
            .as_bytes(),
    )?;
    arkit_core::atomic_file::write_bytes(
        &truth_path,
        serde_json::to_string_pretty(&truth)
            .expect("json")
            .as_bytes(),
    )?;
    if json {
        println!("{}", serde_json::to_string_pretty(&truth).expect("json"));
    } else {
        println!(
            "wrote a {}x{} group photo of {} faces (focal length {:.1} px) to {}, its boxes to {} and its truth to {}",
            options.width,
            options.height,
            photo.faces.len(),
            photo.focal_px,
            path.display(),
            boxes_path.display(),
            truth_path.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}
