//! `png`: the window as a PNG (8-bit RGB, adaptive filters, zlib's default level):
//! about a quarter of the raw bytes, slower to read than `pred-zstd`.

use super::super::format::window_side;
use super::coder::WindowCoder;
use arkit_core::{Error, Result};

/// The `png` codec.
pub(super) struct Png;

impl WindowCoder for Png {
    fn encode(window: &image::RgbImage, _size: u32) -> Result<Vec<u8>> {
        use image::ImageEncoder;
        let mut out = Vec::with_capacity(window.len() / 2);
        image::codecs::png::PngEncoder::new_with_quality(
            &mut out,
            image::codecs::png::CompressionType::Default,
            image::codecs::png::FilterType::Adaptive,
        )
        .write_image(
            window.as_raw(),
            window.width(),
            window.height(),
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| Error::invalid("crop store", format!("PNG encoding: {e}")))?;
        Ok(out)
    }

    /// A PNG whose header is not `W x W` 8-bit RGB is refused before any pixel is
    /// decoded.
    fn decode_whole(bytes: &[u8], size: u32) -> Result<Vec<u8>> {
        use image::ImageDecoder;
        let side = window_side(size);
        let want = 3 * side * side;
        let bad = |e: String| Error::invalid("crop store", format!("its PNG window: {e}"));
        let mut decoder = image::codecs::png::PngDecoder::new(std::io::Cursor::new(bytes))
            .map_err(|e| bad(e.to_string()))?;
        let mut limits = image::Limits::default();
        limits.max_image_width = Some(side as u32);
        limits.max_image_height = Some(side as u32);
        limits.max_alloc = Some(2 * want as u64 + (1 << 16));
        decoder.set_limits(limits).map_err(|e| bad(e.to_string()))?;
        if decoder.dimensions() != (side as u32, side as u32)
            || decoder.color_type() != image::ColorType::Rgb8
            || decoder.total_bytes() != want as u64
        {
            return Err(bad(format!(
                "{:?} {:?}, expected {side}x{side} Rgb8",
                decoder.dimensions(),
                decoder.color_type()
            )));
        }
        let mut out = vec![0u8; want];
        decoder
            .read_image(&mut out)
            .map_err(|e| bad(e.to_string()))?;
        Ok(out)
    }
}
