//! The rasterizers' lanes: the coverage of a triangle's rows and small boxes in SSE2
//! (the x86-64 baseline; [`ScalarRowCoverage`] elsewhere), the depth-tested visibility
//! of small triangles in AVX-512 ([`visibility`]), and the official rules' per-pixel
//! test eight or sixteen pixels at a time ([`OfficialTriangles`]), each beside its
//! scalar definition and chosen by [`crate::lanes::level`]. Every kernel gives its
//! definition's bits; the tests in `raster/mod.rs` compare them at every level the CPU has
//! (random meshes, boxes of every width up to the lanes' and past them).

use super::{
    Culling, OfficialSpan, OfficialTriangle, ScreenVertex, TriangleSetup, VisibilityBuffer,
    for_each_drawable, step,
};
use crate::lanes::Level;

/// The coverage of a box's rows as bit masks, row after row, for boxes up to 64 pixels
/// wide: bit `i` of a row's mask is set when pixel `i` of the row is inside, that is
/// when no biased edge value is negative, so when the sign bit of their OR is clear.
/// On x86-64 two pixels at a time in SSE2 lanes (part of the x86-64 baseline; the sign
/// bits come out with one `movmskpd`), elsewhere one at a time
/// ([`ScalarRowCoverage`]); the two agree (tested).
#[cfg(target_arch = "x86_64")]
pub(crate) struct RowCoverage {
    /// Biased edge values at pixels `(0, 1)` of the current row, per edge.
    lanes: [std::arch::x86_64::__m128i; 3],
    /// Two pixels' step along a row, per edge.
    step: [std::arch::x86_64::__m128i; 3],
    /// One row's step, per edge.
    down: [std::arch::x86_64::__m128i; 3],
    width: u32,
}

#[cfg(target_arch = "x86_64")]
impl RowCoverage {
    /// For edge values `e` at the box's first pixel, steps `dx` along a row and `dy`
    /// down, top-left `bias`, and a box `width` (1 to 64) pixels wide.
    #[inline(always)]
    pub(crate) fn new(e: [i64; 3], dx: [i64; 3], dy: [i64; 3], bias: [i64; 3], width: u32) -> Self {
        use std::arch::x86_64::*;
        // SAFETY (this and the methods below): SSE2 is part of the x86-64 baseline, so
        // every x86-64 CPU has it; the intrinsics take no pointers.
        unsafe {
            RowCoverage {
                lanes: [0, 1, 2].map(|k| _mm_set_epi64x(e[k] + bias[k] + dx[k], e[k] + bias[k])),
                step: dx.map(|d| _mm_set1_epi64x(2 * d)),
                down: dy.map(|d| _mm_set1_epi64x(d)),
                width,
            }
        }
    }

    /// The current row's mask; moves to the next row.
    ///
    /// A box up to four or up to eight pixels wide (most of a face crop's) takes two or
    /// four pairs of pixels in straight-line code, the pixels past the box masked off,
    /// so that the pair loop's exit is not mispredicted once per triangle; wider boxes
    /// loop over pairs. Every width gives the same mask (tested through the walks'
    /// equality).
    #[inline(always)]
    pub(crate) fn next_row(&mut self) -> u64 {
        let outside = match self.width {
            0..=4 => self.pairs::<2>(),
            5..=8 => self.pairs::<4>(),
            _ => {
                let (mut lanes, mut outside, mut i) = (self.lanes, 0, 0);
                while i < self.width {
                    outside |= Self::any_outside(&lanes) << i;
                    Self::step_lanes(&mut lanes, &self.step);
                    i += 2;
                }
                outside
            }
        };
        let down = self.down;
        Self::step_lanes(&mut self.lanes, &down);
        !outside & (u64::MAX >> (64 - self.width))
    }

    /// The outside bits of the current row's first `2 * N` pixels, unrolled.
    #[inline(always)]
    fn pairs<const N: usize>(&self) -> u64 {
        let (mut lanes, mut outside) = (self.lanes, 0);
        for j in 0..N {
            outside |= Self::any_outside(&lanes) << (2 * j);
            Self::step_lanes(&mut lanes, &self.step);
        }
        outside
    }

    /// Bit `k` set when pixel `k` of the two in `lanes` has a negative biased edge value.
    #[inline(always)]
    fn any_outside(lanes: &[std::arch::x86_64::__m128i; 3]) -> u64 {
        use std::arch::x86_64::*;
        // SAFETY: see `new`.
        unsafe {
            let any = _mm_or_si128(_mm_or_si128(lanes[0], lanes[1]), lanes[2]);
            _mm_movemask_pd(_mm_castsi128_pd(any)) as u64
        }
    }

    /// Adds `by` to each edge's lanes.
    #[inline(always)]
    fn step_lanes(
        lanes: &mut [std::arch::x86_64::__m128i; 3],
        by: &[std::arch::x86_64::__m128i; 3],
    ) {
        for (lane, by) in lanes.iter_mut().zip(by) {
            // SAFETY: see `new`.
            *lane = unsafe { std::arch::x86_64::_mm_add_epi64(*lane, *by) };
        }
    }
}

