//! `predict --image --mesh DIR`: each posed face's mesh (.obj, .ply) and landmarks, read
//! back and checked against the report's vertices and pose. (The files read by an
//! independent reader, trimesh: python/tests/test_mesh_files.py.)

use crate::support::tool;
use serde_json::Value;
use std::path::Path;

const TINY: &str = crate::support::TINY_MODEL;

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

#[test]
fn meshes_and_landmarks_agree_with_the_reported_pose() {
    let dir = tempfile::tempdir().unwrap();
    let photo = dir.path().join("group.jpg");
    let out = tool()
        .args(["synth", "--group-photo", &s(&photo), "--faces", "2"])
        .args(["--size", "960x540", "--seed", "5"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let meshes = dir.path().join("meshes");
    let out = tool()
        .args([
            "predict",
            "--model",
            TINY,
            "--image",
            &s(&photo),
            "--vertices",
        ])
        .args(["--boxes", &s(&dir.path().join("group.boxes.json"))])
        .args(["--mesh", &s(&meshes)])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    let p = &report["photos"][0];
    let faces = p["faces"].as_array().unwrap();
    assert_eq!(faces.len(), 2);
    let topology = &arkit_data::mesh::builtin().topology;
    let k = &p["camera"];
    let (fx, cx, cy) = (
        k["fx"].as_f64().unwrap(),
        k["cx"].as_f64().unwrap(),
        k["cy"].as_f64().unwrap(),
    );
    // The demo's square: 960 x 540 padded by 210 rows on top, resized by 800 / 960.
    let (scale, pad_top) = (800.0 / 960.0, 210.0);
    for (fi, f) in faces.iter().enumerate() {
        assert_eq!(f["status"], "ok");
        let obj = meshes.join(format!("group-face{fi}.obj"));
        assert_eq!(f["mesh"]["obj"], s(&obj));
        // The OBJ's vertices are the report's camera-space vertices, exactly.
        let text = std::fs::read_to_string(&obj).unwrap();
        let v: Vec<Vec<f64>> = text
            .lines()
            .filter_map(|l| l.strip_prefix("v "))
            .map(|l| l.split(' ').map(|x| x.parse().unwrap()).collect())
            .collect();
        let reported: Vec<Vec<f64>> = f["vertices_m"]
            .as_array()
            .unwrap()
            .iter()
            .map(floats)
            .collect();
        // (serde_json's reader may round the last bit differently from Rust's parser.)
        let close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-15);
        assert_eq!(v.len(), reported.len());
        assert!(
            v.iter().zip(&reported).all(|(a, b)| close(a, b)),
            "the OBJ's vertices"
        );
        let faces_in_obj = text.lines().filter(|l| l.starts_with("f ")).count();
        assert_eq!(faces_in_obj, topology.triangles.len());
        let ply = std::fs::read_to_string(meshes.join(format!("group-face{fi}.ply"))).unwrap();
        let first = ply
            .split("end_header\n")
            .nth(1)
            .unwrap()
            .lines()
            .next()
            .unwrap();
        let first: Vec<f64> = first.split(' ').map(|x| x.parse().unwrap()).collect();
        assert!(close(&first[..3], &reported[0]), "the PLY's first vertex");
        // Landmarks: the topology's vertices, and their pixels by hand: the release's
        // camera space to OpenCV's, the demo's camera, the square back to the photo.
        let marks: Value = serde_json::from_slice(
            &std::fs::read(meshes.join(format!("group-face{fi}.landmarks.json"))).unwrap(),
        )
        .unwrap();
        for (j, &id) in topology.landmarks.iter().enumerate() {
            assert_eq!(marks["vertex_ids"][j], id);
            assert!(close(
                &floats(&marks["points_m"][j]),
                &reported[id as usize]
            ));
            // The release's camera (y up, looking down -z) to OpenCV's: (x, -y, -z).
            let c = &reported[id as usize];
            let q = nalgebra::Vector3::new(c[0], -c[1], -c[2]);
            let (u, v) = (fx * q.x / q.z + cx, fx * q.y / q.z + cy);
            let (x, y) = (u / scale, v / scale - pad_top);
            let px = floats(&marks["pixels"][j]);
            assert!(
                (px[0] - x).abs() < 1e-6 && (px[1] - y).abs() < 1e-6,
                "{px:?} vs ({x}, {y})"
            );
        }
        // The landmarks lie on the face: most inside its box.
        let b = floats(&f["box"]);
        let inside = (0..topology.landmarks.len())
            .filter(|&j| {
                let px = floats(&marks["pixels"][j]);
                (b[0]..=b[2]).contains(&px[0]) && (b[1]..=b[3]).contains(&px[1])
            })
            .count();
        assert!(inside >= 60, "{inside} of 68 landmarks inside the box");
    }
}
