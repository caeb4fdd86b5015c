//! Hostile but fair input, and faults: every case ends in a clear error or a reported
//! skip, never a silent substitute or stale output (issue 21).
//!
//! - a folder holding another conversion is refused, `--overwrite` replaces it;
//! - a second writer of the same part is refused while the first holds its lock;
//! - an input file changed in place makes its shard be redone on a rerun;
//! - parts of different conversions do not merge;
//! - a shard rewritten after `convert` is refused by readers;
//! - a moved release or a missing image is reported and skipped by `augment`, `train`'s
//!   example reader and `eval`'s report, never read as a grey canvas, and
//!   `ARKIT_INPUT_ROOT` finds a moved release again;
//! - degenerate samples (collapsed mesh, tiny image, image of another size than its
//!   annotation's `points2d`) are skipped with the reason; bytes after a JPEG's end are
//!   not mistaken for truncation;
//! - stale temporaries of killed runs are removed;
//! - a check that skips most of the first samples (an input in another convention)
//!   stops `convert` with the check's name and the way out (`--skip-check points2d`,
//!   `--allow-systematic-skips`); half does not.

use crate::support::{convert_context as context, convert_options as options};
use arkit_core::atomic_file::FolderLock;
use arkit_core::conventions::Camera;
use arkit_core::release::{self, ReleaseLayout, SampleKey, Split};
use arkit_core::{NpyArray, NpzCompression};
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
use arkit_data::ingest::{self, ConvertOptions};
use arkit_data::store;
use arkit_data::store::Dataset;
use std::path::Path;
use std::process::Command;

fn make_release(dir: &Path, subjects: usize, images: usize, seed: u64) {
    let options = SynthOptions {
        subjects,
        images_per_subject: images,
        width: 128,
        height: 128,
        seed,
        ..SynthOptions::default()
    };
    synth::generate(&FaceSource::builtin(), &options, dir, &|| {}).unwrap();
}

fn convert(o: &ConvertOptions) -> arkit_core::Result<arkit_data::store::Manifest> {
    ingest::convert(o, &context(), &|_| {})
}

fn keys(root: &Path, split: Split) -> Vec<SampleKey> {
    release::read_list(&ReleaseLayout::new(root).list_path(split))
        .unwrap()
        .into_iter()
        .map(|r| r.key)
        .collect()
}

#[test]
fn another_conversion_in_the_folder_is_refused_and_overwrite_replaces_it() {
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    make_release(a.path(), 2, 3, 1);
    make_release(b.path(), 3, 2, 2);
    let out = tempfile::tempdir().unwrap();
    let first = convert(&options(a.path(), out.path(), 4)).unwrap();
    let e = convert(&options(b.path(), out.path(), 4))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("other input") && e.contains("--overwrite"),
        "{e}"
    );
    // Nothing of the first conversion was touched.
    assert_eq!(
        arkit_data::store::read_manifest(&out.path().join("dataset.json")).unwrap(),
        first
    );
    // Other options into the same folder: refused too (a sharded part with another
    // shard size would interleave its shards with these).
    let e = convert(&options(a.path(), out.path(), 3))
        .unwrap_err()
        .to_string();
    assert!(e.contains("other options"), "{e}");
    // --overwrite replaces it: the samples are b's, as a fresh conversion gives them.
    let mut o = options(b.path(), out.path(), 4);
    o.overwrite = true;
    convert(&o).unwrap();
    let fresh = tempfile::tempdir().unwrap();
    convert(&options(b.path(), fresh.path(), 4)).unwrap();
    assert_eq!(
        ingest::read_dataset_samples(out.path()).unwrap(),
        ingest::read_dataset_samples(fresh.path()).unwrap()
    );
}

#[test]
fn a_second_writer_of_the_same_part_is_refused() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 2, 3);
    let out = tempfile::tempdir().unwrap();
    let held = FolderLock::acquire(out.path(), "convert-part-0-of-1", "convert").unwrap();
    let e = convert(&options(input.path(), out.path(), 4))
        .unwrap_err()
        .to_string();
    assert!(e.contains("another convert"), "{e}");
    assert!(!out.path().join("dataset.json").exists());
    drop(held);
    convert(&options(input.path(), out.path(), 4)).unwrap();
}

