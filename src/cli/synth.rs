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
/// --video OUT.mp4 (or a folder) instead writes a clip of the synthetic head moving
/// along a known trajectory, for `predict --video`: `--clip turn` (1 s at rest at yaw
/// -30, a 90 degree/s turn to +30, 1 s at rest; the clip docs/video.md measures the
/// smoothing on) or `--clip cross` (two heads that pass each other). Beside it:
/// OUT.truth.jsonl (each frame's faces: box, R_t, yaw/pitch/roll, translation) and
/// OUT.boxes.jsonl (each frame's boxes, for `predict --video --boxes`).
///
/// Example: arkit-tool synth --output data/synth --subjects 10 --images-per-subject 20
///          arkit-tool synth --group-photo group.jpg --faces 3 --size 1280x720
///          arkit-tool synth --video turn.mp4 --size 640x480
#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Folder to write (`ARKitFace_image_train/`, `ARKitFace_info_train/`, ..., `ARKitFace_list/`).
    #[arg(long, required_unless_present_any = ["group_photo", "video"])]
    output: Option<PathBuf>,
    /// Write a group photo (JPEG) instead of a dataset (see above); --size is the
    /// photo's (e.g. 1280x720).
    #[arg(long, value_name = "FILE.jpg", conflicts_with = "output")]
    group_photo: Option<PathBuf>,
    /// Write a clip (an .mp4, or a folder of PNG frames: a path with no extension)
    /// instead of a dataset (see above); --size is the frames' (e.g. 640x480).
    #[arg(long, value_name = "OUT.mp4", conflicts_with_all = ["output", "group_photo"])]
    video: Option<PathBuf>,
    /// With --video: which clip, `turn` or `cross`.
    #[arg(long, value_enum, default_value = "turn")]
    clip: ClipChoice,
    /// With --video: frames a second, in (0, 1000].
    #[arg(long, allow_negative_numbers = true, default_value_t = 30.0, value_parser = super::values::frame_rate)]
    fps: f64,
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
    #[arg(long, default_value = "800x800", value_parser = super::values::parse_size)]
    size: (u32, u32),
    /// Seed of every random choice.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Fraction of subjects put in the test split, in [0, 1].
    #[arg(long, allow_negative_numbers = true, default_value_t = 0.2, value_parser = super::values::unit_interval)]
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
    if let Some(path) = &a.video {
        return video(&source, &options, &a, path);
    }
    if let Some(path) = &a.group_photo {
        return group_photo(&source, &options, a.faces, path, a.json);
    }
    let output = a.output.clone().expect("clap: --output or --group-photo");
    let total = (options.subjects * options.images_per_subject) as u64;
    let bar = super::console::progress_bar(total, "synth", "samples");
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

/// `--clip` values.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum ClipChoice {
    Turn,
    Cross,
}

