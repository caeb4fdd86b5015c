//! `import-arkit`: a synthetic ARKit capture (a known scene) written as ARKit gives it,
//! imported, and checked: the pose comes out to 1e-9, the mesh projects where the
//! written image shows the face, `convert` reads the output with nothing skipped, and
//! every kind of bad frame is reported with its file and reason and skipped.

use crate::support::tool;
use arkit_core::VisibilityBuffer;
use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_core::release::{self, ReleaseLayout, Split};
use arkit_data::ingest::{
    self, ConvertOptions, ImportOptions, InterfaceOrientation, ValidationContext,
};
use image::{Rgb, RgbImage};
use nalgebra::{Matrix3, Matrix4, Point3, Rotation3, Vector3};
use serde_json::{Value, json};
use std::path::Path;

/// A known scene: the face's pose in the camera of the written (turned) image, the
/// camera in the world, the capture's intrinsics and resolution, the orientation.
#[derive(Clone, Debug)]
pub(crate) struct Scene {
    pose: Pose,
    camera_world: Matrix4<f64>,
    k: Matrix3<f64>,
    resolution: (u32, u32),
    orientation: InterfaceOrientation,
}

fn builtin() -> &'static arkit_data::mesh::SyntheticFace {
    arkit_data::mesh::builtin()
}

fn mesh() -> Vec<Point3<f64>> {
    builtin()
        .topology
        .template
        .as_ref()
        .unwrap()
        .iter()
        .map(|p| p.cast())
        .collect()
}

pub(crate) fn scene(orientation: InterfaceOrientation, yaw: f64, pitch: f64, roll: f64) -> Scene {
    let camera_world = Pose::from_euler(
        EulerAngles::new(37.0, -12.0, 4.0),
        Vector3::new(0.4, 1.3, -0.7),
    )
    .face_to_camera
    .to_homogeneous();
    Scene {
        pose: Pose::from_euler(
            EulerAngles::new(yaw, pitch, roll),
            Vector3::new(0.015, -0.01, -0.42),
        ),
        camera_world,
        k: Matrix3::new(500.0, 0.0, 315.2, 0.0, 505.0, 243.9, 0.0, 0.0, 1.0),
        resolution: (640, 480),
        orientation,
    }
}

fn o4(o: InterfaceOrientation) -> Matrix4<f64> {
    let mut m = Matrix4::identity();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&o.rotation());
    m
}

/// The face's pose in the sensor (captured) camera: `O * pose`.
fn sensor_pose(s: &Scene) -> Pose {
    let o = s.orientation.rotation();
    Pose::new(
        Rotation3::from_matrix_unchecked(o * s.pose.rotation().matrix()),
        o * s.pose.translation_m(),
    )
}

/// The capture's camera as a row-vector projection of our convention (pixel centres at
/// +0.5; ARKit's K is read in OpenCV's, centres at integers).
fn capture_camera(s: &Scene) -> Camera {
    let (w, h) = (s.resolution.0 as f64, s.resolution.1 as f64);
    let (cx, cy) = (s.k[(0, 2)] + 0.5, s.k[(1, 2)] + 0.5);
    let mut p = Camera::release_projection();
    p[(0, 0)] = 2.0 * s.k[(0, 0)] / w;
    p[(1, 1)] = 2.0 * s.k[(1, 1)] / h;
    p[(2, 0)] = 1.0 - 2.0 * cx / w;
    p[(2, 1)] = 2.0 * cy / h - 1.0;
    Camera::new(p, s.resolution.0, s.resolution.1).unwrap()
}

/// The face's silhouette (light) on a dark gradient, as the capture camera sees it.
fn draw(camera: &Camera, pose: &Pose) -> RgbImage {
    let (w, h) = (camera.width, camera.height);
    let verts: Vec<Point3<f32>> = builtin().topology.template.clone().unwrap();
    let screen = camera.project_to_screen(pose, &verts);
    let mut vis = VisibilityBuffer::new(w, h);
    vis.rasterize_mesh(&screen, &builtin().topology.triangles)
        .unwrap();
    RgbImage::from_fn(w, h, |x, y| {
        if vis.triangle[vis.index(x, y)] != u32::MAX {
            Rgb([235, 225, 215])
        } else {
            Rgb([(x * 90 / w) as u8, (y * 90 / h) as u8, 40])
        }
    })
}

