//! The `pred-zstd` codec's decoder lanes ([`crate::store::crop_store`]'s predictor):
//! the prediction errors of an RGB rectangle turned back into its bytes, in SSE2 (the
//! x86-64 baseline), in VEX encodings with bands of eight rows in AVX2 registers, or
//! one pixel at a time ([`unpredict_scalar`], the definition beside them). The tests
//! (in the predictor's module) compare every level the CPU has with the definition and
//! with the prediction itself, over every width up to 40 and heights around the bands'.

use crate::lanes::{Level, level};

/// The prediction of a plane's value from the values already decoded: the median edge
/// detector of LOCO-I (JPEG-LS), the median of the left `a`, the above `b` and the
/// plane through them and the above-left `c` (`a + b - c`).
#[inline]
pub(crate) fn med(a: i16, b: i16, c: i16) -> i16 {
    a.min(b).max(a.max(b).min(a + b - c))
}

/// The bytes one decoding of prediction errors reads and writes: `height` rows of
/// `width` pixels, pixel `(y, x)`'s errors at `src + y * src_row + 3 x`, its RGB bytes
/// written at `dst + y * dst_row + x * dst_col` (`dst_col` 3 for an image written as
/// it was predicted, or a row's bytes for one written transposed).
///
/// Its users' safety contract: every pixel's three error bytes are readable at its
/// `src` address (and, but for the last pixel of each row, the byte after them), its
/// three bytes writable at its `dst` address; the two are either the same bytes (`src
/// == dst`, `src_row == dst_row`, `dst_col == 3`: in place) or do not overlap.
#[derive(Clone, Copy)]
pub(crate) struct RectIo {
    pub src: *const u8,
    pub src_row: usize,
    pub dst: *mut u8,
    pub dst_row: usize,
    pub dst_col: usize,
    pub width: usize,
    pub height: usize,
}

impl RectIo {
    /// Pixel `(y, x)`'s errors.
    ///
    /// # Safety
    ///
    /// The pixel is inside the rectangle.
    #[inline(always)]
    unsafe fn src_at(&self, y: usize, x: usize) -> *const u8 {
        // SAFETY: the caller's.
        unsafe { self.src.add(y * self.src_row + 3 * x) }
    }

    /// Where pixel `(y, x)`'s RGB bytes go.
    ///
    /// # Safety
    ///
    /// The pixel is inside the rectangle.
    #[inline(always)]
    unsafe fn dst_at(&self, y: usize, x: usize) -> *mut u8 {
        // SAFETY: the caller's.
        unsafe { self.dst.add(y * self.dst_row + x * self.dst_col) }
    }
}

/// Decodes the prediction errors `io` names, pixel by pixel the same arithmetic as the
/// prediction, at the workspace's SIMD level ([`crate::lanes::level`]): see
/// [`unpredict_io_at`].
///
/// # Safety
///
/// [`RectIo`]'s contract (the bytes; the CPU features are this function's concern).
pub(crate) unsafe fn unpredict_io(io: RectIo) {
    // SAFETY: the caller's.
    unsafe { unpredict_io_at(level(), io) }
}

