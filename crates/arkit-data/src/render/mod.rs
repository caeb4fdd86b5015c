//! `render`: PerspNet's training targets, rendered once on the CPU.
//!
//! Contract: [`face::FaceRenderer`] turns one sample (image, mesh, pose, camera) into
//! its crop, face mask, sparse barycentric correspondences and UV position map, as the
//! official code's rasterizer does; [`dataset`] renders a whole converted dataset shard
//! by shard into `targets/`, deterministic from the seed and the sample's key. Depends
//! on `store`, `crop`, `mesh` and `arkit_core`.

pub mod dataset;
pub mod face;
