//! The byte codecs of the `targets` table's blobs (and of the predictions' `mask_rle`),
//! without polars: masks as run lengths, the UV map's delta bit-planes, little-endian
//! `u16` / `u32` packing, and the correspondence blobs' length checks.
//!
//! Layouts (also `schemas/targets.json`):
//! - a mask is run lengths (u32 LE) over its row-major pixels, starting with a
//!   background run (possibly empty), alternating background / face;
//! - `corr_vertices` is 3 u16 LE vertex ids per mask pixel, `corr_weights` 2 u16 LE
//!   quantised weights per mask pixel;
//! - `uv_map_delta` is a `size^2 x 3` float16 map, per channel the row-wise wrapping
//!   differences of the bits, low-byte plane then high-byte plane ([`encode_uv_map`]).
//!
//! Invariants: decoding never trusts a size from the blob. [`rle_decode`] sums the runs
//! (in `u64`, overflow-checked) and compares the total with the mask's size, and the
//! size with [`limits::MAX_MASK_PIXELS`], before allocating the mask; [`decode_uv_map`]
//! checks the side against [`limits::MAX_UV_SIZE`] and the blob's length with checked
//! arithmetic before allocating; the unpackers refuse lengths that are not a multiple
//! of the element size instead of dropping the tail. `rle_decode(rle_encode(m)) == m`
//! and `encode_uv_map(decode_uv_map(b)) == b` for every blob that decodes. Tested below
//! (round trips, each refusal, a 12-byte blob claiming 6 G pixels) and by the
//! `targets_blobs` fuzz target.

use crate::error::{Error, Result};
use crate::limits;

/// Run-length encodes a mask (first run is background, possibly empty).
pub fn rle_encode(mask: &[bool]) -> Vec<u32> {
    let mut runs = Vec::new();
    let mut current = false;
    let mut n = 0u32;
    for &m in mask {
        if m == current {
            n += 1;
        } else {
            runs.push(n);
            current = m;
            n = 1;
        }
    }
    runs.push(n);
    runs
}

/// The number of pixels of a `width x height` mask, checked against
/// [`limits::MAX_MASK_PIXELS`] (`what` names the mask in the error).
pub fn mask_len(width: u32, height: u32, what: &str) -> Result<usize> {
    let n = width as u64 * height as u64;
    if n > limits::MAX_MASK_PIXELS {
        return Err(Error::invalid(
            what,
            format!(
                "{width}x{height} = {n} pixels, more than the {} allowed",
                limits::MAX_MASK_PIXELS
            ),
        ));
    }
    Ok(n as usize)
}

/// Decodes [`rle_encode`]'s runs into `len` pixels. Errors, before allocating, when
/// `len` is above [`limits::MAX_MASK_PIXELS`] or the runs do not add up to `len`.
pub fn rle_decode(runs: &[u32], len: usize) -> Result<Vec<bool>> {
    if len as u64 > limits::MAX_MASK_PIXELS {
        return Err(Error::invalid(
            "mask_rle",
            format!(
                "a mask of {len} pixels is more than the {} allowed",
                limits::MAX_MASK_PIXELS
            ),
        ));
    }
    // At most 2^32 runs of at most 2^32 - 1: the u64 sum cannot overflow, but stay
    // checked in case a caller ever passes more.
    let total = runs
        .iter()
        .try_fold(0u64, |a, &r| a.checked_add(r as u64))
        .filter(|&t| t == len as u64);
    if total.is_none() {
        let sum: u128 = runs.iter().map(|&r| r as u128).sum();
        return Err(Error::invalid(
            "mask_rle",
            format!("runs cover {sum} pixels, the mask has {len}"),
        ));
    }
    let mut out = Vec::with_capacity(len);
    for (k, &r) in runs.iter().enumerate() {
        out.extend(std::iter::repeat_n(k % 2 == 1, r as usize));
    }
    Ok(out)
}

/// Encodes a UV map's float16 bits (`size^2 x 3`, texel-major) for storage: for each
/// channel, the row-wise wrapping differences of the bits (first texel of a row kept
/// as is), written as the plane of low bytes followed by the plane of high bytes.
/// Lossless; [`decode_uv_map`] inverts it.
pub fn encode_uv_map(bits: &[u16], size: u32) -> Vec<u8> {
    let n = size as usize;
    let texels = bits.len() / 3;
    let mut out = vec![0u8; texels * 6];
    for k in 0..3 {
        let (lo, hi) = out[k * 2 * texels..(k + 1) * 2 * texels].split_at_mut(texels);
        for t in 0..texels {
            let prev = if n > 0 && t % n != 0 {
                bits[(t - 1) * 3 + k]
            } else {
                0
            };
            let d = bits[t * 3 + k].wrapping_sub(prev);
            lo[t] = d as u8;
            hi[t] = (d >> 8) as u8;
        }
    }
    out
}

