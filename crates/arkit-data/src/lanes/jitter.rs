//! The colour jitter's lanes ([`crate::loader::colour_jitter`]): PIL's integer luma
//! summed, its enhancers' blends through a byte table, the HSV hue rotation and the
//! saturation blend, in SSE2, AVX2 and AVX-512 (VBMI for the table lookups), each
//! beside its scalar definition ([`luma`], [`blend`], [`shift_hue`], [`saturate`]) and
//! dispatched on [`crate::lanes::level`]. The tests (in the colour jitter's module)
//! compare every level the CPU has with the definitions on every RGB triple and every
//! byte value, and on lengths around the lanes' widths.

#[cfg(target_arch = "x86_64")]
use super::rgb::{load_rgb8, store_rgb8};
use super::{Level, avx512_vbmi, level};
use arkit_core::lanes::detected_avx512_vbmi;

/// PIL's integer luma of one RGB pixel (ITU-R 601, `L` mode): `(299 R + 587 G + 114 B)
/// / 1000`.
pub(crate) fn luma(p: &[u8]) -> u32 {
    (p[0] as u32 * 299 + p[1] as u32 * 587 + p[2] as u32 * 114) / 1000
}

/// The sum of every pixel's [`luma`]: on x86-64 eight pixels at a time in AVX2 where the
/// CPU has it ([`luma_sum_avx2`]), the rest one by one; the same integer (tested).
pub(crate) fn luma_sum(rgb: &[u8]) -> u64 {
    luma_sum_at(level(), rgb)
}

/// [`luma_sum`] at `level` (lowered to the CPU's): AVX2 from [`Level::Avx2`] up.
pub(crate) fn luma_sum_at(level: Level, rgb: &[u8]) -> u64 {
    #[allow(unused_mut)]
    let (mut sum, mut done) = (0u64, 0);
    #[cfg(target_arch = "x86_64")]
    if level.supported() >= Level::Avx2 {
        done = rgb.len() / 24 * 24;
        // SAFETY: the CPU has AVX2 (the level is supported); whole groups of eight
        // pixels.
        sum = unsafe { luma_sum_avx2(&rgb[..done]) };
    }
    let _ = level;
    sum + rgb[done..]
        .chunks_exact(3)
        .map(|p| luma(p) as u64)
        .sum::<u64>()
}

/// [`luma`] of eight pixels (one channel a register, as [`load_rgb8`] gives them), in
/// AVX2: the weighted sum in integers, its division by 1000 as `1000 = 8 x 125`: the
/// sum shifted down by 3, then multiplied by `ceil(2^22 / 125) = 33555` and shifted
/// down by 22 (no product passes 2^31; the integer quotient for every sum a pixel can
/// have, `0..=255000`, tested), instead of a float division.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub(crate) fn luma_lanes([r, g, b]: [std::arch::x86_64::__m256i; 3]) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let weighted = |v: __m256i, w: i32| _mm256_mullo_epi32(v, _mm256_set1_epi32(w));
    let sum = _mm256_add_epi32(
        _mm256_add_epi32(weighted(r, 299), weighted(g, 587)),
        weighted(b, 114),
    );
    _mm256_srli_epi32::<22>(_mm256_mullo_epi32(
        _mm256_srli_epi32::<3>(sum),
        _mm256_set1_epi32(LUMA_BY_125),
    ))
}

/// `ceil(2^22 / 125)`: `((s >> 3) * LUMA_BY_125) >> 22` is `s / 1000` for every
/// weighted luma sum `s` ([`luma_lanes`]).
pub(crate) const LUMA_BY_125: i32 = 33555;

/// [`blend`] on eight lanes, in AVX2: `grey + f (v - grey)` in `f32`, then
/// [`round_byte_lanes`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn blend_lanes(
    v: std::arch::x86_64::__m256,
    grey: std::arch::x86_64::__m256,
    f: std::arch::x86_64::__m256,
) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    round_byte_lanes(_mm256_add_ps(
        grey,
        _mm256_mul_ps(f, _mm256_sub_ps(v, grey)),
    ))
}

/// `round_half_away(x).clamp(0.0, 255.0)` on eight lanes, as `i32`, in AVX2: the
/// truncation, one up where the fraction is at least a half. A negative value is
/// truncated toward zero instead of rounded away from it; both clamp to 0, as does
/// every value below 0.5.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn round_byte_lanes(x: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let (zero, one) = (_mm256_setzero_ps(), _mm256_set1_ps(1.0));
    let tr = _mm256_round_ps::<{ _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC }>(x);
    let up = _mm256_and_ps(
        _mm256_cmp_ps::<_CMP_GE_OQ>(_mm256_sub_ps(x, tr), _mm256_set1_ps(0.5)),
        one,
    );
    let y = _mm256_min_ps(
        _mm256_max_ps(_mm256_add_ps(tr, up), zero),
        _mm256_set1_ps(255.0),
    );
    _mm256_cvttps_epi32(y)
}

