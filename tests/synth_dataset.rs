//! The synthetic generator: byte-for-byte reproducibility (against the committed
//! fixture and across thread counts), the release layout, and annotations consistent
//! with each other and with the projection, checked in Rust and, when python3 with
//! numpy is installed, by a numpy script that reads the files as the official loader.

use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_core::release::{self, ReleaseLayout, Split};
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
use nalgebra::{Matrix4, Point3};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The options `fixtures/synthetic` was made with:
/// `arkit-tool synth --output fixtures/synthetic --subjects 3 --images-per-subject 2 --size 160x120 --seed 7`
fn fixture_options() -> SynthOptions {
    SynthOptions {
        subjects: 3,
        images_per_subject: 2,
        width: 160,
        height: 120,
        seed: 7,
        ..SynthOptions::default()
    }
}

fn fixture_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("fixtures/synthetic")
}

fn files(root: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|e| e == "lock") {
                // The writer's lock file names its holder: not the fixture's.
                continue;
            } else {
                out.insert(
                    p.strip_prefix(root).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

fn generate_with_threads(options: &SynthOptions, out: &Path, threads: usize) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| synth::generate(&FaceSource::builtin(), options, out, &|| {}).unwrap());
}

#[test]
fn regenerating_the_fixture_gives_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    generate_with_threads(&fixture_options(), dir.path(), 2);
    let ours = files(dir.path());
    let committed = files(&fixture_dir());
    assert_eq!(
        ours.keys().collect::<Vec<_>>(),
        committed.keys().collect::<Vec<_>>()
    );
    for (name, bytes) in &ours {
        assert!(
            bytes == &committed[name],
            "{} differs from the committed fixture",
            name.display()
        );
    }
    assert_eq!(ours.len(), 6 * 2 + 2);
}

#[test]
fn output_does_not_depend_on_the_thread_count() {
    let options = SynthOptions {
        subjects: 2,
        images_per_subject: 3,
        width: 96,
        height: 96,
        seed: 123,
        ..SynthOptions::default()
    };
    let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    generate_with_threads(&options, a.path(), 1);
    generate_with_threads(&options, b.path(), 2);
    assert_eq!(files(a.path()), files(b.path()));
    // A different seed gives different data.
    let c = tempfile::tempdir().unwrap();
    generate_with_threads(
        &SynthOptions {
            seed: 124,
            ..options
        },
        c.path(),
        2,
    );
    assert_ne!(files(a.path()), files(c.path()));
}

#[test]
fn annotations_agree_with_each_other_and_the_image() {
    let root = fixture_dir();
    let layout = ReleaseLayout::new(&root);
    let mut subjects = BTreeMap::new();
    for split in [Split::Train, Split::Test] {
        let rows = release::read_list(&layout.list_path(split)).unwrap();
        assert!(!rows.is_empty());
        for row in rows {
            // Subject-disjoint splits; ids keep their leading zero.
            assert!(row.key.subject_id.starts_with('0'));
            assert_eq!(
                *subjects.entry(row.key.subject_id.clone()).or_insert(split),
                split
            );
            let info = release::read_info(&layout.info_path(split, &row.key)).unwrap();
            let pose = info.pose().unwrap();
            let camera = Camera::release(160, 120);
            let image = image::open(layout.image_path(split, &row.key)).unwrap();
            assert_eq!((image.width(), image.height()), (160, 120));
            // points2d is the projection of verts at R_t (stored as float32).
            let pts: Vec<Point3<f64>> = info.verts.iter().map(|p| p.cast()).collect();
            let projected = camera.project_all(&pose, &pts);
            for (p, q) in projected.iter().zip(info.points2d.as_ref().unwrap()) {
                assert!((p.u - q[0]).abs() < 1e-3 && (p.v - q[1]).abs() < 1e-3);
                assert!(
                    p.u > 0.0 && p.v > 0.0 && p.u < 160.0 && p.v < 120.0,
                    "vertex outside the image"
                );
            }
            // euler_angles ([pitch, yaw, roll]) and translation agree with R_t.
            let e = pose.euler();
            let [pitch, yaw, roll] = info.euler_angles_pyr.unwrap();
            assert!(
                (pitch - e.pitch_deg).abs() < 1e-9
                    && (yaw - e.yaw_deg).abs() < 1e-9
                    && (roll - e.roll_deg).abs() < 1e-9
            );
            assert!(
                (-78.0..=77.0).contains(&yaw)
                    && (-64.0..=51.0).contains(&pitch)
                    && (-90.0..=63.0).contains(&roll)
            );
            assert_eq!(
                info.translation.unwrap(),
                [info.rt[12], info.rt[13], info.rt[14]]
            );
            let distance = -info.rt[14];
            assert!((0.3..=0.9).contains(&distance));
            // R_t = faceAnchortransform @ inv(cameratransform).
            let a = Matrix4::from_row_slice(info.face_anchor_transform.as_ref().unwrap());
            let c = Matrix4::from_row_slice(info.camera_transform.as_ref().unwrap());
            assert!(
                (a * c.try_inverse().unwrap() - Matrix4::from_row_slice(&info.rt))
                    .abs()
                    .max()
                    < 1e-9
            );
            assert_eq!(info.verts_gt.as_ref().unwrap(), &info.verts);
            // The image is not blank where the face is: the nose tip pixel differs from
            // the image corner's colour.
            let rgb = image.to_rgb8();
            let tip = &projected[arkit_data::mesh::builtin().topology.landmarks[30] as usize];
            assert_ne!(
                rgb.get_pixel(tip.u as u32, tip.v as u32),
                rgb.get_pixel(0, 0)
            );
        }
    }
    assert_eq!(subjects.len(), 3);
    assert!(subjects.values().any(|s| *s == Split::Test));
}

