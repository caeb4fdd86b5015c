//! `predict --image`: a photo's faces through the official demo's preprocessing, the
//! shipped tiny model and our PnP. Checked against `predict --dataset` on the same
//! sample (the same crop, the same pose, bit for bit), on a non-square group photo of
//! several faces of different sizes whose poses are known (`synth --group-photo`), on
//! a photo with no face, and against bad input.

use crate::support::tool_ok as ok;
use arkit_data::crop::{CropTransform, RuleSet};
use arkit_data::crop::{LandmarkExtent, official_box};
use arkit_data::picture::{DEMO_SIDE, DemoSquare, demo_crop};
use arkit_data::store::Dataset;
use serde_json::Value;
use std::path::{Path, PathBuf};

const TINY: &str = crate::support::TINY_MODEL;

/// `arkit-tool ARGS`: whether it succeeded, its standard output and error.
fn run(args: &[&str]) -> (bool, String, String) {
    let (code, stdout, stderr) = crate::support::run_tool(args);
    (code == Some(0), stdout, stderr)
}

fn refused(args: &[&str]) -> String {
    let (ok, stdout, stderr) = run(args);
    assert!(!ok, "{args:?} should fail: {stdout}");
    stderr
}

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

fn rt_of(face: &Value) -> [f64; 16] {
    let rows = face["R_t"].as_array().expect("R_t");
    let v: Vec<f64> = rows
        .iter()
        .flat_map(|r| r.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()))
        .collect();
    v.try_into().unwrap()
}

/// A one-sample synthetic release whose official box (the landmarks' extent, the 0.75
/// rule, truncated edges) is square with a side divisible by 3: then the face box
/// `centre -/+ side / 3` gives, by the demo's rule, exactly the official box's edges.
fn one_sample_with_a_demo_box(dir: &Path) -> (PathBuf, PathBuf, [f64; 4], CropTransform) {
    for seed in 0..200u64 {
        let (release, pq) = (
            dir.join(format!("release-{seed}")),
            dir.join(format!("pq-{seed}")),
        );
        ok(&[
            "synth",
            "--subjects",
            "1",
            "--images-per-subject",
            "1",
            "--seed",
            &seed.to_string(),
            "--output",
            &s(&release),
        ]);
        ok(&["convert", "--input", &s(&release), "--output", &s(&pq)]);
        let data = Dataset::open(&pq).unwrap();
        let sample = data.read_all_samples().unwrap().remove(0);
        let extent = LandmarkExtent::of(
            sample
                .landmarks_2d
                .chunks_exact(2)
                .map(|p| (p[0] as f64, p[1] as f64)),
        );
        let [l, t, r, b] = official_box(extent, None);
        let side = r - l;
        if side != b - t || side % 3.0 != 0.0 {
            continue;
        }
        let (cx, cy) = ((l + r) / 2.0, (t + b) / 2.0);
        let face = [
            cx - side / 3.0,
            cy - side / 3.0,
            cx + side / 3.0,
            cy + side / 3.0,
        ];
        let official = RuleSet::Official
            .crop_around_landmarks(&sample.landmarks_2d, 64)
            .unwrap();
        let image = data.image_path(&sample).unwrap();
        return (pq, image, face, official);
    }
    panic!("no seed in 0..200 gave a square official box divisible by 3");
}

#[test]
fn a_photo_gives_the_dataset_samples_crop_and_pose() {
    let dir = tempfile::tempdir().unwrap();
    let (pq, image, face, official) = one_sample_with_a_demo_box(dir.path());

    // The crop: the demo's rule on the face box is the official loader's crop, bit for bit.
    let photo = image::open(&image).unwrap().to_rgb8();
    let square = DemoSquare::of(photo.width(), photo.height(), DEMO_SIDE);
    assert_eq!(square.scale(), 1.0);
    let demo = demo_crop(square.box_to_square(face), 64).unwrap();
    assert_eq!(demo, official);
    let from_photo = demo.crop_image(&square.image(&photo));
    assert_eq!(from_photo, official.crop_image(&photo));

    // The pose: predict --dataset (official crop) and predict --image agree exactly.
    let pred = dir.path().join("pred.parquet");
    ok(&[
        "predict",
        "--model",
        TINY,
        "--dataset",
        &s(&pq),
        "--split",
        "all",
        "--crop",
        "official",
        "--output",
        &s(&pred),
    ]);
    let rows = arkit_data::store::read_predictions(&pred).unwrap();
    assert_eq!(rows.len(), 1);
    let expected = rows[0].rt.expect("a pose");
    let crops = dir.path().join("crops");
    let csv = dir.path().join("faces.csv");
    let face_box = face.map(|v| v.to_string()).join(" ");
    let args = [
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&image),
        "--box",
        &face_box,
        "--dump-crops",
        &s(&crops),
        "--output",
    ];
    ok(&[&args[..], &[&s(&csv)]].concat());
    // The CSV's numbers are Rust's shortest round-trip text: the pose's bits.
    let text = std::fs::read_to_string(&csv).unwrap();
    let row: Vec<&str> = text.lines().nth(1).unwrap().split(',').collect();
    assert_eq!(row[7], "ok");
    let rt: Vec<f64> = row[row.len() - 16..]
        .iter()
        .map(|v| v.parse().unwrap())
        .collect();
    assert_eq!(rt, expected.to_vec(), "the same pose, bit for bit");
    let json = dir.path().join("faces.json");
    ok(&[&args[..], &[&s(&json)]].concat());
    let report: Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let f = &report["photos"][0]["faces"][0];
    for (a, b) in rt_of(f).iter().zip(&expected) {
        assert!((a - b).abs() < 1e-15, "JSON's R_t {a} vs {b}");
    }
    // The crop the network was fed, as written by --dump-crops.
    let dumped = image::open(f["crop"].as_str().unwrap()).unwrap().to_rgb8();
    assert_eq!(dumped, from_photo);
}