/// [`luma`] summed over groups of eight pixels (`rgb.len()` a multiple of 24), in AVX2
/// ([`luma_lanes`]); the lanes' sums are `u32`, emptied into the total every 2^13 groups
/// (each group adds at most 255 a lane).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn luma_sum_avx2(rgb: &[u8]) -> u64 {
    use std::arch::x86_64::*;
    let mut total = 0u64;
    for part in rgb.chunks(24 << 13) {
        let mut lanes = _mm256_setzero_si256();
        for px in part.chunks_exact(24) {
            let px: &[u8; 24] = px.try_into().expect("chunks of 24");
            // SAFETY: AVX2 is enabled here.
            let pixels = unsafe { load_rgb8(px) };
            lanes = _mm256_add_epi32(lanes, luma_lanes(pixels));
        }
        let mut out = [0u32; 8];
        // SAFETY: an unaligned store of eight u32 into `out`.
        unsafe { _mm256_storeu_si256(out.as_mut_ptr().cast(), lanes) };
        total += out.iter().map(|&v| v as u64).sum::<u64>();
    }
    total
}

/// PIL's enhancer blend of a value `v` with `grey` by factor `f`, rounded back to a byte.
pub(crate) fn blend(v: f32, grey: f32, f: f32) -> u8 {
    round_half_away(grey + f * (v - grey)).clamp(0.0, 255.0) as u8
}

/// [`blend`] with one `grey` and factor `f` on every byte (brightness: `grey` 0;
/// contrast: the mean luma), through a 256-entry table of [`blend`]: on x86-64 with
/// AVX-512 VBMI 64 bytes at a time, the table in four registers
/// ([`map_bytes_vbmi`]); else 32 bytes at a time in AVX2 where the CPU has it
/// ([`blend_bytes_avx2`]); the rest one at a time from the table. The same bytes
/// (tested on every byte value).
pub(crate) fn blend_bytes(bytes: &mut [u8], grey: f32, f: f32) {
    blend_bytes_at(level(), avx512_vbmi(), bytes, grey, f)
}

/// [`blend_bytes`] at `level` (lowered to the CPU's), with the VBMI permutes when `vbmi`
/// and the CPU has them at [`Level::Avx512`], AVX2 from [`Level::Avx2`] up.
pub(crate) fn blend_bytes_at(level: Level, vbmi: bool, bytes: &mut [u8], grey: f32, f: f32) {
    let level = level.supported();
    let _ = vbmi;
    let table = || -> [u8; 256] { std::array::from_fn(|v| blend(v as f32, grey, f)) };
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if level == Level::Avx512 && vbmi && detected_avx512_vbmi() {
        done = bytes.len() / 64 * 64;
        // SAFETY: the CPU has AVX-512 F, BW and VBMI (checked just above); whole groups
        // of 64 bytes.
        unsafe { map_bytes_vbmi(&mut bytes[..done], &table()) };
    } else if level >= Level::Avx2 {
        done = bytes.len() / 32 * 32;
        // SAFETY: the CPU has AVX2 (the level is supported); whole groups of 32 bytes.
        unsafe { blend_bytes_avx2(&mut bytes[..done], grey, f) };
    }
    // The table for the rest, made only when there is a rest (the AVX2 path has none
    // on a crop of whole groups).
    if done < bytes.len() {
        let table = table();
        bytes[done..]
            .iter_mut()
            .for_each(|v| *v = table[*v as usize]);
    }
}

/// Each byte `v` replaced by `table[v]`, 64 bytes at a time (`bytes.len()` a
/// multiple of 64), in AVX-512 VBMI: the table's halves looked up by the bytes' low
/// seven bits (two two-register permutes), the half chosen by their top bit.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vbmi")]
pub(crate) unsafe fn map_bytes_vbmi(bytes: &mut [u8], table: &[u8; 256]) {
    use std::arch::x86_64::*;
    // SAFETY: four unaligned 64-byte loads within the 256-byte table.
    let t: [__m512i; 4] =
        std::array::from_fn(|k| unsafe { _mm512_loadu_si512(table.as_ptr().add(64 * k).cast()) });
    for chunk in bytes.chunks_exact_mut(64) {
        let p = chunk.as_mut_ptr();
        // SAFETY: an unaligned load and store of the chunk's 64 bytes.
        unsafe {
            let v = _mm512_loadu_si512(p.cast());
            let low = _mm512_permutex2var_epi8(t[0], v, t[1]);
            let high = _mm512_permutex2var_epi8(t[2], v, t[3]);
            let out = _mm512_mask_blend_epi8(_mm512_movepi8_mask(v), low, high);
            _mm512_storeu_si512(p.cast(), out);
        }
    }
}

