//! What every binding shares: `DataError`, the one exception they raise, and [`run`],
//! which does Rust's work without the GIL and turns any error or panic into it.

use arkit_core::Error;
use pyo3::create_exception;
use pyo3::prelude::*;

create_exception!(
    _native,
    DataError,
    pyo3::exceptions::PyValueError,
    "A dataset, sample or argument that arkit_tool cannot use; the message names the file and the problem."
);

pub(crate) fn py_err(e: Error) -> PyErr {
    DataError::new_err(e.to_string())
}

/// Runs `f` without the GIL, turning an error or a panic into `DataError`.
pub(crate) fn run<T: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> arkit_core::Result<T> + Send,
) -> PyResult<T> {
    py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)))
        .map_err(|p| {
            let why = p
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            DataError::new_err(format!("internal error (a bug in arkit_tool): {why}"))
        })?
        .map_err(py_err)
}