fn columns4(m: &Matrix4<f64>) -> Value {
    json!(
        (0..4)
            .map(|c| (0..4).map(|r| m[(r, c)]).collect::<Vec<_>>())
            .collect::<Vec<_>>()
    )
}

fn columns3(m: &Matrix3<f64>) -> Value {
    json!(
        (0..3)
            .map(|c| (0..3).map(|r| m[(r, c)]).collect::<Vec<_>>())
            .collect::<Vec<_>>()
    )
}

/// The frame's JSON as an ARKit app would write it: `A = C O P`.
fn frame_json(s: &Scene) -> Value {
    let anchor = s.camera_world * o4(s.orientation) * s.pose.face_to_camera.to_homogeneous();
    json!({
        "face_anchor_transform": columns4(&anchor),
        "camera_transform": columns4(&s.camera_world),
        "camera_intrinsics": columns3(&s.k),
        "image_resolution": [s.resolution.0, s.resolution.1],
        "interface_orientation": s.orientation.name(),
        "vertices": mesh().iter().map(|p| vec![p.x, p.y, p.z]).collect::<Vec<_>>(),
    })
}

/// Writes `NAME.json` and `NAME.png` of a scene into `dir`.
pub(crate) fn write_frame(dir: &Path, name: &str, s: &Scene) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(
        dir.join(format!("{name}.json")),
        serde_json::to_string(&frame_json(s)).unwrap(),
    )
    .unwrap();
    draw(&capture_camera(s), &sensor_pose(s))
        .save(dir.join(format!("{name}.png")))
        .unwrap();
}

fn options(input: &Path, output: &Path) -> ImportOptions {
    ImportOptions {
        input: input.to_path_buf(),
        output: output.to_path_buf(),
        subject: Some("me".into()),
        split: Split::Test,
        size: None,
        jpeg_quality: 95,
        overwrite: false,
        systematic_window: arkit_data::ingest::SYSTEMATIC_WINDOW,
    }
}

const ORIENTATIONS: [InterfaceOrientation; 4] = [
    InterfaceOrientation::LandscapeRight,
    InterfaceOrientation::Portrait,
    InterfaceOrientation::LandscapeLeft,
    InterfaceOrientation::PortraitUpsideDown,
];

fn mat(m: &[f64; 16]) -> Matrix4<f64> {
    Matrix4::from_row_slice(m)
}

fn iou(a: &[bool], b: &[bool]) -> f64 {
    let inter = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let union = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    inter as f64 / union as f64
}