/// [`blend`] on groups of 32 bytes (`bytes.len()` a multiple of 32), in AVX2
/// ([`blend_lanes`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn blend_bytes_avx2(bytes: &mut [u8], grey: f32, f: f32) {
    use std::arch::x86_64::*;
    let (fv, gv) = (_mm256_set1_ps(f), _mm256_set1_ps(grey));
    let in_order = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
    for chunk in bytes.chunks_exact_mut(32) {
        let p = chunk.as_mut_ptr();
        let q: [__m256i; 4] = std::array::from_fn(|k| {
            // SAFETY: an unaligned load of bytes 8k..8k+8 of the 32-byte chunk.
            let v = unsafe { _mm_loadl_epi64(p.add(8 * k).cast()) };
            blend_lanes(_mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(v)), gv, fv)
        });
        // Packed lane by lane, then the dwords (four bytes each) put back in order.
        let words = (
            _mm256_packus_epi32(q[0], q[1]),
            _mm256_packus_epi32(q[2], q[3]),
        );
        let packed = _mm256_packus_epi16(words.0, words.1);
        let out = _mm256_permutevar8x32_epi32(packed, in_order);
        // SAFETY: an unaligned store of the 32 bytes of the chunk.
        unsafe { _mm256_storeu_si256(p.cast(), out) };
    }
}

/// `v.round()` (nearest, halves away from zero) for `|v| < 2^23`, by truncation and a
/// comparison: `f32::round` is a library call in the x86-64 baseline, and was most of
/// the colour jitter's time. `v - trunc(v)` is exact, so the halfway test is too.
#[inline]
pub(crate) fn round_half_away(v: f32) -> f32 {
    let t = v as i32 as f32;
    let f = v - t;
    if f >= 0.5 {
        t + 1.0
    } else if f <= -0.5 {
        t - 1.0
    } else {
        t.copysign(v)
    }
}

/// `x.rem_euclid(m)` for `x` in `[-m, 2m)`: `x % m` is then `x` or `x - m`, both exact,
/// and a negative remainder gets `m` added, as `rem_euclid` adds it.
#[inline]
pub(crate) fn wrap_once(x: f32, m: f32) -> f32 {
    if x < 0.0 {
        x + m
    } else if x >= m {
        x - m
    } else {
        x
    }
}

/// `v / 255` for every byte `v` (the same division, done once).
pub(crate) const UNIT: [f32; 256] = {
    let mut t = [0f32; 256];
    let mut i = 0;
    while i < 256 {
        t[i] = i as f32 / 255.0;
        i += 1;
    }
    t
};

/// For each sextant of the hue circle, which of `[val, t, p, q]` the red, green and
/// blue channels take (the six cases of the HSV to RGB conversion).
pub(crate) const SEXTANT: [[usize; 3]; 6] = [
    [0, 1, 2],
    [3, 0, 2],
    [2, 0, 1],
    [2, 3, 0],
    [1, 2, 0],
    [0, 2, 3],
];

/// Rotates one pixel's HSV hue by `h` turns (`|h| <= 0.5`): RGB to HSV, the hue moved,
/// back to RGB, rounded to bytes. The scalar path of [`shift_hue_all`] (the last
/// pixels, and targets without SSE2): the textbook conversion's arithmetic, operation
/// for operation, with the sextant's channels from a table, so the bytes are its bytes
/// (tested against it).
pub(crate) fn shift_hue(p: &mut [u8], h: f32) {
    let [r, g, b] = [p[0], p[1], p[2]].map(|v| UNIT[v as usize]);
    let max = r.max(g).max(b);
    let min = r.min(g).min(b);
    let d = max - min;
    if d == 0.0 {
        return;
    }
    let (red, green) = (max == r, max == g);
    let num = if red {
        g - b
    } else if green {
        b - r
    } else {
        r - g
    };
    let x = num / d;
    // (g - b) / d is in [-1, 1], the hue in [0, 1): one wrap each is rem_euclid.
    let h6 = if red {
        wrap_once(x, 6.0)
    } else {
        x + if green { 2.0 } else { 4.0 }
    };
    let hue = wrap_once(h6 / 6.0 + h, 1.0);
    let (sat, val) = (d / max, max);
    // hue * 6 is in [0, 6): truncation is floor.
    let i = (hue * 6.0) as i32;
    let f = hue * 6.0 - i as f32;
    let values = [
        val,
        val * (1.0 - sat * (1.0 - f)),
        val * (1.0 - sat),
        val * (1.0 - sat * f),
    ];
    for (o, &k) in p.iter_mut().zip(&SEXTANT[(i % 6) as usize]) {
        *o = round_half_away(values[k] * 255.0).clamp(0.0, 255.0) as u8;
    }
}

