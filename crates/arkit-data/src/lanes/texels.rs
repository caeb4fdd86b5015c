//! The UV position map's lanes ([`crate::render::uv_map::UvTexels`]): each covered
//! texel's position as its UV triangle's three positions weighted, one texel per SSE2
//! operation (the x86-64 baseline), two per AVX and four per AVX-512 operation
//! ([`UvTexels::fill_covered_at`]), and the map scaled and clamped into three planes
//! ([`clamp_planes`]: AVX, AVX-512), each beside its scalar definition
//! ([`UvTexels::fill_scalar`], [`clamp_planes_from`]) and tested against it at every
//! level the CPU has (in the renderer's tests).

use super::{Level, level};
use nalgebra::Point3;

// The table's type lives here, beside the kernels that read its fields; its public
// path is `render::uv_map::UvTexels`, where its other methods are.
/// The rasterized UV layout at one map size ([`UvMapper::texels`](crate::render::uv_map::UvMapper::texels)): per covered texel,
/// its UV triangle's three extended vertices and their weights. A position map is then
/// a weighted sum of three positions per texel, with no rasterization: at 192x192 the
/// map of a mesh took 1.0 ms when the layout was rasterized for each mesh. The texels
/// are grouped by triangle, so that a triangle's three positions are read once for
/// its texels (about a dozen at 192x192), not once per texel.
#[derive(Clone, Debug)]
pub struct UvTexels {
    pub(crate) size: u32,
    pub(crate) extended_vertices: usize,
    /// Per group, the UV triangle's extended vertex ids.
    pub(crate) triangles: Vec<[u32; 3]>,
    /// Per group, the end of its texels in `index` and `weights` (the next group's
    /// start).
    pub(crate) ends: Vec<u32>,
    /// Row-major index of each covered texel.
    pub(crate) index: Vec<u32>,
    /// This table's identity, shared by its clones (which cover the same texels): a
    /// position map kept for it has NaN on every texel it leaves uncovered
    /// ([`UvTexels::clamped_planes_into`]).
    pub(crate) layout: u64,
    /// Each covered texel's three weights (and a zero), for one aligned load.
    pub(crate) weights: Vec<TexelWeights>,
}

/// A texel's three barycentric weights and a zero, 16-byte aligned.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
pub(crate) struct TexelWeights(pub(crate) [f32; 4]);

/// [`clamp_planes_from`] of a whole map, at the workspace's SIMD level
/// ([`clamp_planes_at`]).
pub(crate) fn clamp_planes(map: &[[f32; 3]], scale: f32, planes: [&mut [f32]; 3]) {
    clamp_planes_at(level(), map, scale, planes)
}

/// [`clamp_planes`] at `level` (lowered to the CPU's): sixteen texels at a time in
/// AVX-512 at [`Level::Avx512`] (the planes written with streaming stores), eight in
/// AVX from [`Level::Avx2`] up, else the definition. Panics unless every plane holds
/// one value a texel.
pub(crate) fn clamp_planes_at(level: Level, map: &[[f32; 3]], scale: f32, planes: [&mut [f32]; 3]) {
    let n = map.len();
    let [u, v, w] = planes;
    assert!(
        u.len() == n && v.len() == n && w.len() == n,
        "one value a texel"
    );
    #[cfg(target_arch = "x86_64")]
    match level.supported() {
        Level::Avx512 => {
            let done = n / 16 * 16;
            let (u, u_rest) = u.split_at_mut(done);
            let (v, v_rest) = v.split_at_mut(done);
            let (w, w_rest) = w.split_at_mut(done);
            // SAFETY: the CPU has AVX-512 F (the level is supported); whole groups of
            // sixteen texels.
            unsafe { clamp_planes_avx512(&map[..done], scale, [u, v, w]) };
            clamp_planes_from(&map[done..], 0, scale, [u_rest, v_rest, w_rest]);
            return;
        }
        Level::Avx2 => {
            // SAFETY: the CPU has AVX (part of `Level::Avx2`, which is supported).
            unsafe { clamp_planes_avx(map, scale, [u, v, w]) };
            return;
        }
        Level::Scalar => {}
    }
    let _ = level;
    clamp_planes_from(map, 0, scale, [u, v, w]);
}