/// [`unpredict_io`] at `level` (lowered to the CPU's). On x86-64 a pixel's three planes
/// are decoded together in SSE2 lanes (part of the baseline, so at
/// [`Level::Scalar`] too; VEX-encoded, with bands of eight rows in AVX2 registers, from
/// [`Level::Avx2`] up) and four rows at once, each a pixel behind the one above it
/// ([`unpredict_rows_sse2`]): a pixel needs its left neighbour (the decoder's one serial
/// dependency) and the row above's pixel and the one before it, so the four rows'
/// chains run side by side. Elsewhere one pixel at a time ([`unpredict_scalar`], the
/// definition). All are tested against the prediction's own per-pixel definition, and
/// each other.
///
/// # Safety
///
/// [`RectIo`]'s contract.
pub(crate) unsafe fn unpredict_io_at(level: Level, io: RectIo) {
    #[cfg(target_arch = "x86_64")]
    if level.supported() >= Level::Avx2 {
        // SAFETY: the CPU has AVX2 (the level is supported); the bytes are the caller's.
        unsafe { unpredict_rows_vex(io) };
    } else {
        // SAFETY: SSE2 is part of the x86-64 baseline; the bytes are the caller's.
        unsafe { unpredict_rows_sse2::<false>(io) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    // SAFETY: the caller's.
    unsafe {
        let _ = level;
        unpredict_scalar(io)
    };
}

/// [`unpredict_io`] one pixel at a time: the first row and column apart, so the inner
/// loop has no case to choose, and the row above's plane values kept beside the row
/// being decoded.
///
/// # Safety
///
/// [`RectIo`]'s contract.
#[cfg_attr(all(target_arch = "x86_64", not(test)), allow(dead_code))]
pub(crate) unsafe fn unpredict_scalar(io: RectIo) {
    if io.width == 0 {
        return;
    }
    // Each decoded pixel's bytes from its plane predictions and its errors; returns
    // its plane values (green, red less green, blue less green).
    #[inline(always)]
    unsafe fn decode(io: &RectIo, y: usize, x: usize, p: [i16; 3]) -> [i16; 3] {
        // SAFETY: the pixel is inside the rectangle (the caller's); its errors are
        // read before its bytes are written.
        unsafe {
            let e = io.src_at(y, x);
            let [e0, e1, e2] = [e.read(), e.add(1).read(), e.add(2).read()];
            let g = (p[0] as u8).wrapping_add(e0);
            let r = (p[1] as u8).wrapping_add(e1).wrapping_add(g);
            let b = (p[2] as u8).wrapping_add(e2).wrapping_add(g);
            let d = io.dst_at(y, x);
            d.write(r);
            d.add(1).write(g);
            d.add(2).write(b);
            let g = g as i16;
            [g, r as i16 - g, b as i16 - g]
        }
    }
    let (mut prev, mut cur) = (vec![[0i16; 3]; io.width], vec![[0i16; 3]; io.width]);
    for y in 0..io.height {
        // SAFETY (every `decode` below): pixel (y, x) is inside the rectangle.
        // The first pixel: none (top-left) or the one above.
        let mut left = unsafe { decode(&io, y, 0, if y == 0 { [0; 3] } else { prev[0] }) };
        cur[0] = left;
        for x in 1..io.width {
            let p = if y == 0 {
                // The first row: the left neighbour.
                left
            } else {
                let (c, b) = (prev[x - 1], prev[x]);
                [
                    med(left[0], b[0], c[0]),
                    med(left[1], b[1], c[1]),
                    med(left[2], b[2], c[2]),
                ]
            };
            left = unsafe { decode(&io, y, x, p) };
            cur[x] = left;
        }
        std::mem::swap(&mut prev, &mut cur);
    }
}

/// [`unpredict_rows_sse2`] compiled for a CPU with AVX2: the same operations in the
/// three-operand (VEX) encodings, which spare the register copies of SSE2's two-operand
/// ones, and bands of [`WIDE_WAVEFRONT`] rows whose steps away from the window's edges
/// run in two registers of four rows ([`band_middle_avx2`]): 51 against 80 us a
/// 244x244 window (bands of four rows in one register, alternated, one core; 123 us
/// with a register per row).
///
/// # Safety
///
/// The CPU has AVX2; [`RectIo`]'s contract.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn unpredict_rows_vex(io: RectIo) {
    // SAFETY: the caller's.
    unsafe { unpredict_rows_sse2::<true>(io) }
}

/// [`unpredict_io`] in SSE2: a pixel's planes (green, red less green, blue
/// less green) in the first three `i16` lanes of a register, [`med`] lane by lane, and
/// rows decoded [`WAVEFRONT`] at a time, row `k` of a group at column `t - k` in step
/// `t`, so that every pixel's left, above and above-left neighbours are decoded before
/// it (the above ones by the row before in an earlier step) and the rows' dependency
/// chains overlap. With `WIDE` (only inlined into [`unpredict_rows_vex`], on a CPU with
/// AVX2) the steps away from the edges run in [`band_middle_avx2`].
///
/// # Safety
///
/// [`RectIo`]'s contract.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn unpredict_rows_sse2<const WIDE: bool>(io: RectIo) {
    // SAFETY: SSE2 is part of the x86-64 baseline (these run on every x86-64 CPU,
    // inlined into the AVX2 entry on CPUs that have it); the pointers are the caller's.
    unsafe {
        use std::arch::x86_64::*;
        let (width, height) = (io.width, io.height);
        if width == 0 || height == 0 {
            return;
        }
        let zero = _mm_setzero_si128();
        // The planes of the row above the rows being decoded, and the last of those rows'.
        let (mut above, mut below) = (vec![zero; width], vec![zero; width]);
        // The wide bands' staging ([`BandState::stage`]).
        let mut stage = if WIDE {
            vec![[0u64; 4]; width]
        } else {
            Vec::new()
        };
        // The first row: the left neighbour predicts (none for the first pixel).
        let mut left = zero;
        for (x, out) in above.iter_mut().enumerate() {
            // SAFETY: pixel (0, x) is inside the rectangle.
            left = decode_pixel_sse2(&io, 0, x, left);
            *out = left;
        }
        let mut y = 1;
        if WIDE {
            while y + WIDE_WAVEFRONT <= height {
                // SAFETY: rows y..y + WIDE_WAVEFRONT are inside the rectangle.
                unpredict_band_sse2::<WIDE_WAVEFRONT, true>(&io, y, &above, &mut below, &mut stage);
                std::mem::swap(&mut above, &mut below);
                y += WIDE_WAVEFRONT;
            }
        }
        while y + WAVEFRONT <= height {
            // SAFETY: rows y..y + WAVEFRONT are inside the rectangle.
            unpredict_band_sse2::<WAVEFRONT, false>(&io, y, &above, &mut below, &mut []);
            std::mem::swap(&mut above, &mut below);
            y += WAVEFRONT;
        }
        // The last one to three rows as one band, their chains side by side too.
        // SAFETY: rows y..height are inside the rectangle.
        match height - y {
            3 => unpredict_band_sse2::<3, false>(&io, y, &above, &mut below, &mut []),
            2 => unpredict_band_sse2::<2, false>(&io, y, &above, &mut below, &mut []),
            1 => unpredict_band_sse2::<1, false>(&io, y, &above, &mut below, &mut []),
            _ => {}
        }
    }
}

