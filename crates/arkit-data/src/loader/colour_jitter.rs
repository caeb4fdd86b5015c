//! `colour_jitter`: torchvision's `ColorJitter(0.3, 0.3, 0.2, 0.01)` (the official
//! loader's training augmentation) on an interleaved RGB crop, byte for byte as PIL
//! computes it: brightness, contrast, saturation and hue in a drawn order, each rounded
//! back to bytes. The one colour jitter of the workspace: the loader (the Python
//! package's) draws it in the official ranges, `train` in ranges of its
//! `--colour-jitter` strength ([`ColourJitterRanges::of_strength`]; the official ones
//! by default).
//!
//! Invariants: every operation gives the bytes of its textbook definition (PIL's
//! enhancers, the HSV hue rotation with `f32` arithmetic and `round`); the fast paths
//! (byte tables, library-free roundings, SSE2 and AVX2 lanes) do the same operations
//! and give the same bits. Tested below: each operation against values derived by hand,
//! the scalar hue path against the textbook conversion, and each lane path (SSE2, AVX2
//! where the CPU has it) against the scalar path on every one of the 2^24 RGB triples.

#[cfg(target_arch = "x86_64")]
use crate::rgb_lanes::{load_rgb8, store_rgb8};
use arkit_core::rng::Rng;

/// torchvision's `ColorJitter(0.3, 0.3, 0.2, 0.01)`: brightness, contrast and saturation
/// factors uniform in [0.7, 1.3], [0.7, 1.3], [0.8, 1.2], a hue shift uniform in
/// [-0.01, 0.01] of a turn, applied in a random order ([`ColourJitter::apply`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColourJitter {
    /// Brightness factor (1: unchanged).
    pub brightness: f32,
    /// Contrast factor.
    pub contrast: f32,
    /// Saturation factor.
    pub saturation: f32,
    /// Hue shift in turns.
    pub hue: f32,
    /// The order of the four operations (0 brightness, 1 contrast, 2 saturation, 3 hue).
    pub order: [usize; 4],
}

/// The ranges a [`ColourJitter`] is drawn from: torchvision's `ColorJitter(b, c, s, h)`
/// draws its brightness, contrast and saturation factors uniform in `[1-b, 1+b]`,
/// `[1-c, 1+c]`, `[1-s, 1+s]` and its hue shift in `[-h, h]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColourJitterRanges {
    /// Brightness factor range.
    pub brightness: (f64, f64),
    /// Contrast factor range.
    pub contrast: (f64, f64),
    /// Saturation factor range.
    pub saturation: (f64, f64),
    /// Hue shift range, turns.
    pub hue: (f64, f64),
}

impl ColourJitterRanges {
    /// The official loader's `ColorJitter(0.3, 0.3, 0.2, 0.01)`.
    pub const OFFICIAL: ColourJitterRanges = ColourJitterRanges {
        brightness: (0.7, 1.3),
        contrast: (0.7, 1.3),
        saturation: (0.8, 1.2),
        hue: (-0.01, 0.01),
    };

    /// `ColorJitter(c, c, 2c/3, c/30)`: the official ranges scaled to strength `c`
    /// (`train --colour-jitter c`). At `c = 0.3` (as `f32`) they are
    /// [`ColourJitterRanges::OFFICIAL`] exactly, so the same generator state draws the
    /// same jitter as the loader's.
    pub fn of_strength(c: f32) -> Self {
        if c == 0.3 {
            return Self::OFFICIAL;
        }
        let c = c as f64;
        let around_one = |r: f64| (1.0 - r, 1.0 + r);
        ColourJitterRanges {
            brightness: around_one(c),
            contrast: around_one(c),
            saturation: around_one(c * 2.0 / 3.0),
            hue: (-c / 30.0, c / 30.0),
        }
    }
}

impl ColourJitter {
    /// One draw from `rng` in the official ranges ([`ColourJitterRanges::OFFICIAL`]).
    pub fn draw(rng: &mut Rng) -> Self {
        Self::draw_in(rng, &ColourJitterRanges::OFFICIAL)
    }