/// The coverage of a small triangle's whole box at once (in [`TriangleSetup::walk`]):
/// the box widened to `Q` groups of four pixels by `R` rows, each group's three edge
/// values as `i32` in SSE2 lanes (exact for a triangle marked `small`), and one bit per
/// pixel, row-major, set when the pixel is inside both the box and the triangle. The
/// walk then visits the set bits in one loop. Three quarters of a 192x192 face crop's
/// triangles have boxes up to 4x4 or 4x8 pixels and 96% up to 8x8; walking them row by
/// row and run by run ([`TriangleSetup::walk_rows`]) cost a mispredicted branch at the
/// end of most runs and rows, about five per triangle.
#[cfg(target_arch = "x86_64")]
pub(crate) struct BoxCoverage {
    /// Per edge, the unbiased edge values of up to 16 groups of four pixels; only the
    /// groups `fill` wrote are initialised.
    lanes: std::mem::MaybeUninit<[[[i32; 4]; 16]; 3]>,
}

#[cfg(target_arch = "x86_64")]
impl BoxCoverage {
    /// Lanes to be filled.
    #[inline(always)]
    pub(crate) fn new() -> Self {
        BoxCoverage {
            lanes: std::mem::MaybeUninit::uninit(),
        }
    }

    /// Fills the lanes for the box of `t`, which is `small` and at most `4 * Q` pixels
    /// wide and `R` tall (`Q * R <= 16`); returns the covered pixels' bits (bit
    /// `row << shift | col`) and `shift`.
    #[inline(always)]
    pub(crate) fn fill<const Q: usize, const R: usize>(&mut self, t: &TriangleSetup) -> (u64, u32) {
        use std::arch::x86_64::*;
        debug_assert!(Q * R <= 16 && (Q == 1 || Q == 2) && t.small);
        debug_assert!(((t.x1 - t.x0) as usize) < 4 * Q && ((t.y1 - t.y0) as usize) < R);
        let lanes = self.lanes.as_mut_ptr().cast::<[i32; 4]>();
        let mut outside = 0u64;
        // SAFETY: SSE2 is part of the x86-64 baseline; group `g = r * Q + q` is below
        // 16, so each store writes one `[i32; 4]` of edge `k`'s 16 within `lanes`.
        unsafe {
            let quad = |k: usize, q: usize| {
                let (e, d) = (t.e0[k] as i32, t.dx[k] as i32);
                let x = 4 * q as i32;
                _mm_setr_epi32(e + x * d, e + (x + 1) * d, e + (x + 2) * d, e + (x + 3) * d)
            };
            let down = t.dy.map(|d| _mm_set1_epi32(d as i32));
            let bias = t.bias.map(|b| _mm_set1_epi32(b as i32));
            for q in 0..Q {
                let mut e = [quad(0, q), quad(1, q), quad(2, q)];
                for r in 0..R {
                    let g = r * Q + q;
                    let mut any = _mm_setzero_si128();
                    for k in 0..3 {
                        _mm_storeu_si128(lanes.add(16 * k + g).cast(), e[k]);
                        any = _mm_or_si128(any, _mm_add_epi32(e[k], bias[k]));
                        e[k] = _mm_add_epi32(e[k], down[k]);
                    }
                    outside |= (_mm_movemask_ps(_mm_castsi128_ps(any)) as u64) << (4 * g);
                }
            }
        }
        // Pixels of the widened box outside the real one.
        let (w, h) = ((t.x1 - t.x0 + 1) as usize, (t.y1 - t.y0 + 1) as usize);
        // The row's mask repeated every `4 * Q` bits, `R` times: a product with the
        // pattern of ones (no carries, the row's mask being narrower than `4 * Q`),
        // one multiply instead of a shift and an OR per row.
        let row = (1u64 << w) - 1;
        let repeat = (0..R).fold(0u64, |m, r| m | (1 << (4 * Q * r)));
        let real = (row * repeat) & (u64::MAX >> (64 - 4 * Q * h));
        (!outside & real, Q.trailing_zeros() + 2)
    }

    /// The three edge values of the pixel of bit `b`.
    ///
    /// # Safety
    /// `b` is a bit `fill` returned set, so its group was written.
    #[inline(always)]
    pub(crate) unsafe fn edges(&self, b: usize) -> [i64; 3] {
        let lanes = self.lanes.as_ptr().cast::<i32>();
        // SAFETY: the caller's bit lies in a group `fill` wrote (group `b / 4` of each
        // edge's 16, at `i32` offset `64 * k + b`).
        unsafe {
            [
                *lanes.add(b) as i64,
                *lanes.add(64 + b) as i64,
                *lanes.add(128 + b) as i64,
            ]
        }
    }
}

/// [`RowCoverage`] one pixel at a time (the walk's own on targets other than x86-64).
#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
pub(crate) struct ScalarRowCoverage {
    row: [i64; 3],
    dx: [i64; 3],
    dy: [i64; 3],
    width: u32,
}

#[cfg_attr(target_arch = "x86_64", allow(dead_code))]
impl ScalarRowCoverage {
    pub(crate) fn new(e: [i64; 3], dx: [i64; 3], dy: [i64; 3], bias: [i64; 3], width: u32) -> Self {
        ScalarRowCoverage {
            row: [0, 1, 2].map(|k| e[k] + bias[k]),
            dx,
            dy,
            width,
        }
    }