#[test]
fn an_input_file_changed_in_place_is_converted_again_and_temporaries_are_cleaned() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 4, 4);
    let out = tempfile::tempdir().unwrap();
    let first = convert(&options(input.path(), out.path(), 3)).unwrap();
    let before = ingest::read_dataset_samples(out.path()).unwrap();
    // Sample 4 (shard 1) gets sample 0's annotation, in place; a killed run's temporary
    // is left in samples/.
    let root = input.path();
    let layout = ReleaseLayout::new(root);
    let split = |r: &store::SampleRecord| {
        if r.split == "test" {
            Split::Test
        } else {
            Split::Train
        }
    };
    let (r0, r4) = (&before[0], &before[4]);
    std::thread::sleep(std::time::Duration::from_millis(20));
    std::fs::copy(
        layout.info_path(split(r0), &r0.key),
        layout.info_path(split(r4), &r4.key),
    )
    .unwrap();
    let train = [r0.key.clone(), r4.key.clone()];
    let stale = out.path().join("samples/.part-00000.parquet.tmp-4242");
    std::fs::write(&stale, b"half a shard").unwrap();
    let second = convert(&options(root, out.path(), 3)).unwrap();
    assert!(!stale.exists(), "a killed run's temporary survived");
    let after = ingest::read_dataset_samples(out.path()).unwrap();
    let row = |rows: &[store::SampleRecord], k: &SampleKey| {
        rows.iter().find(|r| &r.key == k).unwrap().clone()
    };
    assert_ne!(row(&before, &train[1]).rt, row(&after, &train[1]).rt);
    assert_eq!(row(&after, &train[1]).rt, row(&after, &train[0]).rt);
    // Shard 1 was redone; the others were kept byte for byte.
    for (a, b) in first.shards.iter().zip(&second.shards) {
        assert_eq!(a.sha256 == b.sha256, a.index != 1, "shard {}", a.index);
    }
}

#[test]
fn parts_of_different_conversions_do_not_merge() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 3, 2, 5);
    let out = tempfile::tempdir().unwrap();
    for i in 0..2 {
        let mut o = options(input.path(), out.path(), 2);
        (o.shard_index, o.shard_count) = (i, 2);
        convert(&o).unwrap();
    }
    ingest::merge(out.path()).unwrap();
    // A part manifest from a conversion with another topology.
    let part = out.path().join(ingest::manifest_name(1, 2));
    let mut m = arkit_data::store::read_manifest(&part).unwrap();
    m.topology_sha256 = "0".repeat(64);
    std::fs::write(&part, serde_json::to_string_pretty(&m).unwrap()).unwrap();
    let e = ingest::merge(out.path()).unwrap_err().to_string();
    assert!(e.contains("topology differs"), "{e}");
}

#[test]
fn a_shard_rewritten_after_convert_is_refused() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 3, 6);
    let out = tempfile::tempdir().unwrap();
    let m = convert(&options(input.path(), out.path(), 3)).unwrap();
    assert_eq!(
        ingest::verify_dataset(out.path()).unwrap(),
        2 * m.shards.len()
    );
    // Shard 0 replaced by shard 1's file: a valid Parquet file, the wrong one.
    std::fs::copy(
        out.path().join(&m.shards[1].samples_file),
        out.path().join(&m.shards[0].samples_file),
    )
    .unwrap();
    let e = ingest::read_dataset_samples(out.path())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("part-00000.parquet") && e.contains("changed after convert"),
        "{e}"
    );
    let e = ingest::verify_dataset(out.path()).unwrap_err().to_string();
    assert!(e.contains("SHA-256"), "{e}");
}