#[test]
fn pose_in_is_r_t_out_and_the_mesh_lands_on_the_face() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("cap"), dir.path().join("rel"));
    let scenes: Vec<Scene> = ORIENTATIONS
        .iter()
        .enumerate()
        .map(|(i, &o)| {
            scene(
                o,
                -25.0 + 15.0 * i as f64,
                8.0 - 6.0 * i as f64,
                3.0 * i as f64,
            )
        })
        .collect();
    for (i, s) in scenes.iter().enumerate() {
        write_frame(&input, &format!("frame_{i:03}"), s);
    }
    let summary = ingest::import_capture(&options(&input, &output), &|| {}).unwrap();
    assert_eq!(summary.imported, 4, "{:?}", summary.skipped);
    let layout = ReleaseLayout::new(&output);
    let keys = release::read_list(&layout.list_path(Split::Test)).unwrap();
    assert_eq!(keys.len(), 4);
    let tris = &builtin().topology.triangles;
    for (row, s) in keys.iter().zip(&scenes) {
        assert_eq!(row.key.subject_id, "me");
        assert_eq!(row.key.facial_action, "capture");
        let info = release::read_info(&layout.info_path(Split::Test, &row.key)).unwrap();
        // The pose that went in comes out.
        let want = s.pose.to_release_rt();
        let err = info
            .rt
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-9, "{:?}: R_t off by {err:e}", s.orientation);
        // The release's identity: faceAnchortransform = R_t @ cameratransform.
        let lhs = mat(&info.face_anchor_transform.unwrap());
        let rhs = mat(&info.rt) * mat(&info.camera_transform.unwrap());
        assert!((lhs - rhs).abs().max() < 1e-9, "{:?}", s.orientation);
        // The written camera is the release's.
        assert_eq!(
            mat(&info.projection_matrix.unwrap()),
            Camera::release_projection()
        );
        // The mesh at R_t, projected with the release camera, covers the face the image
        // shows: the silhouette rendered from the annotation against the light pixels.
        let img = image::open(layout.image_path(Split::Test, &row.key))
            .unwrap()
            .to_rgb8();
        assert_eq!(img.width(), img.height());
        assert_eq!(
            img.width(),
            (2.0 * 505.0 / Camera::RELEASE_FOCAL_NDC).round() as u32
        );
        let camera = Camera::release(img.width(), img.height());
        let verts: Vec<Point3<f32>> = info.verts.clone();
        let screen = camera.project_to_screen(&info.pose().unwrap(), &verts);
        let mut vis = VisibilityBuffer::new(img.width(), img.height());
        vis.rasterize_mesh(&screen, tris).unwrap();
        let projected: Vec<bool> = vis.triangle.iter().map(|&t| t != u32::MAX).collect();
        let shown: Vec<bool> = img.pixels().map(|p| p[0] > 160).collect();
        let (inter, n) = (
            iou(&projected, &shown),
            projected.iter().filter(|x| **x).count(),
        );
        assert!(n > 5000, "face too small to test: {n} px");
        assert!(inter > 0.97, "{:?}: IoU {inter}", s.orientation);
        // The same check fails for a pose 5 mm off (about 6 px): the test can tell.
        let off = Pose::new(
            s.pose.rotation(),
            s.pose.translation_m() + Vector3::new(0.005, 0.0, 0.0),
        );
        let mut vis = VisibilityBuffer::new(img.width(), img.height());
        vis.rasterize_mesh(&camera.project_to_screen(&off, &verts), tris)
            .unwrap();
        let wrong: Vec<bool> = vis.triangle.iter().map(|&t| t != u32::MAX).collect();
        let wrong_iou = iou(&wrong, &shown);
        eprintln!(
            "{:?}: IoU {inter:.4} (5 mm off: {wrong_iou:.4})",
            s.orientation
        );
        assert!(
            wrong_iou < inter - 0.03,
            "{:?}: {wrong_iou} vs {inter}",
            s.orientation
        );
        // points2d is the projection too.
        let p2 = info.points2d.clone().unwrap();
        let q = camera.project(&info.pose().unwrap(), &mesh()[100]);
        assert!((p2[100][0] - q.u).abs() < 1e-3 && (p2[100][1] - q.v).abs() < 1e-3);
    }
    // convert reads the output with nothing skipped.
    let pq = dir.path().join("pq");
    let ctx = ValidationContext {
        projection: Camera::release_projection(),
        topology: builtin().topology.clone(),
        embed_images: false,
    };
    let opts = ConvertOptions {
        input: output.clone(),
        output: pq,
        resources: None,
        rows_per_shard: 16,
        embed_images: false,
        shard_index: 0,
        shard_count: 1,
        overwrite: false,
    };
    let m = ingest::convert(&opts, &ctx, &|_| {}).unwrap();
    assert_eq!((m.converted, m.skipped, m.listing_problems), (4, 0, 0));
}

