//! A synthetic BIWI-shaped `hpdb` folder from known release poses and a known head
//! (shared by `tests/biwi.rs` and `tests/perspnet.rs`).

#![allow(dead_code)]

use arkit_core::VisibilityBuffer;
use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_data::ingest::biwi::HEAD_ORIGIN_SHIFT_M;
use image::{Rgb, RgbImage};
use nalgebra::{Matrix3, Point3, Rotation3, Vector3};
use std::fmt::Write as _;
use std::path::Path;

pub const K: [f64; 4] = [517.679, 517.679, 320.0, 240.5]; // fx, fy, cx, cy

pub fn flip() -> Matrix3<f64> {
    Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0))
}

pub fn calibration() -> (Rotation3<f64>, Vector3<f64>) {
    (
        Rotation3::from_euler_angles(0.012, -0.009, 0.004),
        Vector3::new(-24.0198, 5.8896, -13.2308),
    )
}

/// The head in the release's frame: the built-in face's 1,220 vertices repeated to the
/// 6,918 of a BIWI mesh (so the official landmark numbers exist).
pub fn release_head() -> Vec<Point3<f64>> {
    let t = arkit_data::mesh::builtin()
        .topology
        .template
        .clone()
        .unwrap();
    (0..6918).map(|i| t[i % t.len()].cast()).collect()
}

/// The mesh as BIWI stores it: `p = 1000 F (v + c)`, millimetres.
pub fn biwi_head() -> Vec<Point3<f64>> {
    let c = Vector3::from(HEAD_ORIGIN_SHIFT_M);
    release_head()
        .iter()
        .map(|v| Point3::from(flip() * (v.coords + c) * 1000.0))
        .collect()
}

/// The pose file of a release pose (the inverse of the conversion's rules).
pub fn pose_text(pose: &Pose) -> String {
    let (rc, tc) = calibration();
    let c = Vector3::from(HEAD_ORIGIN_SHIFT_M);
    let r_gl = *pose.rotation().matrix();
    let t_gl = pose.translation_m() - r_gl * c;
    let r_cv = flip() * r_gl * flip();
    let t_cv = flip() * t_gl * 1000.0;
    let r = rc.matrix().transpose() * r_cv;
    let t = rc.matrix().transpose() * (t_cv - tc);
    let mut s = String::new();
    for i in 0..3 {
        writeln!(s, "{} {} {} ", r[(i, 0)], r[(i, 1)], r[(i, 2)]).unwrap();
    }
    writeln!(s, "\n{} {} {} ", t.x, t.y, t.z).unwrap();
    s
}

pub fn cal_text(distortion: &str) -> String {
    let (rc, tc) = calibration();
    let m = rc.matrix();
    format!(
        "{} 0 {} \n0 {} {} \n0 0 1 \n\n{distortion}\n\n{} {} {} \n{} {} {} \n{} {} {} \n\n{} {} {} \n\n640 480\n",
        K[0],
        K[2],
        K[1],
        K[3],
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
        tc.x,
        tc.y,
        tc.z
    )
}

/// The RGB camera as a release-form projection (K in OpenCV's convention).
pub fn rgb_camera() -> Camera {
    let (w, h) = (640.0, 480.0);
    let mut p = Camera::release_projection();
    p[(0, 0)] = 2.0 * K[0] / w;
    p[(1, 1)] = 2.0 * K[1] / h;
    p[(2, 0)] = 1.0 - 2.0 * (K[2] + 0.5) / w;
    p[(2, 1)] = 2.0 * (K[3] + 0.5) / h - 1.0;
    Camera::new(p, 640, 480).unwrap()
}

pub fn silhouette(camera: &Camera, pose: &Pose, verts: &[Point3<f64>]) -> Vec<bool> {
    let v32: Vec<Point3<f32>> = verts.iter().map(|p| p.cast()).collect();
    let mut vis = VisibilityBuffer::new(camera.width, camera.height);
    vis.rasterize_mesh(
        &camera.project_to_screen(pose, &v32),
        &arkit_data::mesh::builtin().topology.triangles,
    )
    .unwrap();
    vis.triangle.iter().map(|&t| t != u32::MAX).collect()
}

pub fn poses() -> Vec<Pose> {
    (0..3)
        .map(|i| {
            Pose::from_euler(
                EulerAngles::new(
                    -30.0 + 25.0 * i as f64,
                    10.0 - 8.0 * i as f64,
                    4.0 * i as f64,
                ),
                Vector3::new(0.03 - 0.02 * i as f64, -0.02, -0.85 - 0.05 * i as f64),
            )
        })
        .collect()
}

/// Writes a BIWI-shaped `hpdb` folder: sequences 01 and 02 with three posed frames
/// each and, in 01, one image without a pose file.
pub fn write_hpdb(root: &Path) {
    let obj: String = biwi_head()
        .iter()
        .map(|p| format!("v {} {} {}\n", p.x, p.y, p.z))
        .chain(
            arkit_data::mesh::builtin()
                .topology
                .triangles
                .iter()
                .map(|t| format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1)),
        )
        .collect();
    let camera = rgb_camera();
    let head = release_head();
    for seq in ["01", "02"] {
        let dir = root.join(seq);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(root.join(format!("{seq}.obj")), &obj).unwrap();
        std::fs::write(dir.join("rgb.cal"), cal_text("0 0 0 0")).unwrap();
        for (i, pose) in poses().iter().enumerate() {
            let n = format!("{:05}", 3 + i);
            std::fs::write(dir.join(format!("frame_{n}_pose.txt")), pose_text(pose)).unwrap();
            let mask = silhouette(&camera, pose, &head);
            RgbImage::from_fn(640, 480, |x, y| {
                if mask[(y * 640 + x) as usize] {
                    Rgb([230, 220, 210])
                } else {
                    Rgb([(x / 8) as u8, (y / 8) as u8, 30])
                }
            })
            .save(dir.join(format!("frame_{n}_rgb.png")))
            .unwrap();
        }
    }
    std::fs::copy(
        root.join("01/frame_00003_rgb.png"),
        root.join("01/frame_00009_rgb.png"),
    )
    .unwrap();
}