/// The rows [`unpredict_rows_sse2`] decodes side by side (a row's state in a register
/// of its own).
#[cfg(target_arch = "x86_64")]
const WAVEFRONT: usize = 4;

/// The rows [`unpredict_rows_vex`] decodes side by side: two registers of four rows
/// ([`band_middle_avx2`]).
#[cfg(target_arch = "x86_64")]
const WIDE_WAVEFRONT: usize = 8;

/// Rows `y0..y0 + K` of [`unpredict_rows_sse2`] (`y0 >= 1`, all inside the rectangle):
/// `above` holds row `y0 - 1`'s planes, `below` gets row `y0 + K - 1`'s. The steps
/// where every row is past its first column and before its last run without a case to
/// choose, so the rows' state stays in registers.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn unpredict_band_sse2<const K: usize, const WIDE: bool>(
    io: &RectIo,
    y0: usize,
    above: &[std::arch::x86_64::__m128i],
    below: &mut [std::arch::x86_64::__m128i],
    stage: &mut [[u64; 4]],
) {
    // SAFETY: SSE2 is part of the x86-64 baseline (these run on every x86-64 CPU,
    // inlined into the AVX2 entry on CPUs that have it); the pointers are the caller's.
    unsafe {
        use std::arch::x86_64::*;
        // Row k's planes at its last decoded column and at the one before.
        let mut last = [_mm_setzero_si128(); K];
        let mut before = [_mm_setzero_si128(); K];
        let width = io.width;
        let end = width + K - 1;
        // Steps t in inner..outer: every row k at a column t - k in 1..width - 1.
        let (inner, outer) = if width > K + 1 {
            (K, width - 1)
        } else {
            (end, end)
        };
        let mut band = BandState {
            io,
            y0,
            above,
            below,
            stage,
        };
        for t in 0..inner {
            // SAFETY: rows y0..y0 + K are inside the rectangle (the caller's).
            band_step::<K, true>(&mut band, t, &mut last, &mut before);
        }
        if let (true, Ok(last), Ok(before)) = (
            WIDE,
            <&mut [__m128i; WIDE_WAVEFRONT]>::try_from(&mut last[..]),
            <&mut [__m128i; WIDE_WAVEFRONT]>::try_from(&mut before[..]),
        ) {
            // SAFETY: WIDE runs only on a CPU with AVX2 ([`unpredict_rows_vex`]); the
            // steps are the band's inner ones.
            band_middle_avx2(&mut band, inner..outer, last, before);
        } else {
            for t in inner..outer {
                // SAFETY: as above.
                band_step::<K, false>(&mut band, t, &mut last, &mut before);
            }
        }
        for t in outer..end {
            // SAFETY: as above.
            band_step::<K, true>(&mut band, t, &mut last, &mut before);
        }
    }
}

