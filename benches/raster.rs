//! Rasterizer benchmark: the face mesh (mesh + hole fill) into an 800x800 visibility
//! buffer, as `render` will do per sample. Prints time per frame, ns per covered pixel,
//! and the ratio to the official Python loader's mask render of one 800x800 sample
//! (3.0 ms, ../shared/measurements.md, same machine kind); then the official rules'
//! rasterizer (what the Python loader's `compat="official"` runs per item: the face's
//! window at full resolution, `rasterize_mesh_official_in`) against the same figure.
//! Run: `cargo bench --bench raster`.

use arkit_core::conventions::{Camera, EulerAngles, Pose};
use arkit_core::{
    PixelWindow, VisibilityBuffer, rasterize_mesh_official_in, rasterize_official_visibility_in,
};
use nalgebra::{Point3, Vector3};
use std::time::Instant;

mod timing;
use timing::median_ms;

/// The official loader's face-mask render for one 800x800 sample, ms.
const OFFICIAL_MASK_MS: f64 = 3.0;

fn main() {
    let topo = &arkit_data::mesh::builtin().topology;
    let fill = topo.hole_fill().expect("hole fill");
    let template = topo.template.as_ref().expect("template");
    let mut verts: Vec<Point3<f32>> = template.clone();
    verts.extend(fill.centroid_positions(template));
    let mut triangles = topo.triangles.clone();
    triangles.extend_from_slice(&fill.triangles);
    let camera = Camera::release(800, 800);
    let mut results = Vec::new();
    let mut official_rules = Vec::new();
    for (label, distance) in [
        ("near (0.3 m)", 0.3),
        ("typical (0.5 m)", 0.5),
        ("far (0.9 m)", 0.9),
    ] {
        let pose = Pose::from_euler(
            EulerAngles::new(25.0, -10.0, 5.0),
            Vector3::new(0.0, 0.0, -distance),
        );
        let screen = camera.project_to_screen(&pose, &verts);
        let mut vb = VisibilityBuffer::new(800, 800);
        vb.rasterize_mesh(&screen, &triangles).unwrap();
        let covered = vb.covered_pixels();
        let mut times = Vec::new();
        for _ in 0..60 {
            let t = Instant::now();
            vb.clear();
            vb.rasterize_mesh(&screen, &triangles).unwrap();
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        // Clearing alone, to separate the per-frame fixed cost.
        let mut clear = Vec::new();
        for _ in 0..60 {
            let t = Instant::now();
            vb.clear();
            clear.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        clear.sort_by(f64::total_cmp);
        let median = times[times.len() / 2];
        let clear_ms = clear[clear.len() / 2];
        // The official rules over the face's window, into one buffer (the loader's
        // pooled buffer, which the rasterizer sizes and fills per item).
        let window = PixelWindow::official_extent(&screen, 800, 800);
        let official = median_ms(
            || {
                rasterize_mesh_official_in(&mut vb, window, &screen, &triangles).unwrap();
            },
            60,
        );
        // The same without the weights: the loader's mask (`rasterize_official_visibility_in`).
        let visibility = median_ms(
            || {
                rasterize_official_visibility_in(&mut vb, window, &screen, &triangles).unwrap();
            },
            60,
        );
        official_rules.push((label, window, official, visibility));
        vb.reset(800, 800);
        results.push((label, covered, median, clear_ms));
    }
    println!(
        "rasterizer: {} triangles, 800x800, one thread, median of 60",
        triangles.len()
    );
    println!(
        "{:<16} {:>9} {:>10} {:>10} {:>14} {:>22}",
        "face", "pixels", "frame ms", "clear ms", "ns/pixel", "ratio to official mask"
    );
    for &(label, covered, median, clear_ms) in &results {
        println!(
            "{:<16} {:>9} {:>10.3} {:>10.3} {:>14.2} {:>21.1}x",
            label,
            covered,
            median,
            clear_ms,
            (median - clear_ms) * 1e6 / covered as f64,
            OFFICIAL_MASK_MS / median
        );
    }
    for &(label, window, ms, mask_ms) in &official_rules {
        println!(
            "official rules, {label}: the face's {}x{} window at full resolution, {ms:.3} ms a \
             frame ({mask_ms:.3} ms without the weights, as the loader's mask)",
            window.width, window.height
        );
    }
    for (label, _, median, _) in results {
        println!(
            "ratio: raster {label}: official mask render / ours = {:.1}x",
            OFFICIAL_MASK_MS / median
        );
    }
    for (label, _, ms, _) in official_rules {
        println!(
            "ratio: raster {label}, official rules (the loader's compat=\"official\"): official mask render / ours = {:.1}x",
            OFFICIAL_MASK_MS / ms
        );
    }
}
