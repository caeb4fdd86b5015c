//! `face_targets`: what PerspNet learns from one sample, at crop resolution: the crop,
//! the face mask, and per mask pixel the visible triangle's vertex ids and barycentric
//! weights (the ground-truth rows of the correspondence matrix).
//!
//! A value type shared by the renderer that computes it ([`crate::render::face`]) and the
//! table that stores it ([`crate::store::targets_table`]). Invariants: `corr_vertices` and
//! `corr_weights` have one entry per set pixel of `mask`, in row-major order
//! ([`mask_pixel_indices`]); each weight triple sums to 1. Tested in `render` (every
//! correspondence lands in its pixel) and `targets_table` (storage round trips).

use crate::crop::CropTransform;
use nalgebra::Point3;

/// The targets of one sample at crop resolution.
#[derive(Clone, Debug, PartialEq)]
pub struct FaceTargets {
    /// The crop.
    pub crop: CropTransform,
    /// Face mask, row-major `size * size`.
    pub mask: Vec<bool>,
    /// For each mask pixel in row-major order: the visible triangle's vertex ids.
    pub corr_vertices: Vec<[u16; 3]>,
    /// For each mask pixel: perspective-correct barycentric weights (sum 1).
    pub corr_weights: Vec<[f32; 3]>,
}

impl FaceTargets {
    /// Row-major indices of the mask pixels (the rows of the correspondence matrix).
    pub fn mask_pixels(&self) -> Vec<u32> {
        mask_pixel_indices(&self.mask)
    }

    /// The coordinate map at the mask pixels: the canonical position under each pixel,
    /// `sum_k w_k V_k`.
    pub fn coordinate_map(&self, verts: &[Point3<f32>]) -> Vec<Point3<f32>> {
        (0..self.corr_vertices.len())
            .map(|k| self.coordinate_at(verts, k))
            .collect()
    }

    /// The coordinate map at the `k`-th mask pixel alone (what
    /// [`FaceTargets::coordinate_map`] holds there), for callers that need a few points.
    pub fn coordinate_at(&self, verts: &[Point3<f32>], k: usize) -> Point3<f32> {
        canonical_position(verts, self.corr_vertices[k], self.corr_weights[k])
    }
}

/// The canonical position a correspondence row names: `sum_k w_k V_k` over its three
/// vertex ids `v` and weights `w`.
pub(crate) fn canonical_position(verts: &[Point3<f32>], v: [u16; 3], w: [f32; 3]) -> Point3<f32> {
    Point3::from(
        verts[v[0] as usize].coords * w[0]
            + verts[v[1] as usize].coords * w[1]
            + verts[v[2] as usize].coords * w[2],
    )
}

/// The row-major indices of a mask's set pixels, in order (the rows of the stored
/// correspondences follow this order).
pub fn mask_pixel_indices(mask: &[bool]) -> Vec<u32> {
    mask.iter()
        .enumerate()
        .filter(|(_, m)| **m)
        .map(|(i, _)| i as u32)
        .collect()
}