    pub(crate) fn next_row(&mut self) -> u64 {
        let (mut e, mut bits) = (self.row, 0u64);
        for i in 0..self.width {
            let any = e[0] | e[1] | e[2];
            bits |= (((any >> 63) + 1) as u64) << i;
            step(&mut e, self.dx);
        }
        step(&mut self.row, self.dy);
        bits
    }
}

#[cfg(not(target_arch = "x86_64"))]
pub(crate) use ScalarRowCoverage as RowCoverage;

/// [`super::VisibilityBuffer::rasterize_visibility`]'s triangle loop at `level`
/// (lowered to the CPU's): in AVX-512, small triangles' boxes a row or two at a time
/// ([`visibility_avx512`]); otherwise, the definition, [`visibility_scalar`]. `depth`
/// and `triangle` are the buffer's, `size.0 * size.1` long. Returns whether the AVX-512
/// loop ran. Both leave the same buffer (tested).
pub(crate) fn visibility(
    level: Level,
    vertices: &[ScreenVertex],
    triangles: &[[u32; 3]],
    size: (u32, u32),
    culling: Culling,
    depth: &mut [f32],
    triangle: &mut [u32],
) -> bool {
    #[cfg(target_arch = "x86_64")]
    if level.supported() == Level::Avx512 {
        // SAFETY: `Level::Avx512` is supported: the CPU has AVX-512 F, VL and DQ.
        unsafe { visibility_avx512(vertices, triangles, size, culling, depth, triangle) };
        return true;
    }
    let _ = level;
    visibility_scalar(vertices, triangles, size, culling, depth, triangle);
    false
}

/// [`visibility`]'s definition: every triangle's pixels one at a time
/// ([`TriangleSetup::for_each_nearer_key`]).
pub(crate) fn visibility_scalar(
    vertices: &[ScreenVertex],
    triangles: &[[u32; 3]],
    (width, height): (u32, u32),
    culling: Culling,
    depth: &mut [f32],
    triangle: &mut [u32],
) {
    let row = width as usize;
    for_each_drawable(vertices, triangles, width, height, culling, |ti, setup| {
        setup.for_each_nearer_key(depth, row, |idx| triangle[idx] = ti);
    });
}

/// The official rules' per-triangle kernel, chosen once for a mesh: its level (lowered
/// to the CPU's) and whether the weights are written. Only [`OfficialTriangles::new`]
/// makes one, so a kernel is never run on a CPU without its instructions.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct OfficialTriangles(OfficialKernel);

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum OfficialKernel {
    /// [`official_triangle_scalar`]: the definition.
    Scalar { weights: bool },
    /// [`official_triangle_avx2`]: eight pixels of a row.
    #[cfg(target_arch = "x86_64")]
    Avx2 { weights: bool },
    /// [`official_visibility_avx512`]: eight pixels of two rows, no weights.
    #[cfg(target_arch = "x86_64")]
    Avx512,
}

impl OfficialTriangles {
    /// The kernel for `level` (lowered to the CPU's), writing the weights or not: with
    /// them AVX-512 takes AVX2's eight lanes.
    pub(crate) fn new(level: Level, weights: bool) -> Self {
        #[cfg(target_arch = "x86_64")]
        let kernel = match (level.supported(), weights) {
            (Level::Avx512, false) => OfficialKernel::Avx512,
            (Level::Avx512 | Level::Avx2, _) => OfficialKernel::Avx2 { weights },
            (Level::Scalar, _) => OfficialKernel::Scalar { weights },
        };
        #[cfg(not(target_arch = "x86_64"))]
        let kernel = {
            let _ = level;
            OfficialKernel::Scalar { weights }
        };
        OfficialTriangles(kernel)
    }

    /// Tests and depth-writes the pixels of `area` for triangle `t`.
    #[inline]
    pub(crate) fn draw(
        self,
        buffer: &mut VisibilityBuffer,
        t: &OfficialTriangle,
        area: OfficialSpan,
    ) {
        match self.0 {
            OfficialKernel::Scalar { weights } => {
                official_triangle_scalar(buffer, t, area, weights)
            }
            // SAFETY (both): `new` chose these only for a supported level, AVX2 or
            // AVX-512 (F, VL, DQ).
            #[cfg(target_arch = "x86_64")]
            OfficialKernel::Avx2 { weights: true } => unsafe {
                official_triangle_avx2::<true>(buffer, t, area)
            },
            #[cfg(target_arch = "x86_64")]
            OfficialKernel::Avx2 { weights: false } => unsafe {
                official_triangle_avx2::<false>(buffer, t, area)
            },
            #[cfg(target_arch = "x86_64")]
            OfficialKernel::Avx512 => unsafe { official_visibility_avx512(buffer, t, area) },
        }
    }
}

