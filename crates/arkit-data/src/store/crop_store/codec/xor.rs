//! `xor`: a codec of the tests only (registered under `cfg(test)`, and `cfg(fuzzing)`
//! for cargo-fuzz's builds, which fuzz every codec), which shows what
//! adding a codec takes: this file and one line of the table in `codec/mod.rs`. Its
//! bytes are the window's, each XOR 0x5a, behind a one-byte tag.

use super::super::format::window_side;
use super::coder::WindowCoder;
use arkit_core::{Error, Result};

/// The `xor` codec.
pub(super) struct Xor;

const TAG: u8 = 0xa5;

impl WindowCoder for Xor {
    fn encode(window: &image::RgbImage, _size: u32) -> Result<Vec<u8>> {
        Ok(std::iter::once(TAG)
            .chain(window.as_raw().iter().map(|b| b ^ 0x5a))
            .collect())
    }

    fn decode_whole(bytes: &[u8], size: u32) -> Result<Vec<u8>> {
        let side = window_side(size);
        match bytes.split_first() {
            Some((&TAG, rest)) if rest.len() == 3 * side * side => {
                Ok(rest.iter().map(|b| b ^ 0x5a).collect())
            }
            _ => Err(Error::invalid("crop store", "not an xor window")),
        }
    }
}
