//! The official crop's lanes ([`crate::crop::official::warp_affine_window`]): eight RGB
//! crop pixels at a time blended from their columns' pairs of vertically blended values
//! in AVX2 ([`blend_rgb_columns_avx2`]), beside the definition
//! ([`blend_rgb_columns_scalar`], one value at a time, `cv2.warpAffine`'s integer
//! arithmetic) and tested against it at every level the CPU has.

use super::Level;

/// Fractional bits of OpenCV's source positions (`INTER_BITS`): a tap's fraction is in
/// 1/32 pixel.
pub(crate) const INTER_BITS: u32 = 5;
/// Fractional bits of the bilinear weights (`INTER_REMAP_COEF_BITS`): a pixel's four
/// weights sum to 2^15.
pub(crate) const COEF_BITS: u32 = 15;

/// One axis's tap of a crop column or row: the first image column or row it reads and
/// the fraction past it, in 1/32 pixel.
pub(crate) type AxisTap = (i32, u32);

/// OpenCV's rounding of a pixel's tap sum (in units of 2^-15) to a byte.
#[inline(always)]
pub(crate) fn round_sum(sum: u32) -> u8 {
    ((sum + (1 << (COEF_BITS - 1))) >> COEF_BITS).min(255) as u8
}

/// RGB crop pixels from their columns' blended pairs: byte `k` of column `i` (of
/// `columns`, image column `x` and weight `fx` in 1/32) is `round_sum(((32 - fx) lo +
/// fx hi) 2^(15 - 10))`, `lo` and `hi` the low and high halves of `pairs[3 x + k]` (the
/// vertically blended values of its left and right taps). At `level` (lowered to the
/// CPU's): from [`Level::Avx2`] up whole groups of eight columns in AVX2, the rest (and
/// everything below) by the definition. The same bytes (tested). Panics unless `out`
/// holds three bytes a column and every column's `3 x + 2` is inside `pairs`.
pub(crate) fn blend_rgb_columns_at(
    level: Level,
    out: &mut [u8],
    pairs: &[u32],
    columns: &[AxisTap],
) {
    assert_eq!(out.len(), 3 * columns.len(), "three bytes a column");
    assert!(
        columns
            .iter()
            .all(|&(x, _)| x >= 0 && 3 * x as usize + 2 < pairs.len()),
        "a column's pair outside the blended row"
    );
    #[cfg(target_arch = "x86_64")]
    let done = if level.supported() >= Level::Avx2 {
        let n = columns.len() / 8 * 8;
        // SAFETY: the CPU has AVX2 (the level is supported); every column's pairs are
        // inside `pairs` (asserted).
        unsafe { blend_rgb_columns_avx2(&mut out[..3 * n], pairs, &columns[..n]) };
        n
    } else {
        0
    };
    #[cfg(not(target_arch = "x86_64"))]
    let done = {
        let _ = level;
        0
    };
    blend_rgb_columns_scalar(&mut out[3 * done..], pairs, &columns[done..]);
}

/// [`blend_rgb_columns_at`]'s definition, one value at a time.
pub(crate) fn blend_rgb_columns_scalar(out: &mut [u8], pairs: &[u32], columns: &[AxisTap]) {
    let scale = 1u32 << (COEF_BITS - 2 * INTER_BITS);
    for (o, &(x, fx)) in out.chunks_exact_mut(3).zip(columns) {
        for (k, o) in o.iter_mut().enumerate() {
            let pair = pairs[3 * x as usize + k];
            let sum = (32 - fx) * (pair & 0xffff) + fx * (pair >> 16);
            *o = round_sum(sum * scale);
        }
    }
}

/// [`blend_rgb_columns_scalar`] for eight RGB crop pixels at a time (`out` three bytes a column
/// of `columns`, a multiple of eight), in AVX2: each lane gathers its column's pair of
/// vertically blended values (`pairs[3 x + k]`, the left tap's and the right tap's) and
/// multiplies and adds them with `(32 - fx, fx)` in one step, then rounds as
/// [`round_sum`] does (`(s 32 + 2^14) >> 15` is `(s + 512) >> 10`). The same integers.
///
/// # Safety
///
/// The CPU has AVX2, and `3 x + 2 < pairs.len()` for every column's `x`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn blend_rgb_columns_avx2(out: &mut [u8], pairs: &[u32], columns: &[AxisTap]) {
    use std::arch::x86_64::*;
    let round = _mm256_set1_epi32(512);
    for (o, cols) in out.chunks_exact_mut(24).zip(columns.chunks_exact(8)) {
        let xs: [i32; 8] = std::array::from_fn(|k| 3 * cols[k].0);
        let weights: [i32; 8] = std::array::from_fn(|k| {
            let fx = cols[k].1 as i32;
            (32 - fx) | fx << 16
        });
        // SAFETY: unaligned loads of eight i32.
        let (xs, weights) = unsafe {
            (
                _mm256_loadu_si256(xs.as_ptr().cast()),
                _mm256_loadu_si256(weights.as_ptr().cast()),
            )
        };
        let channel = |k: i32| {
            let at = _mm256_add_epi32(xs, _mm256_set1_epi32(k));
            // SAFETY: every index is below `pairs.len()` (the caller's).
            let pair = unsafe { _mm256_i32gather_epi32::<4>(pairs.as_ptr().cast(), at) };
            let sum = _mm256_madd_epi16(pair, weights);
            _mm256_srli_epi32::<10>(_mm256_add_epi32(sum, round))
        };
        let o: &mut [u8; 24] = o.try_into().expect("chunks of 24");
        // SAFETY: AVX2 is enabled here; each value is at most 255.
        unsafe { super::rgb::store_rgb8(o, [channel(0), channel(1), channel(2)]) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arkit_core::Rng;

    #[test]
    fn blended_columns_at_every_level_equal_the_definition() {
        // Column counts 0 to 40 (groups of eight and their tails) over random blended
        // pairs (each half a sum of two taps' bytes weighted to 32, so up to 32 * 255)
        // and random columns and weights (0 and 31 among them).
        let mut r = Rng::new(31);
        for n in 0..=40usize {
            let width = 2 + r.below(50) as usize;
            let pairs: Vec<u32> = (0..3 * width)
                .map(|_| r.below(32 * 255 + 1) as u32 | (r.below(32 * 255 + 1) as u32) << 16)
                .collect();
            let columns: Vec<AxisTap> = (0..n)
                .map(|_| {
                    let fx = match r.below(4) {
                        0 => 0,
                        1 => 31,
                        _ => r.below(32) as u32,
                    };
                    (r.below(width as u64) as i32, fx)
                })
                .collect();
            let mut want = vec![0u8; 3 * n];
            blend_rgb_columns_scalar(&mut want, &pairs, &columns);
            for level in super::super::available() {
                let mut out = vec![0u8; 3 * n];
                blend_rgb_columns_at(level, &mut out, &pairs, &columns);
                assert_eq!(out, want, "{level}: {n} columns");
            }
        }
    }
}
