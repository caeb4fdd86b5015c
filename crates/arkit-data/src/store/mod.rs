//! `store`: a converted dataset on disk and the tables it holds.
//!
//! Takes a converted dataset's folder. Gives [`Dataset`] (opened once), its
//! [`Manifest`], the tables' rows ([`read_samples`] to [`SampleRecord`],
//! [`read_targets`] to [`TargetsRecord`], [`read_predictions`]), the split files
//! ([`SplitLookup`]), the Parquet helpers the tables share ([`read_parquet`],
//! [`write_parquet`]), the seam the crop store reads through ([`ReadAt`],
//! [`LocalFile`]; `storage` implements it for objects in a bucket), and the crop store
//! ([`crop_store`]). Guarantees: each shard is checked against its manifest (size and
//! hash) before it is read; every column's type and every length is checked against the
//! schema before it is used; writers write under a temporary name and rename; the crop
//! store refuses a record of another dataset, shard, row or sample. Depends on `mesh`,
//! `crop`, `picture` and `arkit_core`.

// `pub mod`: the crop store is a room of its own (one door, its `mod.rs`); its names
// (`read_manifest`, `FORMAT`, `margin`) are the store's and would clash with the dataset's.
pub mod crop_store;
pub(crate) mod dataset;
pub(crate) mod face_targets;
pub(crate) mod manifest;
pub(crate) mod parquet;
pub(crate) mod predictions_table;
pub(crate) mod read_at;
pub(crate) mod rendered_targets;
pub(crate) mod samples_table;
pub(crate) mod splits;
pub(crate) mod targets_table;

pub use self::{
    dataset::Dataset,
    face_targets::{FaceTargets, mask_pixel_indices},
    manifest::{
        LayoutKind, MANIFEST_FILE, MAX_SHARDS, Manifest, ShardEntry, check_shard_file,
        check_topology, dataset_fingerprint, read_manifest, sha256_file, tail_sha256,
    },
    parquet::{
        HeldFile, arrow_schema_value, f64_values, parquet_key_value_metadata, parquet_row_count,
        read_parquet, read_parquet_columns, str_values, write_parquet, write_parquet_with_metadata,
    },
    predictions_table::{predictions_frame, read_predictions, write_predictions},
    read_at::{LocalFile, ReadAt},
    rendered_targets::RenderedTargets,
    samples_table::{
        ColumnSpec, ERRORS_COLUMNS, ErrorRecord, SAMPLES_COLUMNS, SAMPLES_FORMAT, SampleRecord,
        huggingface_metadata, huggingface_shapes, polars_dtype, polars_dtype_with, read_errors,
        read_sample_keys, read_samples, read_samples_expecting, samples_frame,
        samples_frame_format1, write_samples,
    },
    splits::SplitLookup,
    targets_table::{
        DenseTargets, TargetsRecord, WEIGHT_QUANTUM, dense, errors_path, read_skipped_keys,
        read_targets, read_targets_by_key, shard_path,
    },
};
