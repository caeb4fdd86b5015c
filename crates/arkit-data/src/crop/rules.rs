//! [`RuleSet`]: whose rules a stage follows, ours or the official code's, in one type.
//!
//! Every stage that cuts, samples, renders or loads a face takes a `RuleSet`: the crop
//! box ([`RuleSet::crop_around_landmarks`]), where a crop pixel samples the image
//! ([`RuleSet::sample_offset`]), the rasterizer's rules (`render::face`), the loader's
//! projection and targets (`loader::item`) and the crop store's header. Strings are
//! parsed once, at the edges: the CLI's `--compat` and `--crop` values, Python's
//! `compat=`, and the names stored in files ([`RuleSet::parse`] for `exact` /
//! `official` in `crops.json` and `render.json`, [`RuleSet::from_sampling_name`] for the
//! targets' `crop_sampling` column; the crop store's part headers hold
//! `RuleSet::header_code`). Adding a rule set is adding a variant here and following the
//! compiler through each `match`.

use crate::crop::{CropTransform, official};
use arkit_core::{Error, Result};

/// Whose rules a stage follows (see the module docs).
///
/// Serialized as its [`name`](RuleSet::name) (`"exact"`, `"official"`), as `crops.json`
/// and `render.json` store it; read back through [`RuleSet::parse`], so a file naming
/// another rule set gets that function's error.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case", try_from = "String")]
pub enum RuleSet {
    /// Ours: the square box of half-side 0.75 x the landmarks' larger side, sampled at
    /// pixel centres with our bilinear crop; the top-left fill rule and
    /// perspective-correct weights, rendered at the crop's resolution.
    #[default]
    Exact,
    /// The official loader's: its integer box and `cv2` affine map sampled at pixel
    /// corners (`cv2.warpAffine`), its rasterizer over the whole image with
    /// screen-space weights, the mask warped into the crop.
    Official,
}

impl RuleSet {
    /// Every rule set, in the order of their header codes.
    pub const ALL: [RuleSet; 2] = [RuleSet::Exact, RuleSet::Official];

    /// `"exact"` or `"official"`: the name the CLI, Python and the stored files use.
    pub fn parse(name: &str) -> Result<Self> {
        RuleSet::ALL
            .into_iter()
            .find(|r| r.name() == name)
            .ok_or_else(|| {
                Error::invalid(
                    "compat",
                    format!("'{name}': expected 'exact' or 'official'"),
                )
            })
    }

    /// `"exact"` or `"official"`.
    pub fn name(self) -> &'static str {
        match self {
            RuleSet::Exact => "exact",
            RuleSet::Official => "official",
        }
    }

    /// The crop of this rule set's box around projected landmarks
    /// `[u0, v0, u1, v1, ...]`; `None` when the official box is empty.
    pub fn crop_around_landmarks(self, landmarks_2d: &[f32], size: u32) -> Option<CropTransform> {
        match self {
            RuleSet::Exact => Some(CropTransform::around_landmarks(landmarks_2d, size)),
            RuleSet::Official => official::official_crop(
                landmarks_2d
                    .chunks_exact(2)
                    .map(|p| (p[0] as f64, p[1] as f64)),
                size,
            ),
        }
    }

    /// Where crop pixel `(i, j)` samples the crop's continuous coordinates: at its
    /// centre `(i + 0.5, j + 0.5)` (ours, the crate's pixel-centre rule) or at the
    /// integer point `(i, j)` (OpenCV's, the official loader's).
    pub(crate) fn sample_offset(self) -> f64 {
        match self {
            RuleSet::Exact => 0.5,
            RuleSet::Official => 0.0,
        }
    }

    /// The name stored in the targets' `crop_sampling` column: `"centre"` or `"corner"`.
    pub(crate) fn sampling_name(self) -> &'static str {
        match self {
            RuleSet::Exact => "centre",
            RuleSet::Official => "corner",
        }
    }

    /// The rule set of a `crop_sampling` column value; `None` for another name.
    pub(crate) fn from_sampling_name(name: &str) -> Option<Self> {
        RuleSet::ALL.into_iter().find(|r| r.sampling_name() == name)
    }

    /// The code stored in a crop store part's header.
    pub(crate) fn header_code(self) -> u32 {
        match self {
            RuleSet::Exact => 0,
            RuleSet::Official => 1,
        }
    }
}

impl TryFrom<String> for RuleSet {
    type Error = Error;

    fn try_from(name: String) -> Result<Self> {
        RuleSet::parse(&name)
    }
}

impl std::fmt::Display for RuleSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_spelling_round_trips_and_others_are_refused() {
        for r in RuleSet::ALL {
            assert_eq!(RuleSet::parse(r.name()).unwrap(), r);
            assert_eq!(RuleSet::from_sampling_name(r.sampling_name()), Some(r));
            let json = serde_json::to_string(&r).unwrap();
            assert_eq!(json, format!("\"{}\"", r.name()));
            assert_eq!(serde_json::from_str::<RuleSet>(&json).unwrap(), r);
        }
        // The codes the store has always written, and the offsets by hand.
        assert_eq!(RuleSet::Exact.header_code(), 0);
        assert_eq!(RuleSet::Official.header_code(), 1);
        assert_eq!(RuleSet::Exact.sample_offset(), 0.5);
        assert_eq!(RuleSet::Official.sample_offset(), 0.0);
        let e = RuleSet::parse("opencv").unwrap_err().to_string();
        assert!(
            e.contains("'opencv'") && e.contains("'exact' or 'official'"),
            "{e}"
        );
        let e = serde_json::from_str::<RuleSet>("\"ours\"")
            .unwrap_err()
            .to_string();
        assert!(e.contains("'ours'"), "{e}");
        assert_eq!(RuleSet::from_sampling_name("centres"), None);
    }
}
