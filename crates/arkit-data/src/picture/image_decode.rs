//! Every image the tool reads, decoded in one place and bounded before decoding.
//!
//! A PNG, JPEG or WebP declares its size in its header, and a few hundred compressed bytes
//! can declare gigabytes of pixels. `decode_rgb8` reads the header first (no pixel
//! data), checks the size and colour type against [`MAX_DECODED_IMAGE_PIXELS`] and
//! [`MAX_DECODED_IMAGE_BYTES`] (and any check of the caller's, such as "the image has
//! the size its calibration was made for"), and only then decodes, with the decoder's
//! own allocation limit set as well. Files are read by `read_image_file`, whose read
//! is capped at [`MAX_IMAGE_FILE_BYTES`] whatever the file's length says.
//!
//! Colour: every reader works on 8-bit RGB. 16-bit images are converted by scaling
//! (`round(v / 257)`, so 65535 is 255 and mid-grey stays mid-grey), grey is repeated
//! into the three channels and an alpha channel is dropped.

use arkit_core::limits::{
    MAX_DECODED_IMAGE_BYTES, MAX_DECODED_IMAGE_PIXELS, MAX_IMAGE_FILE_BYTES, MAX_IMAGE_SIDE,
};
use arkit_core::{Error, Result};
use image::{ColorType, DynamicImage, ImageDecoder, ImageFormat, RgbImage};
use std::io::{Cursor, Read};
use std::path::Path;

/// What an image's header says, read without decoding a pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageHeader {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// The file's colour type (before conversion to 8-bit RGB).
    pub color: ColorType,
    /// PNG, JPEG or WebP.
    pub format: ImageFormat,
}

impl ImageHeader {
    /// Pixels (`width * height`).
    pub fn pixels(&self) -> u64 {
        self.width as u64 * self.height as u64
    }

    /// Bytes decoding needs: the decoder's output plus the 8-bit RGB copy (none when
    /// the file is 8-bit RGB).
    pub(crate) fn decoded_bytes(&self) -> u64 {
        let own = self.color.bytes_per_pixel() as u64;
        let copy = if self.color == ColorType::Rgb8 { 0 } else { 3 };
        self.pixels().saturating_mul(own + copy)
    }

    /// The colour type in words (`8-bit RGB`, `16-bit grey`, ...).
    pub(crate) fn color_name(&self) -> &'static str {
        match self.color {
            ColorType::L8 => "8-bit grey",
            ColorType::La8 => "8-bit grey with alpha",
            ColorType::Rgb8 => "8-bit RGB",
            ColorType::Rgba8 => "8-bit RGBA",
            ColorType::L16 => "16-bit grey",
            ColorType::La16 => "16-bit grey with alpha",
            ColorType::Rgb16 => "16-bit RGB",
            ColorType::Rgba16 => "16-bit RGBA",
            ColorType::Rgb32F => "32-bit float RGB",
            ColorType::Rgba32F => "32-bit float RGBA",
            _ => "another colour type",
        }
    }
}

/// The decoder's limits: sides within [`MAX_IMAGE_SIDE`], allocations within
/// [`MAX_DECODED_IMAGE_BYTES`] (a second fence behind the header check).
fn limits() -> image::Limits {
    let mut l = image::Limits::default();
    l.max_image_width = Some(MAX_IMAGE_SIDE);
    l.max_image_height = Some(MAX_IMAGE_SIDE);
    l.max_alloc = Some(MAX_DECODED_IMAGE_BYTES);
    l
}

