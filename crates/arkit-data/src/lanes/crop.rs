//! The exact crop's lanes ([`crate::crop::CropTransform::crop_image`]): the vertical
//! blend of two source rows ([`blend_rows`]: AVX2 or SSE2), the horizontal blend of
//! pixel pairs ([`blend_columns`]: SSE2) and the rounding of a float row to bytes
//! ([`round_row_to_u8`]: SSE2), each beside its scalar definition and tested against
//! it at every level the CPU has, over every length up to 40 (the lanes' widths, their
//! multiples and tails).

use super::{Level, level};

/// `floor(v + 0.5)` clamped to 255, for a non-negative `v`: the value rounded half
/// up, as truncating `(v + 0.5).min(255.0) as u8` does. Float arithmetic only, so a
/// loop over a row vectorises with plain SSE2: adding 2^23 leaves the integer nearest
/// `y` (ties to even) in the low mantissa bits, and one is taken off when that rounded
/// up. The saturating `as u8` (or `as i32`) cast compiled to scalar code with a branch
/// per value, a third of the crop's instructions.
#[inline]
pub(crate) fn round_to_u8(v: f32) -> u8 {
    const MAGIC: f32 = 8_388_608.0; // 2^23
    let y = (v + 0.5).min(255.0);
    let t = y + MAGIC;
    let t = if t - MAGIC > y { t - 1.0 } else { t };
    t.to_bits() as u8
}

/// The vertical pass of [`CropTransform::crop_image`]: `out[i] = a[i] * wa + b[i] *
/// wb` over the shortest of the three. On x86-64, sixteen bytes of each row at a time:
/// in AVX2 from [`Level::Avx2`] up ([`blend_rows_avx2`], [`blend_rows_at`]), else in
/// SSE2 (part of the x86-64 baseline; [`blend_rows_sse2`]), where the compiler's own
/// vectorisation loaded four bytes at a time. The same products and sums in every
/// path (no fused multiply-add), so the same bits (tested).
#[inline]
pub(crate) fn blend_rows(a: &[u8], b: &[u8], wa: f32, wb: f32, out: &mut [f32]) {
    blend_rows_at(level(), a, b, wa, wb, out)
}

/// [`blend_rows`] at `level` (lowered to the CPU's): AVX2 from [`Level::Avx2`] up, SSE2
/// (the x86-64 baseline) below, [`blend_rows_scalar`] for the tail and on other
/// targets.
#[inline]
pub(crate) fn blend_rows_at(level: Level, a: &[u8], b: &[u8], wa: f32, wb: f32, out: &mut [f32]) {
    let n = a.len().min(b.len()).min(out.len());
    let (a, b, out) = (&a[..n], &b[..n], &mut out[..n]);
    #[cfg(not(target_arch = "x86_64"))]
    let done = {
        let _ = level;
        0
    };
    #[cfg(target_arch = "x86_64")]
    let done = if level.supported() >= Level::Avx2 {
        // SAFETY: the CPU has AVX2 (the level is supported).
        unsafe { blend_rows_avx2(a, b, wa, wb, out) }
    } else {
        blend_rows_sse2(a, b, wa, wb, out)
    };
    blend_rows_scalar(&a[done..], &b[done..], wa, wb, &mut out[done..]);
}

/// [`blend_rows`] one value at a time (the vector paths' tail).
pub(crate) fn blend_rows_scalar(a: &[u8], b: &[u8], wa: f32, wb: f32, out: &mut [f32]) {
    for ((o, &a), &b) in out.iter_mut().zip(a).zip(b) {
        *o = a as f32 * wa + b as f32 * wb;
    }
}

/// [`blend_rows`] in SSE2 over the whole sixteen-byte chunks of `a`, `b` and `out`
/// (of equal lengths); returns how many values it wrote. One load and six unpacks
/// widen sixteen bytes, then four four-float products and sums: 38 instructions per
/// sixteen bytes of each row.
#[cfg(target_arch = "x86_64")]
#[inline]
fn blend_rows_sse2(a: &[u8], b: &[u8], wa: f32, wb: f32, out: &mut [f32]) -> usize {
    use std::arch::x86_64::*;
    let chunks = a.chunks_exact(16).zip(b.chunks_exact(16));
    for ((a, b), o) in chunks.zip(out.chunks_exact_mut(16)) {
        // SAFETY: SSE2 is part of the x86-64 baseline; each load reads the 16 bytes
        // of a 16-byte chunk and each store writes 4 of the 16 floats of `o`.
        unsafe {
            let zero = _mm_setzero_si128();
            let widen = |p: &[u8]| {
                let v = _mm_loadu_si128(p.as_ptr().cast());
                let (lo, hi) = (_mm_unpacklo_epi8(v, zero), _mm_unpackhi_epi8(v, zero));
                [
                    _mm_unpacklo_epi16(lo, zero),
                    _mm_unpackhi_epi16(lo, zero),
                    _mm_unpacklo_epi16(hi, zero),
                    _mm_unpackhi_epi16(hi, zero),
                ]
                .map(|i| _mm_cvtepi32_ps(i))
            };
            let (pa, pb) = (widen(a), widen(b));
            let (va, vb) = (_mm_set1_ps(wa), _mm_set1_ps(wb));
            for k in 0..4 {
                let v = _mm_add_ps(_mm_mul_ps(pa[k], va), _mm_mul_ps(pb[k], vb));
                _mm_storeu_ps(o.as_mut_ptr().add(4 * k), v);
            }
        }
    }
    a.len() - a.len() % 16
}