    /// One draw from `rng` in `ranges`: brightness, contrast, saturation, hue, then the
    /// order of the four operations.
    pub fn draw_in(rng: &mut Rng, ranges: &ColourJitterRanges) -> Self {
        let mut uniform = |(lo, hi): (f64, f64)| rng.uniform(lo, hi) as f32;
        let brightness = uniform(ranges.brightness);
        let contrast = uniform(ranges.contrast);
        let saturation = uniform(ranges.saturation);
        let hue = uniform(ranges.hue);
        let mut order = [0usize, 1, 2, 3];
        for k in (1..4).rev() {
            order.swap(k, rng.below(k as u64 + 1) as usize);
        }
        ColourJitter {
            brightness,
            contrast,
            saturation,
            hue,
            order,
        }
    }

    /// Applies the jitter to an interleaved RGB image, each operation rounded back to
    /// bytes as PIL does between operations. Brightness blends with black, contrast with
    /// the grey of the image's mean luma (ITU-R 601 integer luma, as PIL's `L`),
    /// saturation with each pixel's luma; the hue shift rotates the HSV hue.
    ///
    /// Brightness and contrast map each byte alone (`blend_bytes`: 32 bytes at a time
    /// where the CPU has AVX2, else a 256-entry table of the same formula); every
    /// rounding is `round_half_away`, `f32::round`'s values without its library call.
    /// Saturation and hue run eight pixels at a time where the CPU has AVX2
    /// (`saturate_all`, `shift_hue_all`).
    pub fn apply(&self, rgb: &mut [u8]) {
        for op in self.order {
            match op {
                0 => blend_bytes(rgb, 0.0, self.brightness),
                1 => {
                    let n = (rgb.len() / 3).max(1) as f64;
                    // An integer sum: the same value as summing the lumas in f64 (every
                    // partial sum is an integer below 2^53), without its latency chain.
                    let sum = luma_sum(rgb);
                    let grey = (sum as f64 / n + 0.5).floor() as f32;
                    blend_bytes(rgb, grey, self.contrast);
                }
                2 => saturate_all(rgb, self.saturation),
                _ => {
                    if self.hue != 0.0 {
                        shift_hue_all(rgb, self.hue)
                    }
                }
            }
        }
    }
}

/// PIL's integer luma of one RGB pixel (ITU-R 601, `L` mode): `(299 R + 587 G + 114 B)
/// / 1000`.
fn luma(p: &[u8]) -> u32 {
    (p[0] as u32 * 299 + p[1] as u32 * 587 + p[2] as u32 * 114) / 1000
}

