//! `convert --format biwi`: a synthetic BIWI-shaped folder (known poses, a known head
//! mesh, calibration), written as the database is distributed, converted, and checked:
//! the pose that went in comes out to 1e-9, the mesh lands where the written image shows
//! the head, frames without a pose are listed, bad files are reported.

use crate::support::biwi_writer::*;
use crate::support::png_bomb::png_bomb;
use crate::support::tool;
use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_core::release::{self, ReleaseLayout, SampleKey, Split};
use arkit_data::ingest::biwi::{self, BIWI_LANDMARKS, HEAD_ORIGIN_SHIFT_M};
use nalgebra::{Matrix3, Rotation3, Vector3};
use serde_json::Value;
use std::path::Path;
use std::process::Command;

fn key(seq: &str, n: &str) -> SampleKey {
    SampleKey {
        subject_id: seq.into(),
        facial_action: "biwi".into(),
        img_id: n.into(),
    }
}

#[test]
fn poses_and_meshes_round_trip_and_land_on_the_head() {
    let dir = tempfile::tempdir().unwrap();
    let (hpdb, staging) = (dir.path().join("hpdb"), dir.path().join("staging"));
    write_hpdb(&hpdb);
    let (summary, topology) = biwi::stage(&hpdb, &staging, 800, &|| {}).unwrap();
    assert_eq!(summary.sequences, 2);
    assert_eq!(summary.frames_found, 7);
    assert_eq!(summary.staged, 6, "{:?}", summary.problems);
    assert_eq!(
        summary.without_pose,
        vec!["01/frame_00009_rgb.png".to_string()]
    );
    assert_eq!(topology.vertex_count, 6918);
    assert_eq!(topology.landmarks, BIWI_LANDMARKS.to_vec());
    let layout = ReleaseLayout::new(&staging);
    let head = release_head();
    let camera = Camera::release(800, 800);
    for seq in ["01", "02"] {
        for (i, pose) in poses().iter().enumerate() {
            let k = key(seq, &format!("{:05}", 3 + i));
            let info =
                release::read_info_with_vertex_count(&layout.info_path(Split::Test, &k), 6918)
                    .unwrap();
            let err = info
                .rt
                .iter()
                .zip(pose.to_release_rt())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            assert!(err < 1e-9, "{k}: R_t off by {err:e}");
            // The subject's own mesh, in metres and the release's axes.
            let verr = info
                .verts
                .iter()
                .zip(&head)
                .map(|(a, b)| (a.cast::<f64>() - b).norm())
                .fold(0.0, f64::max);
            assert!(verr < 1e-6, "{k}: mesh off by {verr}");
            // The written image shows the head where the mesh projects.
            let img = image::open(layout.image_path(Split::Test, &k))
                .unwrap()
                .to_rgb8();
            assert_eq!((img.width(), img.height()), (800, 800));
            let shown: Vec<bool> = img.pixels().map(|p| p[0] > 150).collect();
            let projected = silhouette(&camera, pose, &head);
            let inter = shown
                .iter()
                .zip(&projected)
                .filter(|(a, b)| **a && **b)
                .count();
            let union = shown
                .iter()
                .zip(&projected)
                .filter(|(a, b)| **a || **b)
                .count();
            let iou = inter as f64 / union as f64;
            assert!(inter > 3000, "head too small: {inter} px");
            eprintln!("{k}: IoU {iou:.4}, R_t error {err:.1e}");
            assert!(iou > 0.95, "{k}: IoU {iou}");
        }
    }
}

#[test]
fn the_official_composition_in_row_vector_form_agrees() {
    // The official code: R_t_cv = R_t_raw @ R_t_calibration (row form), then
    // yaw and roll negated, ty and tz negated, then center_mat @ R_t_gl.
    let pose = poses()[1];
    let text = pose_text(&pose);
    let fp = biwi::FramePose::parse(&text, Path::new("p.txt")).unwrap();
    let cal = biwi::Calibration::parse(&cal_text("0 0 0 0"), Path::new("rgb.cal")).unwrap();
    let row = |r: &Matrix3<f64>, t: &Vector3<f64>| {
        let mut m = nalgebra::Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&r.transpose());
        m[(3, 0)] = t.x;
        m[(3, 1)] = t.y;
        m[(3, 2)] = t.z;
        m
    };
    let mut rt_cv = row(&fp.rotation, &fp.translation_mm) * row(&cal.rotation, &cal.translation_mm);
    for c in 0..3 {
        rt_cv[(3, c)] /= 1000.0;
    }
    let r_cv = Rotation3::from_matrix(&rt_cv.fixed_view::<3, 3>(0, 0).transpose().into_owned());
    let e = EulerAngles::from_rotation(&r_cv);
    let r_gl = EulerAngles::new(-e.yaw_deg, e.pitch_deg, -e.roll_deg).to_rotation();
    let mut rt_gl = row(
        r_gl.matrix(),
        &Vector3::new(rt_cv[(3, 0)], -rt_cv[(3, 1)], -rt_cv[(3, 2)]),
    );
    let c = Vector3::from(HEAD_ORIGIN_SHIFT_M);
    rt_gl = row(&Matrix3::identity(), &c) * rt_gl;
    let ours = biwi::release_pose(&fp, &cal).release_matrix();
    assert!((ours - rt_gl).abs().max() < 1e-9, "{ours} vs {rt_gl}");
}