/// [`blend_rows_sse2`] in AVX2: eight bytes widen to eight floats in two instructions
/// (`vpmovzxbd`, `vcvtdq2ps`), so sixteen bytes of each row take 16 instructions
/// instead of 38. The same products and sums, in the same order.
///
/// # Safety
/// The CPU must have AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn blend_rows_avx2(a: &[u8], b: &[u8], wa: f32, wb: f32, out: &mut [f32]) -> usize {
    use std::arch::x86_64::*;
    let (va, vb) = (_mm256_set1_ps(wa), _mm256_set1_ps(wb));
    let chunks = a.chunks_exact(16).zip(b.chunks_exact(16));
    for ((a, b), o) in chunks.zip(out.chunks_exact_mut(16)) {
        for h in 0..2 {
            // SAFETY: each load reads 8 of the 16 bytes of a chunk, the store writes 8
            // of the 16 floats of `o`; the CPU has AVX2 (the caller's promise).
            unsafe {
                let widen = |p: &[u8]| {
                    let v = _mm_loadl_epi64(p.as_ptr().add(8 * h).cast());
                    _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(v))
                };
                let v = _mm256_add_ps(_mm256_mul_ps(widen(a), va), _mm256_mul_ps(widen(b), vb));
                _mm256_storeu_ps(o.as_mut_ptr().add(8 * h), v);
            }
        }
    }
    a.len() - a.len() % 16
}

/// [`round_to_u8`] over a row: `dst[i]` from `src[i]`, for the shorter of the two. On
/// x86-64, sixteen values at a time in SSE2 (part of the x86-64 baseline): truncating
/// `fl(v + 0.5)` (`cvttps2dq`) is its floor, the same number `round_to_u8` finds, and
/// the saturating packs clamp to 255. 18 instructions per four values in
/// `round_to_u8`'s vectorised loop, 17 per sixteen here; the same bytes (tested).
#[inline]
pub(crate) fn round_row_to_u8(src: &[f32], dst: &mut [u8]) {
    let n = src.len().min(dst.len());
    let (src, dst) = (&src[..n], &mut dst[..n]);
    // Values before `done` are written by the vector loop.
    #[cfg(not(target_arch = "x86_64"))]
    let done = 0;
    #[cfg(target_arch = "x86_64")]
    let done = {
        use std::arch::x86_64::*;
        for (s, d) in src.chunks_exact(16).zip(dst.chunks_exact_mut(16)) {
            // SAFETY: SSE2 is part of the x86-64 baseline; the loads read 16 floats of
            // `s` and the store writes 16 bytes of `d`, both exactly 16 long.
            unsafe {
                let half = _mm_set1_ps(0.5);
                let q = |k: usize| {
                    _mm_cvttps_epi32(_mm_add_ps(_mm_loadu_ps(s.as_ptr().add(4 * k)), half))
                };
                let lo = _mm_packs_epi32(q(0), q(1));
                let hi = _mm_packs_epi32(q(2), q(3));
                _mm_storeu_si128(d.as_mut_ptr().cast(), _mm_packus_epi16(lo, hi));
            }
        }
        n - n % 16
    };
    for (d, &v) in dst[done..].iter_mut().zip(&src[done..]) {
        *d = round_to_u8(v);
    }
}

/// The two weights of a column's pixel pair, each repeated for a four-float operation.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
pub(crate) struct PairWeights {
    pub(crate) a: [f32; 4],
    pub(crate) b: [f32; 4],
}