impl UvTexels {
    /// The covered texels of [`UvTexels::position_map`] written into `out` (one per
    /// texel of the map), the others left as they are, at `level` (lowered to the
    /// CPU's): four texels per AVX-512 operation at [`Level::Avx512`], two per AVX
    /// operation from [`Level::Avx2`] up, one per SSE2 operation (the x86-64 baseline)
    /// below, and one coordinate at a time elsewhere ([`UvTexels::fill_scalar`], the
    /// definition). The same bits (tested). Panics unless `extended` holds one
    /// position per UV vertex and `out` one value per texel of the map.
    pub(crate) fn fill_covered_at(
        &self,
        level: Level,
        extended: &[Point3<f32>],
        out: &mut [[f32; 3]],
    ) {
        assert_eq!(
            extended.len(),
            self.extended_vertices,
            "one position per UV vertex"
        );
        #[cfg(target_arch = "x86_64")]
        {
            let padded = padded_positions(extended);
            match level.supported() {
                // SAFETY: the CPU has AVX-512 F and VL (the level is supported).
                Level::Avx512 => unsafe { self.fill_avx512(&padded, out) },
                // SAFETY: the CPU has AVX (part of `Level::Avx2`, which is supported).
                Level::Avx2 => unsafe { self.fill_avx(&padded, out) },
                Level::Scalar => self.fill_sse2(&padded, out),
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = level;
            self.fill_scalar(extended, out);
        }
    }

    /// Checks the buffers of [`UvTexels::fill_sse2`] and [`UvTexels::fill_avx`]: one
    /// padded position per extended vertex, one output per texel of the map. With the
    /// table's own invariants (every vertex id below `extended_vertices`, every texel
    /// index below `size * size`: [`UvMapper::texels`](crate::render::uv_map::UvMapper::texels) makes them so) this keeps their
    /// unchecked reads and writes in bounds.
    #[cfg(target_arch = "x86_64")]
    fn check_fill(&self, padded: &[[f32; 4]], out: &[[f32; 3]]) {
        assert_eq!(padded.len(), self.extended_vertices);
        assert_eq!(out.len(), self.size as usize * self.size as usize);
    }

    /// The covered texels of `out` from the padded positions, one texel per SSE2
    /// operation (the x86-64 baseline).
    #[cfg(target_arch = "x86_64")]
    fn fill_sse2(&self, padded: &[[f32; 4]], out: &mut [[f32; 3]]) {
        use std::arch::x86_64::*;
        self.check_fill(padded, out);
        let (pos, dst) = (padded.as_ptr(), out.as_mut_ptr().cast::<f32>());
        let mut start = 0;
        for (v, &end) in self.triangles.iter().zip(&self.ends) {
            let range = start..end as usize;
            start = end as usize;
            let texels = self.index[range.clone()].iter().zip(&self.weights[range]);
            // SAFETY: SSE2 is part of the x86-64 baseline; the reads and writes are in
            // bounds (`check_fill`); `w` is 16-byte aligned.
            unsafe {
                let p = v.map(|v| _mm_loadu_ps(pos.add(v as usize).cast()));
                for (&i, w) in texels {
                    let q = texel_sum(p, _mm_load_ps(w.0.as_ptr()));
                    store_texel(dst.add(i as usize * 3), q);
                }
            }
        }
    }

    /// [`UvTexels::fill_sse2`] two texels per eight-float AVX operation (the
    /// triangle's positions in both halves), a group's odd texel in four floats:
    /// the same products and sums lane by lane, so the same bits (tested).
    ///
    /// # Safety
    /// The CPU must have AVX.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx")]
    unsafe fn fill_avx(&self, padded: &[[f32; 4]], out: &mut [[f32; 3]]) {
        use std::arch::x86_64::*;
        self.check_fill(padded, out);
        let (pos, dst) = (padded.as_ptr(), out.as_mut_ptr().cast::<f32>());
        let (index, weights) = (self.index.as_ptr(), self.weights.as_ptr());
        let mut start = 0;
        for (v, &end) in self.triangles.iter().zip(&self.ends) {
            let (mut j, end) = (start, end as usize);
            start = end;
            // SAFETY: the reads and writes are in bounds (`check_fill`; `j` and `j + 1`
            // stay below the group's end, at most `index.len() == weights.len()`);
            // the CPU has AVX (the caller's promise).
            unsafe {
                let p = v.map(|v| _mm256_broadcast_ps(&*pos.add(v as usize).cast::<__m128>()));
                while j + 2 <= end {
                    let w = _mm256_loadu_ps(weights.add(j).cast());
                    let lane = |k: usize, w: __m256| _mm256_mul_ps(p[k], w);
                    let q = _mm256_add_ps(
                        _mm256_add_ps(
                            lane(0, _mm256_shuffle_ps::<0x00>(w, w)),
                            lane(1, _mm256_shuffle_ps::<0x55>(w, w)),
                        ),
                        lane(2, _mm256_shuffle_ps::<0xAA>(w, w)),
                    );
                    store_texel(
                        dst.add(*index.add(j) as usize * 3),
                        _mm256_castps256_ps128(q),
                    );
                    store_texel(
                        dst.add(*index.add(j + 1) as usize * 3),
                        _mm256_extractf128_ps::<1>(q),
                    );
                    j += 2;
                }
                if j < end {
                    let p = p.map(|p| _mm256_castps256_ps128(p));
                    let q = texel_sum(p, _mm_load_ps((*weights.add(j)).0.as_ptr()));
                    store_texel(dst.add(*index.add(j) as usize * 3), q);
                }
            }
        }
    }

    /// [`UvTexels::fill_avx`] four texels per sixteen-float AVX-512 operation (the
    /// triangle's positions in each 128-bit part), each texel's three floats stored by
    /// one masked store (where [`store_texel`] takes two stores and a shuffle); a
    /// group's last one to three texels in four floats. The same products and sums
    /// lane by lane, so the same bits (tested).
    ///
    /// # Safety
    /// The CPU must have AVX-512 F and VL.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512vl")]
    unsafe fn fill_avx512(&self, padded: &[[f32; 4]], out: &mut [[f32; 3]]) {
        use std::arch::x86_64::*;
        self.check_fill(padded, out);
        let (pos, dst) = (padded.as_ptr(), out.as_mut_ptr().cast::<f32>());
        let (index, weights) = (self.index.as_ptr(), self.weights.as_ptr());
        let mut start = 0;
        for (v, &end) in self.triangles.iter().zip(&self.ends) {
            let (mut j, end) = (start, end as usize);
            start = end;
            // SAFETY: the reads and writes are in bounds (`check_fill`; `j..j + 4`
            // stay below the group's end, at most `index.len() == weights.len()`);
            // the CPU has AVX-512 F and VL (the caller's promise).
            unsafe {
                let p = v.map(|v| _mm512_broadcast_f32x4(_mm_loadu_ps(pos.add(v as usize).cast())));
                while j + 4 <= end {
                    let w = _mm512_loadu_ps(weights.add(j).cast());
                    let lane = |k: usize, w: __m512| _mm512_mul_ps(p[k], w);
                    let q = _mm512_add_ps(
                        _mm512_add_ps(
                            lane(0, _mm512_shuffle_ps::<0x00>(w, w)),
                            lane(1, _mm512_shuffle_ps::<0x55>(w, w)),
                        ),
                        lane(2, _mm512_shuffle_ps::<0xAA>(w, w)),
                    );
                    let at = |k: usize| dst.add(*index.add(j + k) as usize * 3);
                    _mm_mask_storeu_ps(at(0), 0b111, _mm512_castps512_ps128(q));
                    _mm_mask_storeu_ps(at(1), 0b111, _mm512_extractf32x4_ps::<1>(q));
                    _mm_mask_storeu_ps(at(2), 0b111, _mm512_extractf32x4_ps::<2>(q));
                    _mm_mask_storeu_ps(at(3), 0b111, _mm512_extractf32x4_ps::<3>(q));
                    j += 4;
                }
                let p = p.map(|p| _mm512_castps512_ps128(p));
                while j < end {
                    let q = texel_sum(p, _mm_load_ps((*weights.add(j)).0.as_ptr()));
                    _mm_mask_storeu_ps(dst.add(*index.add(j) as usize * 3), 0b111, q);
                    j += 1;
                }
            }
        }
    }

    /// [`UvTexels::position_map`] one coordinate at a time.
    #[cfg_attr(all(target_arch = "x86_64", not(test)), allow(dead_code))]
    pub(crate) fn position_map_scalar(&self, extended: &[Point3<f32>]) -> Vec<[f32; 3]> {
        let mut out = vec![[f32::NAN; 3]; self.size as usize * self.size as usize];
        self.fill_scalar(extended, &mut out);
        out
    }

    /// [`UvTexels::fill_covered`] one coordinate at a time.
    #[cfg_attr(all(target_arch = "x86_64", not(test)), allow(dead_code))]
    pub(crate) fn fill_scalar(&self, extended: &[Point3<f32>], out: &mut [[f32; 3]]) {
        let mut start = 0;
        for (v, &end) in self.triangles.iter().zip(&self.ends) {
            let range = start..end as usize;
            start = end as usize;
            for (&i, b) in self.index[range.clone()].iter().zip(&self.weights[range]) {
                let p = extended[v[0] as usize].coords * b.0[0]
                    + extended[v[1] as usize].coords * b.0[1]
                    + extended[v[2] as usize].coords * b.0[2];
                out[i as usize] = [p.x, p.y, p.z];
            }
        }
    }
}

/// A position map (row-major `[x, y, z]`) into three planes: each coordinate times
/// `scale`, clamped to [-1, 1] (`f32::clamp`: NaN stays NaN), and the whole texel -1
/// where x is NaN (an uncovered texel). Texels from `start` on (the others are left
/// as they are). The definition [`clamp_planes_avx`] is tested against.
pub(crate) fn clamp_planes_from(
    map: &[[f32; 3]],
    start: usize,
    scale: f32,
    planes: [&mut [f32]; 3],
) {
    let [u, v, w] = planes;
    for (i, p) in map.iter().enumerate().skip(start) {
        let value = |c: f32| {
            if p[0].is_nan() {
                -1.0
            } else {
                (c * scale).clamp(-1.0, 1.0)
            }
        };
        (u[i], v[i], w[i]) = (value(p[0]), value(p[1]), value(p[2]));
    }
}

/// [`clamp_planes_from`] eight texels at a time in AVX lanes: the 24 floats split
/// into x, y and z by shuffles within each 128-bit half, the same multiply, `max` and
/// `min` in the order that keeps a NaN (`max_ps` and `min_ps` return their second
/// operand on NaN), and a blend to -1 where x is NaN; the last texels one at a time.
///
/// # Safety
/// The CPU must have AVX.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn clamp_planes_avx(map: &[[f32; 3]], scale: f32, planes: [&mut [f32]; 3]) {
    use std::arch::x86_64::*;
    let n = map.len();
    assert!(planes.iter().all(|p| p.len() == n));
    let [u, v, w] = planes;
    let src = map.as_ptr().cast::<f32>();
    let (k, lo, hi) = (
        _mm256_set1_ps(scale),
        _mm256_set1_ps(-1.0),
        _mm256_set1_ps(1.0),
    );
    let mut i = 0;
    while i + 8 <= n {
        // SAFETY: texels i..i + 8 are within `map` and each plane (checked above); the
        // CPU has AVX (the caller's promise).
        unsafe {
            let p = src.add(3 * i);
            let half = |a: usize, b: usize| {
                let low = _mm256_castps128_ps256(_mm_loadu_ps(p.add(a)));
                _mm256_insertf128_ps::<1>(low, _mm_loadu_ps(p.add(b)))
            };
            // Per half: [x0 y0 z0 x1], [y1 z1 x2 y2], [z2 x3 y3 z3].
            let (a, b, c) = (half(0, 12), half(4, 16), half(8, 20));
            let xy = _mm256_shuffle_ps::<0b10_01_11_10>(b, c); // x2 y2 x3 y3
            let yz = _mm256_shuffle_ps::<0b01_00_10_01>(a, b); // y0 z0 y1 z1
            let x = _mm256_shuffle_ps::<0b10_00_11_00>(a, xy);
            let y = _mm256_shuffle_ps::<0b11_01_10_00>(yz, xy);
            let z = _mm256_shuffle_ps::<0b11_00_11_01>(yz, c);
            let nan_x = _mm256_cmp_ps::<_CMP_UNORD_Q>(x, x);
            let value = |c: __m256| {
                let r = _mm256_min_ps(hi, _mm256_max_ps(lo, _mm256_mul_ps(c, k)));
                _mm256_blendv_ps(r, lo, nan_x)
            };
            _mm256_storeu_ps(u.as_mut_ptr().add(i), value(x));
            _mm256_storeu_ps(v.as_mut_ptr().add(i), value(y));
            _mm256_storeu_ps(w.as_mut_ptr().add(i), value(z));
        }
        i += 8;
    }
    clamp_planes_from(map, i, scale, [u, v, w]);
}

