//! The loader's batch-plane lanes ([`crate::loader::item`]): an RGB crop's bytes looked
//! up per channel into three planes ([`lookup_planes`]: the normalisation) and a mask's
//! bytes widened to `int64` ([`widen_mask`]), in AVX2 and AVX-512 (VBMI's permutes for
//! the lookups, streaming stores for the planes), each beside its scalar definition and
//! tested against it at every level the CPU has, over every length up to 40 pixels and
//! every alignment of the planes.

use super::{Level, avx512_vbmi, level};
use arkit_core::lanes::detected_avx512_vbmi;

/// `planes[k][i] = table[k][rgb[3 i + k]]` for every pixel `i` of the interleaved `rgb`
/// (each plane holds `rgb.len() / 3` values), at the workspace's SIMD level
/// ([`lookup_planes_at`]).
pub(crate) fn lookup_planes(rgb: &[u8], planes: [&mut [f32]; 3], table: &[[f32; 256]; 3]) {
    lookup_planes_at(level(), avx512_vbmi(), rgb, planes, table)
}

/// [`lookup_planes`] at `level` (lowered to the CPU's): sixteen pixels at a time where
/// `vbmi` and the CPU has AVX-512 VBMI at [`Level::Avx512`] (the table held in
/// registers), else eight at a time from [`Level::Avx2`] up (the table read by
/// gathers), the rest by the definition ([`lookup_planes_scalar`]). Panics unless every
/// plane holds `rgb.len() / 3` values.
pub(crate) fn lookup_planes_at(
    level: Level,
    vbmi: bool,
    rgb: &[u8],
    planes: [&mut [f32]; 3],
    table: &[[f32; 256]; 3],
) {
    let n = rgb.len() / 3;
    let [r, g, b] = planes;
    assert!(
        r.len() == n && g.len() == n && b.len() == n,
        "planes of one value a pixel"
    );
    let level = level.supported();
    let _ = vbmi;
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if level == Level::Avx512 && vbmi && detected_avx512_vbmi() {
        done = n / 16 * 16;
        // SAFETY: the CPU has AVX-512 F, BW and VBMI (checked just above); whole groups
        // of sixteen pixels of each.
        unsafe {
            normalise_avx512(
                &rgb[..3 * done],
                [&mut r[..done], &mut g[..done], &mut b[..done]],
                table,
            )
        };
    } else if level >= Level::Avx2 {
        done = n / 8 * 8;
        // SAFETY: the CPU has AVX2 (the level is supported); whole groups of eight
        // pixels of each.
        unsafe {
            normalise_avx2(
                &rgb[..3 * done],
                [&mut r[..done], &mut g[..done], &mut b[..done]],
                table,
            )
        };
    }
    lookup_planes_scalar(
        &rgb[3 * done..3 * n],
        [&mut r[done..], &mut g[done..], &mut b[done..]],
        table,
    );
}

/// [`lookup_planes`] one pixel at a time: the definition.
pub(crate) fn lookup_planes_scalar(rgb: &[u8], planes: [&mut [f32]; 3], table: &[[f32; 256]; 3]) {
    let [r, g, b] = planes;
    for (((p, r), g), b) in rgb.chunks_exact(3).zip(r).zip(g).zip(b) {
        *r = table[0][p[0] as usize];
        *g = table[1][p[1] as usize];
        *b = table[2][p[2] as usize];
    }
}

/// `out[i] = mask[i] as i64` (the lengths equal), at the workspace's SIMD level
/// ([`widen_mask_at`]).
pub(crate) fn widen_mask(mask: &[u8], out: &mut [i64]) {
    widen_mask_at(level(), mask, out)
}

