//! The official UV map's lanes ([`crate::loader::item::OfficialUvLayout`]): the covered
//! texels' values, each its corners' colours weighted, clamped and mapped to [-1, 1],
//! a texel's three channels in SSE2 lanes (the x86-64 baseline) or eight texels of a
//! run in AVX-512 lanes, beside the definition ([`covered_scalar`]); tested against it
//! at every level the CPU has (in the loader's UV-map test: random meshes, NaN and
//! clamped colours, every map size).

use super::{Level, level};

/// Texels of a map next to each other that one triangle covers: texels
/// `start..start + len` (row-major), whose weights are `first..first + len` of the
/// weight planes, and the triangle's corners (indices into the colours).
#[derive(Clone, Copy, Debug)]
pub(crate) struct TexelRun {
    /// Row-major index in the map of the run's first texel.
    pub(crate) start: u32,
    /// Texels in the run.
    pub(crate) len: u32,
    /// Where the run's weights begin in the weight planes.
    pub(crate) first: u32,
    /// The triangle's corners (extended vertex indices).
    pub(crate) corners: [u32; 3],
}

/// The covered texels' values of `runs` (weights `weights`, extended vertex colours
/// `colors`) into the three `planes`, at the workspace's SIMD level ([`covered_at`]).
pub(crate) fn covered(
    runs: &[TexelRun],
    weights: &[Vec<f32>; 3],
    colors: &[[f32; 3]],
    planes: [&mut [f32]; 3],
) {
    covered_at(level(), runs, weights, colors, planes)
}

/// [`covered`] at `level` (lowered to the CPU's): AVX-512 F and VL at [`Level::Avx512`],
/// SSE2 below it on x86-64, [`covered_scalar`] elsewhere. The same bits (tested).
pub(crate) fn covered_at(
    level: Level,
    runs: &[TexelRun],
    weights: &[Vec<f32>; 3],
    colors: &[[f32; 3]],
    planes: [&mut [f32]; 3],
) {
    #[cfg(target_arch = "x86_64")]
    if level.supported() == Level::Avx512 {
        // SAFETY: the CPU has AVX-512 F and VL (the level is supported).
        unsafe { covered_avx512(runs, weights, colors, planes) };
    } else {
        // SAFETY: SSE2 is part of the x86-64 baseline: every x86-64 CPU has it.
        unsafe { covered_sse(runs, weights, colors, planes) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = level;
        covered_scalar(runs, weights, colors, planes);
    }
}

/// The covered texels' values, one at a time: the definition. A texel is its
/// corners' colours weighted (`w0 a + w1 b + w2 c`, left to right), clamped to
/// [0, 1] and mapped by `2 x - 1`, in float32.
#[cfg_attr(all(target_arch = "x86_64", not(test)), allow(dead_code))]
pub(crate) fn covered_scalar(
    runs: &[TexelRun],
    weights: &[Vec<f32>; 3],
    colors: &[[f32; 3]],
    mut planes: [&mut [f32]; 3],
) {
    for run in runs {
        let [a, b, c] = run.corners.map(|v| colors[v as usize]);
        for k in 0..run.len as usize {
            let (i, j) = (run.start as usize + k, run.first as usize + k);
            let wt = [weights[0][j], weights[1][j], weights[2][j]];
            for (ch, plane) in planes.iter_mut().enumerate() {
                let value = wt[0] * a[ch] + wt[1] * b[ch] + wt[2] * c[ch];
                plane[i] = value.clamp(0.0, 1.0) * 2.0 - 1.0;
            }
        }
    }
}

/// [`covered_scalar`] with a texel's three channels in the lanes
/// of one SSE register (the fourth lane unused): the same float32 operations in the
/// same order lane by lane (no fused multiply-add), and the clamp's `max(0, x)` then
/// `min(1, x)` with `x` as the second operand, which keeps a NaN and a `-0.0` as
/// `f32::clamp` does; so the same bits (tested). (The texels' runs are short, 2.8
/// texels on average in a 192x192 map, so lanes across texels would mostly idle.)
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "sse2")]
fn covered_sse(
    runs: &[TexelRun],
    weights: &[Vec<f32>; 3],
    colors: &[[f32; 3]],
    planes: [&mut [f32]; 3],
) {
    use std::arch::x86_64::*;
    let [u, v, w] = planes;
    let [w0s, w1s, w2s] = weights;
    let lane = |c: [f32; 3]| _mm_setr_ps(c[0], c[1], c[2], 0.0);
    let (zero, one, two) = (_mm_setzero_ps(), _mm_set1_ps(1.0), _mm_set1_ps(2.0));
    for run in runs {
        let [a, b, c] = run.corners.map(|i| lane(colors[i as usize]));
        let (start, first, len) = (run.start as usize, run.first as usize, run.len as usize);
        let texels = (u[start..start + len].iter_mut())
            .zip(&mut v[start..start + len])
            .zip(&mut w[start..start + len]);
        let weights = (w0s[first..first + len].iter())
            .zip(&w1s[first..first + len])
            .zip(&w2s[first..first + len]);
        for (((u, v), w), ((&w0, &w1), &w2)) in texels.zip(weights) {
            let value = _mm_add_ps(
                _mm_add_ps(
                    _mm_mul_ps(_mm_set1_ps(w0), a),
                    _mm_mul_ps(_mm_set1_ps(w1), b),
                ),
                _mm_mul_ps(_mm_set1_ps(w2), c),
            );
            let clamped = _mm_min_ps(one, _mm_max_ps(zero, value));
            let mapped = _mm_sub_ps(_mm_mul_ps(clamped, two), one);
            *u = _mm_cvtss_f32(mapped);
            *v = _mm_cvtss_f32(_mm_shuffle_ps::<0b01>(mapped, mapped));
            *w = _mm_cvtss_f32(_mm_shuffle_ps::<0b10>(mapped, mapped));
        }
    }
}