#[test]
fn bad_files_are_reported_and_the_rest_converted() {
    let dir = tempfile::tempdir().unwrap();
    let hpdb = dir.path().join("hpdb");
    write_hpdb(&hpdb);
    std::fs::write(
        hpdb.join("01/frame_00004_pose.txt"),
        "1 0 0\n0 2 0\n0 0 1\n\n0 0 900\n",
    )
    .unwrap();
    std::fs::write(hpdb.join("01/frame_00005_rgb.png"), b"not a png").unwrap();
    std::fs::write(hpdb.join("02/rgb.cal"), cal_text("0.1 0 0 0")).unwrap();
    let (summary, _) = biwi::stage(&hpdb, &dir.path().join("s"), 400, &|| {}).unwrap();
    assert_eq!(summary.staged, 1, "{:#?}", summary.problems);
    let why = |f: &str| {
        summary
            .problems
            .iter()
            .find(|p| p.file == f)
            .unwrap_or_else(|| panic!("{f}: {:#?}", summary.problems))
            .reason
            .clone()
    };
    assert!(why("01/frame_00004_pose.txt").contains("not a rotation"));
    assert!(why("01/frame_00005_rgb.png").contains("not a PNG, JPEG or WebP"));
    assert!(why("02/rgb.cal").contains("distortion"));
    // A folder that is not BIWI's is a clear error naming it.
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let err = biwi::stage(&empty, &dir.path().join("t"), 400, &|| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("empty") && err.contains("hpdb"), "{err}");
}