#[test]
fn a_missing_image_is_reported_and_skipped_never_grey() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 3, 7);
    let out = tempfile::tempdir().unwrap();
    convert(&options(input.path(), out.path(), 4)).unwrap();
    let data = Dataset::open(out.path()).unwrap();
    let rows = data.read_all_samples().unwrap();
    let gone = rows[2].clone();
    let gone_path = data.image_path(&gone).unwrap();
    std::fs::remove_file(&gone_path).unwrap();
    let e = data.image(&gone).unwrap_err().to_string();
    assert!(
        e.contains(&gone_path.display().to_string()) && e.contains("ARKIT_INPUT_ROOT"),
        "{e}"
    );
    assert!(data.check_image(&gone).is_err());
    assert_eq!(data.image(&rows[0]).unwrap().dimensions(), (128, 128));
    // augment: the other samples are augmented, the missing one reported.
    let aug_out = tempfile::tempdir().unwrap();
    let aopts = arkit_data::augment::AugmentOptions {
        output: aug_out.path().to_path_buf(),
        axis: arkit_data::augment::AxisChoice::Fixed(arkit_data::augment::Axis::Roll),
        rule: arkit_data::augment::ProfilingRule::default(),
        per_sample: 1,
        flip: false,
        with_originals: true,
        seed: 1,
        jpeg_quality: 90,
        preview_pairs: 0,
    };
    let (summary, _) = arkit_data::augment::augment_dataset(
        out.path(),
        &arkit_data::mesh::builtin().topology,
        &aopts,
        &|_| {},
    )
    .unwrap();
    assert_eq!(summary.sources, rows.len());
    assert_eq!(summary.unreadable.len(), 1);
    assert_eq!(summary.unreadable[0].0, gone.key);
    let originals = summary
        .written
        .iter()
        .filter(|w| w.operation == "original")
        .count();
    assert_eq!(originals, rows.len() - 1);
    assert!(
        !summary.written.iter().any(|w| w.source == gone.key),
        "something was written for the sample without an image"
    );
}

#[test]
fn a_moved_release_is_found_again_through_the_environment() {
    let base = tempfile::tempdir().unwrap();
    let release_dir = base.path().join("release");
    make_release(&release_dir, 2, 2, 8);
    let out = base.path().join("pq");
    convert(&options(&release_dir, &out, 4)).unwrap();
    let moved = base.path().join("moved");
    std::fs::rename(&release_dir, &moved).unwrap();
    let tool = env!("CARGO_BIN_EXE_arkit-tool");
    let run = |env: Option<&Path>, strict: bool| {
        let mut c = Command::new(tool);
        c.args(["augment", "--input"])
            .arg(&out)
            .arg("--output")
            .arg(base.path().join("aug"))
            .arg("--with-originals");
        if strict {
            c.arg("--strict");
        }
        c.env_remove("ARKIT_INPUT_ROOT");
        if let Some(p) = env {
            c.env("ARKIT_INPUT_ROOT", p);
        }
        c.output().unwrap()
    };
    // Moved: every image is reported missing, with where it was looked for; nothing is
    // made of grey squares.
    let o = run(None, false);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("unreadable") && err.contains(&release_dir.display().to_string()),
        "{err}"
    );
    // Pointed at its new place, it works.
    let o = run(Some(&moved), true);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// Writes `info` as the `_info.npz` of `key`.
