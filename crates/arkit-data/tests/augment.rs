//! `augment`: geometric consistency of the new images with the new annotations, and the
//! whole path synth -> convert -> augment -> convert.

use arkit_core::VisibilityBuffer;
use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_data::augment::{AugmentOptions, AxisChoice, ProfilingRule};
use arkit_data::augment::{Axis, FaceImage};
use arkit_data::ingest::synth::{self, FaceSource, SynthOptions};
use arkit_data::ingest::{self, ConvertOptions, ValidationContext};
use arkit_data::mesh::FaceTopology;
use image::{Rgb, RgbImage};
use nalgebra::{Point3, Vector3};

/// The face's pixels (mesh with eyes and mouth filled) as rendered from an annotation.
fn face_mask(
    topology: &FaceTopology,
    verts: &[Point3<f32>],
    pose: &Pose,
    w: u32,
    h: u32,
) -> Vec<bool> {
    let fill = topology.hole_fill().unwrap();
    let mut all = verts.to_vec();
    all.extend(fill.centroid_positions(verts));
    let mut tris = topology.triangles.clone();
    tris.extend(fill.triangles.iter().copied());
    let screen = Camera::release(w, h).project_to_screen(pose, &all);
    let mut vis = VisibilityBuffer::new(w, h);
    vis.rasterize_mesh(&screen, &tris).unwrap();
    vis.triangle
        .iter()
        .map(|&t| t != VisibilityBuffer::EMPTY)
        .collect()
}

fn iou(a: &[bool], b: &[bool]) -> f64 {
    let both = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let either = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    both as f64 / either as f64
}

/// The face painted white on black where its annotation says it is: augmenting this
/// image must put the white exactly where the new annotation says the face is.
#[test]
fn augmented_images_agree_with_their_new_annotations() {
    let face = arkit_data::mesh::builtin();
    let topo = &face.topology;
    let verts = topo.template.clone().unwrap();
    let (w, h) = (320, 320);
    let cases = [
        ((35.0, 5.0, 3.0), Axis::Yaw, 25.0),
        ((-40.0, -5.0, 0.0), Axis::Yaw, -30.0),
        ((5.0, 15.0, 2.0), Axis::Pitch, 20.0),
        ((5.0, -25.0, 2.0), Axis::Pitch, -20.0),
        ((10.0, 5.0, 8.0), Axis::Roll, 25.0),
    ];
    for ((yaw, pitch, roll), axis, change) in cases {
        let pose = Pose::from_euler(
            EulerAngles::new(yaw, pitch, roll),
            Vector3::new(0.01, 0.005, -0.45),
        );
        let mask = face_mask(topo, &verts, &pose, w, h);
        let image = RgbImage::from_fn(w, h, |x, y| {
            if mask[(y * w + x) as usize] {
                Rgb([255, 255, 255])
            } else {
                Rgb([0, 0, 0])
            }
        });
        let input = FaceImage {
            image,
            verts: verts.clone(),
            pose,
        };
        let out = arkit_data::augment::profile(topo, &input, axis, change).unwrap();
        let want = face_mask(topo, &out.verts, &out.pose, w, h);
        let got: Vec<bool> = out.image.pixels().map(|p| p[0] > 127).collect();
        let score = iou(&got, &want);
        assert!(
            score >= 0.95,
            "{axis:?} {change} from {yaw}/{pitch}/{roll}: IoU {score:.4}"
        );
        // The new Euler angle is the old one plus the change, the others unchanged.
        let (e0, e1) = (pose.euler(), out.pose.euler());
        let d = [
            e1.yaw_deg - e0.yaw_deg,
            e1.pitch_deg - e0.pitch_deg,
            e1.roll_deg - e0.roll_deg,
        ];
        let k = match axis {
            Axis::Yaw => 0,
            Axis::Pitch => 1,
            Axis::Roll => 2,
        };
        for (i, v) in d.iter().enumerate() {
            let expected = if i == k { change } else { 0.0 };
            assert!((v - expected).abs() < 1e-9, "{axis:?}: {d:?}");
        }
    }
}

