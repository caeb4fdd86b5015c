//! The official crop pipeline's resampling (`official_crop::warp_affine`, our
//! reproduction of OpenCV 4's fixed-point `cv2.warpAffine`) against our own crop
//! (`CropTransform::crop_image`) on an 800x800 image into 192x192, one thread.
//!
//! With `OFFICIAL_CROP_DUMP=DIR` it also writes 300 random crops of a random image and a
//! random 0/1 mask (boxes inside, across and beyond the image edges, down- and
//! up-scaling, boxes a pixel taller or wider, sides 192, 64 and 33) with our outputs,
//! for `python3 benches/official_crop_opencv.py DIR` to compare with `cv2.warpAffine`
//! itself:
//!
//! ```text
//! OFFICIAL_CROP_DUMP=/tmp/oc cargo bench --bench official_crop
//! python3 benches/official_crop_opencv.py /tmp/oc
//! ```

use arkit_tool::official_crop::{warp_affine, warp_mask};
use arkit_tool::render::{CropSampling, CropTransform};
use arkit_tool::rng::Rng;
use image::RgbImage;
use std::time::Instant;

fn median_ms(mut f: impl FnMut(), n: usize) -> f64 {
    let mut t: Vec<f64> = (0..n)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[n / 2]
}

/// The official crop of the integer box `left..right` x `top..bottom`.
fn official(left: i64, top: i64, right: i64, bottom: i64, size: u32) -> CropTransform {
    let s = size as f64;
    CropTransform {
        x0: left as f64,
        y0: top as f64,
        side: s * (right - left) as f64 / (s - 1.0),
        side_y: s * (bottom - top) as f64 / (s - 1.0),
        size,
        sampling: CropSampling::Corners,
    }
}

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
    let crop = official(230, 210, 570, 550, 192);
    let ours = CropTransform {
        sampling: CropSampling::Centres,
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
    let Some(dir) = std::env::var_os("OFFICIAL_CROP_DUMP") else {
        return;
    };
    let dir = std::path::PathBuf::from(dir);
    std::fs::create_dir_all(&dir).expect("dump folder");
    std::fs::write(dir.join("image.bin"), image.as_raw()).expect("write");
    let mask_bytes: Vec<u8> = mask.iter().map(|&m| m as u8).collect();
    std::fs::write(dir.join("mask.bin"), &mask_bytes).expect("write");
    let mut cases = Vec::new();
    for k in 0..300 {
        let size = [192u32, 64, 33][k % 3];
        let side = 20 + rng.below(880) as i64;
        let left = rng.below(1100) as i64 - 300;
        let top = rng.below(1100) as i64 - 300;
        let right = left + side;
        let bottom = top + side + rng.below(3) as i64 - 1;
        let c = official(left, top, right, bottom, size);
        let rgb = warp_affine(image.as_raw(), w, h, 3, &c);
        let m: Vec<u8> = warp_mask(&mask, w, h, &c)
            .into_iter()
            .map(|b| b as u8)
            .collect();
        std::fs::write(dir.join(format!("rgb_{k}.bin")), rgb).expect("write");
        std::fs::write(dir.join(format!("mask_{k}.bin")), m).expect("write");
        cases.push(serde_json::json!({
            "left": left, "top": top, "right": right, "bottom": bottom, "size": size
        }));
    }
    let manifest = serde_json::json!({ "width": w, "height": h, "cases": cases });
    std::fs::write(dir.join("cases.json"), manifest.to_string()).expect("write");
    println!("wrote {} cases to {}", cases.len(), dir.display());
}