#[test]
fn cli_convert_biwi_then_eval_scores_add_on_the_subjects_mesh() {
    let dir = tempfile::tempdir().unwrap();
    let (hpdb, pq) = (dir.path().join("hpdb"), dir.path().join("pq"));
    write_hpdb(&hpdb);
    let out = tool()
        .args(["convert", "--format", "biwi", "--json", "--input"])
        .arg(&hpdb)
        .arg("--output")
        .arg(&pq)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["biwi"]["staged"], 6);
    assert_eq!(v["biwi"]["without_pose"][0], "01/frame_00009_rgb.png");
    assert_eq!(v["manifest"]["converted"], 6);
    assert_eq!(v["manifest"]["skipped"], 0);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("no pose file for 01/frame_00009_rgb.png"),
        "{stderr}"
    );
    // --strict: the image without a pose makes the run exit 1 (after converting the
    // rest); --shard is refused with the reason.
    let out = tool()
        .args(["convert", "--format", "biwi", "--strict", "--input"])
        .arg(&hpdb)
        .arg("--output")
        .arg(dir.path().join("pq-strict"))
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(1),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(dir.path().join("pq-strict/dataset.json").exists());
    let out = tool()
        .args(["convert", "--format", "biwi", "--shard", "0/2", "--input"])
        .arg(&hpdb)
        .arg("--output")
        .arg(dir.path().join("pq-shard"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--shard"));
    let samples = arkit_data::ingest::read_dataset_samples(&pq).unwrap();
    assert_eq!(samples.len(), 6);
    assert!(samples.iter().all(|s| s.verts.len() == 6918 * 3));

    // split by subject: one sequence held out, none in two splits.
    let out = tool()
        .args(["split", "--test-subjects", "1", "--json", "--dataset"])
        .arg(&pq)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut by_subject: std::collections::BTreeMap<String, std::collections::BTreeSet<String>> =
        Default::default();
    for sp in ["train", "test"] {
        let list = pq
            .join("splits/ARKitFace_list/list")
            .join(format!("ARKitFace_{sp}.csv"));
        for r in release::read_list(&list).unwrap() {
            by_subject
                .entry(r.key.subject_id.clone())
                .or_default()
                .insert(sp.to_string());
        }
    }
    assert_eq!(by_subject.len(), 2);
    assert!(by_subject.values().all(|s| s.len() == 1), "{by_subject:?}");

    // predict (the train split's mean pose) then eval: the paper's table layout.
    let mean = dir.path().join("mean.parquet");
    let out = tool()
        .args(["predict", "--mean-pose", "--dataset"])
        .arg(&pq)
        .arg("--output")
        .arg(&mean)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = tool()
        .args(["eval", "--dataset"])
        .arg(&pq)
        .arg("--predictions")
        .arg(&mean)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let table = String::from_utf8_lossy(&out.stdout);
    eprintln!("{table}");
    for col in [
        "yaw", "pitch", "roll", "MAE_r", "tx", "ty", "tz", "MAE_t", "ADD",
    ] {
        assert!(table.contains(col), "{col} missing: {table}");
    }
    assert!(table.starts_with("3 samples"), "{table}");

    // ADD on the subject's own mesh: every prediction is the truth turned by 5 degrees
    // about the head's origin; ADD must be the mean over the 6,918 head vertices of
    // |(R_d - I) v|. One frame is excluded.
    let turn = Rotation3::from_axis_angle(&Vector3::y_axis(), 5f64.to_radians());
    let rows: Vec<arkit_core::PredictionRecord> = samples
        .iter()
        .map(|s| {
            let gt = Pose::from_release_rt(&s.rt).unwrap();
            let p = Pose::new(gt.rotation() * turn, gt.translation_m());
            arkit_core::PredictionRecord {
                key: s.key.clone(),
                rt: Some(p.to_release_rt()),
                verts: None,
                mask_rle: None,
            }
        })
        .collect();
    let preds = dir.path().join("turned.parquet");
    arkit_data::store::write_predictions(&preds, &rows).unwrap();
    let exclude = dir.path().join("exclude.csv");
    std::fs::write(
        &exclude,
        "subject_id,facial_action,img_id\n01,biwi,00004\n01,biwi,99999\n",
    )
    .unwrap();
    let report = dir.path().join("report");
    let out = tool()
        .args(["eval", "--split", "all", "--json", "--report"])
        .arg(&report)
        .arg("--dataset")
        .arg(&pq)
        .arg("--predictions")
        .arg(&preds)
        .arg("--exclude")
        .arg(&exclude)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["summary"]["samples"], 5);
    assert_eq!(v["problems"]["excluded"], 1);
    assert_eq!(v["problems"]["exclude_unknown"], 1);
    assert_eq!(v["problems"]["unknown"], 0);
    // The report draws BIWI heads as points (not with another mesh's triangles).
    assert!(image::open(report.join("worst.png")).is_ok());
    let head = release_head();
    let want: f64 = head
        .iter()
        .map(|p| (turn * p.coords - p.coords).norm())
        .sum::<f64>()
        / head.len() as f64
        * 1000.0;
    let got = v["summary"]["add_mm"].as_f64().unwrap();
    assert!(
        (got - want).abs() < 1e-3,
        "ADD {got} mm, expected {want} mm"
    );
    // The ADD over a random 1,220 x 3 array (the official BIWI loader's `model`) would be
    // another number; ours is the head's.
    assert!(want > 1.0);
}