/// [`shift_hue`] on every pixel of an interleaved RGB image: on x86-64 sixteen pixels
/// at a time in AVX-512 where the CPU has it ([`shift_hue_avx512`]), eight at a time in
/// AVX2 ([`shift_hue_avx2`]), then four at a time in SSE2 (part of the baseline,
/// [`shift_hue_sse2`]), the last pixels one by one. The lanes
/// do the scalar path's operations lane by lane, the channel and sextant choices as
/// masks, so every path gives its bytes (tested on every RGB triple).
pub(crate) fn shift_hue_all(rgb: &mut [u8], h: f32) {
    shift_hue_all_at(level(), rgb, h)
}

/// [`shift_hue_all`] at `level` (lowered to the CPU's): AVX-512 (with AVX2 and FMA) at
/// [`Level::Avx512`], AVX2 from [`Level::Avx2`] up, SSE2 (the x86-64 baseline) always.
pub(crate) fn shift_hue_all_at(level: Level, rgb: &mut [u8], h: f32) {
    let level = level.supported();
    let _ = level;
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if level == Level::Avx512 {
            done = rgb.len() / 48 * 48;
            // SAFETY: the CPU has AVX-512 F, AVX2 and FMA (the level is supported); the
            // function reads and writes only the slice given, whole groups of sixteen
            // pixels.
            unsafe { shift_hue_avx512(&mut rgb[..done], h) };
        }
        if level >= Level::Avx2 {
            let start = done;
            done += (rgb.len() - done) / 24 * 24;
            // SAFETY: the CPU has AVX2 (the level is supported); the function reads and
            // writes only the slice given, whole groups of eight pixels.
            unsafe { shift_hue_avx2(&mut rgb[start..done], h) };
        }
        let whole = done + (rgb.len() - done) / 12 * 12;
        // SAFETY: SSE2 is part of the x86-64 baseline; whole groups of four pixels.
        unsafe { shift_hue_sse2(&mut rgb[done..whole], h) };
        done = whole;
    }
    for p in rgb[done..].chunks_exact_mut(3) {
        shift_hue(p, h);
    }
}

/// Blends one pixel with its grey (`(299 R + 587 G + 114 B) / 1000`, PIL's integer
/// luma) by `f`, each channel rounded back to a byte: PIL's `Color` enhancement, the
/// scalar path of [`saturate_all`].
pub(crate) fn saturate(p: &mut [u8], f: f32) {
    let grey = luma(p) as f32;
    for v in p.iter_mut() {
        *v = blend(*v as f32, grey, f);
    }
}

/// [`saturate`] on every pixel of an interleaved RGB image: on x86-64 eight pixels at a
/// time in AVX2 where the CPU has it ([`saturate_avx2`]), the rest one by one; the same
/// bytes (tested on every RGB triple).
pub(crate) fn saturate_all(rgb: &mut [u8], f: f32) {
    saturate_all_at(level(), rgb, f)
}

/// [`saturate_all`] at `level` (lowered to the CPU's): AVX2 from [`Level::Avx2`] up.
pub(crate) fn saturate_all_at(level: Level, rgb: &mut [u8], f: f32) {
    let _ = level;
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if level.supported() >= Level::Avx2 {
        done = rgb.len() / 24 * 24;
        // SAFETY: the CPU has AVX2 (the level is supported); whole groups of eight
        // pixels.
        unsafe { saturate_avx2(&mut rgb[..done], f) };
    }
    for p in rgb[done..].chunks_exact_mut(3) {
        saturate(p, f);
    }
}

/// [`saturate`] on groups of eight pixels (`rgb.len()` a multiple of 24), in AVX2: each
/// pixel's luma ([`luma_lanes`]), then its channels blended with it ([`blend_lanes`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn saturate_avx2(rgb: &mut [u8], f: f32) {
    use std::arch::x86_64::*;
    let fv = _mm256_set1_ps(f);
    // Two passes over blocks of groups of eight pixels, as in `shift_hue_avx2`: each
    // pixel's grey, then the blends.
    const GROUPS: usize = 16;
    for block in rgb.chunks_mut(24 * GROUPS) {
        let mut greys = [_mm256_setzero_ps(); GROUPS];
        for (px, grey) in block.chunks_exact(24).zip(greys.iter_mut()) {
            let px: &[u8; 24] = px.try_into().expect("chunks of 24");
            // SAFETY: AVX2 is enabled in this function.
            let pixels = unsafe { load_rgb8(px) };
            *grey = _mm256_cvtepi32_ps(luma_lanes(pixels));
        }
        for (px, &grey) in block.chunks_exact_mut(24).zip(greys.iter()) {
            let px: &mut [u8; 24] = px.try_into().expect("chunks of 24");
            // SAFETY: AVX2 is enabled in this function.
            let pixels = unsafe { load_rgb8(px) };
            let out = pixels.map(|v| blend_lanes(_mm256_cvtepi32_ps(v), grey, fv));
            // SAFETY: AVX2 is enabled in this function.
            unsafe { store_rgb8(px, out) };
        }
    }
}

