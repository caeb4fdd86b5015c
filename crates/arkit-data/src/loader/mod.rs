//! `loader`: one training or evaluation item as the official PyTorch loader returns it.
//!
//! Contract: [`item::FaceLoader`] serves item `i` of epoch `e` as a pure function of
//! the dataset, the rules (`exact` or `official`), the seed, `i` and `e`: the crop, the
//! mask, the correspondences and the UV map of the official loader, with its
//! [`colour_jitter`] in training; [`correspondence_matrix`] writes the dense
//! `corr_mat`. [`crop_store`] keeps each sample's crop window and mesh once so an epoch
//! reads small records instead of decoding JPEGs, and refuses a record of another
//! dataset, shard, row or sample; [`crops_dataset`] writes the store of a whole
//! dataset. Depends on `store`, `render`, `crop`, `mesh`, `ingest` and
//! `arkit_core`.

pub mod colour_jitter;
pub mod correspondence_matrix;
pub mod crop_store;
pub mod crops_dataset;
pub mod item;
