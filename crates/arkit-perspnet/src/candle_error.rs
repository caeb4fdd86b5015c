//! candle's errors as the workspace's: one conversion that names what failed.

/// A candle error as ours, naming what failed.
pub(crate) fn candle_err(what: &str, e: candle_core::Error) -> arkit_core::Error {
    arkit_core::Error::invalid(what, e.to_string())
}
