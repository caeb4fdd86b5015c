//! [`RuleSet`]: whose rules a stage follows, ours or the official code's; and
//! [`RuleBook`], the one seam behind which the rule sets differ.
//!
//! Every stage that cuts, samples, renders or loads a face takes a `RuleSet`, a plain
//! name that files store and the CLI parses. What the name decides is its book: one
//! implementation of [`RuleBook`] per rule set (`crop/exact.rs`, ours;
//! `crop/official.rs`, the official loader's), registered in one line each in
//! `crop/mod.rs` (`rule_sets!`). A book answers for the four things that differ between
//! the rule sets:
//! - the crop: the box around the landmarks ([`RuleBook::crop_around`]), where a crop
//!   pixel samples it ([`RuleBook::sample_offset`]) and how an image is resampled into it
//!   ([`RuleBook::resampling`]);
//! - the raster's rounding: the projection as read ([`RuleBook::projection`]) and the
//!   rasterizer's rules ([`RuleBook::rasterize`]);
//! - the mask rules ([`RuleBook::mask`], [`MaskRule`]): where the mask is rasterized,
//!   how the holes are closed and where a loader item's points come from;
//! - the UV layout ([`RuleBook::uv_layout`], [`UvLayout`]).
//!
//! The stages ask the book and never name a rule set; the books are called once per
//! crop, image or item, so every pixel loop below them stays the one the rule picked.
//! Adding a rule set is one file implementing `RuleBook` and one line in `rule_sets!`
//! (the tests add a third, `crop/probe.rs`, that way, and cut, render and load through
//! it in `loader/item.rs`).
//!
//! Strings are parsed once, at the edges: the CLI's `--compat` and `--crop` values,
//! Python's `compat=`, and the names stored in files ([`RuleSet::parse`] for `exact` /
//! `official` in `crops.json` and `render.json`, [`RuleSet::from_sampling_name`] for the
//! targets' `crop_sampling` column; the crop store's part headers hold
//! `RuleSet::header_code`).

use crate::crop::{CropTransform, RuleSet};
use arkit_core::{Error, Result, ScreenVertex, VisibilityBuffer};