/// `synth --video`: the clip, its truth and its boxes.
fn video(
    source: &FaceSource,
    options: &SynthOptions,
    a: &SynthArgs,
    path: &std::path::Path,
) -> Result<ExitCode> {
    use arkit_data::video::{ClipPlan, Mp4Encoder};
    if !(a.fps.is_finite() && a.fps >= 1.0 && a.fps <= 240.0) {
        return Err(Error::invalid(
            "--fps",
            format!("{}: must be in [1, 240]", a.fps),
        ));
    }
    let plan = match a.clip {
        ClipChoice::Turn => ClipPlan::turn(a.fps),
        ClipChoice::Cross => ClipPlan::cross(a.fps),
    };
    let (w, h) = (options.width, options.height);
    let is_mp4 = path
        .extension()
        .is_some_and(|x| x.eq_ignore_ascii_case("mp4"));
    if !is_mp4 && path.extension().is_some() {
        return Err(Error::invalid(
            "--video",
            format!(
                "{}: writes an .mp4 or a folder of frames (a path with no extension)",
                path.display()
            ),
        ));
    }
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_default();
    let beside = |suffix: &str| path.with_file_name(format!("{stem}.{suffix}"));
    let mut encoder = if is_mp4 {
        Some(Mp4Encoder::create(path, a.fps)?)
    } else {
        None
    };
    let folder_tmp = match is_mp4 {
        true => None,
        false => Some(arkit_core::atomic_file::TemporaryDir::create(path)?),
    };
    let (mut truth, mut boxes) = (String::new(), String::new());
    let frames = plan.frames();
    let bar = super::console::progress_bar(frames as u64, "synth", "frames");
    let focal = arkit_core::conventions::Camera::RELEASE_FOCAL_NDC * w.max(h) as f64 / 2.0;
    for i in 0..frames {
        bar.inc(1);
        let faces = plan.faces(i, focal, w, h);
        let (image, _, found) = synth::video_frame(source, options.seed, w, h, &faces)?;
        let time_s = i as f64 / a.fps;
        let entries: Vec<serde_json::Value> = faces
            .iter()
            .zip(&found)
            .map(|((subject, pose), b)| {
                let rt = pose.to_release_rt();
                let e = pose.euler();
                let t = pose.translation_m();
                serde_json::json!({
                    "subject": subject,
                    "box": b,
                    "R_t": [[rt[0], rt[1], rt[2], rt[3]], [rt[4], rt[5], rt[6], rt[7]],
                            [rt[8], rt[9], rt[10], rt[11]], [rt[12], rt[13], rt[14], rt[15]]],
                    "angles": {"yaw": e.yaw_deg, "pitch": e.pitch_deg, "roll": e.roll_deg},
                    "translation_m": [t.x, t.y, t.z],
                })
            })
            .collect();
        truth.push_str(
            &serde_json::json!({"frame": i, "time_s": time_s, "faces": entries}).to_string(),
        );
        truth.push('\n');
        let visible: Vec<[f64; 4]> = found.iter().flatten().copied().collect();
        boxes.push_str(&serde_json::json!({"frame": i, "boxes": visible}).to_string());
        boxes.push('\n');
        match (encoder.as_mut(), folder_tmp.as_ref()) {
            (Some(e), _) => e.push(&image)?,
            (None, None) => unreachable!("a clip is written as an MP4 or a folder"),
            (None, Some(folder_tmp)) => {
                let mut png = std::io::Cursor::new(Vec::new());
                image
                    .write_to(&mut png, image::ImageFormat::Png)
                    .map_err(|e| Error::invalid("frame", e.to_string()))?;
                let file = folder_tmp.path().join(format!("frame-{i:06}.png"));
                std::fs::write(&file, png.get_ref()).map_err(|e| Error::io(path, e))?;
            }
        }
    }
    bar.finish_and_clear();
    match (encoder, folder_tmp) {
        (Some(e), _) => e.finish()?,
        (None, Some(folder_tmp)) => arkit_core::atomic_file::publish_dir(folder_tmp, path)?,
        (None, None) => unreachable!("a clip is written as an MP4 or a folder"),
    }
    let (truth_path, boxes_path) = (beside("truth.jsonl"), beside("boxes.jsonl"));
    arkit_core::atomic_file::write_bytes(&truth_path, truth.as_bytes())?;
    arkit_core::atomic_file::write_bytes(&boxes_path, boxes.as_bytes())?;
    let summary = serde_json::json!({
        "video": path.display().to_string(),
        "frames": frames,
        "fps": a.fps,
        "width": w,
        "height": h,
        "focal_px": focal,
        "truth": truth_path.display().to_string(),
        "boxes": boxes_path.display().to_string(),
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&summary).expect("json"));
    } else {
        println!(
            "wrote a {w}x{h} clip of {frames} frames at {} fps to {}, its truth to {} and its boxes to {}",
            a.fps,
            path.display(),
            truth_path.display(),
            boxes_path.display()
        );
    }
    Ok(ExitCode::SUCCESS)
}
