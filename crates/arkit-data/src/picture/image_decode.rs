//! Every image the tool reads, decoded in one place and bounded before decoding.
//!
//! A PNG or JPEG declares its size in its header, and a few hundred compressed bytes
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
    /// PNG or JPEG.
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

fn decoder<'a>(bytes: &'a [u8], path: &Path) -> Result<(ImageHeader, impl ImageDecoder + 'a)> {
    let format = image::guess_format(bytes)
        .ok()
        .filter(|f| matches!(f, ImageFormat::Png | ImageFormat::Jpeg))
        .ok_or_else(|| Error::format(path, "not a PNG or JPEG image"))?;
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
/// The header of an image in memory (PNG or JPEG), no pixel decoded.
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

/// Decodes a PNG or JPEG in memory into 8-bit RGB (module docs), after `check` has
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
        assert!(e.contains("not a PNG or JPEG"), "{e}");
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