/// The rule sets and their books: `Variant => book,` per rule set (a `#[cfg(...)]`
/// before a line is kept on the variant and its book). Makes the [`RuleSet`] enum,
/// [`RuleSet::ALL`] in the order of the lines, and `RuleSet::book`.
macro_rules! rule_sets {
    ($($(#[cfg($when:meta)])? $(#[doc = $doc:literal])* $variant:ident => $book:expr,)*) => {
        /// Whose rules a stage follows (see the module docs of `crop::rules`).
        ///
        /// Serialized as its [`name`](RuleSet::name) (`"exact"`, `"official"`), as
        /// `crops.json` and `render.json` store it; read back through
        /// [`RuleSet::parse`], so a file naming another rule set gets that function's
        /// error.
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        pub enum RuleSet {
            $($(#[cfg($when)])? $(#[doc = $doc])* $variant,)*
        }

        impl RuleSet {
            /// Every rule set, in the order of their header codes.
            pub const ALL: &'static [RuleSet] = &[$($(#[cfg($when)])? RuleSet::$variant,)*];

            /// What this rule set decides.
            pub(crate) fn book(self) -> &'static dyn crate::crop::rules::RuleBook {
                match self {
                    $($(#[cfg($when)])? RuleSet::$variant => &$book,)*
                }
            }
        }
    };
}
pub(crate) use rule_sets;

/// What a rule set decides (see the module docs): one implementation per rule set.
pub(crate) trait RuleBook: Sync {
    /// The name the CLI, Python and the stored files use (`"exact"`).
    fn name(&self) -> &'static str;

    /// The name stored in the targets' `crop_sampling` column (`"centre"`).
    fn sampling_name(&self) -> &'static str;

    /// The code stored in a crop store part's header.
    fn header_code(&self) -> u32;

    /// Where crop pixel `(i, j)` samples the crop's continuous coordinates: at
    /// `(i + o, j + o)`.
    fn sample_offset(&self) -> f64;

    /// The crop of this rule set's box around the projected landmarks `(u, v)` at side
    /// `size`, or why there is none (the message names the box).
    fn crop_around(
        &self,
        landmarks: &[(f64, f64)],
        size: u32,
    ) -> std::result::Result<CropTransform, String>;

    /// How an image is resampled into the crop ([`CropTransform::crop_window`]).
    fn resampling(&self) -> Resampling;

    /// The release camera's projection matrix as this rule set's loader reads it.
    fn projection(&self, release: nalgebra::Matrix4<f64>) -> nalgebra::Matrix4<f64>;

    /// Rasterizes `triangles` of `screen` into `buffer` (cleared, at the size to fill)
    /// by this rule set's rules; with the weights, or where the rules allow without
    /// them (`weights` false: triangles and depths only).
    fn rasterize(
        &self,
        buffer: &mut VisibilityBuffer,
        screen: &[ScreenVertex],
        triangles: &[[u32; 3]],
        weights: bool,
    ) -> std::result::Result<(), String>;

    /// Where the mask is drawn, the holes closed and the points drawn.
    fn mask(&self) -> MaskRule;

    /// The loader's UV position map's layout.
    fn uv_layout(&self) -> UvLayout;
}

/// The mask rules: where the face mask is rasterized and what follows from it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum MaskRule {
    /// At the crop's resolution, the eye and mouth holes closed by centroid fans; the
    /// renderer's landmarks those stored in the samples table; a loader item's points
    /// drawn from the crop mask.
    Crop,
    /// Over the whole image (held over the window the face can cover), then warped
    /// into the crop; the holes closed by the official organ triangles; the landmarks
    /// projected in `f64`; a loader item's points drawn from the official slice of
    /// the full-resolution mask.
    WarpedFromImage,
}

/// How an image is resampled into a crop: a choice of the crop's own code, so that a
/// crop's pixel loop is the one the rule picked, inlined where the crop is cut.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Resampling {
    /// Ours: bilinear at pixel centres, black outside the image
    /// ([`CropTransform::crop_image`]).
    Bilinear,
    /// `cv2.warpAffine`'s fixed-point bilinear at pixel corners
    /// ([`crate::crop::warp_affine`]).
    WarpAffine,
}

/// The loader's UV position map's layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum UvLayout {
    /// Ours: texel centres, `S` texels a side (`render::uv_map::UvMapper`).
    TexelCentres,
    /// The official: the UV triangles drawn at `uv * (S - 1)` (`OfficialUvLayout`).
    Official,
}

/// `--compat`'s values: every registered rule set, by its name.
#[cfg(feature = "clap")]
impl clap::ValueEnum for RuleSet {
    fn value_variants<'a>() -> &'a [Self] {
        RuleSet::ALL
    }

    fn to_possible_value(&self) -> Option<clap::builder::PossibleValue> {
        Some(clap::builder::PossibleValue::new(self.name()))
    }
}

impl RuleSet {
    /// `"exact"` or `"official"`: the name the CLI, Python and the stored files use.
    pub fn parse(name: &str) -> Result<Self> {
        RuleSet::ALL
            .iter()
            .copied()
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
        self.book().name()
    }

    /// The crop of this rule set's box around projected landmarks
    /// `[u0, v0, u1, v1, ...]`; `None` when the official box is empty.
    pub fn crop_around_landmarks(self, landmarks_2d: &[f32], size: u32) -> Option<CropTransform> {
        let points: Vec<(f64, f64)> = landmarks_2d
            .chunks_exact(2)
            .map(|p| (p[0] as f64, p[1] as f64))
            .collect();
        self.book().crop_around(&points, size).ok()
    }

    /// Where crop pixel `(i, j)` samples the crop's continuous coordinates: at its
    /// centre `(i + 0.5, j + 0.5)` (ours, the crate's pixel-centre rule) or at the
    /// integer point `(i, j)` (OpenCV's, the official loader's).
    pub(crate) fn sample_offset(self) -> f64 {
        self.book().sample_offset()
    }

    /// The name stored in the targets' `crop_sampling` column: `"centre"` or `"corner"`.
    pub(crate) fn sampling_name(self) -> &'static str {
        self.book().sampling_name()
    }

    /// The rule set of a `crop_sampling` column value; `None` for another name.
    pub(crate) fn from_sampling_name(name: &str) -> Option<Self> {
        RuleSet::ALL
            .iter()
            .copied()
            .find(|r| r.sampling_name() == name)
    }

    /// The code stored in a crop store part's header.
    pub(crate) fn header_code(self) -> u32 {
        self.book().header_code()
    }
}

impl Default for RuleSet {
    /// Ours.
    fn default() -> Self {
        RuleSet::Exact
    }
}

impl serde::Serialize for RuleSet {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> serde::Deserialize<'de> for RuleSet {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        RuleSet::parse(&name).map_err(serde::de::Error::custom)
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
        for &r in RuleSet::ALL {
            assert_eq!(RuleSet::parse(r.name()).unwrap(), r);
            assert_eq!(RuleSet::from_sampling_name(r.sampling_name()), Some(r));
            let json = serde_json::to_string(&r).unwrap();
            assert_eq!(json, format!("\"{}\"", r.name()));
            assert_eq!(serde_json::from_str::<RuleSet>(&json).unwrap(), r);
        }
        // Every header code and every name is one rule set's.
        for (i, &a) in RuleSet::ALL.iter().enumerate() {
            for &b in &RuleSet::ALL[i + 1..] {
                assert_ne!(a.header_code(), b.header_code());
                assert_ne!(a.name(), b.name());
                assert_ne!(a.sampling_name(), b.sampling_name());
            }
        }
        // The codes the store has always written, and the offsets by hand.
        assert_eq!(RuleSet::Exact.header_code(), 0);
        assert_eq!(RuleSet::Official.header_code(), 1);
        assert_eq!(RuleSet::Exact.sample_offset(), 0.5);
        assert_eq!(RuleSet::Official.sample_offset(), 0.0);
        assert_eq!(RuleSet::default(), RuleSet::Exact);
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