/// Reads an image file whole, refusing one larger than [`MAX_IMAGE_FILE_BYTES`] before
/// reading it (and capping the read, for files whose length lies, such as pipes).
pub(crate) fn read_image_file(path: &Path) -> Result<Vec<u8>> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let too_large = |n: u64| {
        Error::format(
            path,
            format!("{n} bytes, more than the {MAX_IMAGE_FILE_BYTES} an image file may have"),
        )
    };
    if len > MAX_IMAGE_FILE_BYTES {
        return Err(too_large(len));
    }
    let mut bytes = Vec::with_capacity(len as usize);
    file.take(MAX_IMAGE_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, e))?;
    if bytes.len() as u64 > MAX_IMAGE_FILE_BYTES {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// Checks that `bytes` are a complete JPEG: the start-of-image marker, then marker
/// segments (each within the file) and entropy-coded scans up to an end-of-image marker.
/// Bytes after the end-of-image marker (camera padding, appended data) are allowed and
/// ignored, as decoders ignore them. Returns the offset just past the end marker.
pub fn check_jpeg_framing(bytes: &[u8]) -> std::result::Result<usize, String> {
    if bytes.len() < 4 || bytes[..3] != [0xFF, 0xD8, 0xFF] {
        return Err("not a JPEG file (no start-of-image marker)".into());
    }
    let truncated = |at: usize| {
        format!(
            "truncated JPEG (the data ends at byte {at} of {} before the end-of-image marker)",
            bytes.len()
        )
    };
    let mut pos = 2;
    loop {
        if pos >= bytes.len() {
            return Err(truncated(bytes.len()));
        }
        if bytes[pos] != 0xFF {
            return Err(format!(
                "corrupt JPEG: byte {pos} should start a marker (0xFF), found {:#04x}",
                bytes[pos]
            ));
        }
        while pos < bytes.len() && bytes[pos] == 0xFF {
            pos += 1;
        }
        let Some(&marker) = bytes.get(pos) else {
            return Err(truncated(bytes.len()));
        };
        pos += 1;
        match marker {
            0xD9 => return Ok(pos),
            0x01 | 0xD0..=0xD7 => continue,
            0x00 => return Err(format!("corrupt JPEG: stray 0xFF00 at byte {}", pos - 2)),
            _ => {}
        }
        let Some(len) = bytes
            .get(pos..pos + 2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]) as usize)
        else {
            return Err(truncated(bytes.len()));
        };
        if len < 2 {
            return Err(format!(
                "corrupt JPEG: marker {marker:#04x} at byte {} has length {len}",
                pos - 2
            ));
        }
        pos += len;
        if pos > bytes.len() {
            return Err(truncated(bytes.len()));
        }
        if marker == 0xDA {
            // Entropy-coded data: 0xFF is followed by 0x00 (a stuffed byte), a restart
            // marker, or fill; anything else is the next marker.
            loop {
                match bytes[pos..].iter().position(|&b| b == 0xFF) {
                    None => return Err(truncated(bytes.len())),
                    Some(k) => pos += k,
                }
                match bytes.get(pos + 1) {
                    None => return Err(truncated(bytes.len())),
                    Some(0x00 | 0xD0..=0xD7) => pos += 2,
                    Some(0xFF) => pos += 1,
                    Some(_) => break,
                }
            }
        }
    }
}

fn decoder<'a>(bytes: &'a [u8], path: &Path) -> Result<(ImageHeader, impl ImageDecoder + 'a)> {
    let format = image::guess_format(bytes)
        .ok()
        .filter(|f| matches!(f, ImageFormat::Png | ImageFormat::Jpeg | ImageFormat::WebP))
        .ok_or_else(|| Error::format(path, "not a PNG, JPEG or WebP image"))?;
    // A JPEG decoder fills missing data with grey and reports nothing: the framing
    // (every marker segment and scan up to the end-of-image marker) is checked first,
    // as `convert` checks the release's images.
    if format == ImageFormat::Jpeg {
        check_jpeg_framing(bytes).map_err(|m| Error::format(path, m))?;
    }
    let mut reader = image::ImageReader::with_format(Cursor::new(bytes), format);
    reader.limits(limits());
    let d = reader.into_decoder().map_err(|e| {
        Error::format(
            path,
            format!("cannot decode the image's header (damaged, or over the limits): {e}"),
        )
    })?;
    let (width, height) = d.dimensions();
    let header = ImageHeader {
        width,
        height,
        color: d.color_type(),
        format,
    };
    Ok((header, d))
}