/// Inverts [`encode_uv_map`]: `size^2 x 3` float16 bits. Errors, before allocating,
/// when `size` is above [`limits::MAX_UV_SIZE`] or the blob does not hold exactly
/// `size^2 x 6` bytes.
pub fn decode_uv_map(bytes: &[u8], size: u32) -> Result<Vec<u16>> {
    if size > limits::MAX_UV_SIZE {
        return Err(Error::invalid(
            "uv_size",
            format!("{size} is more than the {} allowed", limits::MAX_UV_SIZE),
        ));
    }
    let n = size as usize;
    // size <= 4096: n * n * 6 <= 2^27, no overflow on any target.
    let texels = n * n;
    if bytes.len() != texels * 6 {
        return Err(Error::invalid(
            "uv_map_delta",
            format!(
                "{} bytes, a {size}x{size} map needs {}",
                bytes.len(),
                texels * 6
            ),
        ));
    }
    let mut bits = vec![0u16; texels * 3];
    for k in 0..3 {
        let plane = &bytes[k * 2 * texels..(k + 1) * 2 * texels];
        let (lo, hi) = plane.split_at(texels);
        for t in 0..texels {
            let d = lo[t] as u16 | (hi[t] as u16) << 8;
            let prev = if t % n != 0 { bits[(t - 1) * 3 + k] } else { 0 };
            bits[t * 3 + k] = prev.wrapping_add(d);
        }
    }
    Ok(bits)
}