#[test]
fn a_group_photo_of_faces_of_several_sizes_and_a_photo_with_none() {
    let dir = tempfile::tempdir().unwrap();
    let photo = dir.path().join("group.jpg");
    ok(&[
        "synth",
        "--group-photo",
        &s(&photo),
        "--faces",
        "3",
        "--size",
        "1280x720",
        "--seed",
        "1",
    ]);
    let truth: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("group.truth.json")).unwrap())
            .unwrap();
    let boxes = dir.path().join("group.boxes.json");
    let drawn = dir.path().join("drawn.jpg");
    let csv = dir.path().join("faces.csv");
    let json = dir.path().join("faces.json");
    ok(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&photo),
        "--boxes",
        &s(&boxes),
        "--draw",
        &s(&drawn),
        "--output",
        &s(&csv),
    ]);
    ok(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&photo),
        "--boxes",
        &s(&boxes),
        "--vertices",
        "--output",
        &s(&json),
    ]);
    let report: Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let faces = report["photos"][0]["faces"].as_array().unwrap();
    assert_eq!(faces.len(), 3);
    let mut widths = Vec::new();
    for (f, t) in faces.iter().zip(truth["faces"].as_array().unwrap()) {
        assert_eq!(f["status"], "ok");
        assert_eq!(f["box"], t["box"]);
        let b: Vec<f64> = serde_json::from_value(f["box"].clone()).unwrap();
        widths.push(b[2] - b[0]);
        // The shipped tiny model on faces it never saw, at three sizes: each angle within
        // 12 degrees, the depth within 20 % (the demo's camera is the photo's here).
        for a in ["yaw", "pitch", "roll"] {
            let (p, q) = (
                f["angles"][a].as_f64().unwrap(),
                t["angles"][a].as_f64().unwrap(),
            );
            assert!((p - q).abs() < 12.0, "{a}: {p} vs {q}");
        }
        let (pz, tz) = (
            f["translation_m"][2].as_f64().unwrap(),
            t["translation_m"][2].as_f64().unwrap(),
        );
        assert!(((pz - tz) / tz).abs() < 0.2, "depth {pz} vs {tz}");
        assert_eq!(f["vertices_m"].as_array().unwrap().len(), 1220);
        assert!(f["inliers"].as_u64().unwrap() >= 100);
    }
    // Different sizes: the largest face at least 1.5 times the smallest.
    let (lo, hi) = widths
        .iter()
        .fold((f64::MAX, 0f64), |(a, b), w| (a.min(*w), b.max(*w)));
    assert!(hi > 1.5 * lo, "{widths:?}");
    // The CSV has one row per face, with the JSON's numbers.
    let text = std::fs::read_to_string(&csv).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 4);
    assert!(lines[0].starts_with("image,face,boxes_from,x0,y0,x1,y1,status,yaw,pitch,roll"));
    let yaw: f64 = lines[1].split(',').nth(8).unwrap().parse().unwrap();
    assert!((yaw - faces[0]["angles"]["yaw"].as_f64().unwrap()).abs() < 1e-12);
    // The drawing is the photo's size, and differs from the photo where the faces are.
    let (a, b) = (
        image::open(&photo).unwrap().to_rgb8(),
        image::open(&drawn).unwrap().to_rgb8(),
    );
    assert_eq!(a.dimensions(), b.dimensions());
    let changed = a
        .pixels()
        .zip(b.pixels())
        .filter(|(p, q)| p.0.iter().zip(q.0).any(|(x, y)| x.abs_diff(y) > 60));
    assert!(changed.count() > 2000, "the meshes and boxes are drawn");

    // A photo with no face: the detector says so; nothing fails.
    let empty = dir.path().join("empty.png");
    image::RgbImage::from_fn(640, 360, |x, y| {
        image::Rgb([(x / 3) as u8, (y / 2) as u8, 90])
    })
    .save(&empty)
    .unwrap();
    let (ok_, stdout, stderr) = run(&["predict", "--model", TINY, "--image", &s(&empty)]);
    assert!(ok_, "{stderr}");
    assert!(stderr.contains("no face found"), "{stderr}");
    let report: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(report["photos"][0]["faces"].as_array().unwrap().len(), 0);
    assert_eq!(report["photos"][0]["boxes_from"], "detector");

    // Another convention's angles: 6DRepNet's order is pitch, yaw, roll.
    let out = ok(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&photo),
        "--boxes",
        &s(&boxes),
        "--angles",
        "6drepnet",
    ]);
    let r: Value = serde_json::from_str(&out).unwrap();
    assert_eq!(r["angles"]["order"][0], "pitch");
    assert!(r["photos"][0]["faces"][0]["angles"]["pitch"].is_number());
}

