//! `ingest`: data from outside into a converted dataset.
//!
//! Takes the release's files, BIWI's (through [`biwi`]), a user's captures (made
//! release-shaped by [`import_capture`]) or a synthetic release ([`synth`]). Gives a
//! converted dataset: validated, sharded Parquet ([`convert()`], [`merge`]),
//! subject-disjoint splits from a seed ([`split_dataset`]), another camera's images
//! resampled into the release's ([`resample_to_release`]). Guarantees: a bad sample is
//! reported in the `errors` table and skipped, never substituted; a run stops when one
//! check ([`Check`]) skips most samples (the input is in another convention). Depends on `store`, `picture`,
//! `mesh` and `arkit_core`.

// `pub mod`: BIWI's own vocabulary (its `Calibration`, `FramePose`, `HeadMesh`, `stage`)
// reads as `biwi::X`; flat in `ingest` it would pass for the release's.
pub mod biwi;
// `pub mod`: the synthetic source's own vocabulary (`synth::generate`, `synth::plan`,
// `synth::ranges`) names nothing without `synth::`.
pub(crate) mod convert;
pub(crate) mod discover;
pub(crate) mod import_arkit;
pub(crate) mod merge;
pub(crate) mod release_camera;
pub(crate) mod split;
pub mod synth;
pub(crate) mod systematic;

/// The JPEG framing check `convert` runs on the release's images (it lives with the
/// image decoder, which runs it on every JPEG).
pub use crate::picture::check_jpeg_framing;

pub use self::{
    convert::{
        CONVERSION_FILE, ConversionFingerprint, ConvertChecks, ConvertOptions, Progress, Skip,
        ValidationContext, convert, convert_planned_with, manifest_name, read_conversion_record,
        read_dataset_samples, verify_dataset,
    },
    discover::{DiscoveredInput, PlannedRow, discover, plan_rows},
    import_arkit::{
        FoundFrame, FrameProblem, ImportOptions, ImportSummary, InterfaceOrientation, find_frames,
        import_capture,
    },
    merge::{Merged, merge},
    release_camera::resample_to_release,
    split::{HoldOut, SplitAssignment, SplitCount, assign, split_dataset},
    systematic::{Check, SYSTEMATIC_WINDOW},
};
