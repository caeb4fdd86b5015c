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
    #[cfg(test)]
    pub(crate) fn coordinate_map(&self, verts: &[Point3<f32>]) -> Vec<Point3<f32>> {
        (0..self.corr_vertices.len())
            .map(|k| self.coordinate_at(verts, k))
            .collect()
    }

    /// The coordinate map at the `k`-th mask pixel alone (what
    /// [`FaceTargets::coordinate_map`] holds there), for callers that need a few points.
    #[cfg(test)]
    pub(crate) fn coordinate_at(&self, verts: &[Point3<f32>], k: usize) -> Point3<f32> {
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
    let mut out = Vec::new();
    for_each_set_run(mask, |start, len| {
        out.extend(start as u32..(start + len) as u32)
    });
    out
}

/// Calls `run(start, len)` for the set values of `mask`, `start..start + len`, in
/// order, looking at sixteen values at a time: a chunk all unset is skipped, a chunk all
/// set is one run, and in a chunk that holds an edge each set value is found from the
/// chunk's bits (a face's rows are long runs, so few chunks are looked into).
pub(crate) fn for_each_set_run(mask: &[bool], mut run: impl FnMut(usize, usize)) {
    const ALL_SET: u128 = u128::from_ne_bytes([1; 16]);
    let mut chunks = mask.chunks_exact(16);
    let mut at = 0;
    for chunk in &mut chunks {
        // A bool is the byte 0 or 1, so value k is bit 8k of the little-endian word.
        let bytes: [u8; 16] = std::array::from_fn(|k| chunk[k] as u8);
        match u128::from_le_bytes(bytes) {
            0 => {}
            ALL_SET => run(at, 16),
            mut bits => {
                while bits != 0 {
                    run(at + bits.trailing_zeros() as usize / 8, 1);
                    bits &= bits - 1;
                }
            }
        }
        at += 16;
    }
    for (k, &set) in chunks.remainder().iter().enumerate() {
        if set {
            run(at + k, 1);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mask_pixel_indices_are_the_set_values_in_order() {
        // By hand: a chunk all set (0..16), one with an edge (set at 17, 18 and 31), one
        // all unset (32..48), and a remainder of five values with the last set.
        let mut mask = vec![false; 53];
        for i in (0..16).chain([17, 18, 31, 52]) {
            mask[i] = true;
        }
        let want: Vec<u32> = (0..16).chain([17, 18, 31, 52]).collect();
        assert_eq!(mask_pixel_indices(&mask), want);
        // And every single set value at every position of two chunks and a remainder.
        for at in 0..37 {
            let mut one = vec![false; 37];
            one[at] = true;
            assert_eq!(mask_pixel_indices(&one), [at as u32]);
            let all_but: Vec<bool> = (0..37).map(|i| i != at).collect();
            let want: Vec<u32> = (0..37).filter(|&i| i != at as u32).collect();
            assert_eq!(mask_pixel_indices(&all_but), want);
        }
        assert!(mask_pixel_indices(&[]).is_empty());
    }
}