/// [`widen_mask`] at `level` (lowered to the CPU's): at [`Level::Avx512`] eight at a
/// time, written with streaming stores (whole 64-byte lines, realigned to the plane);
/// the rest one at a time ([`widen_mask_scalar`]). Panics unless the lengths are equal.
pub(crate) fn widen_mask_at(level: Level, mask: &[u8], out: &mut [i64]) {
    assert_eq!(mask.len(), out.len(), "one value per mask byte");
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if level.supported() == Level::Avx512 {
        done = mask.len() / 8 * 8;
        // SAFETY: the CPU has AVX-512 F (the level is supported); whole groups of
        // eight.
        unsafe { widen_mask_avx512(&mask[..done], &mut out[..done]) };
    }
    let _ = level;
    widen_mask_scalar(&mask[done..], &mut out[done..]);
}

/// [`widen_mask`] one value at a time: the definition.
pub(crate) fn widen_mask_scalar(mask: &[u8], out: &mut [i64]) {
    for (o, &m) in out.iter_mut().zip(mask) {
        *o = m as i64;
    }
}

/// The table lookups of [`lookup_planes`] for groups of eight pixels (`rgb` 24 bytes a
/// group, each plane eight values a group), in AVX2: each channel's eight bytes as
/// indices of one gather from its table.
///
/// # Safety
///
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn normalise_avx2(rgb: &[u8], planes: [&mut [f32]; 3], table: &[[f32; 256]; 3]) {
    use std::arch::x86_64::*;
    let [r, g, b] = planes;
    let groups = rgb.chunks_exact(24).zip(r.chunks_exact_mut(8));
    for ((px, r), (g, b)) in groups.zip(g.chunks_exact_mut(8).zip(b.chunks_exact_mut(8))) {
        let px: &[u8; 24] = px.try_into().expect("chunks of 24");
        // SAFETY: AVX2 is enabled here.
        let bytes = unsafe { super::rgb::load_rgb8(px) };
        for ((plane, index), table) in [r, g, b].into_iter().zip(bytes).zip(table) {
            // SAFETY: every index is a byte, below the table's 256 entries; the store
            // writes the plane's eight values.
            unsafe {
                let v = _mm256_i32gather_ps::<4>(table.as_ptr(), index);
                _mm256_storeu_ps(plane.as_mut_ptr(), v);
            }
        }
    }
}

/// The table lookups of [`lookup_planes`] for groups of sixteen pixels (`rgb` 48
/// bytes a group, each plane sixteen values a group), in AVX-512, a plane at a time:
/// the channel's 256 values held in sixteen registers, its sixteen bytes picked out of
/// the group's 48 by one byte permute, each looked up among 32 values by a
/// two-register permute (the index's low five bits) in the eight pairs of registers,
/// and the right pair's value chosen by the index's three high bits. No gathers.
///
/// # Safety
///
/// The CPU has AVX-512 F, BW and VBMI.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vbmi")]
unsafe fn normalise_avx512(rgb: &[u8], planes: [&mut [f32]; 3], table: &[[f32; 256]; 3]) {
    use std::arch::x86_64::*;
    let group_bytes: __mmask64 = (1 << 48) - 1;
    for (c, (plane, table)) in planes.into_iter().zip(table).enumerate() {
        // SAFETY: sixteen unaligned 64-byte loads within the 256-value table.
        let t: [__m512; 16] =
            std::array::from_fn(|j| unsafe { _mm512_loadu_ps(table.as_ptr().add(16 * j)) });
        // Byte `3 k + c` of the group into byte `k`, for the sixteen pixels.
        let pick: [u8; 64] = std::array::from_fn(|k| if k < 16 { (3 * k + c) as u8 } else { 0 });
        // SAFETY: an unaligned load of the 64 bytes of `pick`.
        let pick = unsafe { _mm512_loadu_si512(pick.as_ptr().cast()) };
        let bit = |b: i32| _mm512_set1_epi32(b);
        let mut out = crate::lanes::streamed_plane::StreamedPlane::new(plane);
        for px in rgb.chunks_exact(48) {
            // SAFETY: a masked load of the group's 48 bytes (the 16 past them masked
            // off, neither read nor faulting).
            unsafe {
                let bytes = _mm512_maskz_loadu_epi8(group_bytes, px.as_ptr().cast());
                let idx = _mm512_cvtepu8_epi32(_mm512_castsi512_si128(_mm512_permutexvar_epi8(
                    pick, bytes,
                )));
                let pair = |j: usize| _mm512_permutex2var_ps(t[2 * j], idx, t[2 * j + 1]);
                let by = |b: i32, low: __m512, high: __m512| {
                    _mm512_mask_blend_ps(_mm512_test_epi32_mask(idx, bit(b)), low, high)
                };
                let q = [
                    by(32, pair(0), pair(1)),
                    by(32, pair(2), pair(3)),
                    by(32, pair(4), pair(5)),
                    by(32, pair(6), pair(7)),
                ];
                out.push(_mm512_castps_si512(by(
                    128,
                    by(64, q[0], q[1]),
                    by(64, q[2], q[3]),
                )));
            }
        }
        out.finish();
    }
}