/// The sum of every pixel's [`luma`]: on x86-64 eight pixels at a time in AVX2 where the
/// CPU has it ([`luma_sum_avx2`]), the rest one by one; the same integer (tested).
fn luma_sum(rgb: &[u8]) -> u64 {
    #[allow(unused_mut)]
    let (mut sum, mut done) = (0u64, 0);
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        done = rgb.len() / 24 * 24;
        // SAFETY: AVX2 was detected; whole groups of eight pixels.
        sum = unsafe { luma_sum_avx2(&rgb[..done]) };
    }
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
fn luma_lanes([r, g, b]: [std::arch::x86_64::__m256i; 3]) -> std::arch::x86_64::__m256i {
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
const LUMA_BY_125: i32 = 33555;

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
unsafe fn luma_sum_avx2(rgb: &[u8]) -> u64 {
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
fn blend(v: f32, grey: f32, f: f32) -> u8 {
    round_half_away(grey + f * (v - grey)).clamp(0.0, 255.0) as u8
}

/// [`blend`] with one `grey` and factor `f` on every byte (brightness: `grey` 0;
/// contrast: the mean luma), through a 256-entry table of [`blend`]: on x86-64 with
/// AVX-512 VBMI 64 bytes at a time, the table in four registers
/// ([`map_bytes_vbmi`]); else 32 bytes at a time in AVX2 where the CPU has it
/// ([`blend_bytes_avx2`]); the rest one at a time from the table. The same bytes
/// (tested on every byte value).
fn blend_bytes(bytes: &mut [u8], grey: f32, f: f32) {
    let table = || -> [u8; 256] { std::array::from_fn(|v| blend(v as f32, grey, f)) };
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if crate::rgb_lanes::has_avx512_vbmi() {
        done = bytes.len() / 64 * 64;
        // SAFETY: AVX-512 F, BW and VBMI were detected; whole groups of 64 bytes.
        unsafe { map_bytes_vbmi(&mut bytes[..done], &table()) };
    } else if std::arch::is_x86_feature_detected!("avx2") {
        done = bytes.len() / 32 * 32;
        // SAFETY: AVX2 was detected; whole groups of 32 bytes.
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
unsafe fn map_bytes_vbmi(bytes: &mut [u8], table: &[u8; 256]) {
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
unsafe fn blend_bytes_avx2(bytes: &mut [u8], grey: f32, f: f32) {
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

/// [`ColourJitter::draw`] then [`ColourJitter::apply`].
pub fn jitter_colour(rgb: &mut [u8], rng: &mut Rng) {
    ColourJitter::draw(rng).apply(rgb)
}

/// `v.round()` (nearest, halves away from zero) for `|v| < 2^23`, by truncation and a
/// comparison: `f32::round` is a library call in the x86-64 baseline, and was most of
/// the colour jitter's time. `v - trunc(v)` is exact, so the halfway test is too.
#[inline]
fn round_half_away(v: f32) -> f32 {
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
fn wrap_once(x: f32, m: f32) -> f32 {
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
const SEXTANT: [[usize; 3]; 6] = [
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
fn shift_hue(p: &mut [u8], h: f32) {
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
fn shift_hue_all(rgb: &mut [u8], h: f32) {
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    {
        if has_avx512() {
            done = rgb.len() / 48 * 48;
            // SAFETY: AVX-512 F and AVX2 were detected; the function reads and writes
            // only the slice given, whole groups of sixteen pixels.
            unsafe { shift_hue_avx512(&mut rgb[..done], h) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            let start = done;
            done += (rgb.len() - done) / 24 * 24;
            // SAFETY: AVX2 was detected; the function reads and writes only the slice
            // given, whole groups of eight pixels.
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
fn saturate(p: &mut [u8], f: f32) {
    let grey = luma(p) as f32;
    for v in p.iter_mut() {
        *v = blend(*v as f32, grey, f);
    }
}

/// [`saturate`] on every pixel of an interleaved RGB image: on x86-64 eight pixels at a
/// time in AVX2 where the CPU has it ([`saturate_avx2`]), the rest one by one; the same
/// bytes (tested on every RGB triple).
fn saturate_all(rgb: &mut [u8], f: f32) {
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        done = rgb.len() / 24 * 24;
        // SAFETY: AVX2 was detected; whole groups of eight pixels.
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
unsafe fn saturate_avx2(rgb: &mut [u8], f: f32) {
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
unsafe fn shift_hue_sse2(rgb: &mut [u8], h: f32) {
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
unsafe fn shift_hue_avx2(rgb: &mut [u8], h: f32) {
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

/// Whether the CPU has AVX-512 F, AVX2 and FMA ([`shift_hue_avx512`]).
#[cfg(target_arch = "x86_64")]
fn has_avx512() -> bool {
    std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
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
unsafe fn shift_hue_avx512(rgb: &mut [u8], h: f32) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_jitter_operations_match_their_definitions() {
        let pixels = [200u8, 100, 50, 10, 20, 30];
        let none = ColourJitter {
            brightness: 1.0,
            contrast: 1.0,
            saturation: 1.0,
            hue: 0.0,
            order: [0, 1, 2, 3],
        };
        let mut p = pixels;
        none.apply(&mut p);
        assert_eq!(p, pixels);
        let mut p = pixels;
        ColourJitter {
            brightness: 0.5,
            ..none
        }
        .apply(&mut p);
        assert_eq!(p, [100, 50, 25, 5, 10, 15]);
        // Saturation 0: each pixel its integer luma (299 R + 587 G + 114 B) / 1000.
        let mut p = pixels;
        ColourJitter {
            saturation: 0.0,
            ..none
        }
        .apply(&mut p);
        let l0 = (200 * 299 + 100 * 587 + 50 * 114) / 1000;
        let l1 = (10 * 299 + 20 * 587 + 30 * 114) / 1000;
        assert_eq!(p, [l0, l0, l0, l1, l1, l1].map(|v| v as u8));
        // Contrast 0: every value the rounded mean luma.
        let mut p = pixels;
        ColourJitter {
            contrast: 0.0,
            ..none
        }
        .apply(&mut p);
        let mean = ((l0 + l1) as f64 / 2.0 + 0.5).floor() as u8;
        assert_eq!(p, [mean; 6]);
        // A third of a turn takes pure red to pure green.
        let mut p = [255u8, 0, 0];
        ColourJitter {
            hue: 1.0 / 3.0,
            ..none
        }
        .apply(&mut p);
        assert_eq!(p, [0, 255, 0]);
    }

    /// The HSV hue rotation as the textbook writes it, with the library's roundings.
    fn shift_hue_reference(p: &mut [u8], h: f32) {
        let [r, g, b] = [p[0], p[1], p[2]].map(|v| v as f32 / 255.0);
        let max = r.max(g).max(b);
        let min = r.min(g).min(b);
        let d = max - min;
        if d == 0.0 {
            return;
        }
        let hue = if max == r {
            ((g - b) / d).rem_euclid(6.0)
        } else if max == g {
            (b - r) / d + 2.0
        } else {
            (r - g) / d + 4.0
        } / 6.0;
        let hue = (hue + h).rem_euclid(1.0);
        let (sat, val) = (d / max, max);
        let i = (hue * 6.0).floor();
        let f = hue * 6.0 - i;
        let (pp, q, t) = (
            val * (1.0 - sat),
            val * (1.0 - sat * f),
            val * (1.0 - sat * (1.0 - f)),
        );
        let (r, g, b) = match i as i32 % 6 {
            0 => (val, t, pp),
            1 => (q, val, pp),
            2 => (pp, val, t),
            3 => (pp, q, val),
            4 => (t, pp, val),
            _ => (val, pp, q),
        };
        for (o, v) in p.iter_mut().zip([r, g, b]) {
            *o = (v * 255.0).round().clamp(0.0, 255.0) as u8;
        }
    }

    #[test]
    fn the_hue_rotation_gives_the_textbook_bytes() {
        let mut rng = Rng::new(8);
        for k in 0..300_000 {
            let p: [u8; 3] = if k < 4096 {
                // Every corner-ish and grey case: channels from a coarse grid.
                [
                    (k % 16 * 17) as u8,
                    (k / 16 % 16 * 17) as u8,
                    (k / 256 * 17) as u8,
                ]
            } else {
                [0; 3].map(|_| rng.below(256) as u8)
            };
            let h = match k % 4 {
                0 => rng.uniform(-0.01, 0.01) as f32,
                1 => rng.uniform(-0.5, 0.5) as f32,
                2 => 1.0 / 3.0,
                _ => -0.01,
            };
            let (mut a, mut b) = (p, p);
            shift_hue(&mut a, h);
            shift_hue_reference(&mut b, h);
            assert_eq!(a, b, "{p:?} {h}");
        }
        // The coarse grid (greys, ties between channels) through the lanes.
        let grid: Vec<u8> = (0..4096)
            .flat_map(|k| [k % 16 * 17, k / 16 % 16 * 17, k / 256 * 17].map(|v| v as u8))
            .collect();
        for h in [0.01f32, -0.01, 1.0 / 3.0, -0.5] {
            let (mut a, mut b) = (grid.clone(), grid.clone());
            shift_hue_all(&mut a, h);
            b.chunks_exact_mut(3)
                .for_each(|p| shift_hue_reference(p, h));
            assert_eq!(a, b, "grid, hue {h}");
        }
        // Whole images through the lanes (and the remainder), against pixel by pixel.
        for n in [1usize, 7, 8, 9, 64, 1001] {
            let h = rng.uniform(-0.02, 0.02) as f32;
            let img: Vec<u8> = (0..3 * n).map(|_| rng.below(256) as u8).collect();
            let (mut a, mut b) = (img.clone(), img);
            shift_hue_all(&mut a, h);
            b.chunks_exact_mut(3)
                .for_each(|p| shift_hue_reference(p, h));
            assert_eq!(a, b, "{n} pixels");
        }
    }

    #[test]
    fn the_fast_roundings_equal_the_library_ones() {
        let mut rng = Rng::new(3);
        let mut values: Vec<f32> = vec![0.0, -0.0, 0.5, -0.5, 1.5, 2.5, -2.5, 254.5, 255.49998];
        values.push(0.5f32.next_down()); // 0.49999997: rounds to 0, though + 0.5 gives 1
        values.push((-0.5f32).next_up());
        for _ in 0..200_000 {
            values.push(rng.uniform(-400.0, 700.0) as f32);
            let k = rng.below(512) as f32;
            values.push(k + 0.5);
            values.push(-k - 0.5);
        }
        for v in values {
            assert_eq!(round_half_away(v).to_bits(), v.round().to_bits(), "{v}");
        }
        for _ in 0..200_000 {
            let x = rng.uniform(-1.0, 2.0) as f32;
            assert_eq!(
                wrap_once(x, 1.0).to_bits(),
                x.rem_euclid(1.0).to_bits(),
                "{x}"
            );
            let y = rng.uniform(-6.0, 12.0) as f32;
            assert_eq!(
                wrap_once(y, 6.0).to_bits(),
                y.rem_euclid(6.0).to_bits(),
                "{y}"
            );
        }
    }

    #[test]
    fn strength_ranges_are_the_official_ones_scaled() {
        assert_eq!(
            ColourJitterRanges::of_strength(0.3),
            ColourJitterRanges::OFFICIAL
        );
        // The same generator state, the same draw as the loader's.
        assert_eq!(
            ColourJitter::draw_in(&mut Rng::new(4), &ColourJitterRanges::of_strength(0.3)),
            ColourJitter::draw(&mut Rng::new(4))
        );
        let r = ColourJitterRanges::of_strength(0.15);
        let c = 0.15f32 as f64;
        assert_eq!(r.brightness, (1.0 - c, 1.0 + c));
        assert_eq!(r.contrast, (1.0 - c, 1.0 + c));
        assert!((r.saturation.1 - 1.1).abs() < 1e-7 && (r.hue.1 - 0.005).abs() < 1e-8);
        // Strength 0: every factor 1 and no hue shift, so the bytes are unchanged.
        let zero = ColourJitter::draw_in(&mut Rng::new(9), &ColourJitterRanges::of_strength(0.0));
        let pixels = [200u8, 100, 50, 10, 20, 30, 0, 255, 128];
        let mut p = pixels;
        zero.apply(&mut p);
        assert_eq!(p, pixels);
    }

    #[test]
    fn colour_jitter_draws_stay_in_torchvision_ranges() {
        let mut rng = Rng::new(5);
        for _ in 0..1000 {
            let j = ColourJitter::draw(&mut rng);
            assert!((0.7..1.3).contains(&j.brightness) && (0.7..1.3).contains(&j.contrast));
            assert!((0.8..1.2).contains(&j.saturation) && (-0.01..0.01).contains(&j.hue));
            let mut o = j.order;
            o.sort();
            assert_eq!(o, [0, 1, 2, 3]);
        }
    }

    #[test]
    fn the_luma_sum_lanes_give_the_integer_sum() {
        // The lanes' multiply and shifts are the integer division on every weighted
        // sum, and no product passes 2^31.
        for s in 0..=255_000u32 {
            let product = (s >> 3) * LUMA_BY_125 as u32;
            assert!(product < 1 << 31, "{s}");
            assert_eq!(product >> 22, s / 1000, "{s}");
        }
        // The lanes themselves, on pixels whose sums run over the whole range.
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            let mut rng = Rng::new(29);
            let mut px: Vec<u8> = (0..65_536 * 3).map(|_| rng.below(256) as u8).collect();
            px.extend([255u8; 24].iter().chain(&[0u8; 24]));
            for group in px.chunks_exact(24) {
                let group: &[u8; 24] = group.try_into().unwrap();
                let mut out = [0u32; 8];
                // SAFETY: AVX2 detected; a store of eight u32 into `out`.
                unsafe {
                    let lanes = luma_lanes(load_rgb8(group));
                    std::arch::x86_64::_mm256_storeu_si256(out.as_mut_ptr().cast(), lanes);
                }
                for (k, p) in group.chunks_exact(3).enumerate() {
                    assert_eq!(out[k], luma(p), "pixel {p:?}");
                }
            }
        }
        // Images of any length, lanes and remainder, against pixel by pixel.
        let mut rng = Rng::new(23);
        for n in [0usize, 1, 7, 8, 9, 100, 65_536 + 13] {
            let img: Vec<u8> = (0..3 * n).map(|_| rng.below(256) as u8).collect();
            let plain: u64 = img.chunks_exact(3).map(|p| luma(p) as u64).sum();
            assert_eq!(luma_sum(&img), plain, "{n} pixels");
        }
        let white = vec![255u8; 3 * 70_000];
        assert_eq!(luma_sum(&white), 255 * 70_000);
    }

    #[test]
    fn the_byte_blend_lanes_give_blends_bytes_for_every_byte() {
        let mut rng = Rng::new(21);
        // Every byte value in several places of the 32-byte groups, then a remainder.
        let bytes: Vec<u8> = (0..256 * 5 + 17).map(|k| (k * 7 % 256) as u8).collect();
        let mut factors = vec![(0.0f32, 0.7f32), (0.0, 1.3), (128.0, 0.0), (0.0, 1.0)];
        factors.extend([(255.0, 1.3), (0.0, 0.5), (3.0, 1.2999)]);
        for _ in 0..200 {
            factors.push((rng.below(256) as f32, rng.uniform(0.0, 2.0) as f32));
        }
        for (grey, f) in factors {
            let mut fast = bytes.clone();
            blend_bytes(&mut fast, grey, f);
            let by_formula: Vec<u8> = bytes.iter().map(|&v| blend(v as f32, grey, f)).collect();
            assert_eq!(fast, by_formula, "grey {grey}, factor {f}");
            // Each lane path on its own, whichever `blend_bytes` took.
            #[cfg(target_arch = "x86_64")]
            {
                let whole = bytes.len() / 64 * 64;
                if std::arch::is_x86_feature_detected!("avx2") {
                    let mut lanes = bytes[..whole].to_vec();
                    // SAFETY: AVX2 was detected; whole groups of 32 bytes.
                    unsafe { blend_bytes_avx2(&mut lanes, grey, f) };
                    assert_eq!(lanes, by_formula[..whole], "avx2, grey {grey}, factor {f}");
                }
                if crate::rgb_lanes::has_avx512_vbmi() {
                    let table: [u8; 256] = std::array::from_fn(|v| blend(v as f32, grey, f));
                    let mut lanes = bytes[..whole].to_vec();
                    // SAFETY: AVX-512 F, BW and VBMI were detected; groups of 64.
                    unsafe { map_bytes_vbmi(&mut lanes, &table) };
                    assert_eq!(lanes, by_formula[..whole], "vbmi, grey {grey}, factor {f}");
                }
            }
        }
        // Brightness 0.5 by hand: 200 -> 100, 3 -> 1.5 -> 2 (halves away from zero).
        let mut p = [200u8; 40];
        p[33] = 3;
        blend_bytes(&mut p, 0.0, 0.5);
        assert_eq!((p[0], p[31], p[32], p[33]), (100, 100, 100, 2));
    }

    /// Every RGB triple, interleaved.
    fn every_triple() -> Vec<u8> {
        (0..1u32 << 24)
            .flat_map(|k| [(k >> 16) as u8, (k >> 8) as u8, k as u8])
            .collect()
    }

    #[test]
    fn the_hue_lanes_give_the_scalar_bytes_for_every_triple() {
        let all = every_triple();
        for h in [0.0093f32, -0.01, 0.5] {
            let mut scalar = all.clone();
            scalar.chunks_exact_mut(3).for_each(|p| shift_hue(p, h));
            #[cfg(target_arch = "x86_64")]
            {
                let mut sse2 = all.clone();
                // SAFETY: SSE2 is part of the x86-64 baseline; 2^24 pixels are whole
                // groups of four.
                unsafe { shift_hue_sse2(&mut sse2, h) };
                assert!(sse2 == scalar, "SSE2, hue {h}");
                if std::arch::is_x86_feature_detected!("avx2") {
                    let mut avx2 = all.clone();
                    // SAFETY: AVX2 detected; whole groups of eight pixels.
                    unsafe { shift_hue_avx2(&mut avx2, h) };
                    assert!(avx2 == scalar, "AVX2, hue {h}");
                } else {
                    eprintln!("SKIPPED: AVX2 hue lanes (this CPU has no AVX2)");
                }
                if has_avx512() {
                    let mut avx512 = all.clone();
                    // SAFETY: AVX-512 F and AVX2 detected; 2^24 pixels are whole
                    // groups of sixteen.
                    unsafe { shift_hue_avx512(&mut avx512, h) };
                    assert!(avx512 == scalar, "AVX-512, hue {h}");
                } else {
                    eprintln!("SKIPPED: AVX-512 hue lanes (this CPU has no AVX-512)");
                }
            }
            let mut dispatched = all.clone();
            shift_hue_all(&mut dispatched, h);
            assert!(dispatched == scalar, "shift_hue_all, hue {h}");
        }
    }

    #[test]
    fn the_saturation_lanes_give_the_scalar_bytes_for_every_triple() {
        let all = every_triple();
        for f in [0.8f32, 1.1999, 0.0, 1.0] {
            let mut scalar = all.clone();
            scalar.chunks_exact_mut(3).for_each(|p| saturate(p, f));
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                let mut avx2 = all.clone();
                // SAFETY: AVX2 detected; whole groups of eight pixels.
                unsafe { saturate_avx2(&mut avx2, f) };
                assert!(avx2 == scalar, "AVX2, factor {f}");
            } else {
                eprintln!("SKIPPED: AVX2 saturation lanes (this CPU has no AVX2)");
            }
            let mut dispatched = all.clone();
            saturate_all(&mut dispatched, f);
            assert!(dispatched == scalar, "saturate_all, factor {f}");
        }
        // The scalar path is PIL's blend with the integer luma, derived by hand.
        let mut p = [200u8, 100, 50];
        saturate(&mut p, 1.2);
        let l = (200 * 299 + 100 * 587 + 50 * 114) / 1000; // 123
        let by_hand = [200, 100, 50]
            .map(|v: i32| (l as f32 + 1.2 * (v - l) as f32).round().clamp(0.0, 255.0) as u8);
        assert_eq!(p, by_hand);
        assert_eq!(by_hand, [215, 95, 35]);
        // Images of any length: lanes and remainder.
        let mut rng = Rng::new(11);
        for n in [1usize, 7, 8, 9, 17, 1001] {
            let img: Vec<u8> = (0..3 * n).map(|_| rng.below(256) as u8).collect();
            let (mut a, mut b) = (img.clone(), img);
            saturate_all(&mut a, 0.9);
            b.chunks_exact_mut(3).for_each(|p| saturate(p, 0.9));
            assert_eq!(a, b, "{n} pixels");
        }
    }
}
