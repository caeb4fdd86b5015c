//! Our rule set's book ([`Exact`]): the square box of half-side 0.75 x the landmarks'
//! larger side, sampled at pixel centres with our bilinear crop; the release camera's
//! projection as is; the top-left fill rule and perspective-correct weights at the
//! crop's resolution; the UV map at texel centres.

use crate::crop::CropTransform;
use crate::crop::rules::{MaskRule, Resampling, RuleBook, UvLayout};
use arkit_core::{ScreenVertex, VisibilityBuffer};

/// Our rules (see the module docs).
pub(crate) struct Exact;

impl RuleBook for Exact {
    fn name(&self) -> &'static str {
        "exact"
    }

    fn sampling_name(&self) -> &'static str {
        "centre"
    }

    fn header_code(&self) -> u32 {
        0
    }

    fn sample_offset(&self) -> f64 {
        0.5
    }

    fn crop_around(
        &self,
        landmarks: &[(f64, f64)],
        size: u32,
    ) -> std::result::Result<CropTransform, String> {
        // The box of the landmarks as float32, as the samples table stores them.
        let flat: Vec<f32> = landmarks
            .iter()
            .flat_map(|&(u, v)| [u as f32, v as f32])
            .collect();
        Ok(CropTransform::around_landmarks(&flat, size))
    }

    fn resampling(&self) -> Resampling {
        Resampling::Bilinear
    }

    fn projection(&self, release: nalgebra::Matrix4<f64>) -> nalgebra::Matrix4<f64> {
        release
    }

    fn rasterize(
        &self,
        buffer: &mut VisibilityBuffer,
        screen: &[ScreenVertex],
        triangles: &[[u32; 3]],
        weights: bool,
    ) -> std::result::Result<(), String> {
        let drawn = if weights {
            buffer.rasterize_mesh(screen, triangles)
        } else {
            buffer.rasterize_visibility(screen, triangles)
        };
        drawn.map_err(|e| e.to_string())
    }

    fn mask(&self) -> MaskRule {
        MaskRule::Crop
    }

    fn uv_layout(&self) -> UvLayout {
        UvLayout::TexelCentres
    }
}
