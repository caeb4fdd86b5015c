//! `codec`: how a record's window is stored, and the one table of the window codecs.
//!
//! Every codec is lossless: the window decoded is the window `crops` resampled, byte for
//! byte, so evaluation crops from any of them are those cut from the decoded JPEG.
//! Each lives in a file of its own, as a unit struct implementing
//! [`coder::WindowCoder`] (encode; decode the whole window, or the part asked for).
//!
//! To add a codec: write `codec/NAME.rs` and add one line to the table below
//! (`Variant = code, "name", file::Struct;`). The line declares the file, adds the
//! [`WindowCodec`] variant, gives its name in `crops.json` and on the command line and
//! its code in the part files' headers (both checked unique), and routes
//! [`encode_window`], [`decode_window`] and the reader to it; the tests that run every
//! codec ([`WindowCodec::ALL`]) then run it too. `xor` below, a codec of the tests (and the fuzz builds) only,
//! was added so. (The command line's `--codec` names its codecs by hand, with their
//! help: a codec is offered to users there on purpose.)

mod coder;
mod predictor;

pub use predictor::{predict_rect, unpredict_in_place, unpredict_rect};

use super::format::{WindowPart, window_side};
use arkit_core::{Error, Result};
use coder::WindowCoder;

/// Declares each codec's file and builds [`WindowCodec`] and its dispatch from the table.
macro_rules! window_codecs {
    ($(
        $(#[cfg($cfg:meta)])?
        $(#[doc = $doc:literal])*
        $variant:ident = $code:literal, $name:literal, $file:ident::$coder:ident;
    )*) => {
        $( $(#[cfg($cfg)])? mod $file; )*

        /// How a record's window is stored (its name in `crops.json`: [`WindowCodec::name`]).
        /// Every codec is lossless.
        #[derive(Clone, Copy, Debug, PartialEq, Eq)]
        pub enum WindowCodec {
            $( $(#[doc = $doc])* $(#[cfg($cfg)])? $variant, )*
        }

        impl WindowCodec {
            /// Every codec, in the table's order.
            pub const ALL: &[WindowCodec] = &[$( $(#[cfg($cfg)])? WindowCodec::$variant, )*];

            /// Every codec's name, in the table's order.
            const NAMES: &[&str] = &[$( $(#[cfg($cfg)])? $name, )*];

            /// Its name in `crops.json` and on the command line.
            pub fn name(self) -> &'static str {
                match self { $( $(#[cfg($cfg)])? WindowCodec::$variant => $name, )* }
            }

            /// Its code in a part file's header.
            pub(crate) fn code(self) -> u32 {
                match self { $( $(#[cfg($cfg)])? WindowCodec::$variant => $code, )* }
            }

            /// Whether it stores the window's pixels as they are
            /// ([`WindowCoder::STORES_PIXELS`]).
            pub(in super::super) fn stores_pixels(self) -> bool {
                match self {
                    $( $(#[cfg($cfg)])? WindowCodec::$variant =>
                        <$file::$coder as WindowCoder>::STORES_PIXELS, )*
                }
            }

            fn encode(self, window: &image::RgbImage, size: u32) -> Result<Vec<u8>> {
                match self {
                    $( $(#[cfg($cfg)])? WindowCodec::$variant =>
                        <$file::$coder as WindowCoder>::encode(window, size), )*
                }
            }

            fn decode(self, bytes: &[u8], size: u32, part: WindowPart) -> Result<Vec<u8>> {
                match self {
                    $( $(#[cfg($cfg)])? WindowCodec::$variant =>
                        <$file::$coder as WindowCoder>::decode(bytes, size, part), )*
                }
            }
        }
    };
}

window_codecs! {
    /// The `W x W x 3` bytes as they are.
    Raw = 0, "raw", raw::Raw;
    /// A PNG (8-bit RGB, adaptive filters, zlib's default level).
    Png = 1, "png", png::Png;
    /// The default: each pixel predicted from its decoded neighbours and the
    /// prediction errors compressed by zstd ([`predict_rect`]): green, then red and
    /// blue less green, each plane by the median edge detector of LOCO-I (JPEG-LS).
    /// The window's five parts ([`super::window_parts`]: the centre, which is the
    /// evaluation crop, and the four parts of the ring around it) are a zstd frame each,
    /// after the byte counts of the first four (four bytes each, little endian), so that
    /// evaluation decodes the centre alone and a training crop the parts it reaches.
    PredZstd = 2, "pred-zstd", pred_zstd::PredZstd;
    #[cfg(any(test, fuzzing))] #[doc = "A codec of the tests (and of the fuzz targets, built with `--cfg fuzzing`) only."] Xor = 255, "xor", xor::Xor;
}

/// `--codec`'s values: every codec of the table, by its name.
#[cfg(feature = "clap")]
impl clap::ValueEnum for WindowCodec {
    fn value_variants<'a>() -> &'a [Self] {
        WindowCodec::ALL
    }

    fn to_possible_value(&self) -> Option<clap::builder::PossibleValue> {
        Some(clap::builder::PossibleValue::new(self.name()))
    }
}

impl serde::Serialize for WindowCodec {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> serde::Deserialize<'de> for WindowCodec {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        WindowCodec::ALL
            .iter()
            .copied()
            .find(|c| c.name() == name)
            .ok_or_else(|| serde::de::Error::unknown_variant(&name, WindowCodec::NAMES))
    }
}

/// The bytes `codec` stores for `window`, the `W x W` RGB window of crop side `size`
/// ([`window_side`]).
pub fn encode_window(codec: WindowCodec, window: &image::RgbImage, size: u32) -> Result<Vec<u8>> {
    let w = window_side(size);
    if window.dimensions() != (w as u32, w as u32) {
        return Err(Error::invalid(
            "crop store",
            format!(
                "a {:?} window, crop side {size} has {w}x{w}",
                window.dimensions()
            ),
        ));
    }
    codec.encode(window, size)
}

/// The pixels `bytes` (stored by `codec`) hold of the window of crop side `size`: the
/// `W x W x 3` window (for a region, with the parts it does not meet zero where the
/// codec stores parts) or its centre's `S x S x 3` bytes, as `part` asks. Bounded: the
/// output is allocated from `size` (the store's, checked against its manifest), never
/// from a size read from `bytes`; a zstd frame that gives more or fewer bytes than its
/// part has is refused, and a PNG whose header is not `W x W` 8-bit RGB is refused
/// before any pixel is decoded. Pixels of another count than `part` has are refused,
/// whichever the codec.
pub fn decode_window(
    codec: WindowCodec,
    bytes: &[u8],
    size: u32,
    part: WindowPart,
) -> Result<Vec<u8>> {
    let out = codec.decode(bytes, size, part)?;
    let side = match part {
        WindowPart::Centre => size as usize,
        WindowPart::Whole | WindowPart::Region(_) => window_side(size),
    };
    if out.len() != 3 * side * side {
        return Err(Error::invalid(
            "crop store",
            format!(
                "its {} window decoded to {} bytes, expected {}",
                codec.name(),
                out.len(),
                3 * side * side
            ),
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::super::format::window_centre;
    use super::*;

    #[test]
    fn every_codec_has_a_name_and_a_code_of_its_own_and_its_name_in_json() {
        for (i, a) in WindowCodec::ALL.iter().enumerate() {
            for b in &WindowCodec::ALL[i + 1..] {
                assert!(a.name() != b.name() && a.code() != b.code(), "{a:?} {b:?}");
            }
            let json = serde_json::to_string(a).unwrap();
            assert_eq!(json, format!("\"{}\"", a.name()));
            assert_eq!(serde_json::from_str::<WindowCodec>(&json).unwrap(), *a);
        }
        // The names and codes stores have on disk.
        let disk = [
            (WindowCodec::Raw, "raw", 0),
            (WindowCodec::Png, "png", 1),
            (WindowCodec::PredZstd, "pred-zstd", 2),
        ];
        for (c, name, code) in disk {
            assert_eq!((c.name(), c.code()), (name, code));
        }
        let e = serde_json::from_str::<WindowCodec>("\"webp\"").unwrap_err();
        assert!(e.to_string().contains("unknown variant `webp`"), "{e}");
    }

    #[test]
    fn every_codec_round_trips_a_window_whole_and_its_centre() {
        let w = window_side(16) as u32;
        let window = image::RgbImage::from_fn(w, w, |x, y| {
            image::Rgb([(x * 7 + y) as u8, (y * 3) as u8, (x ^ y) as u8])
        });
        for &codec in WindowCodec::ALL {
            let stored = encode_window(codec, &window, 16).unwrap();
            let whole = decode_window(codec, &stored, 16, WindowPart::Whole).unwrap();
            assert_eq!(whole, *window.as_raw(), "{codec:?}");
            let centre = decode_window(codec, &stored, 16, WindowPart::Centre).unwrap();
            assert_eq!(centre, window_centre(window.as_raw(), 16), "{codec:?}");
            assert!(encode_window(codec, &window, 17).is_err(), "{codec:?}");
        }
    }

    #[test]
    fn a_png_window_of_another_size_or_colour_is_refused_before_decoding() {
        use image::ImageEncoder;
        let side = window_side(16) as u32;
        let window = image::RgbImage::from_raw(
            side,
            side,
            (0..side * side * 3).map(|i| (i * 7 % 251) as u8).collect(),
        )
        .unwrap();
        let png = encode_window(WindowCodec::Png, &window, 16).unwrap();
        let decode = |b: &[u8], part| decode_window(WindowCodec::Png, b, 16, part);
        assert_eq!(decode(&png, WindowPart::Whole).unwrap(), *window.as_raw());
        assert_eq!(
            decode(&png, WindowPart::Centre).unwrap(),
            window_centre(window.as_raw(), 16)
        );
        assert!(png.len() < window.len(), "{} bytes", png.len());
        // A PNG of a larger side than the store's: refused from its header.
        let mut big = Vec::new();
        image::codecs::png::PngEncoder::new(&mut big)
            .write_image(
                &vec![0u8; 3 * 1024 * 1024],
                1024,
                1024,
                image::ExtendedColorType::Rgb8,
            )
            .unwrap();
        let e = decode(&big, WindowPart::Whole).unwrap_err();
        assert!(e.to_string().contains("PNG window"), "{e}");
        // Grey instead of RGB, of the right side.
        let mut grey = Vec::new();
        image::codecs::png::PngEncoder::new(&mut grey)
            .write_image(
                &vec![9u8; (side * side) as usize],
                side,
                side,
                image::ExtendedColorType::L8,
            )
            .unwrap();
        let e = decode(&grey, WindowPart::Whole).unwrap_err();
        assert!(e.to_string().contains("expected"), "{e}");
        // Raw bytes of the wrong length; damaged PNG bytes; a window of another side.
        assert!(decode_window(WindowCodec::Raw, &[0; 10], 16, WindowPart::Centre).is_err());
        assert!(decode(&png[..png.len() / 2], WindowPart::Whole).is_err());
        assert!(encode_window(WindowCodec::Png, &window, 17).is_err());
    }
}
