//! Pictures written for people and for the release layout: JPEG bytes, and contact
//! sheets of previews.

use arkit_core::{Error, Result};
use image::{Rgb, RgbImage};

/// Encodes an image as JPEG bytes.
pub fn jpeg_bytes(image: &RgbImage, quality: u8) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality)
        .encode_image(image)
        .map_err(|e| Error::invalid("jpeg", e.to_string()))?;
    Ok(out)
}

/// A grid of images (scaled to `cell` pixels wide) for previews.
pub fn contact_sheet(images: &[RgbImage], columns: usize, cell: u32) -> RgbImage {
    let columns = columns.max(1);
    let rows = images.len().div_ceil(columns).max(1);
    let cell_h = images
        .first()
        .map(|i| (cell as f64 * i.height() as f64 / i.width() as f64).round() as u32)
        .unwrap_or(cell);
    let mut sheet = RgbImage::from_pixel(
        columns as u32 * cell,
        rows as u32 * cell_h,
        Rgb([30, 30, 30]),
    );
    for (k, img) in images.iter().enumerate() {
        let small =
            image::imageops::resize(img, cell, cell_h, image::imageops::FilterType::Triangle);
        image::imageops::overlay(
            &mut sheet,
            &small,
            (k % columns) as i64 * cell as i64,
            (k / columns) as i64 * cell_h as i64,
        );
    }
    sheet
}
