//! `coder`: what a window codec's file implements ([`WindowCoder`]), and nothing else:
//! the table in `codec/mod.rs` dispatches to it. Uses only [`super::super::format`].

use super::super::format::{WindowPart, window_centre};
use arkit_core::Result;

/// A window codec: the bytes a record stores for the window of crop side `size` (`W x W`
/// RGB, `W =` [`super::super::format::window_side`]`(size)`) and the pixels back, losslessly.
/// Implemented by a unit struct in the codec's own file; registered by one line of the
/// table in `codec/mod.rs`, which gives it its name (in `crops.json`) and its code (in
/// every part file's header).
pub(super) trait WindowCoder {
    /// Whether the stored bytes are the window's `W x W x 3` pixels as they are: the
    /// reader then keeps a record's bytes as its window, with no decoding and no copy.
    const STORES_PIXELS: bool = false;

    /// The bytes stored for `window`, which the caller has checked is `W x W`.
    fn encode(window: &image::RgbImage, size: u32) -> Result<Vec<u8>>;

    /// The whole `W x W x 3` window that `bytes` hold. Bounded: the output is sized from
    /// `size` (the store's, checked against its manifest), never from a size read from
    /// `bytes`; what gives more or fewer bytes is refused (the caller checks the length
    /// again).
    fn decode_whole(bytes: &[u8], size: u32) -> Result<Vec<u8>>;

    /// The pixels `part` asks for ([`WindowPart`]): by default the whole window decoded
    /// and, for [`WindowPart::Centre`], its centre cut out. A codec that stores the
    /// window's parts apart decodes only those asked for.
    fn decode(bytes: &[u8], size: u32, part: WindowPart) -> Result<Vec<u8>> {
        let whole = Self::decode_whole(bytes, size)?;
        Ok(match part {
            WindowPart::Whole | WindowPart::Region(_) => whole,
            WindowPart::Centre => window_centre(&whole, size),
        })
    }
}