/// [`widen_mask`] for groups of eight bytes, in AVX-512.
///
/// # Safety
/// The CPU has AVX-512 F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn widen_mask_avx512(mask: &[u8], out: &mut [i64]) {
    use std::arch::x86_64::*;
    let mut plane = crate::lanes::streamed_plane::StreamedPlane::new(out);
    for group in mask.chunks_exact(8) {
        // SAFETY: an unaligned load of the group's eight bytes.
        let bytes = unsafe { _mm_loadl_epi64(group.as_ptr().cast()) };
        plane.push(_mm512_cvtepu8_epi64(bytes));
    }
    plane.finish();
}

#[cfg(test)]
mod tests {
    use super::*;
    use arkit_core::Rng;

    #[test]
    fn lookups_and_widening_at_every_level_equal_the_definitions() {
        // Random bytes and tables; every pixel count up to 40 and a few larger, at
        // every float offset of the planes from a 64-byte line (the AVX-512 paths
        // stream whole lines and write the values before and after them plainly):
        // the definitions' bits, nothing written outside the planes.
        let mut r = Rng::new(41);
        let table: [[f32; 256]; 3] =
            std::array::from_fn(|_| std::array::from_fn(|_| r.uniform(-3.0, 3.0) as f32));
        for n in (0..=40).chain([63, 64, 65, 512]) {
            let rgb: Vec<u8> = (0..3 * n).map(|_| r.below(256) as u8).collect();
            let mut want = [0, 1, 2].map(|_| vec![0f32; n]);
            let [a, b, c] = &mut want;
            lookup_planes_scalar(&rgb, [a, b, c], &table);
            let mask: Vec<u8> = (0..n).map(|_| r.below(2) as u8).collect();
            let mut widened = vec![0i64; n];
            widen_mask_scalar(&mask, &mut widened);
            assert!(widened.iter().zip(&mask).all(|(&w, &m)| w == m as i64));
            for level in super::super::available() {
                for vbmi in [false, true] {
                    for off in 0..16 {
                        let mut planes = [0, 1, 2].map(|_| vec![f32::NAN; n + 32]);
                        let [a, b, c] = &mut planes;
                        let [a, b, c] = [a, b, c].map(|p| &mut p[off..off + n]);
                        lookup_planes_at(level, vbmi, &rgb, [a, b, c], &table);
                        for (p, w) in planes.iter().zip(&want) {
                            let bits =
                                |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                            assert_eq!(
                                bits(&p[off..off + n]),
                                bits(w),
                                "{level} {vbmi}: {n} at +{off}"
                            );
                            assert!(p[..off].iter().chain(&p[off + n..]).all(|v| v.is_nan()));
                        }
                    }
                }
                for off in 0..8 {
                    let mut out = vec![-7i64; n + 16];
                    widen_mask_at(level, &mask, &mut out[off..off + n]);
                    assert_eq!(out[off..off + n], widened, "{level}: {n} at +{off}");
                    assert!(out[..off].iter().chain(&out[off + n..]).all(|&v| v == -7));
                }
            }
        }
    }
}