#[test]
fn numpy_reads_the_dataset_as_the_official_loader_does() {
    let script =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/python/check_release_layout.py");
    let has_numpy = std::process::Command::new("python3")
        .args(["-c", "import numpy"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !has_numpy {
        eprintln!(
            "SKIPPED: python3 with numpy is not installed; the numpy cross-check did not run"
        );
        return;
    }
    let out = std::process::Command::new("python3")
        .arg(&script)
        .arg(fixture_dir())
        .args(["160", "120"])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("6 passed, 0 failed"), "{stdout}");
}

#[test]
fn synth_draws_the_real_template_when_resources_exist() {
    let dir = std::env::var_os("ARKIT_RESOURCES")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/arkitface-resources")
        });
    if !dir.join("template_verts.npy").exists() {
        eprintln!("SKIPPED: {} is absent", dir.display());
        return;
    }
    let source =
        FaceSource::new(arkit_data::mesh::FaceTopology::from_resources(&dir).unwrap()).unwrap();
    let options = SynthOptions {
        subjects: 1,
        images_per_subject: 2,
        width: 200,
        height: 200,
        seed: 1,
        ..SynthOptions::default()
    };
    let out = tempfile::tempdir().unwrap();
    let summary = synth::generate(&source, &options, out.path(), &|| {}).unwrap();
    assert_eq!(summary.train_samples, 2);
    let layout = ReleaseLayout::new(out.path());
    for s in synth::plan(&options) {
        let info = release::read_info(&layout.info_path(s.split, &s.key)).unwrap();
        assert_eq!(info.verts.len(), 1220);
    }
}

#[test]
fn a_pose_rendered_is_a_pose_read_back() {
    // One sample rendered in memory: its annotation's pose is the drawn pose, and the
    // camera check accepts it.
    let options = fixture_options();
    let plan = synth::plan(&options);
    let sample = synth::render_sample(&FaceSource::builtin(), &options, &plan[0]).unwrap();
    let pose = sample.info.pose().unwrap();
    let back = Pose::from_euler(
        EulerAngles::new(
            sample.info.euler_angles_pyr.unwrap()[1],
            sample.info.euler_angles_pyr.unwrap()[0],
            sample.info.euler_angles_pyr.unwrap()[2],
        ),
        pose.translation_m(),
    );
    assert!(pose.rotation_angle_to_deg(&back) < 1e-9);
    let pts: Vec<Point3<f64>> = sample.info.verts.iter().map(|p| p.cast()).collect();
    Camera::release(160, 120)
        .check_projectable(&pose, &pts)
        .unwrap();
}