/// [`VisibilityBuffer::rasterize_visibility`]'s triangle loop in AVX-512: a `small`
/// triangle takes its box's rows whole, two at a time in eight lanes up to four pixels
/// wide ([`nearer_row_pairs_avx512`]: three quarters of a 192x192 face crop's
/// triangles), two at a time in sixteen lanes up to eight, one at a time up to sixteen
/// ([`nearer_rows16_avx512`]); any other triangle takes the pixel walk. `depth` and
/// `triangle` are the buffer's, `size.0 * size.1` long. (Eight lanes of one row for
/// boxes up to eight wide ran at 0.459-0.465 ms an evaluation item; two rows for
/// boxes up to four, 0.444-0.446; sixteen lanes for the wider ones, 0.427-0.433.)
///
/// # Safety
/// The CPU has AVX-512 F, VL and DQ.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq")]
unsafe fn visibility_avx512(
    vertices: &[ScreenVertex],
    triangles: &[[u32; 3]],
    (width, height): (u32, u32),
    culling: Culling,
    depth: &mut [f32],
    triangle: &mut [u32],
) {
    let row = width as usize;
    for_each_drawable(vertices, triangles, width, height, culling, |ti, setup| {
        // SAFETY (each call): this function's caller promised the features.
        match (setup.small, setup.x1 - setup.x0) {
            (true, 0..4) => unsafe { nearer_row_pairs_avx512(&setup, depth, triangle, row, ti) },
            (true, 4..8) => unsafe { nearer_rows16_avx512::<2>(&setup, depth, triangle, row, ti) },
            (true, 8..16) => unsafe { nearer_rows16_avx512::<1>(&setup, depth, triangle, row, ti) },
            _ => setup.for_each_nearer_key(depth, row, |idx| triangle[idx] = ti),
        }
    });
}

/// [`TriangleSetup::for_each_nearer_key`] storing `id` into `triangle` where a pixel
/// passes, for a `small` triangle whose box is at most four pixels wide: two rows of
/// the box at a time in eight lanes (four columns of each). The row pair's edge values
/// as `i32` (exact, as in [`BoxCoverage`]: the box widened to eight pixels, or by a
/// row, stays within its bound), the coverage from their biased signs, the depth keys
/// in `f64` lanes with the scalar key's operations in its order (so the same bits),
/// and the test and both stores masked to the covered pixels. A triangle covers each
/// pixel once, so taking its pixels in another order leaves the same buffer (tested
/// against the pixel walk). Row pairs without a covered pixel are skipped; no branch
/// depends on a single pixel. Wider boxes: [`nearer_rows16_avx512`].
///
/// # Safety
/// The CPU has AVX-512 F, VL and DQ.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq")]
#[inline]
unsafe fn nearer_row_pairs_avx512(
    t: &TriangleSetup,
    depth: &mut [f32],
    triangle: &mut [u32],
    width: usize,
    id: u32,
) {
    use std::arch::x86_64::*;
    debug_assert!(t.small && t.x1 - t.x0 < 4);
    let (x0, y0, y1) = (t.x0 as usize, t.y0 as usize, t.y1 as usize);
    // The box is inside the viewport (the setup clipped it), so its last pixel is in
    // both buffers: checked once, as the pixel walk's indexing checks each pixel.
    let last = y1 * width + t.x1 as usize;
    assert!(
        (t.x1 as usize) < width && last < depth.len() && last < triangle.len(),
        "a triangle's box outside the buffer"
    );
    // Lane `l`: column `l % 4` of row `l / 4` of the pair.
    let columns = _mm256_setr_epi32(0, 1, 2, 3, 0, 1, 2, 3);
    let rows = _mm256_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1);
    // Each edge's values in a plain loop (through `map`, its closure was a call of its
    // own, outside the AVX-512 code).
    let mut e = [_mm256_setzero_si256(); 3];
    let (mut down, mut bias, mut w) = (e, e, [_mm512_setzero_pd(); 3]);
    // As in `walk_nearer`: each vertex's `1 / w` over twice the area, in f64.
    let inv_area = 1.0 / t.area2 as f64;
    for k in 0..3 {
        let along = _mm256_mullo_epi32(columns, _mm256_set1_epi32(t.dx[k] as i32));
        let below = _mm256_mullo_epi32(rows, _mm256_set1_epi32(t.dy[k] as i32));
        e[k] = _mm256_add_epi32(
            _mm256_set1_epi32(t.e0[k] as i32),
            _mm256_add_epi32(along, below),
        );
        down[k] = _mm256_set1_epi32(2 * t.dy[k] as i32);
        bias[k] = _mm256_set1_epi32(t.bias[k] as i32);
        w[k] = _mm512_set1_pd(t.inv_w[k] as f64 * inv_area);
    }
    let row_box = ((1u32 << (t.x1 - t.x0 + 1)) - 1) as __mmask8;
    let id = _mm_set1_epi32(id as i32);
    let zero = _mm256_setzero_si256();
    let mut y = y0;
    while y <= y1 {
        // The pair's second row is in the box unless `y` is the last.
        let in_box = if y < y1 {
            row_box | row_box << 4
        } else {
            row_box
        };
        let any = _mm256_or_si256(
            _mm256_or_si256(
                _mm256_add_epi32(e[0], bias[0]),
                _mm256_add_epi32(e[1], bias[1]),
            ),
            _mm256_add_epi32(e[2], bias[2]),
        );
        let inside = _mm256_mask_cmpge_epi32_mask(in_box, any, zero);
        if inside != 0 {
            // Written out: as a closure, this was a call of its own.
            let term0 = _mm512_mul_pd(_mm512_cvtepi32_pd(e[0]), w[0]);
            let term1 = _mm512_mul_pd(_mm512_cvtepi32_pd(e[1]), w[1]);
            let term2 = _mm512_mul_pd(_mm512_cvtepi32_pd(e[2]), w[2]);
            let key = _mm512_cvtpd_ps(_mm512_add_pd(_mm512_add_pd(term0, term1), term2));
            let at = y * width + x0;
            // Row `y + 1`'s pixels (row `y`'s when there is none: no lane of it is
            // live, and the pointer stays inside the buffers).
            let below = if y < y1 { at + width } else { at };
            // SAFETY: the masked loads and stores touch only covered pixels, columns
            // `x0..=x1` of rows `y` and (when it is in the box) `y + 1`, inside both
            // buffers (checked above); masked-off lanes are never accessed.
            unsafe {
                let depth = depth.as_mut_ptr();
                let triangle = triangle.as_mut_ptr().cast::<i32>();
                let (lo, hi) = (inside & 0xf, inside >> 4);
                let old = _mm256_set_m128(
                    _mm_maskz_loadu_ps(hi, depth.add(below)),
                    _mm_maskz_loadu_ps(lo, depth.add(at)),
                );
                let nearer = _mm256_mask_cmp_ps_mask::<_CMP_GT_OQ>(inside, key, old);
                let (lo, hi) = (nearer & 0xf, nearer >> 4);
                _mm_mask_storeu_ps(depth.add(at), lo, _mm256_castps256_ps128(key));
                _mm_mask_storeu_ps(depth.add(below), hi, _mm256_extractf128_ps::<1>(key));
                _mm_mask_storeu_epi32(triangle.add(at), lo, id);
                _mm_mask_storeu_epi32(triangle.add(below), hi, id);
            }
        }
        for k in 0..3 {
            e[k] = _mm256_add_epi32(e[k], down[k]);
        }
        y += 2;
    }
}