/// What every step of [`unpredict_band_sse2`] reads or writes besides the rows' state.
#[cfg(target_arch = "x86_64")]
struct BandState<'a> {
    io: &'a RectIo,
    y0: usize,
    above: &'a [std::arch::x86_64::__m128i],
    below: &'a mut [std::arch::x86_64::__m128i],
    /// [`band_middle_avx2`]'s second register per column (`width` of them; empty
    /// elsewhere), whose last row becomes `below` after the steps.
    stage: &'a mut [[u64; 4]],
}

/// Step `t` of [`unpredict_band_sse2`]: row `k` decodes column `t - k`, from the last
/// row up, so that row `k` reads row `k - 1`'s last two pixels before row `k - 1`
/// moves on. With `EDGE` false every row is at a column in `1..width - 1` (no first
/// column, no row end), and the cases are compiled out.
///
/// # Safety
///
/// Rows `y0..y0 + K` are inside the rectangle of `band.io` ([`RectIo`]'s contract).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn band_step<const K: usize, const EDGE: bool>(
    band: &mut BandState<'_>,
    t: usize,
    last: &mut [std::arch::x86_64::__m128i; K],
    before: &mut [std::arch::x86_64::__m128i; K],
) {
    // SAFETY: SSE2 is part of the x86-64 baseline (these run on every x86-64 CPU,
    // inlined into the AVX2 entry on CPUs that have it); the pointers are the caller's.
    unsafe {
        use std::arch::x86_64::*;
        let med = |a: __m128i, b: __m128i, c: __m128i| {
            let plane = _mm_sub_epi16(_mm_add_epi16(a, b), c);
            _mm_max_epi16(
                _mm_min_epi16(a, b),
                _mm_min_epi16(_mm_max_epi16(a, b), plane),
            )
        };
        let io = band.io;
        for k in (0..K).rev() {
            let x = t.wrapping_sub(k);
            if EDGE && x >= io.width {
                continue;
            }
            let (b, c) = match k {
                0 if EDGE && x == 0 => (band.above[0], band.above[0]),
                0 => (band.above[x], band.above[x - 1]),
                _ => (last[k - 1], before[k - 1]),
            };
            // The first column: the pixel above predicts.
            let p = if EDGE && x == 0 {
                b
            } else {
                med(last[k], b, c)
            };
            let y = band.y0 + k;
            let planes = if EDGE {
                // SAFETY: pixel (y, x) is inside the rectangle.
                decode_pixel_sse2(io, y, x, p)
            } else {
                // SAFETY: as above, and x + 1 < width: the fourth byte is the next
                // pixel's.
                decode_inner_pixel_sse2(io.src_at(y, x), io.dst_at(y, x), p)
            };
            before[k] = last[k];
            last[k] = planes;
            if k == K - 1 {
                band.below[x] = planes;
            }
        }
    }
}