#[test]
fn portrait_turns_the_captured_image_clockwise() {
    // A red block at the middle of the captured image's top edge appears at the middle
    // of the written image's right edge.
    let mut captured = RgbImage::from_pixel(400, 300, Rgb([0, 0, 100]));
    for y in 0..20 {
        for x in 190..210 {
            captured.put_pixel(x, y, Rgb([255, 0, 0]));
        }
    }
    let k = Matrix3::new(300.0, 0.0, 199.5, 0.0, 300.0, 149.5, 0.0, 0.0, 1.0);
    let out = arkit_data::ingest::resample_to_release(
        &captured,
        &k,
        &InterfaceOrientation::Portrait.rotation(),
        400,
    );
    let red: Vec<(u32, u32)> = out
        .enumerate_pixels()
        .filter(|(_, _, p)| p[0] > 200 && p[2] < 50)
        .map(|(x, y, _)| (x, y))
        .collect();
    assert!(!red.is_empty());
    let mx = red.iter().map(|p| p.0 as f64).sum::<f64>() / red.len() as f64;
    let my = red.iter().map(|p| p.1 as f64).sum::<f64>() / red.len() as f64;
    // The captured top edge is 149.5 px above the centre at f = 300: tan = 0.498; in the
    // written camera (f = 1.5744 * 200 = 314.9) that is 157 px right of the centre.
    assert!(mx > 340.0 && mx < 360.0, "{mx}");
    assert!((my - 200.0).abs() < 3.0, "{my}");
    // landscapeRight keeps it at the top.
    let out = arkit_data::ingest::resample_to_release(
        &captured,
        &k,
        &InterfaceOrientation::LandscapeRight.rotation(),
        400,
    );
    let p = out.get_pixel(200, 50);
    assert!(p[0] > 200 && p[2] < 50, "{p:?}");
    // Rays the capture did not see (beyond its 300 px height) are black.
    assert_eq!(*out.get_pixel(200, 5), Rgb([0, 0, 0]));
}

fn edit(input: &Path, name: &str, f: impl FnOnce(&mut Value)) {
    let p = input.join(format!("{name}.json"));
    let mut v: Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
}

fn bad_capture(input: &Path) {
    let s = scene(InterfaceOrientation::Portrait, 10.0, 0.0, 0.0);
    for name in [
        "good", "nokey", "short", "scaled", "rowmajor", "garbage", "resized", "behind",
    ] {
        write_frame(input, name, &s);
    }
    edit(input, "nokey", |v| {
        v.as_object_mut().unwrap().remove("camera_transform");
    });
    edit(input, "short", |v| {
        v["vertices"].as_array_mut().unwrap().pop();
    });
    edit(input, "scaled", |v| {
        for c in 0..3 {
            for r in 0..3 {
                let x = v["face_anchor_transform"][c][r].as_f64().unwrap();
                v["face_anchor_transform"][c][r] = json!(x * 1.1);
            }
        }
    });
    edit(input, "rowmajor", |v| {
        let m = v["camera_transform"].clone();
        for c in 0..4 {
            for r in 0..4 {
                v["camera_transform"][c][r] = m[r][c].clone();
            }
        }
    });
    std::fs::write(input.join("garbage.png"), b"\x89PNG\r\n\x1a\nnot really").unwrap();
    image::imageops::resize(
        &image::open(input.join("resized.png")).unwrap().to_rgb8(),
        320,
        240,
        image::imageops::FilterType::Triangle,
    )
    .save(input.join("resized.png"))
    .unwrap();
    let mut behind = s.clone();
    behind.pose = Pose::from_euler(
        EulerAngles::new(10.0, 0.0, 0.0),
        Vector3::new(0.0, 0.0, 0.4),
    );
    let anchor =
        behind.camera_world * o4(behind.orientation) * behind.pose.face_to_camera.to_homogeneous();
    edit(input, "behind", |v| {
        v["face_anchor_transform"] = columns4(&anchor)
    });
}

#[test]
fn bad_frames_are_reported_with_file_and_reason_and_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("cap"), dir.path().join("rel"));
    bad_capture(&input);
    let summary = ingest::import_capture(&options(&input, &output), &|| {}).unwrap();
    assert_eq!(summary.frames_found, 8);
    assert_eq!(summary.imported, 1, "{:#?}", summary.skipped);
    let why = |file: &str| -> String {
        summary
            .skipped
            .iter()
            .find(|p| p.file == file)
            .unwrap_or_else(|| panic!("{file} not reported: {:#?}", summary.skipped))
            .reason
            .clone()
    };
    assert!(why("nokey.json").contains("missing key 'camera_transform'"));
    assert!(why("short.json").contains("1219 vertices"));
    assert!(why("scaled.json").contains("not orthonormal"));
    assert!(why("rowmajor.json").contains("last row"));
    assert!(
        why("garbage.png").contains("decode"),
        "{}",
        why("garbage.png")
    );
    assert!(why("resized.png").contains("320x240"));
    assert!(
        why("behind.json").contains("negative"),
        "{}",
        why("behind.json")
    );
    let keys = release::read_list(&ReleaseLayout::new(&output).list_path(Split::Test)).unwrap();
    assert_eq!(keys.len(), 1);
    assert_eq!(keys[0].key.img_id, "good");
    // Nothing of a skipped frame is written.
    assert!(
        !ReleaseLayout::new(&output)
            .info_path(
                Split::Test,
                &arkit_core::SampleKey {
                    subject_id: "me".into(),
                    facial_action: "capture".into(),
                    img_id: "short".into(),
                }
            )
            .exists()
    );
    // A second import into the same folder is refused without --overwrite.
    let err = ingest::import_capture(&options(&input, &output), &|| {})
        .unwrap_err()
        .to_string();
    assert!(err.contains("--overwrite"), "{err}");
}

