//! `rgb`: eight interleaved RGB pixels in and out of AVX2 lanes, one `i32` lane per
//! pixel and one register per channel, by byte shuffles (the colour jitter's and the
//! official crop warp's lanes). Tested through their users, against their scalar paths
//! (every RGB triple; every warped byte).

/// Eight interleaved RGB pixels (24 bytes) as three lanes of `i32`, one per channel.
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn load_rgb8(px: &[u8; 24]) -> [std::arch::x86_64::__m256i; 3] {
    use std::arch::x86_64::*;
    // SAFETY: unaligned loads of bytes 0..16 and 16..24 of the 24.
    let (lo, hi) = unsafe {
        (
            _mm_loadu_si128(px.as_ptr().cast()),
            _mm_loadl_epi64(px.as_ptr().add(16).cast()),
        )
    };
    // Pixels 0-3 (bytes 0..12) in the low 128 bits, pixels 4-7 (12..24) in the high.
    let halves = _mm256_permutevar8x32_epi32(
        _mm256_set_m128i(hi, lo),
        _mm256_setr_epi32(0, 1, 2, 2, 3, 4, 5, 5),
    );
    std::array::from_fn(|c| {
        let c = c as i8;
        let z = -128i8; // a shuffle index with its top bit set gives 0
        let pick = _mm256_setr_epi8(
            c,
            z,
            z,
            z,
            c + 3,
            z,
            z,
            z,
            c + 6,
            z,
            z,
            z,
            c + 9,
            z,
            z,
            z, //
            c,
            z,
            z,
            z,
            c + 3,
            z,
            z,
            z,
            c + 6,
            z,
            z,
            z,
            c + 9,
            z,
            z,
            z,
        );
        _mm256_shuffle_epi8(halves, pick)
    })
}

/// Stores three lanes of `i32` in `0..=255`, one per channel, as eight interleaved RGB
/// pixels: the inverse of [`load_rgb8`].
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn store_rgb8(px: &mut [u8; 24], [r, g, b]: [std::arch::x86_64::__m256i; 3]) {
    use std::arch::x86_64::*;
    let pixels = _mm256_or_si256(
        r,
        _mm256_or_si256(_mm256_slli_epi32::<8>(g), _mm256_slli_epi32::<16>(b)),
    );
    let z = -128i8;
    let tight = _mm256_setr_epi8(
        0, 1, 2, 4, 5, 6, 8, 9, 10, 12, 13, 14, z, z, z, z, //
        0, 1, 2, 4, 5, 6, 8, 9, 10, 12, 13, 14, z, z, z, z,
    );
    let both = _mm256_permutevar8x32_epi32(
        _mm256_shuffle_epi8(pixels, tight),
        _mm256_setr_epi32(0, 1, 2, 4, 5, 6, 7, 7),
    );
    // SAFETY: unaligned stores of bytes 0..16 and 16..24 of the 24.
    unsafe {
        _mm_storeu_si128(px.as_mut_ptr().cast(), _mm256_castsi256_si128(both));
        _mm_storel_epi64(
            px.as_mut_ptr().add(16).cast(),
            _mm256_extracti128_si256::<1>(both),
        );
    }
}