#[cfg(test)]
/// The header of an image in memory (PNG, JPEG or WebP), no pixel decoded.
pub(crate) fn read_header(bytes: &[u8], path: &Path) -> Result<ImageHeader> {
    decoder(bytes, path).map(|(h, _)| h)
}

/// Checks a header against [`MAX_DECODED_IMAGE_PIXELS`] and [`MAX_DECODED_IMAGE_BYTES`].
fn check_budget(h: &ImageHeader, path: &Path) -> Result<()> {
    if h.pixels() > MAX_DECODED_IMAGE_PIXELS || h.decoded_bytes() > MAX_DECODED_IMAGE_BYTES {
        return Err(Error::format(
            path,
            format!(
                "the image declares {}x{} {} pixels ({:.1} M pixels, {} MiB to decode): more than an image may have ({:.1} M pixels, {} MiB decoded); refused before decoding",
                h.width,
                h.height,
                h.color_name(),
                h.pixels() as f64 / 1e6,
                h.decoded_bytes().div_ceil(1 << 20),
                MAX_DECODED_IMAGE_PIXELS as f64 / 1e6,
                MAX_DECODED_IMAGE_BYTES >> 20
            ),
        ));
    }
    Ok(())
}

/// Decodes a PNG, JPEG or WebP in memory into 8-bit RGB (module docs), after `check` has
/// accepted its header (for example: the size the caller expects) and the header has
/// passed `check_budget`. `path` names the image in errors.
pub(crate) fn decode_rgb8_checked(
    bytes: &[u8],
    path: &Path,
    check: impl FnOnce(&ImageHeader) -> Result<()>,
) -> Result<RgbImage> {
    let (header, d) = decoder(bytes, path)?;
    check(&header)?;
    check_budget(&header, path)?;
    let image = DynamicImage::from_decoder(d)
        .map_err(|e| Error::format(path, format!("the image does not decode: {e}")))?;
    Ok(image.into_rgb8())
}

#[cfg(test)]
/// [`decode_rgb8_checked`] without a check of the caller's.
pub(crate) fn decode_rgb8(bytes: &[u8], path: &Path) -> Result<RgbImage> {
    decode_rgb8_checked(bytes, path, |_| Ok(()))
}

/// `read_image_file` then `decode_rgb8_checked`.
pub fn read_rgb8_checked(
    path: &Path,
    check: impl FnOnce(&ImageHeader) -> Result<()>,
) -> Result<RgbImage> {
    decode_rgb8_checked(&read_image_file(path)?, path, check)
}

