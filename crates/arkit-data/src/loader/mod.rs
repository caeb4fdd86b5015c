//! `loader`: one training or evaluation item as the official PyTorch loader returns it.
//!
//! Contract: [`item::FaceLoader`] serves item `i` of epoch `e` as a pure function of
//! the dataset, the rules (`exact` or `official`), the seed, `i` and `e`: the crop, the
//! mask, the correspondences and the UV map of the official loader, with its
//! [`colour_jitter`] in training; [`correspondence_matrix`] writes the dense
//! `corr_mat`. With a crop store ([`crate::store::crop_store`]) it reads each sample's
//! crop window and mesh from one small record instead of decoding its JPEG;
//! [`crops_dataset`] writes the store of a whole dataset, each record computed by the
//! loader's own rules (so it lives here, not in `store`, which comes before the loader).
//! Depends on `store`, `render`, `crop`, `mesh`, `ingest` and `arkit_core`.

pub mod colour_jitter;
pub mod correspondence_matrix;
pub mod crops_dataset;
pub mod item;
