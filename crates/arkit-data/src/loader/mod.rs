//! `loader`: one training or evaluation item as the official PyTorch loader returns it.
//!
//! Takes a converted, rendered dataset ([`crate::store::Dataset`]), the rules (`exact`
//! or `official`), a seed, and optionally a crop store ([`crate::store::crop_store`]).
//! Gives [`FaceLoader`]'s [`LoaderItem`]s: the crop, the mask, the correspondences and
//! the UV map of the official loader, colour-jittered in training ([`ColourJitter`]);
//! the dense `corr_mat` ([`write_correspondence_matrix`]); the crop store of a whole
//! dataset ([`write_crop_store`], each record computed by the loader's own rules, so it
//! lives here, not in `store`, which comes before the loader). Guarantees: item `i` of
//! epoch `e` is a pure function of the dataset, the rules, the seed, `i` and `e`; an
//! evaluation item is bit for bit the same with and without the crop store. Depends on `store`, `render`, `crop`, `mesh`,
//! `ingest` and `arkit_core`.

pub(crate) mod colour_jitter;
pub(crate) mod correspondence_matrix;
pub(crate) mod crops_dataset;
pub(crate) mod item;
pub(crate) mod official_uv;

pub use self::{
    colour_jitter::{ColourJitter, ColourJitterRanges, jitter_colour},
    correspondence_matrix::{rewrite_correspondence_matrix, write_correspondence_matrix},
    crops_dataset::{CropStoreSummary, write_crop_store, write_crop_store_with},
    item::{
        FaceLoader, IMAGENET_MEAN, IMAGENET_STD, ItemPlanes, LoaderItem, LoaderMode, LoaderOptions,
        normalise, read_uv_triangles, tform_inv, widen_mask_into,
    },
    official_uv::official_organ_triangles,
};