/// [`nearer_row_pairs_avx512`] in sixteen lanes: `ROWS` rows (1 or 2) of a `small`
/// triangle's box up to `16 / ROWS` pixels wide at a time, the depth keys in two
/// eight-lane `f64` halves. The `i32` edge values stay exact: a box widened to sixteen
/// pixels (or by a row) keeps each product below `(64 + 16) * 256 * 64 * 256`, the
/// sum below `2^30`.
///
/// # Safety
/// The CPU has AVX-512 F, VL and DQ.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq")]
#[inline]
unsafe fn nearer_rows16_avx512<const ROWS: usize>(
    t: &TriangleSetup,
    depth: &mut [f32],
    triangle: &mut [u32],
    width: usize,
    id: u32,
) {
    use std::arch::x86_64::*;
    let cols = 16 / ROWS;
    debug_assert!(t.small && ((t.x1 - t.x0) as usize) < cols && (ROWS == 1 || ROWS == 2));
    let (x0, y0, y1) = (t.x0 as usize, t.y0 as usize, t.y1 as usize);
    // As in `nearer_row_pairs_avx512`.
    let last = y1 * width + t.x1 as usize;
    assert!(
        (t.x1 as usize) < width && last < depth.len() && last < triangle.len(),
        "a triangle's box outside the buffer"
    );
    let lane: [i32; 16] = std::array::from_fn(|l| l as i32);
    // SAFETY: an unaligned load of sixteen i32.
    let lane = unsafe { _mm512_loadu_si512(lane.as_ptr().cast()) };
    let (columns, rows) = if ROWS == 2 {
        (
            _mm512_and_si512(lane, _mm512_set1_epi32(7)),
            _mm512_srli_epi32::<3>(lane),
        )
    } else {
        (lane, _mm512_setzero_si512())
    };
    // As in `nearer_row_pairs_avx512`, in a plain loop.
    let mut e = [_mm512_setzero_si512(); 3];
    let (mut down, mut bias, mut w) = (e, e, [_mm512_setzero_pd(); 3]);
    let inv_area = 1.0 / t.area2 as f64;
    for k in 0..3 {
        let along = _mm512_mullo_epi32(columns, _mm512_set1_epi32(t.dx[k] as i32));
        let below = _mm512_mullo_epi32(rows, _mm512_set1_epi32(t.dy[k] as i32));
        e[k] = _mm512_add_epi32(
            _mm512_set1_epi32(t.e0[k] as i32),
            _mm512_add_epi32(along, below),
        );
        down[k] = _mm512_set1_epi32(ROWS as i32 * t.dy[k] as i32);
        bias[k] = _mm512_set1_epi32(t.bias[k] as i32);
        w[k] = _mm512_set1_pd(t.inv_w[k] as f64 * inv_area);
    }
    let row_box = ((1u32 << (t.x1 - t.x0 + 1)) - 1) as __mmask16;
    let id = _mm512_set1_epi32(id as i32);
    let zero = _mm512_setzero_si512();
    let mut y = y0;
    while y <= y1 {
        let in_box = if ROWS == 2 && y < y1 {
            row_box | row_box << 8
        } else {
            row_box
        };
        let any = _mm512_or_si512(
            _mm512_or_si512(
                _mm512_add_epi32(e[0], bias[0]),
                _mm512_add_epi32(e[1], bias[1]),
            ),
            _mm512_add_epi32(e[2], bias[2]),
        );
        let inside = _mm512_mask_cmpge_epi32_mask(in_box, any, zero);
        if inside != 0 {
            // Lanes 0-7, then 8-15, each in the scalar key's order (written out: no
            // closure, see above).
            let (lo, hi) = (
                [
                    _mm512_castsi512_si256(e[0]),
                    _mm512_castsi512_si256(e[1]),
                    _mm512_castsi512_si256(e[2]),
                ],
                [
                    _mm512_extracti64x4_epi64::<1>(e[0]),
                    _mm512_extracti64x4_epi64::<1>(e[1]),
                    _mm512_extracti64x4_epi64::<1>(e[2]),
                ],
            );
            let mut halves = [_mm256_setzero_ps(); 2];
            for (half, lanes) in halves.iter_mut().zip([lo, hi]) {
                let term0 = _mm512_mul_pd(_mm512_cvtepi32_pd(lanes[0]), w[0]);
                let term1 = _mm512_mul_pd(_mm512_cvtepi32_pd(lanes[1]), w[1]);
                let term2 = _mm512_mul_pd(_mm512_cvtepi32_pd(lanes[2]), w[2]);
                *half = _mm512_cvtpd_ps(_mm512_add_pd(_mm512_add_pd(term0, term1), term2));
            }
            let key = _mm512_insertf32x8::<1>(_mm512_castps256_ps512(halves[0]), halves[1]);
            let at = y * width + x0;
            // SAFETY: as in `nearer_row_pairs_avx512`: only covered pixels of rows `y` and
            // (with two rows, in the box) `y + 1` are touched, inside both buffers.
            unsafe {
                let depth = depth.as_mut_ptr();
                let triangle = triangle.as_mut_ptr().cast::<i32>();
                if ROWS == 2 {
                    let below = if y < y1 { at + width } else { at };
                    let (lo, hi) = (inside as __mmask8, (inside >> 8) as __mmask8);
                    let old = _mm512_insertf32x8::<1>(
                        _mm512_castps256_ps512(_mm256_maskz_loadu_ps(lo, depth.add(at))),
                        _mm256_maskz_loadu_ps(hi, depth.add(below)),
                    );
                    let nearer = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(inside, key, old);
                    let (lo, hi) = (nearer as __mmask8, (nearer >> 8) as __mmask8);
                    _mm256_mask_storeu_ps(depth.add(at), lo, _mm512_castps512_ps256(key));
                    _mm256_mask_storeu_ps(depth.add(below), hi, _mm512_extractf32x8_ps::<1>(key));
                    let id8 = _mm512_castsi512_si256(id);
                    _mm256_mask_storeu_epi32(triangle.add(at), lo, id8);
                    _mm256_mask_storeu_epi32(triangle.add(below), hi, id8);
                } else {
                    let old = _mm512_maskz_loadu_ps(inside, depth.add(at));
                    let nearer = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(inside, key, old);
                    _mm512_mask_storeu_ps(depth.add(at), nearer, key);
                    _mm512_mask_storeu_epi32(triangle.add(at), nearer, id);
                }
            }
        }
        for k in 0..3 {
            e[k] = _mm512_add_epi32(e[k], down[k]);
        }
        y += ROWS;
    }
}