/// [`shift_hue`] on groups of four pixels (`rgb.len()` a multiple of 12), in SSE2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "sse2")]
pub(crate) unsafe fn shift_hue_sse2(rgb: &mut [u8], h: f32) {
    use std::arch::x86_64::*;
    let sel = |m: __m128, a: __m128, b: __m128| _mm_or_ps(_mm_and_ps(m, a), _mm_andnot_ps(m, b));
    let (zero, one, six) = (_mm_setzero_ps(), _mm_set1_ps(1.0), _mm_set1_ps(6.0));
    let (half, full) = (_mm_set1_ps(0.5), _mm_set1_ps(255.0));
    let hv = _mm_set1_ps(h);
    // `wrap_once(x, m)` lane by lane.
    let wrap = |x: __m128, m: __m128| {
        let low = _mm_cmplt_ps(x, zero);
        let high = _mm_cmpge_ps(x, m);
        sel(low, _mm_add_ps(x, m), sel(high, _mm_sub_ps(x, m), x))
    };
    for px in rgb.chunks_exact_mut(12) {
        let lane = |c: usize| {
            let v: [f32; 4] = std::array::from_fn(|k| UNIT[px[3 * k + c] as usize]);
            // SAFETY: an unaligned load of the four floats of `v`.
            unsafe { _mm_loadu_ps(v.as_ptr()) }
        };
        let (r, g, b) = (lane(0), lane(1), lane(2));
        let max = _mm_max_ps(_mm_max_ps(r, g), b);
        let min = _mm_min_ps(_mm_min_ps(r, g), b);
        let d = _mm_sub_ps(max, min);
        let keep = _mm_movemask_ps(_mm_cmpeq_ps(d, zero));
        if keep == 0b1111 {
            continue;
        }
        let red = _mm_cmpeq_ps(max, r);
        let green = _mm_andnot_ps(red, _mm_cmpeq_ps(max, g));
        let num = sel(
            red,
            _mm_sub_ps(g, b),
            sel(green, _mm_sub_ps(b, r), _mm_sub_ps(r, g)),
        );
        let x = _mm_div_ps(num, d);
        let off = sel(green, _mm_set1_ps(2.0), _mm_set1_ps(4.0));
        let h6 = sel(red, wrap(x, six), _mm_add_ps(x, off));
        let hue = wrap(_mm_add_ps(_mm_div_ps(h6, six), hv), one);
        let sat = _mm_div_ps(d, max);
        let scaled = _mm_mul_ps(hue, six);
        let i = _mm_cvttps_epi32(scaled);
        let f = _mm_sub_ps(scaled, _mm_cvtepi32_ps(i));
        let i = _mm_andnot_si128(_mm_cmpeq_epi32(i, _mm_set1_epi32(6)), i);
        let is = |k: i32| _mm_castsi128_ps(_mm_cmpeq_epi32(i, _mm_set1_epi32(k)));
        let t = _mm_mul_ps(max, _mm_sub_ps(one, _mm_mul_ps(sat, _mm_sub_ps(one, f))));
        let p = _mm_mul_ps(max, _mm_sub_ps(one, sat));
        let q = _mm_mul_ps(max, _mm_sub_ps(one, _mm_mul_ps(sat, f)));
        // SEXTANT, as masks.
        let or = _mm_or_ps;
        let out = [
            sel(or(is(0), is(5)), max, sel(is(1), q, sel(is(4), t, p))),
            sel(is(0), t, sel(or(is(1), is(2)), max, sel(is(3), q, p))),
            sel(is(2), t, sel(or(is(3), is(4)), max, sel(is(5), q, p))),
        ];
        let mut bytes = [[0i32; 4]; 3];
        for (o, v) in bytes.iter_mut().zip(out) {
            // round_half_away for the non-negative values here, then the clamp.
            let v = _mm_mul_ps(v, full);
            let tr = _mm_cvtepi32_ps(_mm_cvttps_epi32(v));
            let up = _mm_and_ps(_mm_cmpge_ps(_mm_sub_ps(v, tr), half), one);
            let v = _mm_min_ps(_mm_max_ps(_mm_add_ps(tr, up), zero), full);
            // SAFETY: an unaligned store of four i32 into `o`, four i32 long.
            unsafe { _mm_storeu_si128(o.as_mut_ptr().cast(), _mm_cvttps_epi32(v)) };
        }
        for k in 0..4 {
            if keep & (1 << k) == 0 {
                for c in 0..3 {
                    px[3 * k + c] = bytes[c][k] as u8;
                }
            }
        }
    }
}