fn write_info(root: &Path, key: &SampleKey, arrays: Vec<(&'static str, NpyArray)>) {
    let path = ReleaseLayout::new(root).info_path(Split::Train, key);
    let refs: Vec<(&str, &NpyArray)> = arrays.iter().map(|(k, a)| (*k, a)).collect();
    let mut f = std::fs::File::create(path).unwrap();
    arkit_core::write_npz(&mut f, &refs, NpzCompression::Stored).unwrap();
}

#[test]
fn degenerate_samples_are_skipped_with_the_reason() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 3, 3, 9);
    let root = input.path();
    let layout = ReleaseLayout::new(root);
    let train = keys(root, Split::Train);
    let image = |k: &SampleKey| layout.image_path(Split::Train, k);
    let good = release::read_info(&layout.info_path(Split::Train, &train[0])).unwrap();
    let arrays = good.to_arrays();
    let get = |name: &str| arrays.iter().find(|(n, _)| *n == name).unwrap().1.clone();
    // 0: an all-zero mesh (projects to one point, inside the image).
    write_info(
        root,
        &train[0],
        vec![
            (
                "verts",
                NpyArray::from_f32(vec![1220, 3], vec![0.0; 3660]).unwrap(),
            ),
            ("R_t", get("R_t")),
        ],
    );
    // 1: a 1x1 JPEG.
    let tiny = image::RgbImage::from_pixel(1, 1, image::Rgb([9, 9, 9]));
    std::fs::write(
        image(&train[1]),
        arkit_data::picture::jpeg_bytes(&tiny, 90).unwrap(),
    )
    .unwrap();
    // 2: the image resized (the annotation's own points2d say where the face was).
    let img = image::open(image(&train[2])).unwrap().to_rgb8();
    let bigger = image::imageops::resize(&img, 160, 160, image::imageops::FilterType::Triangle);
    std::fs::write(
        image(&train[2]),
        arkit_data::picture::jpeg_bytes(&bigger, 90).unwrap(),
    )
    .unwrap();
    // 3: bytes after the JPEG's end marker: a good sample.
    let mut bytes = std::fs::read(image(&train[3])).unwrap();
    bytes.extend_from_slice(&[0u8; 300]);
    bytes.extend_from_slice(b"trailer");
    std::fs::write(image(&train[3]), bytes).unwrap();
    let out = tempfile::tempdir().unwrap();
    let m = convert(&options(root, out.path(), 16)).unwrap();
    let mut errors = Vec::new();
    for s in &m.shards {
        errors.extend(store::read_errors(&out.path().join(&s.errors_file)).unwrap());
    }
    let reason = |k: &SampleKey| {
        errors
            .iter()
            .find(|e| &e.key == k)
            .map(|e| e.reason.clone())
            .unwrap_or_else(|| panic!("{k} was not skipped"))
    };
    assert!(
        reason(&train[0]).contains("collapsed"),
        "{}",
        reason(&train[0])
    );
    assert!(reason(&train[1]).contains("1x1"), "{}", reason(&train[1]));
    assert!(
        reason(&train[2]).contains("points2d"),
        "{}",
        reason(&train[2])
    );
    assert_eq!(errors.len(), 3, "{errors:?}");
    let rows = ingest::read_dataset_samples(out.path()).unwrap();
    assert!(rows.iter().any(|r| r.key == train[3]));
}

#[test]
fn jpeg_framing_walks_the_segments() {
    let img = image::RgbImage::from_fn(40, 30, |x, y| image::Rgb([x as u8 * 5, y as u8 * 7, 90]));
    let jpg = arkit_data::picture::jpeg_bytes(&img, 85).unwrap();
    assert_eq!(ingest::check_jpeg_framing(&jpg), Ok(jpg.len()));
    let mut padded = jpg.clone();
    padded.extend_from_slice(&[0xFF, 0xD9, 1, 2, 3]);
    assert_eq!(ingest::check_jpeg_framing(&padded), Ok(jpg.len()));
    for cut in [jpg.len() - 2, jpg.len() / 2, 30, 5] {
        let e = ingest::check_jpeg_framing(&jpg[..cut]).unwrap_err();
        assert!(
            e.contains("truncated") || e.contains("corrupt"),
            "{cut}: {e}"
        );
    }
    assert!(ingest::check_jpeg_framing(b"\x89PNG\r\n\x1a\n").is_err());
}

