//! Drawing a posed face mesh over an image, for people to look at: previews of
//! `synth` and `augment`, and the worst predictions of `eval`'s report.

use crate::mesh::topology::FaceTopology;
use arkit_core::Result;
use arkit_core::conventions::{Camera, Pose};
use image::{Rgb, RgbImage};
use nalgebra::Point3;

/// Colours of a drawn mesh.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshStyle {
    /// A sparse set of mesh edges (every 7th triangle's first edge).
    pub edges: Option<Rgb<u8>>,
    /// The outer contour and the eye and mouth openings.
    pub outline: Rgb<u8>,
    /// The 68 landmarks, as 3x3 dots.
    pub landmarks: Option<Rgb<u8>>,
}

impl MeshStyle {
    /// Dark green edges, light green outline, red landmarks: the annotation preview.
    pub const ANNOTATION: MeshStyle = MeshStyle {
        edges: Some(Rgb([20, 120, 40])),
        outline: Rgb([40, 240, 90]),
        landmarks: Some(Rgb([255, 40, 40])),
    };

    /// Only an outline in one colour (for comparing two meshes on one image).
    pub fn outline(colour: Rgb<u8>) -> Self {
        MeshStyle {
            edges: None,
            outline: colour,
            landmarks: None,
        }
    }
}

/// Draws the mesh `verts` (canonical frame, metres) posed by `pose` and projected with
/// the release camera of the image's size.
pub(crate) fn draw_mesh(
    image: &mut RgbImage,
    topology: &FaceTopology,
    verts: &[Point3<f64>],
    pose: &Pose,
    style: &MeshStyle,
) -> Result<()> {
    let camera = Camera::release(image.width(), image.height());
    let p: Vec<Option<(f64, f64)>> = camera
        .project_all(pose, verts)
        .iter()
        .map(|q| Some((q.u, q.v)))
        .collect();
    draw_projected_mesh(image, topology, &p, style)
}

/// Draws a mesh whose vertices are already projected to the image's pixels (`None`: a
/// vertex behind the camera; its edges are left out).
pub fn draw_projected_mesh(
    image: &mut RgbImage,
    topology: &FaceTopology,
    p: &[Option<(f64, f64)>],
    style: &MeshStyle,
) -> Result<()> {
    let edge = |image: &mut RgbImage, a: u32, b: u32, colour: Rgb<u8>| {
        if let (Some(Some(a)), Some(Some(b))) = (p.get(a as usize), p.get(b as usize)) {
            draw_line(image, *a, *b, colour);
        }
    };
    if let Some(colour) = style.edges {
        for t in topology.triangles.iter().step_by(7) {
            edge(image, t[0], t[1], colour);
        }
    }
    for (_, l) in &topology.boundary_loops()?.loops {
        for k in 0..l.len() {
            edge(image, l[k], l[(k + 1) % l.len()], style.outline);
        }
    }
    if let Some(colour) = style.landmarks {
        for &l in &topology.landmarks {
            let Some(Some(q)) = p.get(l as usize) else {
                continue;
            };
            for dy in -1..=1 {
                for dx in -1..=1 {
                    put(
                        image,
                        q.0.floor() as i64 + dx,
                        q.1.floor() as i64 + dy,
                        colour,
                    );
                }
            }
        }
    }
    Ok(())
}

/// Draws the rectangle `[x0, y0, x1, y1]` (pixels), `width` pixels wide inwards.
pub fn draw_box(image: &mut RgbImage, b: [f64; 4], width: u32, colour: Rgb<u8>) {
    let [x0, y0, x1, y1] = b;
    for k in 0..width.max(1) {
        let k = k as f64;
        let (a0, b0, a1, b1) = (x0 + k, y0 + k, x1 - 1.0 - k, y1 - 1.0 - k);
        draw_line(image, (a0, b0), (a1, b0), colour);
        draw_line(image, (a1, b0), (a1, b1), colour);
        draw_line(image, (a1, b1), (a0, b1), colour);
        draw_line(image, (a0, b1), (a0, b0), colour);
    }
}

fn put(image: &mut RgbImage, x: i64, y: i64, colour: Rgb<u8>) {
    if x >= 0 && y >= 0 && (x as u32) < image.width() && (y as u32) < image.height() {
        image.put_pixel(x as u32, y as u32, colour);
    }
}

/// Draws a one-pixel line from `a` to `b` (pixel coordinates), clipped to the image.
fn draw_line(image: &mut RgbImage, a: (f64, f64), b: (f64, f64), colour: Rgb<u8>) {
    if !(a.0.is_finite() && a.1.is_finite() && b.0.is_finite() && b.1.is_finite()) {
        return;
    }
    let steps = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).clamp(1, 1 << 16);
    for i in 0..=steps {
        let t = i as f64 / steps as f64;
        let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
        if x >= 0.0 && y >= 0.0 {
            put(image, x as i64, y as i64, colour);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_are_clipped_and_reach_both_ends() {
        let mut img = RgbImage::new(10, 10);
        let c = Rgb([255, 0, 0]);
        draw_line(&mut img, (0.5, 0.5), (9.5, 9.5), c);
        assert_eq!(*img.get_pixel(0, 0), c);
        assert_eq!(*img.get_pixel(9, 9), c);
        assert_eq!(img.pixels().filter(|p| **p == c).count(), 10);
        // Off-image and non-finite ends do not panic.
        draw_line(&mut img, (-50.0, 5.0), (500.0, 5.0), c);
        draw_line(&mut img, (f64::NAN, 5.0), (5.0, 5.0), c);
    }
}
