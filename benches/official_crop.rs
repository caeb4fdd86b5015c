//! The official crop pipeline's resampling (`official_crop::warp_affine`, our
//! reproduction of OpenCV 4's fixed-point `cv2.warpAffine`) against our own crop
//! (`CropTransform::crop_image`) on an 800x800 image into 192x192, one thread.
//!
//! Run: `cargo bench --bench official_crop`. Its exactness against OpenCV itself is
//! `tests/official_crop.rs`.

use arkit_core::Rng;
use arkit_core::VisibilityBuffer;
use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_data::crop::{CropTransform, RuleSet};
use arkit_data::crop::{box_crop, warp_mask};
use arkit_data::render::FaceRenderer;
use image::RgbImage;
use nalgebra::Vector3;

mod timing;
use timing::median_ms;

fn main() {
    let (w, h) = (800u32, 800u32);
    let mut rng = Rng::new(11);
    let pixels: Vec<u8> = (0..w * h * 3).map(|_| rng.below(256) as u8).collect();
    let image = RgbImage::from_raw(w, h, pixels).expect("size");
    // A disc with a ragged edge: a mask whose warps have many boundary pixels.
    let mask: Vec<bool> = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f64 - 400.0, (i / w) as f64 - 380.0);
            (x * x + y * y).sqrt() < 250.0 + 8.0 * rng.next_f64()
        })
        .collect();
    let crop = box_crop(230.0, 210.0, 570.0, 550.0, 192);
    let ours = CropTransform {
        rules: RuleSet::Exact,
        side_y: crop.side,
        ..crop
    };
    let n = 300;
    let t_official = median_ms(|| drop(crop.crop_image(&image)), n);
    let t_ours = median_ms(|| drop(ours.crop_image(&image)), n);
    let t_mask = median_ms(|| drop(warp_mask(&mask, w, h, &crop)), n);
    println!("official crop resampling, 800x800 -> 192x192 RGB, one thread, median of {n}");
    println!(
        "{:<44} {:>8.3} ms",
        "cv2.warpAffine reproduction (RGB)", t_official
    );
    println!(
        "{:<44} {:>8.3} ms",
        "our crop_image (RGB, pixel centres)", t_ours
    );
    println!(
        "{:<44} {:>8.3} ms",
        "official mask warp (full-res 0/1 mask)", t_mask
    );
    println!(
        "ratio: official warp / our crop = {:.2}x",
        t_official / t_ours
    );
    // The whole visibility job per sample, ours at crop resolution against the
    // official pipeline's full-resolution render, warp and tap choice.
    let topo = arkit_data::mesh::builtin().topology.clone();
    let verts = topo.template.clone().expect("template");
    let renderer = FaceRenderer::new(topo.clone(), Camera::release_projection()).unwrap();
    let pose = Pose::from_euler(
        EulerAngles::new(25.0, -10.0, 5.0),
        Vector3::new(0.01, 0.0, -0.5),
    );
    let cam = Camera::release(w, h);
    let landmarks: Vec<f32> = topo
        .landmarks
        .iter()
        .flat_map(|&i| {
            let p = cam.project(&pose, &verts[i as usize].cast());
            [p.u as f32, p.v as f32]
        })
        .collect();
    let exact_crop = CropTransform::around_landmarks(&landmarks, 192);
    let official_crop = renderer
        .official_crop(&verts, &pose, w, h, 192)
        .expect("a box");
    let mut vb = VisibilityBuffer::new(192, 192);
    let t_exact = median_ms(
        || drop(renderer.render(&verts, &pose, w, h, &exact_crop, &mut vb)),
        n,
    );
    let renderer = renderer.with_rules(RuleSet::Official);
    let t_pipeline = median_ms(
        || drop(renderer.render(&verts, &pose, w, h, &official_crop, &mut vb)),
        n,
    );
    println!(
        "{:<44} {:>8.3} ms",
        "visibility + targets, ours (crop resolution)", t_exact
    );
    println!(
        "{:<44} {:>8.3} ms",
        "visibility + targets, official pipeline", t_pipeline
    );
    println!(
        "ratio: official pipeline / ours (visibility stage) = {:.1}x",
        t_pipeline / t_exact
    );
}