/// [`clamp_planes_avx`] sixteen texels at a time in AVX-512 lanes (`map.len()` a
/// multiple of 16): the 48 floats split into x, y and z by two two-register permutes
/// each, the same multiply, `max`, `min` (NaN kept) and -1 where x is NaN, and each
/// plane written with streaming stores (whole 64-byte lines, not read first). The
/// same bits (tested against [`clamp_planes_from`] at every plane alignment).
///
/// # Safety
/// The CPU must have AVX-512 F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn clamp_planes_avx512(map: &[[f32; 3]], scale: f32, planes: [&mut [f32]; 3]) {
    use std::arch::x86_64::*;
    assert!(map.len().is_multiple_of(16) && planes.iter().all(|p| p.len() == map.len()));
    let (k, lo, hi) = (
        _mm512_set1_ps(scale),
        _mm512_set1_ps(-1.0),
        _mm512_set1_ps(1.0),
    );
    // Coordinate `c` of texel `t` is float `3 t + c` of the 48: in the first two
    // registers (32 floats) for `3 t + c < 32`, else in the third.
    let first: [__m512i; 3] = std::array::from_fn(|c| {
        let i: [i32; 16] = std::array::from_fn(|t| ((3 * t + c) % 32) as i32);
        // SAFETY: an unaligned load of sixteen i32.
        unsafe { _mm512_loadu_si512(i.as_ptr().cast()) }
    });
    let third: [__m512i; 3] = std::array::from_fn(|c| {
        let i: [i32; 16] = std::array::from_fn(|t| {
            let f = 3 * t + c;
            // Lanes 0-15 keep the first permute's value; 16-31 take the third register's.
            if f < 32 {
                t as i32
            } else {
                (16 + f - 32) as i32
            }
        });
        // SAFETY: an unaligned load of sixteen i32.
        unsafe { _mm512_loadu_si512(i.as_ptr().cast()) }
    });
    let [u, v, w] = planes;
    let mut out = [u, v, w].map(|p| crate::lanes::streamed_plane::StreamedPlane::new(p));
    let src = map.as_ptr().cast::<f32>();
    for g in 0..map.len() / 16 {
        // SAFETY: floats `48 g .. 48 g + 48` of the map's `3 * len`.
        let [a, b, c] = [0, 1, 2].map(|r| unsafe { _mm512_loadu_ps(src.add(48 * g + 16 * r)) });
        let coord = |i: usize| {
            let ab = _mm512_permutex2var_ps(a, first[i], b);
            _mm512_permutex2var_ps(ab, third[i], c)
        };
        let (x, y, z) = (coord(0), coord(1), coord(2));
        let nan_x = _mm512_cmp_ps_mask::<_CMP_UNORD_Q>(x, x);
        let value = |c: __m512| {
            let r = _mm512_min_ps(hi, _mm512_max_ps(lo, _mm512_mul_ps(c, k)));
            _mm512_castps_si512(_mm512_mask_blend_ps(nan_x, r, lo))
        };
        for (plane, c) in out.iter_mut().zip([x, y, z]) {
            plane.push(value(c));
        }
    }
    for plane in out {
        plane.finish();
    }
}