/// [`covered_scalar`] with up to eight texels of a run in the lanes
/// of one register, one register per channel: the weights loaded and the values
/// stored under a mask of the run's texels, so a run's setup is paid once rather
/// than per texel. The same float32 operations in the same order lane by lane (no
/// fused multiply-add), and the clamp as [`covered_sse`] has it;
/// so the same bits (tested).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl")]
unsafe fn covered_avx512(
    runs: &[TexelRun],
    weights: &[Vec<f32>; 3],
    colors: &[[f32; 3]],
    planes: [&mut [f32]; 3],
) {
    use std::arch::x86_64::*;
    let [u, v, w] = planes;
    let [w0s, w1s, w2s] = weights;
    let (zero, one, two) = (
        _mm256_setzero_ps(),
        _mm256_set1_ps(1.0),
        _mm256_set1_ps(2.0),
    );
    let (n, m) = (
        u.len().min(v.len()).min(w.len()),
        w0s.len().min(w1s.len()).min(w2s.len()),
    );
    for run in runs {
        let [a, b, c] = run.corners.map(|i| colors[i as usize]);
        let (start, first, len) = (run.start as usize, run.first as usize, run.len as usize);
        assert!(start + len <= n && first + len <= m, "a run inside the map");
        let mut k = 0;
        while k < len {
            let lanes: __mmask8 = if len - k >= 8 {
                0xff
            } else {
                (1u8 << (len - k)) - 1
            };
            // SAFETY: the masked lanes are texels `start + k ..` and weights
            // `first + k ..` of this run, inside `u`, `v`, `w` and the weight
            // planes (asserted above); masked-off lanes are neither read nor written.
            unsafe {
                let at = first + k;
                let w0 = _mm256_maskz_loadu_ps(lanes, w0s.as_ptr().add(at));
                let w1 = _mm256_maskz_loadu_ps(lanes, w1s.as_ptr().add(at));
                let w2 = _mm256_maskz_loadu_ps(lanes, w2s.as_ptr().add(at));
                for (ch, plane) in [&mut *u, &mut *v, &mut *w].into_iter().enumerate() {
                    let value = _mm256_add_ps(
                        _mm256_add_ps(
                            _mm256_mul_ps(w0, _mm256_set1_ps(a[ch])),
                            _mm256_mul_ps(w1, _mm256_set1_ps(b[ch])),
                        ),
                        _mm256_mul_ps(w2, _mm256_set1_ps(c[ch])),
                    );
                    let clamped = _mm256_min_ps(one, _mm256_max_ps(zero, value));
                    let mapped = _mm256_sub_ps(_mm256_mul_ps(clamped, two), one);
                    _mm256_mask_storeu_ps(plane.as_mut_ptr().add(start + k), lanes, mapped);
                }
            }
            k += 8;
        }
    }
}
