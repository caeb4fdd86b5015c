//! `eval`: the paper's metrics and a dataset's predictions scored.
//!
//! Takes a converted dataset and a predictions file (or in-memory poses). Gives the
//! per-sample errors ([`sample_errors`]), their [`Summary`] ([`summarize`]), the
//! dataset's [`Evaluation`] ([`evaluate`]) and the report ([`write_report`]).
//! Guarantees: every metric is computed exactly as the official evaluation does; every
//! row of the predictions file is matched to a sample or reported ([`MatchProblems`]);
//! a missing or unusable prediction is replaced by the identity, as the official
//! evaluation does, and counted ([`PoseFailure`]). Depends on `store`, `picture`, `ingest` (BIWI's topology prefix) and
//! `arkit_core`.

pub(crate) mod dataset;
pub(crate) mod metrics;

pub use self::{
    dataset::{
        EvalOptions, Evaluation, MatchProblems, PER_SAMPLE_COLUMNS, ReportFiles, ScoredSample,
        evaluate, per_sample_frame, png_bytes, write_report,
    },
    metrics::{
        EulerDifference, IDENTITY_RT, MaskScores, PoseFailure, SampleErrors, Summary,
        check_prediction, mask_scores, median, sample_errors, sample_errors_in, summarize,
    },
};
