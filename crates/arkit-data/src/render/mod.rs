//! `render`: PerspNet's training targets, rendered once on the CPU.
//!
//! Takes one sample (image, mesh, pose, camera) or a whole converted dataset. Gives its
//! crop, face mask, sparse barycentric correspondences and UV position map
//! ([`FaceRenderer`], [`UvMapper`]), and for a dataset the `targets/` shards
//! ([`render_dataset`], [`RenderSummary`]). Guarantees: the targets are the official
//! code's rasterizer's; a dataset's are deterministic from the seed and each sample's
//! position; a sample that cannot be rendered gets a row in the `errors` table instead
//! of targets, never a substitute, and never stops the run. Depends on `store`,
//! `crop`, `mesh` and `arkit_core`.

pub(crate) mod dataset;
pub(crate) mod face;
pub(crate) mod uv_map;

pub use self::{
    dataset::{RenderOptions, RenderSummary, render_dataset, render_dataset_replacing},
    face::{FaceRenderer, ModeDifference, sample_points},
    uv_map::{UvMapper, UvTexels},
};
