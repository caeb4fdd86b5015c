//! `official_crop::warp_affine` against `cv2.warpAffine` itself: 300 random crops of a
//! random image and of a random 0/1 mask (boxes inside, across and beyond the image's
//! edges, down- and up-scaling, boxes a pixel taller or wider, sides 192, 64 and 33),
//! compared byte for byte by `tests/official_crop_opencv.py` under the Python named by
//! `ARKIT_OPENCV_PYTHON` (one with numpy and opencv-python-headless 4.x, the official
//! code's era; CI installs 4.6.0.66 in a virtual environment). Skips with a message
//! without it.

use arkit_core::Rng;
use arkit_data::crop::{box_crop, warp_affine, warp_mask};
use std::path::Path;
use std::process::Command;

/// Writes the image, the mask, the cases and our outputs for the script.
fn write_cases(dir: &Path) -> usize {
    let (w, h) = (800u32, 800u32);
    let mut rng = Rng::new(11);
    let image: Vec<u8> = (0..w * h * 3).map(|_| rng.below(256) as u8).collect();
    // A disc with a ragged edge: warps of it have many boundary pixels.
    let mask: Vec<bool> = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f64 - 400.0, (i / w) as f64 - 380.0);
            (x * x + y * y).sqrt() < 250.0 + 8.0 * rng.next_f64()
        })
        .collect();
    std::fs::write(dir.join("image.bin"), &image).unwrap();
    let mask_bytes: Vec<u8> = mask.iter().map(|&m| m as u8).collect();
    std::fs::write(dir.join("mask.bin"), &mask_bytes).unwrap();
    let mut cases = Vec::new();
    for k in 0..300 {
        let size = [192u32, 64, 33][k % 3];
        let side = 20 + rng.below(880) as i64;
        let left = rng.below(1100) as i64 - 300;
        let top = rng.below(1100) as i64 - 300;
        let (right, bottom) = (left + side, top + side + rng.below(3) as i64 - 1);
        let c = box_crop(left as f64, top as f64, right as f64, bottom as f64, size);
        let rgb = warp_affine(&image, w, h, 3, &c);
        let m: Vec<u8> = warp_mask(&mask, w, h, &c)
            .into_iter()
            .map(|b| b as u8)
            .collect();
        std::fs::write(dir.join(format!("rgb_{k}.bin")), rgb).unwrap();
        std::fs::write(dir.join(format!("mask_{k}.bin")), m).unwrap();
        cases.push(serde_json::json!({
            "left": left, "top": top, "right": right, "bottom": bottom, "size": size
        }));
    }
    let manifest = serde_json::json!({ "width": w, "height": h, "cases": cases });
    std::fs::write(dir.join("cases.json"), manifest.to_string()).unwrap();
    cases.len()
}

#[test]
fn warp_affine_equals_opencv_byte_for_byte() {
    let Some(python) = std::env::var_os("ARKIT_OPENCV_PYTHON") else {
        eprintln!(
            "SKIPPED: set ARKIT_OPENCV_PYTHON to a Python with numpy and \
             opencv-python-headless 4.x to compare with cv2.warpAffine"
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    assert_eq!(write_cases(dir.path()), 300);
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/official_crop_opencv.py");
    let out = Command::new(&python)
        .arg(&script)
        .arg(dir.path())
        .output()
        .expect("run the OpenCV script");
    let text = String::from_utf8_lossy(&out.stdout);
    eprintln!("{text}{}", String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "cv2.warpAffine differs:\n{text}");
    assert!(text.contains("300 crops, 0 with any difference"), "{text}");
}
