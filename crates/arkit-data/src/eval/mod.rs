//! `eval`: the paper's metrics and a dataset's predictions scored.
//!
//! Contract: [`metrics`] computes every metric exactly as the official evaluation does;
//! [`dataset`] matches a predictions file to a dataset's samples (every row matched or
//! reported), and writes the per-sample table and the report. Depends on `store`,
//! `picture`, `ingest` (BIWI's topology prefix) and `arkit_core`.

pub mod dataset;
pub mod metrics;