/// The crop's horizontal pass: column `i`'s three floats of `row` from the pixel pair at
/// float `starts[i]` of the blended span `blend` and its weights `weights[i]`, `row[3i +
/// k] = blend[s + k] * a + blend[s + 3 + k] * b`. On x86-64 four floats at a time in
/// SSE2 (the baseline; the fourth lands on the next column's first, written after),
/// [`blend_columns_scalar`] elsewhere: the same products and sums, so the same bits
/// (tested). Panics unless `row` holds `3 * starts.len() + 1` floats and each pair's
/// seven floats from its start are inside `blend`.
#[inline]
pub(crate) fn blend_columns(
    starts: &[usize],
    weights: &[PairWeights],
    blend: &[f32],
    row: &mut [f32],
) {
    let n = starts.len().min(weights.len());
    assert!(
        row.len() > 3 * n,
        "a row of {} floats for {n} columns",
        row.len()
    );
    #[cfg(not(target_arch = "x86_64"))]
    blend_columns_scalar(starts, weights, blend, row);
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        let (len, blend, out) = (blend.len(), blend.as_ptr(), row.as_mut_ptr());
        for (i, (&s, w)) in starts.iter().zip(weights).enumerate() {
            assert!(s + 7 <= len, "a column's pair past the span");
            // SAFETY: SSE2 is part of the x86-64 baseline. The reads are floats `s..s +
            // 7` of `blend` (checked just above); the store writes floats `3i..3i + 4`
            // of `row`, which has `3n + 1` (asserted); `w` is 16-byte aligned.
            unsafe {
                let p = blend.add(s);
                let v = _mm_add_ps(
                    _mm_mul_ps(_mm_loadu_ps(p), _mm_load_ps(w.a.as_ptr())),
                    _mm_mul_ps(_mm_loadu_ps(p.add(3)), _mm_load_ps(w.b.as_ptr())),
                );
                _mm_storeu_ps(out.add(3 * i), v);
            }
        }
    }
}

/// [`blend_columns`] one float at a time: the definition.
#[cfg_attr(all(target_arch = "x86_64", not(test)), allow(dead_code))]
pub(crate) fn blend_columns_scalar(
    starts: &[usize],
    weights: &[PairWeights],
    blend: &[f32],
    row: &mut [f32],
) {
    for ((d, &s), w) in row.chunks_exact_mut(3).zip(starts).zip(weights) {
        for (k, d) in d.iter_mut().enumerate() {
            *d = blend[s + k] * w.a[0] + blend[s + 3 + k] * w.b[0];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arkit_core::Rng;

    #[test]
    fn blend_rows_at_every_level_equals_the_definition() {
        let mut r = Rng::new(21);
        for n in (0..=40).chain([63, 64, 65, 203]) {
            let a: Vec<u8> = (0..n).map(|_| r.below(256) as u8).collect();
            let b: Vec<u8> = (0..n + r.below(3) as usize)
                .map(|_| r.below(256) as u8)
                .collect();
            for (wa, wb) in [
                (0.3f32, 0.7f32),
                (1.0, 0.0),
                (r.next_f64() as f32, r.next_f64() as f32),
            ] {
                let mut want = vec![f32::NAN; n];
                blend_rows_scalar(&a, &b, wa, wb, &mut want);
                for level in super::super::available() {
                    let mut out = vec![f32::NAN; n + 1];
                    blend_rows_at(level, &a, &b, wa, wb, &mut out);
                    let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&out[..n]), bits(&want), "{level}: {n} values");
                    assert!(out[n].is_nan(), "{level}: wrote past {n} values");
                }
            }
        }
    }

    #[test]
    fn blend_columns_equals_the_definition() {
        let mut r = Rng::new(22);
        for n in 0..=40 {
            let span = 3 * (n + 3) + 1;
            let blend: Vec<f32> = (0..span).map(|_| r.uniform(0.0, 255.0) as f32).collect();
            let starts: Vec<usize> = (0..n)
                .map(|_| 3 * r.below((n + 2) as u64) as usize)
                .collect();
            let weights: Vec<PairWeights> = (0..n)
                .map(|_| {
                    let t = r.next_f64() as f32;
                    PairWeights {
                        a: [1.0 - t; 4],
                        b: [t; 4],
                    }
                })
                .collect();
            let (mut want, mut got) = (vec![f32::NAN; 3 * n + 1], vec![f32::NAN; 3 * n + 1]);
            blend_columns_scalar(&starts, &weights, &blend, &mut want);
            blend_columns(&starts, &weights, &blend, &mut got);
            let bits = |v: &[f32]| v[..3 * n].iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "{n} columns");
        }
    }

    #[test]
    fn round_row_equals_round_to_u8() {
        let mut r = Rng::new(23);
        for n in (0..=40).chain([255, 256, 257]) {
            let src: Vec<f32> = (0..n)
                .map(|_| match r.below(4) {
                    0 => r.below(256) as f32 + 0.5,
                    1 => r.uniform(255.0, 400.0) as f32,
                    _ => r.uniform(0.0, 256.0) as f32,
                })
                .collect();
            let mut dst = vec![7u8; n + 1];
            round_row_to_u8(&src, &mut dst);
            for i in 0..n {
                assert_eq!(dst[i], round_to_u8(src[i]), "{n} values: {}", src[i]);
            }
            assert_eq!(dst[n], 7, "{n} values: wrote past them");
        }
    }
}
