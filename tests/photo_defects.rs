//! `predict --image` against the photos users bring: a truncated JPEG, a WebP, a phone
//! photo with an EXIF orientation, a boxes file naming other photos, a read-only output
//! folder, and two photos with the same file name in two folders.

use crate::support::{run_tool as run, tool_ok as ok};
use serde_json::Value;
use std::path::{Path, PathBuf};

const TINY: &str = crate::support::TINY_MODEL;

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

/// A synthetic photo of one face (`synth --group-photo`), its boxes file and the box.
fn face_photo(dir: &Path, name: &str, seed: u64) -> (PathBuf, PathBuf, [f64; 4]) {
    std::fs::create_dir_all(dir).unwrap();
    let photo = dir.join(format!("{name}.jpg"));
    ok(&[
        "synth",
        "--group-photo",
        &s(&photo),
        "--faces",
        "1",
        "--size",
        "640x480",
        "--seed",
        &seed.to_string(),
    ]);
    let boxes = dir.join(format!("{name}.boxes.json"));
    let b: Vec<[f64; 4]> = serde_json::from_slice(&std::fs::read(&boxes).unwrap()).unwrap();
    (photo, boxes, b[0])
}

fn box_arg(b: [f64; 4]) -> String {
    b.map(|v| v.to_string()).join(" ")
}

/// The first face's R_t of a report.
fn first_rt(report: &Value) -> Vec<f64> {
    report["photos"][0]["faces"][0]["R_t"]
        .as_array()
        .unwrap_or_else(|| panic!("no pose: {report}"))
        .iter()
        .flat_map(|r| r.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()))
        .collect()
}

fn predict_one(photo: &Path, b: [f64; 4]) -> Value {
    let out = ok(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(photo),
        "--box",
        &box_arg(b),
    ]);
    serde_json::from_str(&out).unwrap()
}

#[test]
fn a_truncated_jpeg_is_refused_by_name_and_skipped_in_a_folder() {
    let dir = tempfile::tempdir().unwrap();
    let (photo, _, b) = face_photo(&dir.path().join("in"), "whole", 1);
    let bytes = std::fs::read(&photo).unwrap();
    let half = dir.path().join("in").join("half.jpg");
    std::fs::write(&half, &bytes[..bytes.len() / 2]).unwrap();
    // Given by name: refused (exit 1), the file and the problem named.
    let (code, _, stderr) = run(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&half),
        "--box",
        &box_arg(b),
    ]);
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("half.jpg") && stderr.contains("truncated"),
        "{stderr}"
    );
    // A corrupt one (a stray byte where a marker belongs) too.
    let mut corrupt = bytes.clone();
    corrupt[2] = 0x00;
    let bad = dir.path().join("corrupt.jpg");
    std::fs::write(&bad, &corrupt).unwrap();
    let (code, _, stderr) = run(&["predict", "--model", TINY, "--image", &s(&bad)]);
    assert_eq!(code, Some(1), "{stderr}");
    assert!(stderr.contains("corrupt.jpg"), "{stderr}");
    // Under a folder: reported and skipped, the whole photo still posed; --strict exits 1.
    let folder = s(&dir.path().join("in"));
    let (code, stdout, stderr) = run(&["predict", "--model", TINY, "--image", &folder]);
    assert_eq!(code, Some(0), "{stderr}");
    assert!(
        stderr.contains("half.jpg") && stderr.contains("truncated"),
        "{stderr}"
    );
    let r: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(r["summary"]["photos"], 2);
    assert_eq!(r["summary"]["skipped"], 1);
    let (code, _, _) = run(&["predict", "--model", TINY, "--image", &folder, "--strict"]);
    assert_eq!(code, Some(1));
}