#[test]
fn a_resized_frame_and_an_unreadable_sequence_folder_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    let hpdb = dir.path().join("hpdb");
    write_hpdb(&hpdb);
    // A frame resized to 320x240 while rgb.cal says 640x480: its intrinsics no longer
    // match, so its image would not match its pose.
    let f = hpdb.join("01/frame_00004_rgb.png");
    image::open(&f)
        .unwrap()
        .resize_exact(320, 240, image::imageops::FilterType::Triangle)
        .save(&f)
        .unwrap();
    // A sequence folder that is a symbolic link to itself (a loop).
    std::os::unix::fs::symlink("03", hpdb.join("03")).unwrap();
    let (summary, _) = biwi::stage(&hpdb, &dir.path().join("s"), 400, &|| {}).unwrap();
    assert_eq!(summary.staged, 5, "{:#?}", summary.problems);
    let why = |f: &str| {
        summary
            .problems
            .iter()
            .find(|p| p.file == f)
            .unwrap_or_else(|| panic!("{f}: {:#?}", summary.problems))
            .reason
            .clone()
    };
    let r = why("01/frame_00004_rgb.png");
    assert!(
        r.contains("320x240") && r.contains("640x480") && r.contains("rgb.cal"),
        "{r}"
    );
    let r = why("03");
    assert!(
        r.contains("symbolic link") && r.contains("cannot be read"),
        "{r}"
    );

    // Without the image size line, the principal point (320, 240.5) on the border of a
    // 320x240 frame refuses it all the same.
    let cal = cal_text("0 0 0 0").replace("\n640 480\n", "\n");
    let parsed = biwi::Calibration::parse(&cal, Path::new("rgb.cal")).unwrap();
    assert_eq!(parsed.image_size, None);
    assert!(parsed.check_frame_size(640, 480).is_ok());
    let e = parsed.check_frame_size(320, 240).unwrap_err();
    assert!(
        e.contains("principal point") && e.contains("320x240"),
        "{e}"
    );
    let with = biwi::Calibration::parse(&cal_text("0 0 0 0"), Path::new("rgb.cal")).unwrap();
    assert_eq!(with.image_size, Some((640, 480)));
    // A malformed size line is an error naming it.
    let bad = cal_text("0 0 0 0").replace("\n640 480\n", "\n640.5 480\n");
    let e = biwi::Calibration::parse(&bad, Path::new("rgb.cal"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("image size"), "{e}");
}

#[test]
fn the_png_bomb_generator_makes_a_png_that_decodes_to_zeros() {
    // The generator checked at a small size by an independent decoder (the image crate).
    let img = image::load_from_memory(&png_bomb(300)).unwrap();
    assert_eq!((img.width(), img.height()), (300, 300));
    assert_eq!(img.color(), image::ColorType::L16);
    assert!(img.into_luma16().pixels().all(|p| p.0 == [0]));
}

/// Peak resident memory (KiB) of a finished child, from `/usr/bin/time -v`'s report.
fn peak_rss_kib(stderr: &str) -> u64 {
    stderr
        .lines()
        .find_map(|l| {
            l.trim()
                .strip_prefix("Maximum resident set size (kbytes): ")
        })
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no peak RSS in: {stderr}"))
}

#[test]
fn png_bombs_are_refused_before_decoding_in_bounded_memory() {
    let dir = tempfile::tempdir().unwrap();
    let hpdb = dir.path().join("hpdb");
    write_hpdb(&hpdb);
    // Two 16000x16000 16-bit PNGs of a few MB, in place of two frames.
    let bomb = png_bomb(16000);
    assert!(bomb.len() < 4 << 20, "{}", bomb.len());
    std::fs::write(hpdb.join("01/frame_00004_rgb.png"), &bomb).unwrap();
    std::fs::write(hpdb.join("02/frame_00005_rgb.png"), &bomb).unwrap();
    // In sequence 02, rgb.cal claims the bomb's size (principal point at its centre), so
    // that frame passes the size check and meets the decoded-size limit instead.
    let cal = cal_text("0 0 0 0")
        .replace("\n640 480\n", "\n16000 16000\n")
        .replacen(" 0 320 \n", " 0 8000 \n", 1)
        .replacen(" 240.5 \n", " 8000 \n", 1);
    assert!(cal.contains("8000"), "{cal}");
    std::fs::write(hpdb.join("02/rgb.cal"), cal).unwrap();
    let out = Command::new("/usr/bin/time")
        .arg("-v")
        .arg(env!("CARGO_BIN_EXE_arkit-tool"))
        .args(["convert", "--format", "biwi", "--json", "--input"])
        .arg(&hpdb)
        .arg("--output")
        .arg(dir.path().join("pq"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let problems = v["biwi"]["problems"].as_array().unwrap();
    let why = |f: &str| {
        problems
            .iter()
            .find(|p| p["file"] == f)
            .unwrap_or_else(|| panic!("{f}: {problems:#?}"))["reason"]
            .as_str()
            .unwrap()
            .to_string()
    };
    let r = why("01/frame_00004_rgb.png");
    assert!(r.contains("16000x16000") && r.contains("640x480"), "{r}");
    let r = why("02/frame_00005_rgb.png");
    assert!(
        r.contains("16000x16000 16-bit grey") && r.contains("refused before decoding"),
        "{r}"
    );
    // Before: a 2.4 GiB peak. Now the whole run stays within a few hundred MiB.
    let peak = peak_rss_kib(&stderr);
    eprintln!("peak RSS of convert --format biwi with two PNG bombs: {peak} KiB");
    assert!(peak < 300 * 1024, "peak RSS {peak} KiB");
}