#[test]
fn bad_input_is_refused_by_name_and_one_bad_photo_is_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let photo = dir.path().join("photos").join("a.png");
    std::fs::create_dir_all(photo.parent().unwrap()).unwrap();
    image::RgbImage::from_pixel(300, 200, image::Rgb([100, 90, 80]))
        .save(&photo)
        .unwrap();
    let p = s(&photo);
    // A box outside the photo, an empty box, a malformed one.
    let e = refused(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &p,
        "--box",
        "400 10 500 90",
    ]);
    assert!(e.contains("outside the 300x200 photo"), "{e}");
    let e = refused(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &p,
        "--box",
        "50 50 50 90",
    ]);
    assert!(e.contains("x0 < x1"), "{e}");
    let e = refused(&["predict", "--model", TINY, "--image", &p, "--box", "1 2 3"]);
    assert!(e.contains("four numbers"), "{e}");
    // Photo-only options without --image, and --image without a model.
    let e = refused(&["predict", "--oracle", "--image", &p]);
    assert!(e.contains("--model"), "{e}");
    let e = refused(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &p,
        "--focal-px",
        "800",
        "--fov-deg",
        "60",
    ]);
    assert!(e.contains("--focal-px"), "{e}");
    // An unreadable photo among good ones is reported and skipped; --strict fails.
    let bad = dir.path().join("photos").join("b.jpg");
    std::fs::write(&bad, b"not a jpeg at all").unwrap();
    let folder = s(photo.parent().unwrap());
    let (ok_, stdout, stderr) = run(&["predict", "--model", TINY, "--image", &folder]);
    assert!(ok_, "{stderr}");
    assert!(stderr.contains("b.jpg"), "{stderr}");
    let r: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(r["summary"]["photos"], 2);
    assert_eq!(r["summary"]["skipped"], 1);
    let (ok_, _, _) = run(&["predict", "--model", TINY, "--image", &folder, "--strict"]);
    assert!(!ok_);
    // A huge image (its header claims 40000 x 40000) is refused from its header.
    let huge = dir.path().join("huge.png");
    std::fs::write(&huge, crate::support::png_bomb::png_bomb(40_000)).unwrap();
    let (_, stdout, stderr) = run(&["predict", "--model", TINY, "--image", &s(&huge)]);
    let r: Value = serde_json::from_str(&stdout).unwrap();
    assert!(
        r["photos"][0]["error"]
            .as_str()
            .unwrap()
            .contains("huge.png"),
        "{stderr}"
    );
    assert!(stderr.contains("huge.png"), "{stderr}");
    // Weights of another configuration: named, not loaded.
    let other = dir.path().join("other-model");
    std::fs::create_dir_all(&other).unwrap();
    for f in ["model.safetensors", "perspnet.json"] {
        std::fs::copy(Path::new(TINY).join(f), other.join(f)).unwrap();
    }
    let cfg = std::fs::read_to_string(other.join("perspnet.json")).unwrap();
    std::fs::write(
        other.join("perspnet.json"),
        cfg.replacen("\"fc_channels\": 64", "\"fc_channels\": 96", 1),
    )
    .unwrap();
    let e = refused(&[
        "predict",
        "--model",
        &s(&other),
        "--image",
        &p,
        "--box",
        "10 10 90 90",
    ]);
    assert!(
        e.contains("model.safetensors") || e.contains("shape"),
        "{e}"
    );
    // A boxes file that is not one.
    let boxes = dir.path().join("boxes.csv");
    std::fs::write(&boxes, "photo,left,top\n").unwrap();
    let e = refused(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &p,
        "--boxes",
        &s(&boxes),
    ]);
    assert!(
        e.contains("boxes.csv") && e.contains("image,x0,y0,x1,y1"),
        "{e}"
    );
}