#[test]
fn a_webp_photo_is_posed_as_the_same_pixels_in_a_png() {
    let dir = tempfile::tempdir().unwrap();
    let (photo, _, b) = face_photo(dir.path(), "face", 2);
    let pixels = image::open(&photo).unwrap().to_rgb8();
    let (png, webp) = (dir.path().join("face.png"), dir.path().join("face.webp"));
    pixels.save(&png).unwrap();
    let mut bytes = Vec::new();
    image::codecs::webp::WebPEncoder::new_lossless(&mut bytes)
        .encode(
            pixels.as_raw(),
            pixels.width(),
            pixels.height(),
            image::ExtendedColorType::Rgb8,
        )
        .unwrap();
    std::fs::write(&webp, &bytes).unwrap();
    let (a, w) = (predict_one(&png, b), predict_one(&webp, b));
    assert_eq!(first_rt(&a), first_rt(&w), "lossless WebP: the same pose");
    // A truncated WebP is refused by name.
    let cut = dir.path().join("cut.webp");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let (code, _, stderr) = run(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&cut),
        "--box",
        &box_arg(b),
    ]);
    assert_eq!(code, Some(1), "{stderr}");
    assert!(stderr.contains("cut.webp"), "{stderr}");
}

/// `jpeg` with an EXIF APP1 segment (big-endian TIFF, one IFD entry: Orientation)
/// inserted after its start-of-image marker.
fn with_exif_orientation(jpeg: &[u8], orientation: u16) -> Vec<u8> {
    let mut tiff = b"MM\x00\x2a\x00\x00\x00\x08".to_vec();
    tiff.extend(1u16.to_be_bytes()); // one entry
    tiff.extend(0x0112u16.to_be_bytes()); // Orientation
    tiff.extend(3u16.to_be_bytes()); // SHORT
    tiff.extend(1u32.to_be_bytes()); // one value
    tiff.extend(orientation.to_be_bytes());
    tiff.extend([0, 0]);
    tiff.extend(0u32.to_be_bytes()); // no next IFD
    let mut payload = b"Exif\x00\x00".to_vec();
    payload.extend(tiff);
    let mut out = jpeg[..2].to_vec();
    out.extend([0xFF, 0xE1]);
    out.extend(((payload.len() + 2) as u16).to_be_bytes());
    out.extend(payload);
    out.extend(&jpeg[2..]);
    out
}

#[test]
fn exif_orientation_6_is_turned_upright_before_anything_else() {
    let dir = tempfile::tempdir().unwrap();
    let (photo, _, b) = face_photo(dir.path(), "upright", 3);
    let upright = image::open(&photo).unwrap().to_rgb8();
    // As a phone stores it: the pixels turned a quarter counter-clockwise, with
    // orientation 6 ("turn 90 degrees clockwise to view").
    let stored = image::imageops::rotate270(&upright);
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 95)
        .encode_image(&stored)
        .unwrap();
    let phone = dir.path().join("phone.jpg");
    std::fs::write(&phone, with_exif_orientation(&jpeg, 6)).unwrap();
    // The same decoded pixels turned by hand, losslessly.
    let decoded = image::load_from_memory_with_format(&jpeg, image::ImageFormat::Jpeg)
        .unwrap()
        .to_rgb8();
    let by_hand = dir.path().join("by-hand.png");
    image::imageops::rotate90(&decoded).save(&by_hand).unwrap();

    // The box is in the upright photo's pixels, as the user sees it.
    let drawn = dir.path().join("drawn.jpg");
    let out = ok(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&phone),
        "--box",
        &box_arg(b),
        "--draw",
        &s(&drawn),
    ]);
    let phone_report: Value = serde_json::from_str(&out).unwrap();
    let p = &phone_report["photos"][0];
    assert_eq!(
        (p["width"].as_u64(), p["height"].as_u64()),
        (Some(640), Some(480))
    );
    assert_eq!(p["exif_orientation"], 6);
    let hand_report = predict_one(&by_hand, b);
    assert_eq!(
        first_rt(&phone_report),
        first_rt(&hand_report),
        "the same pose as the photo turned by hand"
    );
    // And the upright photo's pose is the truth's, roughly (the tiny model, 12 degrees).
    let truth: Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("upright.truth.json")).unwrap())
            .unwrap();
    for a in ["yaw", "pitch", "roll"] {
        let (x, y) = (
            p["faces"][0]["angles"][a].as_f64().unwrap(),
            truth["faces"][0]["angles"][a].as_f64().unwrap(),
        );
        assert!((x - y).abs() < 12.0, "{a}: {x} vs {y}");
    }
    // The drawing is upright: the upright photo's size.
    assert_eq!(
        image::open(&drawn).unwrap().to_rgb8().dimensions(),
        (640, 480)
    );
}