/// A photo as people see it: decoded as [`read_rgb8_checked`] decodes it, then turned
/// upright by its EXIF orientation (1 to 8; a phone stores a portrait photo sideways
/// with orientation 6), before anything else looks at it. Returns the upright image
/// and the orientation applied (1 when the file has none). The dataset's images are
/// read without this: their calibration is for the pixels as stored.
pub fn read_photo_upright(path: &Path) -> Result<(RgbImage, u8)> {
    let bytes = read_image_file(path)?;
    let (header, mut d) = decoder(&bytes, path)?;
    check_budget(&header, path)?;
    // An unreadable EXIF block is no orientation, as viewers treat it.
    let orientation = d
        .orientation()
        .unwrap_or(image::metadata::Orientation::NoTransforms);
    let mut image = DynamicImage::from_decoder(d)
        .map_err(|e| Error::format(path, format!("the image does not decode: {e}")))?;
    image.apply_orientation(orientation);
    Ok((image.into_rgb8(), orientation.to_exif()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{ImageBuffer, Luma, Rgb};

    fn png<P: image::PixelWithColorType>(img: &ImageBuffer<P, Vec<P::Subpixel>>) -> Vec<u8>
    where
        [P::Subpixel]: image::EncodableLayout,
    {
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, ImageFormat::Png).unwrap();
        out.into_inner()
    }

    #[test]
    fn sixteen_bit_png_converts_by_scaling_not_to_black() {
        let p = Path::new("x.png");
        let img = ImageBuffer::<Rgb<u16>, Vec<u16>>::from_fn(64, 32, |x, y| {
            Rgb([(x * 1000) as u16, (y * 2000) as u16, 65535])
        });
        let bytes = png(&img);
        let h = read_header(&bytes, p).unwrap();
        assert_eq!((h.width, h.height, h.color), (64, 32, ColorType::Rgb16));
        let rgb = decode_rgb8(&bytes, p).unwrap();
        for (x, y, q) in rgb.enumerate_pixels() {
            let v = img.get_pixel(x, y);
            for c in 0..3 {
                let want = (v[c] as f64 / 257.0).round() as u8;
                assert_eq!(q[c], want, "({x}, {y}) channel {c}");
            }
        }
        // Mid-grey stays mid-grey, grey is repeated into the three channels.
        let grey = ImageBuffer::<Luma<u16>, Vec<u16>>::from_pixel(40, 40, Luma([32896]));
        let rgb = decode_rgb8(&png(&grey), p).unwrap();
        assert!(rgb.pixels().all(|q| q.0 == [128, 128, 128]));
    }

    #[test]
    fn declared_size_over_the_limit_is_refused_before_decoding() {
        // A valid header declaring 16000 x 16000 16-bit grey pixels, with no pixel data:
        // refused from the header (decoding would fail later, and cost 1.2 GiB first).
        let mut small = Cursor::new(Vec::new());
        ImageBuffer::<Luma<u16>, Vec<u16>>::new(1, 1)
            .write_to(&mut small, ImageFormat::Png)
            .unwrap();
        let mut bytes = small.into_inner();
        // IHDR's width and height at bytes 16..24, its CRC at 29..33.
        bytes[16..20].copy_from_slice(&16000u32.to_be_bytes());
        bytes[20..24].copy_from_slice(&16000u32.to_be_bytes());
        let crc = crc32fast::hash(&bytes[12..29]);
        bytes[29..33].copy_from_slice(&crc.to_be_bytes());
        let p = Path::new("bomb.png");
        let h = read_header(&bytes, p).unwrap();
        assert_eq!((h.width, h.height, h.color), (16000, 16000, ColorType::L16));
        let e = decode_rgb8(&bytes, p).unwrap_err().to_string();
        assert!(
            e.contains("bomb.png")
                && e.contains("16000x16000 16-bit grey")
                && e.contains("refused before decoding"),
            "{e}"
        );
        // At the limit in pixels but 16-bit RGB: over the bytes.
        let h = ImageHeader {
            width: 4096,
            height: 4096,
            color: ColorType::Rgb16,
            format: ImageFormat::Png,
        };
        assert!(check_budget(&h, p).is_err());
        let h = ImageHeader {
            color: ColorType::Rgb8,
            ..h
        };
        assert!(check_budget(&h, p).is_ok());
        let h = ImageHeader { width: 4097, ..h };
        assert!(check_budget(&h, p).is_err());
    }

    #[test]
    fn the_callers_check_runs_before_decoding_and_other_formats_are_refused() {
        let p = Path::new("x.png");
        let img = RgbImage::from_pixel(40, 30, Rgb([1, 2, 3]));
        let mut bytes = png(&img);
        let e = decode_rgb8_checked(&bytes, p, |h| {
            Err(Error::format(
                p,
                format!("{}x{} is not 640x480", h.width, h.height),
            ))
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("40x30 is not 640x480"), "{e}");
        assert_eq!(decode_rgb8(&bytes, p).unwrap(), img);
        // Truncated pixel data: an error, not a partly black image.
        bytes.truncate(bytes.len() - 20);
        assert!(decode_rgb8(&bytes, p).is_err());
        let e = decode_rgb8(b"GIF89a......", p).unwrap_err().to_string();
        assert!(e.contains("not a PNG, JPEG or WebP"), "{e}");
    }

    #[test]
    fn a_file_over_the_size_cap_is_not_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.jpg");
        let f = std::fs::File::create(&path).unwrap();
        f.set_len(MAX_IMAGE_FILE_BYTES + 1).unwrap();
        let e = read_image_file(&path).unwrap_err().to_string();
        assert!(e.contains("big.jpg") && e.contains("more than"), "{e}");
    }
}
