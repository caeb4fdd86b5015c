//! `raw`: the window's `W x W x 3` bytes as they are: no decoding, about four times the
//! disk of `pred-zstd`, the fastest to read.

use super::super::format::window_side;
use super::coder::WindowCoder;
use arkit_core::{Error, Result};

/// The `raw` codec.
pub(super) struct Raw;

impl WindowCoder for Raw {
    const STORES_PIXELS: bool = true;

    fn encode(window: &image::RgbImage, _size: u32) -> Result<Vec<u8>> {
        Ok(window.as_raw().clone())
    }

    fn decode_whole(bytes: &[u8], size: u32) -> Result<Vec<u8>> {
        let side = window_side(size);
        let want = 3 * side * side;
        if bytes.len() != want {
            return Err(Error::invalid(
                "crop store",
                format!("a raw window of {} bytes, expected {want}", bytes.len()),
            ));
        }
        Ok(bytes.to_vec())
    }
}
