//! `arkit-tool synth`.

use arkit_core::error::Error;
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};

use arkit_core::error::Result;
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
/// Example: arkit-tool synth --output data/synth --subjects 10 --images-per-subject 20
#[derive(Args, Debug)]
pub struct SynthArgs {
    /// Folder to write (`ARKitFace_image_train/`, `ARKitFace_info_train/`, ..., `ARKitFace_list/`).
    #[arg(long)]
    output: PathBuf,
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
        Some(dir) => FaceSource::new(arkit_data::mesh::topology::FaceTopology::from_resources(
            dir,
        )?)?,
        None => FaceSource::builtin(),
    };
    let total = (options.subjects * options.images_per_subject) as u64;
    let bar = super::progress_bar(total, "synth", "samples");
    let summary = synth::generate(&source, &options, &a.output, &|| bar.inc(1))?;
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
        let sheet = arkit_data::picture::encode::contact_sheet(&images, 4, 320);
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