#[test]
fn boxes_that_name_no_given_photo_are_an_error_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let (photo, _, b) = face_photo(dir.path(), "mine", 4);
    let boxes = dir.path().join("boxes.json");
    std::fs::write(
        &boxes,
        serde_json::to_string(&serde_json::json!({"someone-else.jpg": [b], "mine.jpg": [b]}))
            .unwrap(),
    )
    .unwrap();
    let (code, _, stderr) = run(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&photo),
        "--boxes",
        &s(&boxes),
    ]);
    assert_ne!(code, Some(0), "{stderr}");
    assert!(stderr.contains("someone-else.jpg"), "{stderr}");
    // A CSV keyed by another photo, likewise.
    let csv = dir.path().join("boxes.csv");
    std::fs::write(
        &csv,
        format!(
            "image,x0,y0,x1,y1\nother.png,{}\n",
            b.map(|v| v.to_string()).join(",")
        ),
    )
    .unwrap();
    let (code, _, stderr) = run(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&photo),
        "--boxes",
        &s(&csv),
    ]);
    assert_ne!(code, Some(0), "{stderr}");
    assert!(stderr.contains("other.png"), "{stderr}");
    // A bare list of boxes with two photos: which photo is meant is unknown.
    let (other, _, _) = face_photo(dir.path(), "second", 5);
    let list = dir.path().join("list.json");
    std::fs::write(&list, serde_json::to_string(&vec![b]).unwrap()).unwrap();
    let (code, _, stderr) = run(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&photo),
        &s(&other),
        "--boxes",
        &s(&list),
    ]);
    assert_ne!(code, Some(0), "{stderr}");
    assert!(stderr.contains("list.json"), "{stderr}");
    // Keys that all match: fine.
    std::fs::write(
        &boxes,
        serde_json::to_string(&serde_json::json!({"mine.jpg": [b]})).unwrap(),
    )
    .unwrap();
    ok(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&photo),
        "--boxes",
        &s(&boxes),
    ]);
}

/// A folder this process cannot write in: a read-only copy of a temporary folder, or
/// (as root, who writes anywhere chmod allows) /sys. `None` when neither refuses.
fn read_only_folder(dir: &Path) -> Option<PathBuf> {
    use std::os::unix::fs::PermissionsExt;
    let ro = dir.join("read-only");
    std::fs::create_dir_all(&ro).unwrap();
    std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
    let probe = |d: &Path| std::fs::write(d.join(".probe"), b"x").is_err();
    if probe(&ro) {
        return Some(ro);
    }
    let _ = std::fs::remove_file(ro.join(".probe"));
    let sys = PathBuf::from("/sys");
    probe(&sys).then_some(sys)
}

#[test]
fn a_read_only_output_folder_is_named_by_the_users_path() {
    let dir = tempfile::tempdir().unwrap();
    let Some(ro) = read_only_folder(dir.path()) else {
        eprintln!("SKIPPED: no read-only folder here (root, and /sys writable)");
        return;
    };
    let (photo, _, b) = face_photo(&dir.path().join("in"), "face", 6);
    for (flag, name) in [
        ("--output", "poses.json"),
        ("--draw", "drawn.jpg"),
        ("--output", "poses.csv"),
    ] {
        let target = ro.join(name);
        let (code, _, stderr) = run(&[
            "predict",
            "--model",
            TINY,
            "--image",
            &s(&photo),
            "--box",
            &box_arg(b),
            flag,
            &s(&target),
        ]);
        assert_ne!(code, Some(0), "{stderr}");
        assert!(
            stderr.contains(&format!("{}:", target.display())) && !stderr.contains(".tmp-"),
            "{flag}: {stderr}"
        );
    }
}