#[test]
fn cli_strict_json_and_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("cap"), dir.path().join("rel"));
    bad_capture(&input);
    // Sub-folders are facial actions; a `capture/` sub-folder repeating a root frame's
    // key is reported, not written over it.
    write_frame(
        &input.join("smile"),
        "f1",
        &scene(InterfaceOrientation::LandscapeRight, 0.0, 5.0, 0.0),
    );
    write_frame(
        &input.join("capture"),
        "good",
        &scene(InterfaceOrientation::LandscapeRight, 0.0, 5.0, 0.0),
    );
    let preview = dir.path().join("preview.png");
    let out = tool()
        .args(["import-arkit", "--json", "--strict", "--input"])
        .arg(&input)
        .arg("--output")
        .arg(&output)
        .arg("--preview")
        .arg(&preview)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(1),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["imported"], 2);
    let skipped = v["skipped"].as_array().unwrap();
    assert_eq!(skipped.len(), 8);
    assert!(
        skipped.iter().any(|p| p["file"] == "good.json"
            && p["reason"].as_str().unwrap().contains("capture/good.json"))
    );
    assert_eq!(v["subject_id"], "cap");
    assert!(image::open(&preview).is_ok());
    let keys = release::read_list(&ReleaseLayout::new(&output).list_path(Split::Test)).unwrap();
    assert!(
        keys.iter()
            .any(|r| r.key.facial_action == "smile" && r.key.img_id == "f1")
    );
    // `convert` on the output: nothing skipped, no listing problems.
    let out = tool()
        .args(["convert", "--strict", "--json", "--input"])
        .arg(&output)
        .arg("--output")
        .arg(dir.path().join("pq"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // A missing capture folder is an error naming it.
    let out = tool()
        .args([
            "import-arkit",
            "--input",
            "/nonexistent/capture",
            "--output",
        ])
        .arg(dir.path().join("x"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("/nonexistent/capture") && err.contains("does not exist"),
        "{err}"
    );
    let out = tool().args(["import-arkit", "--help"]).output().unwrap();
    let help = String::from_utf8_lossy(&out.stdout);
    assert!(help.contains("face_anchor_transform") && help.contains("column"));
}

#[test]
fn intrinsics_of_another_resolution_and_unreadable_folders_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    let (input, out) = (dir.path().join("cap"), dir.path().join("rel"));
    let s = scene(InterfaceOrientation::LandscapeRight, 10.0, 5.0, 0.0);
    write_frame(&input, "good", &s);
    // Intrinsics for a capture twice the size (principal point near (630, 488)) with
    // the 640x480 image and resolution: the image would not match its pose.
    write_frame(&input, "other_k", &s);
    let mut v: Value =
        serde_json::from_str(&std::fs::read_to_string(input.join("other_k.json")).unwrap())
            .unwrap();
    v["camera_intrinsics"] = columns3(&Matrix3::new(
        1000.0, 0.0, 630.4, 0.0, 1010.0, 487.8, 0.0, 0.0, 1.0,
    ));
    std::fs::write(input.join("other_k.json"), v.to_string()).unwrap();
    // A sub-folder (facial action) that is a symbolic link to itself.
    std::os::unix::fs::symlink("loop", input.join("loop")).unwrap();
    let summary = ingest::import_capture(&options(&input, &out), &|| {}).unwrap();
    assert_eq!(summary.imported, 1, "{:#?}", summary.skipped);
    let why = |f: &str| {
        summary
            .skipped
            .iter()
            .find(|p| p.file == f)
            .unwrap_or_else(|| panic!("{f}: {:#?}", summary.skipped))
            .reason
            .clone()
    };
    let r = why("other_k.json");
    assert!(
        r.contains("principal point") && r.contains("640x480"),
        "{r}"
    );
    let r = why("loop");
    assert!(r.contains("symbolic link"), "{r}");
}

#[test]
fn a_png_bomb_is_refused_from_its_header() {
    let dir = tempfile::tempdir().unwrap();
    let (input, out) = (dir.path().join("cap"), dir.path().join("rel"));
    let mut s = scene(InterfaceOrientation::LandscapeRight, 10.0, 5.0, 0.0);
    write_frame(&input, "good", &s);
    // A frame whose JSON claims the bomb's 16000x16000 (principal point at its centre),
    // so only the decoded-size limit stands between it and 1.5 GiB.
    s.resolution = (16000, 16000);
    s.k = Matrix3::new(500.0, 0.0, 8000.0, 0.0, 505.0, 8000.0, 0.0, 0.0, 1.0);
    std::fs::write(
        input.join("bomb.json"),
        serde_json::to_string(&frame_json(&s)).unwrap(),
    )
    .unwrap();
    std::fs::write(
        input.join("bomb.png"),
        crate::support::png_bomb::png_bomb(16000),
    )
    .unwrap();
    let summary = ingest::import_capture(&options(&input, &out), &|| {}).unwrap();
    assert_eq!(summary.imported, 1, "{:#?}", summary.skipped);
    let p = &summary.skipped[0];
    assert_eq!(p.file, "bomb.png");
    assert!(
        p.reason.contains("16000x16000 16-bit grey")
            && p.reason.contains("refused before decoding"),
        "{}",
        p.reason
    );
}

#[test]
fn row_major_matrices_in_most_frames_stop_the_import_and_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (input, out) = (dir.path().join("cap"), dir.path().join("rel"));
    let s = scene(InterfaceOrientation::LandscapeRight, 10.0, 5.0, 0.0);
    for i in 0..6 {
        write_frame(&input, &format!("f{i}"), &s);
    }
    // An app that writes its matrices row-major, in 4 of the first 5 frames.
    for i in 0..4 {
        let f = input.join(format!("f{i}.json"));
        let mut v: Value = serde_json::from_str(&std::fs::read_to_string(&f).unwrap()).unwrap();
        v["camera_transform"] = columns4(&s.camera_world.transpose());
        std::fs::write(&f, v.to_string()).unwrap();
    }
    let mut o = options(&input, &out);
    o.systematic_window = 5;
    let e = ingest::import_capture(&o, &|| {}).unwrap_err().to_string();
    assert!(
        e.contains("'transforms' check skipped 4 of the first 5 frames")
            && e.contains("f0.json")
            && e.contains("columns")
            && e.contains("--allow-systematic-skips"),
        "{e}"
    );
    assert!(
        std::fs::read_dir(&out).map_or(true, |d| d
            .filter_map(|e| e.ok())
            .all(|e| e.path().extension().is_some_and(|x| x == "lock"))),
        "a stopped import left output (its lock file aside)"
    );
    // Not stopping (--allow-systematic-skips): each frame skipped with its reason.
    o.systematic_window = 0;
    let summary = ingest::import_capture(&o, &|| {}).unwrap();
    assert_eq!((summary.imported, summary.skipped.len()), (2, 4));
    // 3 of the first 6 (half) does not stop.
    let out2 = dir.path().join("rel2");
    let f = input.join("f0.json");
    let mut v: Value = serde_json::from_str(&std::fs::read_to_string(&f).unwrap()).unwrap();
    v["camera_transform"] = columns4(&s.camera_world);
    std::fs::write(&f, v.to_string()).unwrap();
    let mut o = options(&input, &out2);
    o.systematic_window = 6;
    let summary = ingest::import_capture(&o, &|| {}).unwrap();
    assert_eq!((summary.imported, summary.skipped.len()), (3, 3));
}
