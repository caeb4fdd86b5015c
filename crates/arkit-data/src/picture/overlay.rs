//! Drawing a posed face mesh over an image, for people to look at: previews of
//! `synth` and `augment`, and the worst predictions of `eval`'s report.

use crate::mesh::topology::FaceTopology;
use arkit_core::conventions::{Camera, Pose};
use arkit_core::error::Result;
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
pub fn draw_mesh(
    image: &mut RgbImage,
    topology: &FaceTopology,
    verts: &[Point3<f64>],
    pose: &Pose,
    style: &MeshStyle,
) -> Result<()> {
    let camera = Camera::release(image.width(), image.height());
    let p = camera.project_all(pose, verts);
    if let Some(colour) = style.edges {
        for t in topology.triangles.iter().step_by(7) {
            let (a, b) = (&p[t[0] as usize], &p[t[1] as usize]);
            draw_line(image, (a.u, a.v), (b.u, b.v), colour);
        }
    }
    for (_, l) in &topology.boundary_loops()?.loops {
        for k in 0..l.len() {
            let (a, b) = (&p[l[k] as usize], &p[l[(k + 1) % l.len()] as usize]);
            draw_line(image, (a.u, a.v), (b.u, b.v), style.outline);
        }
    }
    if let Some(colour) = style.landmarks {
        for &l in &topology.landmarks {
            let q = &p[l as usize];
            for dy in -1..=1 {
                for dx in -1..=1 {
                    put(
                        image,
                        q.u.floor() as i64 + dx,
                        q.v.floor() as i64 + dy,
                        colour,
                    );
                }
            }
        }
    }
    Ok(())
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