/// `u32`s as little-endian bytes.
pub fn pack_u32_le(v: &[u32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// `u16`s as little-endian bytes.
pub fn pack_u16_le(v: impl Iterator<Item = u16>) -> Vec<u8> {
    v.flat_map(|x| x.to_le_bytes()).collect()
}

/// Little-endian `u32`s of a blob; errors (naming the blob `what`) unless its length is
/// a multiple of 4.
pub fn unpack_u32_le(b: &[u8], what: &str) -> Result<Vec<u32>> {
    if !b.len().is_multiple_of(4) {
        return Err(Error::invalid(
            what,
            format!("{} bytes, not a whole number of u32s", b.len()),
        ));
    }
    Ok(b.chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

/// Little-endian `u16`s of a blob; errors (naming the blob `what`) unless its length is
/// even.
pub(crate) fn unpack_u16_le(b: &[u8], what: &str) -> Result<Vec<u16>> {
    if !b.len().is_multiple_of(2) {
        return Err(Error::invalid(
            what,
            format!("{} bytes, not a whole number of u16s", b.len()),
        ));
    }
    Ok(b.chunks_exact(2)
        .map(|c| u16::from_le_bytes([c[0], c[1]]))
        .collect())
}

/// Per-pixel vertex ids and quantised weights, decoded from the `corr_vertices` and
/// `corr_weights` blobs.
pub type Correspondences = (Vec<[u16; 3]>, Vec<[u16; 2]>);

/// Decodes the correspondence blobs: `vertices` must hold 6 bytes per pixel and
/// `weights` 4 bytes per pixel, for the same number of pixels.
pub fn decode_correspondences(vertices: &[u8], weights: &[u8]) -> Result<Correspondences> {
    if !vertices.len().is_multiple_of(6)
        || !weights.len().is_multiple_of(4)
        || vertices.len() / 6 != weights.len() / 4
    {
        return Err(Error::invalid(
            "correspondences",
            format!(
                "corr_vertices has {} bytes and corr_weights {}: they must be 6 and 4 \
                 bytes per mask pixel, for the same pixels",
                vertices.len(),
                weights.len()
            ),
        ));
    }
    let ids = unpack_u16_le(vertices, "corr_vertices")?;
    let ws = unpack_u16_le(weights, "corr_weights")?;
    Ok((
        ids.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
        ws.chunks_exact(2).map(|c| [c[0], c[1]]).collect(),
    ))
}

/// Encodes correspondences as the two blobs [`decode_correspondences`] reads.
pub fn encode_correspondences(vertices: &[[u16; 3]], weights: &[[u16; 2]]) -> (Vec<u8>, Vec<u8>) {
    (
        pack_u16_le(vertices.iter().flatten().copied()),
        pack_u16_le(weights.iter().flatten().copied()),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rle_round_trip() {
        for mask in [
            vec![],
            vec![true],
            vec![false, false],
            vec![true, true, false, true, false, false],
        ] {
            let runs = rle_encode(&mask);
            assert_eq!(rle_decode(&runs, mask.len()).unwrap(), mask);
        }
        assert_eq!(rle_encode(&[true, true, false]), vec![0, 2, 1]);
        assert!(rle_decode(&[1, 2], 5).is_err());
        // Zero-length runs in the middle are accepted (they only change the colour).
        assert_eq!(
            rle_decode(&[1, 0, 2, 1], 4).unwrap(),
            vec![false, false, false, true]
        );
    }

    #[test]
    fn runs_are_summed_before_anything_is_allocated() {
        // 12 bytes (3 runs of 2^31) claiming 6 G pixels against a 192x192 crop: refused
        // from the sum; against a 6 G mask: refused from the mask size limit.
        let runs = [1u32 << 31, 1 << 31, 1 << 31];
        let e = rle_decode(&runs, 192 * 192).unwrap_err().to_string();
        assert!(
            e.contains("runs cover 6442450944 pixels, the mask has 36864"),
            "{e}"
        );
        let e = rle_decode(&runs, 6_442_450_944).unwrap_err().to_string();
        assert!(e.contains("more than the 67108864 allowed"), "{e}");
        // Runs that would overflow a u32 total are summed in u64.
        assert!(rle_decode(&[u32::MAX, u32::MAX, 2], 4).is_err());
        // At the limit exactly, a mask is allocated and right.
        let n = limits::MAX_MASK_PIXELS as usize;
        let m = rle_decode(&[n as u32 - 1, 1], n).unwrap();
        assert_eq!((m.len(), m[n - 1], m[n - 2]), (n, true, false));
        assert!(rle_decode(&[n as u32, 1], n + 1).is_err());
        assert!(mask_len(8192, 8192, "m").is_ok());
        let e = mask_len(65535, 65535, "full_mask").unwrap_err().to_string();
        assert!(e.starts_with("invalid full_mask: 65535x65535"), "{e}");
    }

    #[test]
    fn uv_map_round_trips_and_refuses_wrong_sizes() {
        let size = 5u32;
        let bits: Vec<u16> = (0..75u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 16) as u16)
            .collect();
        let blob = encode_uv_map(&bits, size);
        assert_eq!(blob.len(), 150);
        assert_eq!(decode_uv_map(&blob, size).unwrap(), bits);
        assert_eq!(
            encode_uv_map(&decode_uv_map(&blob, size).unwrap(), size),
            blob
        );
        assert!(decode_uv_map(&blob[1..], size).is_err());
        assert!(decode_uv_map(&blob, size + 1).is_err());
        assert_eq!(decode_uv_map(&[], 0).unwrap(), Vec::<u16>::new());
        // A huge side from a file: refused before `size^2 * 6` is computed.
        for s in [limits::MAX_UV_SIZE + 1, 1 << 31, u32::MAX] {
            let e = decode_uv_map(&blob, s).unwrap_err().to_string();
            assert!(e.contains("more than the 4096 allowed"), "{e}");
        }
    }

    #[test]
    fn packers_round_trip_and_refuse_partial_elements() {
        let v = [0u32, 1, u32::MAX, 0x0102_0304];
        let b = pack_u32_le(&v);
        assert_eq!(&b[12..], &[4, 3, 2, 1]);
        assert_eq!(unpack_u32_le(&b, "x").unwrap(), v);
        let e = unpack_u32_le(&b[..15], "mask_rle").unwrap_err().to_string();
        assert_eq!(e, "invalid mask_rle: 15 bytes, not a whole number of u32s");
        let w = [7u16, 0xABCD];
        let b = pack_u16_le(w.iter().copied());
        assert_eq!(b, [7, 0, 0xCD, 0xAB]);
        assert_eq!(unpack_u16_le(&b, "x").unwrap(), w);
        assert!(unpack_u16_le(&b[..3], "x").is_err());
    }

    #[test]
    fn correspondences_round_trip_and_need_matching_lengths() {
        let ids = vec![[1u16, 2, 3], [1219, 0, 7]];
        let ws = vec![[65535u16, 0], [100, 200]];
        let (vb, wb) = encode_correspondences(&ids, &ws);
        assert_eq!((vb.len(), wb.len()), (12, 8));
        assert_eq!(decode_correspondences(&vb, &wb).unwrap(), (ids, ws));
        assert!(decode_correspondences(&vb[..6], &wb).is_err());
        assert!(decode_correspondences(&vb[..11], &wb[..7]).is_err());
        assert!(decode_correspondences(&vb, &wb[..6]).is_err());
        assert_eq!(decode_correspondences(&[], &[]).unwrap(), (vec![], vec![]));
    }
}