#[test]
#[cfg(feature = "model")]
fn library_options_are_checked_without_the_cli() {
    use arkit_perspnet::{Augmentation, TrainOptions};
    let base = TrainOptions {
        config: arkit_perspnet::PerspNetConfig::tiny(),
        epochs: 1,
        max_steps: None,
        batch: 2,
        learning_rate: 1e-3,
        lr_hold: 0.5,
        augmentation: Augmentation {
            colour: 0.1,
            shift_px: 0,
            resample_points: true,
            legacy_colour: None,
        },
        lowered_start: false,
        seed: 0,
        output: std::path::PathBuf::from("/nonexistent/model"),
        resume: false,
    };
    base.validate().unwrap();
    type Change = Box<dyn Fn(&mut TrainOptions)>;
    let cases: Vec<(&str, Change)> = vec![
        ("--epochs", Box::new(|o| o.epochs = 0)),
        ("--batch", Box::new(|o| o.batch = 0)),
        ("--steps", Box::new(|o| o.max_steps = Some(0))),
        ("--lr", Box::new(|o| o.learning_rate = -1.0)),
        ("--lr", Box::new(|o| o.learning_rate = f64::NAN)),
        ("--lr-hold", Box::new(|o| o.lr_hold = 2.0)),
        ("--colour-jitter", Box::new(|o| o.augmentation.colour = 3.0)),
    ];
    for (what, change) in cases {
        let mut o = base.clone();
        change(&mut o);
        let e = o.validate().unwrap_err().to_string();
        assert!(e.contains(what), "{what}: {e}");
    }
    // augment and the oracle check theirs before reading anything.
    let missing = Path::new("/nonexistent/dataset");
    let aopts = arkit_data::augment::AugmentOptions {
        output: std::path::PathBuf::from("/nonexistent/out"),
        axis: arkit_data::augment::AxisChoice::Auto,
        rule: arkit_data::augment::ProfilingRule::default(),
        per_sample: 1,
        flip: false,
        with_originals: false,
        seed: 1,
        jpeg_quality: 0,
        preview_pairs: 0,
    };
    let topo = &arkit_data::mesh::builtin().topology;
    let e = arkit_data::augment::augment_dataset(missing, topo, &aopts, &|_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("--jpeg-quality"), "{e}");
    let mut bad_rule = aopts.clone();
    bad_rule.jpeg_quality = 90;
    bad_rule.rule.max_angle = 1000.0;
    let e = arkit_data::augment::augment_dataset(missing, topo, &bad_rule, &|_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("max-angle"), "{e}");
    // A maximum angle below the largest change is fine: changes stop at the angle.
    bad_rule.rule.max_angle = 20.0;
    assert!(bad_rule.rule.max_change > 20.0);
    bad_rule.validate().unwrap();
    let o = arkit_data::pose::OracleOptions {
        noise_px: 0.0,
        outliers: 1.0,
        seed: 0,
        split: None,
        ransac: arkit_data::pose::RansacParams::default(),
    };
    let e = arkit_data::pose::oracle_predictions(missing, missing, &o, &|_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("--outliers"), "{e}");
}

#[test]
fn a_second_render_of_the_same_part_is_refused_and_its_temporaries_are_cleaned() {
    use arkit_data::render::FaceRenderer;
    use arkit_data::render::RenderOptions;
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 2, 2, 10);
    let out = tempfile::tempdir().unwrap();
    convert(&options(input.path(), out.path(), 4)).unwrap();
    let renderer = FaceRenderer::new(
        arkit_data::mesh::builtin().topology.clone(),
        Camera::release_projection(),
    )
    .unwrap();
    let ro = RenderOptions {
        size: 32,
        uv_size: 16,
        points: 32,
        seed: 0,
        shard: (0, 1),
        full_mask: false,
        output: out.path().to_path_buf(),
    };
    let targets = out.path().join("targets");
    let held = FolderLock::acquire(&targets, "render-part-0-of-1", "render").unwrap();
    let e = arkit_data::render::render_dataset(out.path(), &renderer, &ro, &|_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("another render of this part"), "{e}");
    drop(held);
    let stale = targets.join(".part-00000.parquet.tmp-777");
    std::fs::write(&stale, b"half").unwrap();
    arkit_data::render::render_dataset(out.path(), &renderer, &ro, &|_| {}).unwrap();
    assert!(!stale.exists());
    assert!(arkit_data::store::shard_path(out.path(), 0).exists());
}