/// The official per-pixel test and depth write of one triangle, one pixel at a time:
/// the definition (`official_triangle_avx2` computes the same float32 operations, in
/// the same order, eight pixels at a time, and is tested equal to it).
pub(crate) fn official_triangle_scalar(
    buffer: &mut VisibilityBuffer,
    t: &OfficialTriangle,
    area: OfficialSpan,
    weights: bool,
) {
    let (ox, oy) = area.origin;
    for y in area.ys.clone() {
        for x in area.xs.clone() {
            let (u, v) = t.uv_at(x, y);
            if !(u >= 0.0 && v >= 0.0 && u + v < 1.0) {
                continue;
            }
            let wts = [1.0 - u - v, v, u];
            let z = wts[0] * t.depth[0] + wts[1] * t.depth[1] + wts[2] * t.depth[2];
            let idx = ((y - oy) * area.width + (x - ox)) as usize;
            if z > buffer.inv_w[idx] {
                buffer.inv_w[idx] = z;
                buffer.triangle[idx] = t.index;
                if weights {
                    buffer.bary[idx] = wts;
                }
            }
        }
    }
}

/// [`official_triangle_scalar`] eight pixels of a row at a time: the same IEEE float32
/// operations lane by lane (no fused multiply-add, no reordering), so every weight,
/// depth and comparison has the scalar path's bits; pixels past the box's right edge
/// are masked off (their depths are never read or written). The weights are written
/// when `WEIGHTS`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn official_triangle_avx2<const WEIGHTS: bool>(
    buffer: &mut VisibilityBuffer,
    t: &OfficialTriangle,
    area: OfficialSpan,
) {
    use std::arch::x86_64::*;
    let ((p0x, p0y), (v0x, v0y), (v1x, v1y)) = (t.p0, t.v0, t.v1);
    let (dot00, dot01, dot11) = t.dots;
    let (ox, oy) = area.origin;
    let set = _mm256_set1_ps;
    let (v0x8, v0y8, v1x8, v1y8) = (set(v0x), set(v0y), set(v1x), set(v1y));
    let (d00, d01, d11, inv) = (set(dot00), set(dot01), set(dot11), set(t.inv_deno));
    let (z0, z1, z2) = (set(t.depth[0]), set(t.depth[1]), set(t.depth[2]));
    let (zero, one) = (_mm256_setzero_ps(), set(1.0));
    let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let id = _mm256_set1_epi32(t.index as i32);
    let len = buffer.inv_w.len();
    for y in area.ys.clone() {
        let v2y = set(y as f32 - p0y);
        let (a, b) = (_mm256_mul_ps(v0y8, v2y), _mm256_mul_ps(v1y8, v2y));
        let row = ((y - oy) * area.width - ox) as isize;
        let mut x = area.xs.start;
        while x < area.xs.end {
            let left = (area.xs.end - x).min(8) as i32;
            let live = _mm256_cmpgt_epi32(_mm256_set1_epi32(left), lanes);
            // x + k as float32: exact (|x| is far below 2^24), as `x as f32` is.
            let xs = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(x as i32), lanes));
            let v2x = _mm256_sub_ps(xs, set(p0x));
            let dot02 = _mm256_add_ps(_mm256_mul_ps(v0x8, v2x), a);
            let dot12 = _mm256_add_ps(_mm256_mul_ps(v1x8, v2x), b);
            let u = _mm256_mul_ps(
                _mm256_sub_ps(_mm256_mul_ps(d11, dot02), _mm256_mul_ps(d01, dot12)),
                inv,
            );
            let v = _mm256_mul_ps(
                _mm256_sub_ps(_mm256_mul_ps(d00, dot12), _mm256_mul_ps(d01, dot02)),
                inv,
            );
            // Ordered comparisons: a NaN weight is outside, as in the scalar test.
            let inside = _mm256_and_ps(
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_GE_OQ>(u, zero),
                    _mm256_cmp_ps::<_CMP_GE_OQ>(v, zero),
                ),
                _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_add_ps(u, v), one),
            );
            let inside = _mm256_and_ps(inside, _mm256_castsi256_ps(live));
            // No branch on whether any lane is inside (which a triangle's rows make
            // hard to predict): the depth test and the masked writes of a chunk with
            // no lane inside write nothing.
            let w0 = _mm256_sub_ps(_mm256_sub_ps(one, u), v);
            let z = _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(w0, z0), _mm256_mul_ps(v, z1)),
                _mm256_mul_ps(u, z2),
            );
            let at = (row + x as isize) as usize;
            // The live lanes are pixels of this row inside the window (the box was
            // clamped to it), so of the buffer: checked, as the scalar path's indexing
            // checks it.
            assert!(
                at + left as usize <= len,
                "a triangle's box outside the window"
            );
            // SAFETY: the masked loads and stores touch only the live lanes,
            // `at..at + left`, inside all three buffers (each `len` long), and the bary
            // writes only lanes with a bit in `m` (the lanes that won), a subset of them.
            unsafe {
                let depth_ptr = buffer.inv_w.as_mut_ptr().add(at);
                let old = _mm256_maskload_ps(depth_ptr, live);
                let win = _mm256_and_ps(inside, _mm256_cmp_ps::<_CMP_GT_OQ>(z, old));
                let wi = _mm256_castps_si256(win);
                _mm256_maskstore_ps(depth_ptr, wi, z);
                _mm256_maskstore_epi32(buffer.triangle.as_mut_ptr().add(at) as *mut i32, wi, id);
                if WEIGHTS {
                    let mut m = _mm256_movemask_ps(win) as u32;
                    if m != 0 {
                        let (mut w0s, mut vs, mut us) = ([0f32; 8], [0f32; 8], [0f32; 8]);
                        _mm256_storeu_ps(w0s.as_mut_ptr(), w0);
                        _mm256_storeu_ps(vs.as_mut_ptr(), v);
                        _mm256_storeu_ps(us.as_mut_ptr(), u);
                        while m != 0 {
                            let k = m.trailing_zeros() as usize;
                            *buffer.bary.get_unchecked_mut(at + k) = [w0s[k], vs[k], us[k]];
                            m &= m - 1;
                        }
                    }
                }
            }
            x += 8;
        }
    }
}