#[test]
fn photos_with_one_file_name_in_two_folders_never_share_an_output() {
    let dir = tempfile::tempdir().unwrap();
    let (a, a_boxes, _) = face_photo(&dir.path().join("trip1"), "face", 7);
    let (b, b_boxes, _) = face_photo(&dir.path().join("trip2"), "face", 8);
    // Their boxes files out of the folders, so that each folder holds one photo.
    let (ab, bb) = (
        dir.path().join("a.boxes.json"),
        dir.path().join("b.boxes.json"),
    );
    std::fs::rename(&a_boxes, &ab).unwrap();
    std::fs::rename(&b_boxes, &bb).unwrap();
    for t in ["trip1", "trip2"] {
        std::fs::remove_file(dir.path().join(t).join("face.truth.json")).unwrap();
    }
    let boxes = dir.path().join("boxes.json");
    let la: Vec<[f64; 4]> = serde_json::from_slice(&std::fs::read(&ab).unwrap()).unwrap();
    let lb: Vec<[f64; 4]> = serde_json::from_slice(&std::fs::read(&bb).unwrap()).unwrap();
    std::fs::write(
        &boxes,
        serde_json::to_string(&serde_json::json!({s(&a): la, s(&b): lb})).unwrap(),
    )
    .unwrap();
    let (draw, crops) = (dir.path().join("drawn"), dir.path().join("crops"));
    for images in [
        vec![s(&dir.path().join("trip1")), s(&dir.path().join("trip2"))],
        vec![s(&a), s(&b)],
    ] {
        let _ = std::fs::remove_dir_all(&draw);
        let _ = std::fs::remove_dir_all(&crops);
        let mut args = vec!["predict", "--model", TINY, "--image"];
        args.extend(images.iter().map(String::as_str));
        let (bs, ds, cs) = (s(&boxes), s(&draw), s(&crops));
        args.extend(["--boxes", &bs, "--draw", &ds, "--dump-crops", &cs]);
        let report: Value = serde_json::from_str(&ok(&args)).unwrap();
        let mut written = Vec::new();
        for t in ["trip1", "trip2"] {
            let d = draw.join(t).join("face.jpg");
            let c = crops.join(t).join("face-face0.png");
            assert!(d.is_file() && c.is_file(), "{images:?}: {}", d.display());
            written.push((std::fs::read(d).unwrap(), std::fs::read(c).unwrap()));
        }
        assert_ne!(written[0].0, written[1].0, "two drawings");
        assert_ne!(written[0].1, written[1].1, "two crops");
        let crop_paths: Vec<&str> = (0..2)
            .map(|i| report["photos"][i]["faces"][0]["crop"].as_str().unwrap())
            .collect();
        assert_ne!(crop_paths[0], crop_paths[1]);
    }
    // Names that cannot be made unique (face.jpg and face.png in one folder): refused
    // before anything runs, both photos named.
    let png = dir.path().join("trip1").join("face.png");
    image::open(&a).unwrap().to_rgb8().save(&png).unwrap();
    let (code, _, stderr) = run(&[
        "predict",
        "--model",
        TINY,
        "--image",
        &s(&dir.path().join("trip1")),
        "--draw",
        &s(&draw),
    ]);
    assert_ne!(code, Some(0), "{stderr}");
    assert!(
        stderr.contains("face.jpg") && stderr.contains("face.png"),
        "{stderr}"
    );
}

#[test]
fn video_options_given_with_image_are_refused_by_name() {
    // Each of these shapes only a video's run; with --image it used to be accepted and
    // do nothing. It is refused before the photo is read (exit 2), naming the option
    // and --video; the photo need not exist.
    for (flag, value) in [
        ("--fps", Some("25")),
        ("--detect-every", Some("5")),
        ("--max-missed", Some("3")),
        ("--smooth-min-cutoff", Some("0.5")),
        ("--smooth-beta", Some("2")),
        ("--smooth-beta-translation", Some("5")),
        ("--no-smooth", None),
    ] {
        let mut args = vec![
            "predict",
            "--model",
            TINY,
            "--image",
            "no-such-photo.jpg",
            flag,
        ];
        args.extend(value);
        let (code, stdout, stderr) = run(&args);
        assert_eq!(code, Some(2), "{flag}: {stdout}{stderr}");
        assert!(
            stderr.contains(flag) && stderr.contains("--video"),
            "{flag}: the refusal names neither the option nor --video: {stderr}"
        );
    }
}