#[test]
fn a_check_that_skips_most_samples_stops_convert_with_the_reason_and_the_way_out() {
    let input = tempfile::tempdir().unwrap();
    make_release(input.path(), 3, 4, 21);
    let root = input.path();
    let layout = ReleaseLayout::new(root);
    // Every annotation's points2d in another convention (normalised to 0..1 instead of
    // pixels): the points2d check fails on every sample.
    let mut n = 0;
    for split in [Split::Train, Split::Test] {
        for k in keys(root, split) {
            let path = layout.info_path(split, &k);
            let mut info = release::read_info(&path).unwrap();
            for p in info.points2d.as_mut().unwrap() {
                *p = [p[0] / 128.0, p[1] / 128.0];
            }
            release::write_info(&path, &info, NpzCompression::Deflated).unwrap();
            n += 1;
        }
    }
    assert_eq!(n, 12);
    let tool = |out: &str, extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_arkit-tool"))
            .args(["convert", "--json", "--systematic-window", "8", "--input"])
            .arg(root)
            .arg("--output")
            .arg(input.path().join(out))
            .args(extra)
            .output()
            .unwrap()
    };
    // Stopped, with the check, the count, the first sample and what to do.
    let out = tool("pq", &[]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("'points2d' check skipped 8 of the first 8 samples")
            && stderr.contains("points2d lie a median")
            && stderr.contains("--skip-check points2d")
            && stderr.contains("--allow-systematic-skips"),
        "{stderr}"
    );
    assert!(!input.path().join("pq/dataset.json").exists());
    // A rerun into the same folder with the check off is another conversion.
    let out = tool("pq", &["--skip-check", "points2d"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("other checks turned off"),
        "{stderr}"
    );
    // With the check off (and --overwrite), every sample converts: the pose and image
    // still agree through the landmarks.
    let out = tool("pq", &["--skip-check", "points2d", "--overwrite"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let m: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        (m["converted"].as_u64(), m["skipped"].as_u64()),
        (Some(12), Some(0))
    );
    // --allow-systematic-skips: skipped one by one, each with its reason.
    let out = tool("pq-each", &["--allow-systematic-skips"]);
    assert!(out.status.success());
    let m: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        (m["converted"].as_u64(), m["skipped"].as_u64()),
        (Some(0), Some(12))
    );
    // With the default window (1,000), an input of 12 samples is never stopped.
    let o = options(root, &input.path().join("pq-lib"), 16);
    let m = convert(&o).unwrap();
    assert_eq!(m.skipped, 12);
    // Only points2d can be turned off.
    let out = tool("pq-x", &["--skip-check", "pose"]);
    assert!(!out.status.success());
    // Half is not "most": 4 of 8 skipped for one check does not stop.
    let fresh = tempfile::tempdir().unwrap();
    make_release(fresh.path(), 3, 4, 21);
    let rows = ingest::plan_rows(&ingest::discover(fresh.path()).unwrap())
        .unwrap()
        .0;
    for r in rows.iter().take(8).skip(4) {
        let path = fresh.path().join(&r.info);
        let mut info = release::read_info(&path).unwrap();
        for p in info.points2d.as_mut().unwrap() {
            *p = [p[0] / 128.0, p[1] / 128.0];
        }
        release::write_info(&path, &info, NpzCompression::Deflated).unwrap();
    }
    let checks = ingest::ConvertChecks {
        skip: Vec::new(),
        window: 8,
    };
    let input2 = ingest::discover(fresh.path()).unwrap();
    let plan = ingest::plan_rows(&input2).unwrap();
    let m = ingest::convert_planned_with(
        &options(fresh.path(), &fresh.path().join("pq"), 16),
        &context(),
        &checks,
        &input2,
        plan,
        &|_| {},
    )
    .unwrap();
    assert_eq!(m.skipped, 4);
}
