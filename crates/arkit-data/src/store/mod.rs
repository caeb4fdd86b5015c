//! `store`: a converted dataset on disk and the tables it holds.
//!
//! Contract: [`dataset::Dataset`] opens a dataset once and checks each shard against
//! its [`manifest`] (size and hash) before it is read; the tables' readers
//! ([`samples_table`], [`targets_table`], [`predictions_table`]) check every column's
//! type and every length against the schema before using it; writers write under a
//! temporary name and rename. [`parquet`] holds the Parquet helpers the tables share,
//! [`splits`] the `splits/` files every stage that picks a split reads. [`crop_store`]
//! keeps every sample's crop window and mesh once, for the loader, and refuses a record
//! of another dataset, shard, row or sample. Depends on `mesh`, `crop`, `picture` and
//! `arkit_core`.

pub mod crop_store;
pub mod dataset;
pub mod face_targets;
pub mod manifest;
pub mod parquet;
pub mod predictions_table;
pub mod samples_table;
pub mod splits;
pub mod targets_table;