/// The inner steps `steps` of a band of eight rows ([`unpredict_band_sse2`]) in two
/// AVX2 registers of four rows, row `k`'s planes in 64-bit lane `k % 4` (`i16` lanes
/// `4 (k % 4)..4 (k % 4) + 3`, the fourth zero) of register `k / 4`, where
/// [`band_step`] does each row in a register of its own. Per step and register one
/// median and one decode; the rows above move one row down by a lane permute (the
/// first register's lane 3 into the second's lane 0). The two registers' dependency
/// chains overlap: the second reads only the first's values of the step before. The
/// same arithmetic lane by lane, so the same bytes (tested against the scalar
/// decoder). `last` and `before` hold the rows' state as [`band_step`] keeps it, on
/// entry and on return.
///
/// # Safety
///
/// The CPU has AVX2; `band`'s eight rows are inside its rectangle ([`RectIo`]'s
/// contract), and every step is an inner one: each row at a column in `1..width - 1`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn band_middle_avx2(
    band: &mut BandState<'_>,
    steps: std::ops::Range<usize>,
    last: &mut [std::arch::x86_64::__m128i; WIDE_WAVEFRONT],
    before: &mut [std::arch::x86_64::__m128i; WIDE_WAVEFRONT],
) {
    use std::arch::x86_64::*;
    let io = *band.io;
    if steps.is_empty() {
        return;
    }
    assert!(
        steps.start >= WIDE_WAVEFRONT
            && steps.end < io.width
            && band.y0 + WIDE_WAVEFRONT <= io.height
            && band.stage.len() == io.width
            && band.below.len() == io.width,
        "inner steps of a band inside the rectangle"
    );
    let zero = _mm_setzero_si128();
    // Four rows' xmm state (planes in lanes 0-2) to and from the 64-bit lanes of one
    // register.
    let join = |r: &[__m128i]| {
        _mm256_set_m128i(
            _mm_unpacklo_epi64(r[2], r[3]),
            _mm_unpacklo_epi64(r[0], r[1]),
        )
    };
    let split = |v: __m256i, r: &mut [__m128i]| {
        let (lo, hi) = (_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
        r[0] = _mm_move_epi64(lo);
        r[1] = _mm_unpackhi_epi64(lo, zero);
        r[2] = _mm_move_epi64(hi);
        r[3] = _mm_unpackhi_epi64(hi, zero);
    };
    // Lanes 0-2 of every row.
    let planes_mask = _mm256_set1_epi64x(0x0000_00ff_00ff_00ff);
    // Green modulo 256 (the low byte of the row's lane 0) into its lanes 1 and 2, lanes
    // 0 and 3 zero.
    let green_of = _mm256_setr_epi8(
        -128, -128, 0, -128, 0, -128, -128, -128, -128, -128, 8, -128, 8, -128, -128, -128, -128,
        -128, 0, -128, 0, -128, -128, -128, -128, -128, 8, -128, 8, -128, -128, -128,
    );
    // A row's red, green and blue (lanes 1, 0, 2) as its first three bytes.
    let rgb_of = _mm256_setr_epi8(
        2, 0, 4, -128, 10, 8, 12, -128, -128, -128, -128, -128, -128, -128, -128, -128, 2, 0, 4,
        -128, 10, 8, 12, -128, -128, -128, -128, -128, -128, -128, -128, -128,
    );
    // Rows 0-3 (`_a`) and 4-7 (`_b`): planes at the last decoded column and the one before.
    let (mut last_a, mut before_a) = (join(&last[..4]), join(&before[..4]));
    let (mut last_b, mut before_b) = (join(&last[4..]), join(&before[4..]));
    // Row k's pixel of step t is a row down and a pixel left of row k - 1's: its errors
    // `src_step` bytes after, its bytes `dst_step` after (before, for a transposed
    // destination), offsets computed one by one (an array of them would be built in
    // vector lanes and each taken out again).
    let src_step = io.src_row - 3;
    let dst_step = io.dst_row as isize - io.dst_col as isize;
    // One register's rows `k0..k0 + 4` of a step whose row 0 pixel goes to `dst0`,
    // from their left `a`, above `b` and above-left `c` planes and their errors: writes
    // each row's pixel and returns the rows' planes.
    let decode = |a: __m256i, b: __m256i, c: __m256i, errors: __m256i, dst0: *mut u8, k0: usize| {
        let plane = _mm256_sub_epi16(_mm256_add_epi16(a, b), c);
        let p = _mm256_max_epi16(
            _mm256_min_epi16(a, b),
            _mm256_min_epi16(_mm256_max_epi16(a, b), plane),
        );
        // Green, red less green and blue less green, modulo 256 once masked.
        let sums = _mm256_add_epi16(p, errors);
        let green = _mm256_shuffle_epi8(sums, green_of);
        let grb = _mm256_and_si256(_mm256_add_epi16(sums, green), planes_mask);
        // Each half's low 64 bits (two rows' bytes, `rgb_of`) moved to a general
        // register, then stored from there: lane extracts into memory would each take
        // the shuffle unit, which is what a step waits on.
        let rgb = _mm256_shuffle_epi8(grb, rgb_of);
        let (mut lo, mut hi) = (
            _mm_cvtsi128_si64(_mm256_castsi256_si128(rgb)) as u64,
            _mm_cvtsi128_si64(_mm256_extracti128_si256::<1>(rgb)) as u64,
        );
        // SAFETY: an empty instruction: the values stay in general registers (else
        // the compiler folds the moves and shifts back into lane extracts).
        unsafe {
            std::arch::asm!("/* {0} {1} */", inout(reg) lo, inout(reg) hi, options(pure, nomem, nostack))
        };
        let out = [lo as u32, (lo >> 32) as u32, hi as u32, (hi >> 32) as u32];
        for (k, &o) in (k0..k0 + 4).zip(&out) {
            // SAFETY: the caller's (below): the pixel is inside the rectangle.
            // Three bytes (two and one), as `decode_inner_pixel_sse2` writes them.
            unsafe {
                let ptr = dst0.offset(k as isize * dst_step);
                ptr.cast::<u16>().write_unaligned(o as u16);
                ptr.add(2).write((o >> 16) as u8);
            }
        }
        _mm256_sub_epi16(grb, green)
    };
    // Above: row k - 1's last pixel, row 0's from the band above, row 4's from row 3
    // (the first register's lane 3). Above-left: the pixel before those, which is the
    // step before's above.
    let down = |v: __m256i| _mm256_permute4x64_epi64::<0b10_01_00_00>(v);
    let down_from = |a: __m256i, b: __m256i| {
        _mm256_alignr_epi8::<8>(b, _mm256_permute2x128_si256::<0x21>(a, b))
    };
    // SAFETY: `above` holds a value for every column, and `steps.start >= 1`.
    let above = |x: usize| unsafe { _mm256_castsi128_si256(*band.above.get_unchecked(x)) };
    let mut c_a = _mm256_blend_epi32::<0b11>(down(before_a), above(steps.start - 1));
    let mut c_b = down_from(before_a, before_b);
    let first = steps.start;
    let stage = band.stage.as_mut_ptr();
    for t in steps.clone() {
        // SAFETY: every row's pixel t - k is an inner one (the caller's), so its four
        // error bytes (its three and the next pixel's first) are readable and its
        // three bytes writable ([`RectIo`]); `stage` holds a value for every column
        // (asserted above).
        unsafe {
            let (src0, dst0) = (io.src_at(band.y0, t), io.dst_at(band.y0, t));
            let read = |k: usize| src0.add(k * src_step).cast::<i32>().read_unaligned();
            // Lane 3 of each row gets the next pixel's first byte: it never reaches a
            // result (green is taken from lane 0, the sums are masked to lanes 0-2).
            let errors = |k: usize| {
                _mm256_cvtepu8_epi16(_mm_setr_epi32(
                    read(k),
                    read(k + 1),
                    read(k + 2),
                    read(k + 3),
                ))
            };
            let b_a = _mm256_blend_epi32::<0b11>(down(last_a), above(t));
            let b_b = down_from(last_a, last_b);
            let new_a = decode(last_a, b_a, c_a, errors(0), dst0, 0);
            let new_b = decode(last_b, b_b, c_b, errors(4), dst0, 4);
            (before_a, last_a, c_a) = (last_a, new_a, b_a);
            (before_b, last_b, c_b) = (last_b, new_b, b_b);
            // The whole register kept (a plain store), its last row taken out below.
            _mm256_storeu_si256(stage.add(t - (WIDE_WAVEFRONT - 1)).cast(), last_b);
        }
    }
    for x in first - (WIDE_WAVEFRONT - 1)..steps.end - (WIDE_WAVEFRONT - 1) {
        // Row 7's planes: the register's lane 3, the upper half zero.
        // SAFETY: SSE2 is part of the x86-64 baseline; the eight bytes are `stage[x][3]`.
        band.below[x] = unsafe { _mm_loadl_epi64(band.stage[x][3..].as_ptr().cast()) };
    }
    split(last_a, &mut last[..4]);
    split(last_b, &mut last[4..]);
    split(before_a, &mut before[..4]);
    split(before_b, &mut before[4..]);
}

/// Decodes pixel `(y, x)` of `io`'s rectangle from its plane predictions `p` (lanes
/// 0-2; lane 3 and up zero): its three error bytes give its RGB bytes, and its planes
/// come back in lanes 0-2 (the others zero). Reads and writes the pixel's three bytes
/// only (for the rectangle's last pixels, where no fourth byte follows).
///
/// # Safety
///
/// `(y, x)` is inside the rectangle ([`RectIo`]'s contract).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn decode_pixel_sse2(
    io: &RectIo,
    y: usize,
    x: usize,
    p: std::arch::x86_64::__m128i,
) -> std::arch::x86_64::__m128i {
    debug_assert!(y < io.height && x < io.width);
    let mut four = [0u8; 4];
    // SAFETY: the pixel's three bytes are readable and writable (the caller's); `four`
    // holds four bytes.
    unsafe {
        std::ptr::copy_nonoverlapping(io.src_at(y, x), four.as_mut_ptr(), 3);
        decode_inner_pixel_sse2(four.as_ptr(), io.dst_at(y, x), p)
    }
}