/// [`shift_hue`] on groups of eight pixels (`rgb.len()` a multiple of 24), in AVX2: the
/// operations of [`shift_hue_sse2`] on eight lanes up to the sextant, then only the one
/// channel value that is neither the largest nor the smallest byte computed and
/// rounded (the same bytes, tested on every RGB triple).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn shift_hue_avx2(rgb: &mut [u8], h: f32) {
    use std::arch::x86_64::*;
    let sel = |m: __m256, a: __m256, b: __m256| _mm256_blendv_ps(b, a, m);
    let (zero, one, six) = (
        _mm256_setzero_ps(),
        _mm256_set1_ps(1.0),
        _mm256_set1_ps(6.0),
    );
    let full = _mm256_set1_ps(255.0);
    let hv = _mm256_set1_ps(h);
    // `wrap_once(x, m)` lane by lane.
    let wrap = |x: __m256, m: __m256| {
        let low = _mm256_cmp_ps::<_CMP_LT_OQ>(x, zero);
        let high = _mm256_cmp_ps::<_CMP_GE_OQ>(x, m);
        sel(low, _mm256_add_ps(x, m), sel(high, _mm256_sub_ps(x, m), x))
    };
    // Two passes over blocks of groups of eight pixels, each pass's chain of dependent
    // operations about half the whole one, so more groups are in flight at once: the
    // first computes each pixel's sextant, its fraction, saturation and value, the
    // second the bytes from them.
    const GROUPS: usize = 16;
    for block in rgb.chunks_mut(24 * GROUPS) {
        let mut hsv = [(_mm256_setzero_si256(), [zero; 3]); GROUPS];
        for (px, out) in block.chunks_exact(24).zip(hsv.iter_mut()) {
            let px: &[u8; 24] = px.try_into().expect("chunks of 24");
            // SAFETY: AVX2 is enabled in this function.
            let bytes = unsafe { load_rgb8(px) };
            // `UNIT[v]`: the same correctly rounded division.
            let [r, g, b] = bytes.map(|v| _mm256_div_ps(_mm256_cvtepi32_ps(v), full));
            let max = _mm256_max_ps(_mm256_max_ps(r, g), b);
            let min = _mm256_min_ps(_mm256_min_ps(r, g), b);
            // Grey pixels (`d == 0`) get NaNs here and keep their bytes in the second pass.
            let d = _mm256_sub_ps(max, min);
            let red = _mm256_cmp_ps::<_CMP_EQ_OQ>(max, r);
            let green = _mm256_andnot_ps(red, _mm256_cmp_ps::<_CMP_EQ_OQ>(max, g));
            let num = sel(
                red,
                _mm256_sub_ps(g, b),
                sel(green, _mm256_sub_ps(b, r), _mm256_sub_ps(r, g)),
            );
            let x = _mm256_div_ps(num, d);
            let off = sel(green, _mm256_set1_ps(2.0), _mm256_set1_ps(4.0));
            let h6 = sel(red, wrap(x, six), _mm256_add_ps(x, off));
            let hue = wrap(_mm256_add_ps(_mm256_div_ps(h6, six), hv), one);
            let sat = _mm256_div_ps(d, max);
            let scaled = _mm256_mul_ps(hue, six);
            let i = _mm256_cvttps_epi32(scaled);
            let f = _mm256_sub_ps(scaled, _mm256_cvtepi32_ps(i));
            let i = _mm256_andnot_si256(_mm256_cmpeq_epi32(i, _mm256_set1_epi32(6)), i);
            *out = (i, [f, sat, max]);
        }
        for (px, &(i, [f, sat, max])) in block.chunks_exact_mut(24).zip(hsv.iter()) {
            let px: &mut [u8; 24] = px.try_into().expect("chunks of 24");
            // SAFETY: AVX2 is enabled in this function.
            let bytes = unsafe { load_rgb8(px) };
            // Of [val, t, p, q], each sextant takes val, p and one of t (even sextants)
            // and q (odd): `t = val (1 - sat (1 - f))`, `q = val (1 - sat f)`, so that
            // one is the same operations on `1 - f` or `f`. `val` rounds back to the
            // largest byte and `p = val (1 - sat)` to the smallest (their float errors
            // are far below half a byte), so only t or q is rounded here (every triple
            // tested).
            let odd = _mm256_castsi256_ps(_mm256_slli_epi32::<31>(i));
            let factor = _mm256_blendv_ps(_mm256_sub_ps(one, f), f, odd);
            let mid = _mm256_mul_ps(max, _mm256_sub_ps(one, _mm256_mul_ps(sat, factor)));
            let mid = round_byte_lanes(_mm256_mul_ps(mid, full));
            let [rb, gb, bb] = bytes;
            let high = _mm256_max_epi32(_mm256_max_epi32(rb, gb), bb);
            let low = _mm256_min_epi32(_mm256_min_epi32(rb, gb), bb);
            // SEXTANT, as masks: per channel, the sextants where it takes val, or t or q
            // (else p).
            let is = |k: i32| _mm256_cmpeq_epi32(i, _mm256_set1_epi32(k));
            let either = |a: i32, b: i32| _mm256_or_si256(is(a), is(b));
            let channel = |val: __m256i, middle: __m256i| {
                _mm256_blendv_epi8(_mm256_blendv_epi8(low, mid, middle), high, val)
            };
            let grey = _mm256_cmpeq_epi32(high, low);
            let out = [
                channel(either(0, 5), either(1, 4)),
                channel(either(1, 2), either(0, 3)),
                channel(either(3, 4), either(2, 5)),
            ];
            let out = std::array::from_fn(|c| _mm256_blendv_epi8(out[c], bytes[c], grey));
            // SAFETY: AVX2 is enabled in this function.
            unsafe { store_rgb8(px, out) };
        }
    }
}