/// Positions padded to four floats, for one four-float load each.
#[cfg(target_arch = "x86_64")]
fn padded_positions(extended: &[Point3<f32>]) -> Vec<[f32; 4]> {
    extended.iter().map(|p| [p.x, p.y, p.z, 0.0]).collect()
}

/// One texel's position from its triangle's three positions and its weights (lanes
/// 0-2 of `w`): `(p0 * w0 + p1 * w1) + p2 * w2` in four lanes, the fourth junk.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn texel_sum(
    p: [std::arch::x86_64::__m128; 3],
    w: std::arch::x86_64::__m128,
) -> std::arch::x86_64::__m128 {
    use std::arch::x86_64::*;
    // SAFETY: SSE2 is part of the x86-64 baseline; no memory is touched.
    unsafe {
        let t0 = _mm_mul_ps(p[0], _mm_shuffle_ps::<0x00>(w, w));
        let t1 = _mm_mul_ps(p[1], _mm_shuffle_ps::<0x55>(w, w));
        let t2 = _mm_mul_ps(p[2], _mm_shuffle_ps::<0xAA>(w, w));
        _mm_add_ps(_mm_add_ps(t0, t1), t2)
    }
}

/// Stores lanes 0-2 of `q` at `d`.
///
/// # Safety
/// `d` must be valid for writing three floats.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn store_texel(d: *mut f32, q: std::arch::x86_64::__m128) {
    use std::arch::x86_64::*;
    // SAFETY: the caller's promise; SSE2 is part of the x86-64 baseline.
    unsafe {
        _mm_storel_epi64(d.cast(), _mm_castps_si128(q));
        _mm_store_ss(d.add(2), _mm_movehl_ps(q, q));
    }
}