/// [`decode_pixel_sse2`] of the pixel whose errors start at `src`, with a fourth byte
/// after them (read with them, and left as it was), its RGB bytes written at `dst`.
///
/// # Safety
///
/// Four bytes are readable at `src`, three writable at `dst`; if the two overlap, they
/// are the same address.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn decode_inner_pixel_sse2(
    src: *const u8,
    dst: *mut u8,
    p: std::arch::x86_64::__m128i,
) -> std::arch::x86_64::__m128i {
    // SAFETY: SSE2 is part of the x86-64 baseline (these run on every x86-64 CPU,
    // inlined into the AVX2 entry on CPUs that have it); the pointers are the caller's.
    unsafe {
        use std::arch::x86_64::*;
        let read = src.cast::<u32>().read_unaligned();
        let zero = _mm_setzero_si128();
        let low_byte = _mm_set1_epi16(0xff);
        let errors = _mm_unpacklo_epi8(_mm_cvtsi32_si128(read as i32), zero);
        // Green, and red and blue less green, each modulo 256.
        let sums = _mm_and_si128(_mm_add_epi16(p, errors), low_byte);
        // Green in lanes 1 and 2: red and blue are their planes plus green, modulo 256.
        let green = _mm_and_si128(
            _mm_shufflelo_epi16::<0>(sums),
            _mm_setr_epi16(0, -1, -1, 0, 0, 0, 0, 0),
        );
        let grb = _mm_and_si128(
            _mm_add_epi16(sums, green),
            _mm_setr_epi16(0xff, 0xff, 0xff, 0, 0, 0, 0, 0),
        );
        // Lanes red, green, blue, packed to bytes.
        let rgb = _mm_packus_epi16(_mm_shufflelo_epi16::<0b11_10_00_01>(grb), zero);
        let out = _mm_cvtsi128_si32(rgb) as u32;
        // Three bytes written (two and one): in place, a four-byte store would overlap
        // the next pixel's four-byte read, which the CPU could then not forward from
        // the store; elsewhere, it would write past the pixel.
        dst.cast::<u16>().write_unaligned(out as u16);
        dst.add(2).write((out >> 16) as u8);
        _mm_sub_epi16(grb, green)
    }
}
