//! A third rule set, for the tests only ([`Probe`]): ours with a box of half-side 0.9
//! x the landmarks' larger side instead of 0.75, and every other rule ours. It shows
//! what a rule set is made of: this file and its line in `rule_sets!` (`crop/mod.rs`).
//! The tests that cut, render and load through it are in `loader/item.rs`
//! (`a_third_rule_set_cuts_renders_and_loads`).

use crate::crop::exact::Exact;
use crate::crop::rules::{MaskRule, Resampling, RuleBook, UvLayout};
use crate::crop::{CropTransform, RuleSet};
use arkit_core::{ScreenVertex, VisibilityBuffer};

/// Ours with a wider box (see the module docs).
pub(crate) struct Probe;

/// The box's half-side over the landmarks' larger side (ours: 0.75).
pub(crate) const HALF_SIDE: f64 = 0.9;

impl RuleBook for Probe {
    fn name(&self) -> &'static str {
        "probe"
    }

    fn sampling_name(&self) -> &'static str {
        "probe-centre"
    }

    fn header_code(&self) -> u32 {
        2
    }

    fn sample_offset(&self) -> f64 {
        Exact.sample_offset()
    }

    fn crop_around(
        &self,
        landmarks: &[(f64, f64)],
        size: u32,
    ) -> std::result::Result<CropTransform, String> {
        let ours = Exact.crop_around(landmarks, size)?;
        let (cx, cy) = (ours.x0 + ours.side / 2.0, ours.y0 + ours.side_y / 2.0);
        let side = ours.side * HALF_SIDE / 0.75;
        Ok(CropTransform {
            x0: cx - side / 2.0,
            y0: cy - side / 2.0,
            side,
            side_y: side,
            size,
            rules: RuleSet::Probe,
        })
    }

    fn resampling(&self) -> Resampling {
        Resampling::Bilinear
    }

    fn projection(&self, release: nalgebra::Matrix4<f64>) -> nalgebra::Matrix4<f64> {
        Exact.projection(release)
    }

    fn rasterize(
        &self,
        buffer: &mut VisibilityBuffer,
        screen: &[ScreenVertex],
        triangles: &[[u32; 3]],
        weights: bool,
    ) -> std::result::Result<(), String> {
        Exact.rasterize(buffer, screen, triangles, weights)
    }

    fn mask(&self) -> MaskRule {
        MaskRule::Crop
    }

    fn uv_layout(&self) -> UvLayout {
        UvLayout::TexelCentres
    }
}