#[test]
fn far_background_is_kept_and_the_face_turns() {
    // A textured synthetic sample: pixels far from the face are untouched by profiling.
    let options = SynthOptions {
        subjects: 1,
        images_per_subject: 1,
        width: 400,
        height: 400,
        seed: 5,
        ..SynthOptions::default()
    };
    let plan = synth::plan(&options);
    let s = synth::render_sample(&FaceSource::builtin(), &options, &plan[0]).unwrap();
    let input = FaceImage {
        image: s.image.clone(),
        verts: s.info.verts.clone(),
        pose: s.info.pose().unwrap(),
    };
    let e = input.pose.euler();
    let axis = if e.yaw_deg.abs() < 60.0 {
        Axis::Yaw
    } else {
        Axis::Roll
    };
    let change = 10.0f64.copysign(e.yaw_deg);
    let topo = &arkit_data::mesh::builtin().topology;
    let Ok(out) = arkit_data::augment::profile(topo, &input, axis, change) else {
        return;
    };
    // The corners of the image are outside the anchor box unless the face is huge.
    for (x, y) in [(0, 0), (399, 0), (0, 399), (399, 399)] {
        let (a, b) = (input.image.get_pixel(x, y), out.image.get_pixel(x, y));
        for k in 0..3 {
            assert!(
                (a[k] as i32 - b[k] as i32).abs() <= 1,
                "corner ({x},{y}) changed"
            );
        }
    }
    assert_ne!(out.image, input.image);
}

#[test]
fn synth_convert_augment_convert_round_trip() {
    let release = tempfile::tempdir().unwrap();
    let options = SynthOptions {
        subjects: 3,
        images_per_subject: 3,
        width: 192,
        height: 192,
        seed: 21,
        ..SynthOptions::default()
    };
    synth::generate(&FaceSource::builtin(), &options, release.path(), &|| {}).unwrap();
    let pq = tempfile::tempdir().unwrap();
    let ctx = ValidationContext {
        projection: Camera::release_projection(),
        topology: arkit_data::mesh::builtin().topology.clone(),
        embed_images: false,
    };
    let copts = |input: &std::path::Path, output: &std::path::Path| ConvertOptions {
        input: input.to_path_buf(),
        output: output.to_path_buf(),
        resources: None,
        rows_per_shard: 4,
        embed_images: false,
        shard_index: 0,
        shard_count: 1,
        overwrite: false,
    };
    ingest::convert(&copts(release.path(), pq.path()), &ctx, &|_| {}).unwrap();
    let out = tempfile::tempdir().unwrap();
    let aopts = AugmentOptions {
        output: out.path().to_path_buf(),
        axis: AxisChoice::Fixed(Axis::Roll),
        rule: ProfilingRule::default(),
        per_sample: 1,
        flip: true,
        with_originals: true,
        seed: 1,
        jpeg_quality: 95,
        preview_pairs: 2,
    };
    let topo = &arkit_data::mesh::builtin().topology;
    let (summary, previews) =
        arkit_data::augment::augment_dataset(pq.path(), topo, &aopts, &|_| {}).unwrap();
    assert_eq!(summary.sources, 9);
    let written = summary.written.len();
    assert_eq!(
        written + summary.skipped.len(),
        9 * 3,
        "{:?}",
        summary.skipped
    );
    assert!(!previews.is_empty());
    // The output is a release: convert reads every sample back, and the annotations it
    // validates carry the requested angles.
    let pq2 = tempfile::tempdir().unwrap();
    let m = ingest::convert(&copts(out.path(), pq2.path()), &ctx, &|_| {}).unwrap();
    assert_eq!(
        m.converted, written,
        "skipped on reconversion: {}",
        m.skipped
    );
    let rows = ingest::read_dataset_samples(pq2.path()).unwrap();
    let original = ingest::read_dataset_samples(pq.path()).unwrap();
    for w in &summary.written {
        let new = rows.iter().find(|r| r.key == w.key).unwrap();
        let old = original.iter().find(|r| r.key == w.source).unwrap();
        match w.operation.as_str() {
            "roll" => assert!((new.roll_deg - old.roll_deg - w.change_deg).abs() < 1e-6),
            "flip" => assert!((new.yaw_deg + old.yaw_deg).abs() < 1e-6),
            "original" => assert_eq!(new.rt, old.rt),
            other => panic!("unexpected operation {other}"),
        }
    }
    // The same seed writes the same files.
    let again = tempfile::tempdir().unwrap();
    let aopts2 = AugmentOptions {
        output: again.path().to_path_buf(),
        ..aopts
    };
    arkit_data::augment::augment_dataset(pq.path(), topo, &aopts2, &|_| {}).unwrap();
    for w in &summary.written {
        let rel = arkit_core::ReleaseLayout::image_relative(
            if w.split == "test" {
                arkit_core::Split::Test
            } else {
                arkit_core::Split::Train
            },
            &w.key,
        );
        assert_eq!(
            std::fs::read(out.path().join(&rel)).unwrap(),
            std::fs::read(again.path().join(&rel)).unwrap()
        );
    }
}