/// [`official_triangle_scalar`] without the weights, sixteen pixels at a time: eight
/// of a row and the eight below them, in the lanes of one AVX-512 register (a face's
/// triangles at full resolution are mostly under eight pixels wide, so a row of eight
/// lanes is mostly one step; two rows are one). The same IEEE float32 operations lane
/// by lane as [`official_triangle_avx2`] (no fused multiply-add, no reordering), so
/// the same bits; lanes past the box's right edge or below its last row are masked
/// off (their depths are never read or written).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq")]
unsafe fn official_visibility_avx512(
    buffer: &mut VisibilityBuffer,
    t: &OfficialTriangle,
    area: OfficialSpan,
) {
    use std::arch::x86_64::*;
    let ((p0x, p0y), (v0x, v0y), (v1x, v1y)) = (t.p0, t.v0, t.v1);
    let (dot00, dot01, dot11) = t.dots;
    let (ox, oy) = area.origin;
    let set = _mm512_set1_ps;
    let (v0x16, v0y16, v1x16, v1y16) = (set(v0x), set(v0y), set(v1x), set(v1y));
    let (d00, d01, d11, inv) = (set(dot00), set(dot01), set(dot11), set(t.inv_deno));
    let (z0, z1, z2) = (set(t.depth[0]), set(t.depth[1]), set(t.depth[2]));
    let (zero, one) = (_mm512_setzero_ps(), set(1.0));
    // Lane k: column k % 8 of row k / 8.
    let cols = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 0, 1, 2, 3, 4, 5, 6, 7);
    let rows = _mm512_setr_epi32(0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1, 1, 1);
    let id = _mm256_set1_epi32(t.index as i32);
    let len = buffer.inv_w.len();
    let mut y = area.ys.start;
    while y < area.ys.end {
        // y + row as float32: exact (|y| is far below 2^24), as `y as f32` is.
        let ys = _mm512_cvtepi32_ps(_mm512_add_epi32(_mm512_set1_epi32(y as i32), rows));
        let v2y = _mm512_sub_ps(ys, set(p0y));
        let (a, b) = (_mm512_mul_ps(v0y16, v2y), _mm512_mul_ps(v1y16, v2y));
        let two_rows = y + 1 < area.ys.end;
        let row = ((y - oy) * area.width - ox) as isize;
        let mut x = area.xs.start;
        while x < area.xs.end {
            let left = (area.xs.end - x).min(8) as u32;
            let row_mask = ((1u32 << left) - 1) as u16;
            let live: __mmask16 = row_mask | if two_rows { row_mask << 8 } else { 0 };
            let xs = _mm512_cvtepi32_ps(_mm512_add_epi32(_mm512_set1_epi32(x as i32), cols));
            let v2x = _mm512_sub_ps(xs, set(p0x));
            let dot02 = _mm512_add_ps(_mm512_mul_ps(v0x16, v2x), a);
            let dot12 = _mm512_add_ps(_mm512_mul_ps(v1x16, v2x), b);
            let u = _mm512_mul_ps(
                _mm512_sub_ps(_mm512_mul_ps(d11, dot02), _mm512_mul_ps(d01, dot12)),
                inv,
            );
            let v = _mm512_mul_ps(
                _mm512_sub_ps(_mm512_mul_ps(d00, dot12), _mm512_mul_ps(d01, dot02)),
                inv,
            );
            // Ordered comparisons: a NaN weight is outside, as in the scalar test.
            let inside = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(live, u, zero)
                & _mm512_cmp_ps_mask::<_CMP_GE_OQ>(v, zero)
                & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(_mm512_add_ps(u, v), one);
            let w0 = _mm512_sub_ps(_mm512_sub_ps(one, u), v);
            let z = _mm512_add_ps(
                _mm512_add_ps(_mm512_mul_ps(w0, z0), _mm512_mul_ps(v, z1)),
                _mm512_mul_ps(u, z2),
            );
            let at = (row + x as isize) as usize;
            // Row y + 1's pixel (the row itself when there is none: no lane of it is
            // live, and the pointer stays inside the buffer).
            let below = if two_rows {
                at + area.width as usize
            } else {
                at
            };
            // The live lanes are pixels of the box inside the window (the box was
            // clamped to it), so of the buffer: checked, as the scalar path's indexing
            // checks it.
            assert!(
                at + left as usize <= len && (!two_rows || below + left as usize <= len),
                "a triangle's box outside the window"
            );
            // SAFETY: the masked loads and stores touch only the live lanes, the
            // first `left` pixels from `at` (and from `below` with two rows), inside
            // both buffers (each `len` long); masked-off lanes are never accessed.
            unsafe {
                let depth = buffer.inv_w.as_mut_ptr();
                let triangle = buffer.triangle.as_mut_ptr().cast::<i32>();
                let (live_lo, live_hi) = (live as __mmask8, (live >> 8) as __mmask8);
                let old = _mm512_insertf32x8::<1>(
                    _mm512_castps256_ps512(_mm256_maskz_loadu_ps(live_lo, depth.add(at))),
                    _mm256_maskz_loadu_ps(live_hi, depth.add(below)),
                );
                let win = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(inside, z, old);
                let (win_lo, win_hi) = (win as __mmask8, (win >> 8) as __mmask8);
                _mm256_mask_storeu_ps(depth.add(at), win_lo, _mm512_castps512_ps256(z));
                _mm256_mask_storeu_ps(depth.add(below), win_hi, _mm512_extractf32x8_ps::<1>(z));
                _mm256_mask_storeu_epi32(triangle.add(at), win_lo, id);
                _mm256_mask_storeu_epi32(triangle.add(below), win_hi, id);
            }
            x += 8;
        }
        y += 2;
    }
}