/// [`shift_hue_avx2`] on sixteen pixels a register (`rgb.len()` a multiple of 48), in
/// AVX-512: the same operations lane by lane, in the same two passes, with the choices
/// made by mask registers (one instruction a select, where AVX2's blends take two or
/// three); the pixels in and out of the lanes eight at a time ([`load_rgb8`],
/// [`store_rgb8`]), each eight a half of the register. The divisions by the constants
/// 255 and 6 are a product by the reciprocal and one correction by the remainder (a
/// fused multiply-add each), which gives the divider's bits for every byte and every
/// hue sextant value a triple gives (both covered by the every-triple test), and
/// leaves two of the six divisions to the divider. The same bytes (tested on every RGB
/// triple).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
pub(crate) unsafe fn shift_hue_avx512(rgb: &mut [u8], h: f32) {
    use std::arch::x86_64::*;
    // `m ? a : b`, as `shift_hue_avx2`'s `sel`.
    let sel = |m: __mmask16, a: __m512, b: __m512| _mm512_mask_blend_ps(m, b, a);
    let (zero, one, six) = (
        _mm512_setzero_ps(),
        _mm512_set1_ps(1.0),
        _mm512_set1_ps(6.0),
    );
    let full = _mm512_set1_ps(255.0);
    let hv = _mm512_set1_ps(h);
    // `wrap_once(x, m)` lane by lane.
    let wrap = |x: __m512, m: __m512| {
        let low = _mm512_cmp_ps_mask::<_CMP_LT_OQ>(x, zero);
        let high = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(x, m);
        sel(low, _mm512_add_ps(x, m), sel(high, _mm512_sub_ps(x, m), x))
    };
    let join = |a: __m256i, b: __m256i| _mm512_inserti64x4::<1>(_mm512_castsi256_si512(a), b);
    // `a / b` for the constant `b`: the quotient by its reciprocal, and one correction
    // by the remainder (exact by a fused multiply-add).
    let (inv255, inv6) = (_mm512_set1_ps(1.0 / 255.0), _mm512_set1_ps(1.0 / 6.0));
    let div_exact = |a: __m512, b: __m512, inv: __m512| {
        let q = _mm512_mul_ps(a, inv);
        let r = _mm512_fnmadd_ps(q, b, a);
        _mm512_fmadd_ps(r, inv, q)
    };
    // Sixteen pixels' channels, eight from each half of the 48 bytes.
    let load = |px: &[u8]| -> [__m512i; 3] {
        let (a, b) = px.split_at(24);
        // SAFETY: AVX2 is enabled in this function; two groups of 24 bytes.
        let (a, b) = unsafe {
            (
                load_rgb8(a.try_into().expect("24")),
                load_rgb8(b.try_into().expect("24")),
            )
        };
        std::array::from_fn(|c| join(a[c], b[c]))
    };
    const GROUPS: usize = 8;
    for block in rgb.chunks_mut(48 * GROUPS) {
        let mut hsv = [(_mm512_setzero_si512(), [zero; 3]); GROUPS];
        for (px, out) in block.chunks_exact(48).zip(hsv.iter_mut()) {
            // `UNIT[v]`: the same correctly rounded division.
            let [r, g, b] = load(px).map(|v| div_exact(_mm512_cvtepi32_ps(v), full, inv255));
            let max = _mm512_max_ps(_mm512_max_ps(r, g), b);
            let min = _mm512_min_ps(_mm512_min_ps(r, g), b);
            // Grey pixels (`d == 0`) get NaNs here and keep their bytes in the second pass.
            let d = _mm512_sub_ps(max, min);
            let red = _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(max, r);
            let green = !red & _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(max, g);
            let num = sel(
                red,
                _mm512_sub_ps(g, b),
                sel(green, _mm512_sub_ps(b, r), _mm512_sub_ps(r, g)),
            );
            let x = _mm512_div_ps(num, d);
            let off = sel(green, _mm512_set1_ps(2.0), _mm512_set1_ps(4.0));
            let h6 = sel(red, wrap(x, six), _mm512_add_ps(x, off));
            let hue = wrap(_mm512_add_ps(div_exact(h6, six, inv6), hv), one);
            let sat = _mm512_div_ps(d, max);
            let scaled = _mm512_mul_ps(hue, six);
            let i = _mm512_cvttps_epi32(scaled);
            let f = _mm512_sub_ps(scaled, _mm512_cvtepi32_ps(i));
            let i = _mm512_mask_mov_epi32(
                i,
                _mm512_cmpeq_epi32_mask(i, _mm512_set1_epi32(6)),
                _mm512_setzero_si512(),
            );
            *out = (i, [f, sat, max]);
        }
        for (px, &(i, [f, sat, max])) in block.chunks_exact_mut(48).zip(hsv.iter()) {
            let bytes = load(px);
            // As in `shift_hue_avx2`: only t or q is rounded here, val and p being the
            // largest and smallest bytes.
            let odd = _mm512_test_epi32_mask(i, _mm512_set1_epi32(1));
            let factor = sel(odd, f, _mm512_sub_ps(one, f));
            let mid = _mm512_mul_ps(max, _mm512_sub_ps(one, _mm512_mul_ps(sat, factor)));
            let mid = round_byte_lanes_avx512(_mm512_mul_ps(mid, full));
            let [rb, gb, bb] = bytes;
            let high = _mm512_max_epi32(_mm512_max_epi32(rb, gb), bb);
            let low = _mm512_min_epi32(_mm512_min_epi32(rb, gb), bb);
            // SEXTANT, as masks: per channel, the sextants where it takes val, or t or q
            // (else p).
            let is = |k: i32| _mm512_cmpeq_epi32_mask(i, _mm512_set1_epi32(k));
            let either = |a: i32, b: i32| is(a) | is(b);
            let channel = |val: __mmask16, middle: __mmask16| {
                _mm512_mask_blend_epi32(val, _mm512_mask_blend_epi32(middle, low, mid), high)
            };
            let grey = _mm512_cmpeq_epi32_mask(high, low);
            let out = [
                channel(either(0, 5), either(1, 4)),
                channel(either(1, 2), either(0, 3)),
                channel(either(3, 4), either(2, 5)),
            ];
            let out: [__m512i; 3] =
                std::array::from_fn(|c| _mm512_mask_blend_epi32(grey, out[c], bytes[c]));
            let (a, b) = px.split_at_mut(24);
            let half = |v: __m512i, k: usize| {
                if k == 0 {
                    _mm512_castsi512_si256(v)
                } else {
                    _mm512_extracti64x4_epi64::<1>(v)
                }
            };
            // SAFETY: AVX2 is enabled in this function; two groups of 24 bytes.
            unsafe {
                store_rgb8(a.try_into().expect("24"), out.map(|v| half(v, 0)));
                store_rgb8(b.try_into().expect("24"), out.map(|v| half(v, 1)));
            }
        }
    }
}

/// [`round_byte_lanes`] on sixteen lanes, in AVX-512: the truncation, one added where
/// the fraction is at least a half, clamped to [0, 255].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
fn round_byte_lanes_avx512(x: std::arch::x86_64::__m512) -> std::arch::x86_64::__m512i {
    use std::arch::x86_64::*;
    let (zero, one) = (_mm512_setzero_ps(), _mm512_set1_ps(1.0));
    let tr = _mm512_roundscale_ps::<{ _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC }>(x);
    let up = _mm512_maskz_mov_ps(
        _mm512_cmp_ps_mask::<_CMP_GE_OQ>(_mm512_sub_ps(x, tr), _mm512_set1_ps(0.5)),
        one,
    );
    let y = _mm512_min_ps(
        _mm512_max_ps(_mm512_add_ps(tr, up), zero),
        _mm512_set1_ps(255.0),
    );
    _mm512_cvttps_epi32(y)
}
