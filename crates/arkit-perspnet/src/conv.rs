//! 2-D convolution kernels for training on the CPU (f32): the forward pass, the
//! input gradient and the kernel gradient, each as im2col + GEMM over blocks of
//! output rows.
//!
//! # Design
//! For one image `x_b` (`C x H x W`) and a kernel `W` (`Co x K`, `K = C kh kw`),
//! with `cols_b` the `K x N` patch matrix (`N = Ho Wo`):
//! - forward: `y_b = W cols_b` (`Co x N`);
//! - input gradient: `dcols = Wᵀ g_b` (`K x N`), scattered back onto `dx_b`
//!   (col2im, adding where patches overlap);
//! - kernel gradient: `dW = Σ_b g_b cols_bᵀ`.
//!
//! The patch matrix is never built whole: it is built for a block of output rows
//! at a time ([`BLOCK_FLOATS`] floats, about 1 MiB, meant to be still in cache
//! when the GEMM reads it; the size was chosen, not tuned by a sweep) in a
//! per-thread scratch buffer reused across calls, and a 1x1 stride-1
//! convolution uses the image itself as its patch matrix. The GEMMs are the `gemm` crate's (the one candle's
//! matmul uses), called directly with strides so that no operand is transposed
//! or copied.
//!
//! Why: the previous back end built each batch's full patch matrix as a fresh
//! tensor, and zero-filling and building it dominated a training step's profile
//! (the figures: docs/performance.md, "Where the PerspNet time goes").
//!
//! # Threads and determinism
//! Work is split by batch element (and, in the forward pass, by block) with
//! rayon; every GEMM runs on one thread. Each batch element's kernel gradient is
//! computed on its own and the partial sums are added in batch order, so results
//! do not depend on the number of threads or on scheduling.

use rayon::prelude::*;

use crate::blas::{Mat, gemm, gemm_raw_maybe_par};

/// Target size of one block of the patch matrix, in floats (1 MiB).
pub(crate) const BLOCK_FLOATS: usize = 1 << 18;

/// The shape of one convolution: input `b x c x h x w`, kernel
/// `co x c x kh x kw`, stride and zero padding (the same on both axes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ConvShape {
    /// Batch size.
    pub b: usize,
    /// Input channels.
    pub c: usize,
    /// Input height.
    pub h: usize,
    /// Input width.
    pub w: usize,
    /// Output channels.
    pub co: usize,
    /// Kernel height.
    pub kh: usize,
    /// Kernel width.
    pub kw: usize,
    /// Stride.
    pub stride: usize,
    /// Zero padding on each side.
    pub pad: usize,
}

impl ConvShape {
    /// Output height.
    pub(crate) fn ho(&self) -> usize {
        (self.h + 2 * self.pad - self.kh) / self.stride + 1
    }

    /// Output width.
    pub(crate) fn wo(&self) -> usize {
        (self.w + 2 * self.pad - self.kw) / self.stride + 1
    }

    /// Rows of the patch matrix (`c kh kw`).
    pub fn k(&self) -> usize {
        self.c * self.kh * self.kw
    }

    /// Output pixels per image (`ho wo`).
    pub fn n(&self) -> usize {
        self.ho() * self.wo()
    }

    /// Whether the image is its own patch matrix (1x1 kernel, stride 1, no padding).
    fn is_pointwise(&self) -> bool {
        self.kh == 1 && self.kw == 1 && self.stride == 1 && self.pad == 0
    }

    /// Output rows per block of the patch matrix.
    fn rows_per_block(&self) -> usize {
        if self.is_pointwise() {
            return self.ho();
        }
        (BLOCK_FLOATS / (self.k() * self.wo()).max(1)).clamp(1, self.ho())
    }

    /// The blocks of output rows, `[start, end)`.
    fn blocks(&self) -> Vec<(usize, usize)> {
        let step = self.rows_per_block();
        (0..self.ho())
            .step_by(step)
            .map(|r| (r, (r + step).min(self.ho())))
            .collect()
    }

    fn check(&self, x: usize, w: usize, y: usize) {
        assert_eq!(x, self.b * self.c * self.h * self.w, "conv: input length");
        assert_eq!(w, self.co * self.k(), "conv: kernel length");
        assert_eq!(y, self.b * self.co * self.n(), "conv: output length");
    }
}

/// For kernel offset `d` (after subtracting the padding), the output columns
/// `[lo, hi)` whose input column `o * stride + d` lies inside `0..len`.
fn valid_range(d: isize, stride: usize, len: usize, count: usize) -> (usize, usize) {
    let s = stride as isize;
    // smallest o with o*s + d >= 0
    let lo = if d >= 0 { 0 } else { ((-d) + s - 1) / s };
    // largest o with o*s + d <= len - 1, plus one
    let hi = if (len as isize - 1 - d) < 0 {
        0
    } else {
        (len as isize - 1 - d) / s + 1
    };
    let lo = (lo as usize).min(count);
    (lo, (hi as usize).clamp(lo, count))
}

/// Writes the patch matrix of image `x` (`c x h x w`) for output rows
/// `[oy0, oy1)` into `cols` (`k x (oy1 - oy0) wo`, row-major).
fn im2col_block(x: &[f32], s: &ConvShape, oy0: usize, oy1: usize, cols: &mut [f32]) {
    let (wo, rows) = (s.wo(), oy1 - oy0);
    let nb = rows * wo;
    let pad = s.pad as isize;
    for ci in 0..s.c {
        let plane = &x[ci * s.h * s.w..(ci + 1) * s.h * s.w];
        for di in 0..s.kh {
            for dj in 0..s.kw {
                let r = (ci * s.kh + di) * s.kw + dj;
                let dst = &mut cols[r * nb..(r + 1) * nb];
                let dx = dj as isize - pad;
                let (lo, hi) = valid_range(dx, s.stride, s.w, wo);
                for (row, oy) in (oy0..oy1).enumerate() {
                    let drow = &mut dst[row * wo..(row + 1) * wo];
                    let iy = (oy * s.stride + di) as isize - pad;
                    if iy < 0 || iy >= s.h as isize {
                        drow.fill(0.0);
                        continue;
                    }
                    let srow = &plane[iy as usize * s.w..(iy as usize + 1) * s.w];
                    drow[..lo].fill(0.0);
                    drow[hi..].fill(0.0);
                    let first = (lo as isize * s.stride as isize + dx) as usize;
                    if s.stride == 1 {
                        drow[lo..hi].copy_from_slice(&srow[first..first + hi - lo]);
                    } else {
                        for (o, d) in drow[lo..hi].iter_mut().enumerate() {
                            *d = srow[first + o * s.stride];
                        }
                    }
                }
            }
        }
    }
}

/// Adds the patch-matrix block `cols` (as written by [`im2col_block`] for output
/// rows `[oy0, oy1)`) back onto image `dx` (`c x h x w`).
fn col2im_block(cols: &[f32], s: &ConvShape, oy0: usize, oy1: usize, dx: &mut [f32]) {
    let (wo, rows) = (s.wo(), oy1 - oy0);
    let nb = rows * wo;
    let pad = s.pad as isize;
    for ci in 0..s.c {
        let plane = &mut dx[ci * s.h * s.w..(ci + 1) * s.h * s.w];
        for di in 0..s.kh {
            for dj in 0..s.kw {
                let r = (ci * s.kh + di) * s.kw + dj;
                let src = &cols[r * nb..(r + 1) * nb];
                let dxo = dj as isize - pad;
                let (lo, hi) = valid_range(dxo, s.stride, s.w, wo);
                for (row, oy) in (oy0..oy1).enumerate() {
                    let iy = (oy * s.stride + di) as isize - pad;
                    if iy < 0 || iy >= s.h as isize {
                        continue;
                    }
                    let srow = &src[row * wo..(row + 1) * wo];
                    let drow = &mut plane[iy as usize * s.w..(iy as usize + 1) * s.w];
                    let first = (lo as isize * s.stride as isize + dxo) as usize;
                    for (o, v) in srow[lo..hi].iter().enumerate() {
                        drow[first + o * s.stride] += v;
                    }
                }
            }
        }
    }
}

/// A raw output pointer shared by tasks that write disjoint parts of it.
#[derive(Clone, Copy)]
struct SharedOut(*mut f32, usize);
// SAFETY: tasks holding it write disjoint index sets (see each use).
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

impl SharedOut {
    /// The pointer `start` values in (a method, so that closures capture the whole
    /// `SharedOut`, not its raw-pointer field) and the number of values after it.
    fn at(&self, start: usize) -> (*mut f32, usize) {
        assert!(start <= self.1, "SharedOut: out of bounds");
        // SAFETY: `start` is within the allocation (checked).
        (unsafe { self.0.add(start) }, self.1 - start)
    }
}

/// Forward convolution: `x` is `b x c x h x w`, `w` is `co x c x kh x kw`;
/// returns `b x co x ho x wo`.
pub fn forward(x: &[f32], w: &[f32], s: &ConvShape) -> Vec<f32> {
    let (k, n, co, wo) = (s.k(), s.n(), s.co, s.wo());
    let len = s.b * co * n;
    s.check(x.len(), w.len(), len);
    // Zero-filled although every value is written below: the GEMM may load (and
    // then discard) parts of its destination, which must not be uninitialised.
    let mut y = vec![0f32; len];
    let img = s.c * s.h * s.w;
    let wm = Mat::row_major(co, k, k);
    let out = SharedOut(y.as_mut_ptr(), len);
    let tasks: Vec<(usize, usize, usize)> = if s.is_pointwise() {
        (0..s.b).map(|bi| (bi, 0, s.ho())).collect()
    } else {
        let blocks = s.blocks();
        (0..s.b)
            .flat_map(|bi| blocks.iter().map(move |&(a, e)| (bi, a, e)))
            .collect()
    };
    // Fewer tasks than twice the threads (the deep layers of one image: one block
    // each): each task's product is split over the threads too, or one thread would
    // do a layer alone while the others wait.
    let nested = tasks.len() < 2 * rayon::current_num_threads();
    tasks.par_iter().for_each(|&(bi, oy0, oy1)| {
        let nb = (oy1 - oy0) * wo;
        let xb = &x[bi * img..(bi + 1) * img];
        let product = |cols: &[f32]| {
            // SAFETY: task (bi, block) writes only columns [oy0 wo, oy1 wo) of
            // image bi's rows, each once; no two tasks share a (bi, block) pair;
            // `y` outlives the parallel loop and nothing else touches it during it.
            unsafe {
                gemm_raw_maybe_par(
                    out.at(bi * co * n + oy0 * wo),
                    Mat::row_major(co, nb, n),
                    w,
                    wm,
                    cols,
                    Mat::row_major(k, nb, nb),
                    nested,
                )
            }
        };
        if s.is_pointwise() {
            product(xb);
        } else if nested {
            // Not this thread's scratch: while its product waits on the other
            // threads, this thread may run another task of this loop.
            let mut cols = vec![0f32; k * nb];
            im2col_block(xb, s, oy0, oy1, &mut cols);
            product(&cols);
        } else {
            with_scratch(k * nb, |cols| {
                im2col_block(xb, s, oy0, oy1, cols);
                product(cols);
            });
        }
    });
    y
}

thread_local! {
    /// Per-thread buffer for blocks of the patch matrix, reused across calls.
    static SCRATCH: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Runs `f` on this thread's scratch buffer of at least `len` values (contents
/// unspecified: `f` must write before it reads). `f` must not call back here.
fn with_scratch<R>(len: usize, f: impl FnOnce(&mut [f32]) -> R) -> R {
    SCRATCH.with(|cell| {
        let mut buf = cell.borrow_mut();
        if buf.len() < len {
            buf.resize(len, 0.0);
        }
        f(&mut buf[..len])
    })
}

/// Input gradient: `g` is the output gradient (`b x co x ho x wo`), `w` the
/// kernel; returns `b x c x h x w`.
pub(crate) fn input_grad(g: &[f32], w: &[f32], s: &ConvShape) -> Vec<f32> {
    let (k, n, co, wo) = (s.k(), s.n(), s.co, s.wo());
    let img = s.c * s.h * s.w;
    let mut dx = vec![0f32; s.b * img];
    s.check(dx.len(), w.len(), g.len());
    let wt = Mat::row_major(co, k, k).transposed();
    let blocks = s.blocks();
    dx.par_chunks_mut(img)
        .zip(g.par_chunks(co * n))
        .for_each(|(dxb, gb)| {
            if s.is_pointwise() {
                gemm(
                    dxb,
                    Mat::row_major(k, n, n),
                    w,
                    wt,
                    gb,
                    Mat::row_major(co, n, n),
                    false,
                );
                return;
            }
            with_scratch(k * s.rows_per_block() * wo, |buf| {
                for &(oy0, oy1) in &blocks {
                    let nb = (oy1 - oy0) * wo;
                    let cols = &mut buf[..k * nb];
                    gemm(
                        cols,
                        Mat::row_major(k, nb, nb),
                        w,
                        wt,
                        &gb[oy0 * wo..],
                        Mat::row_major(co, nb, n),
                        false,
                    );
                    col2im_block(cols, s, oy0, oy1, dxb);
                }
            });
        });
    dx
}

/// Kernel gradient: `x` is the input (`b x c x h x w`), `g` the output gradient;
/// returns `co x c x kh x kw`.
pub(crate) fn kernel_grad(x: &[f32], g: &[f32], s: &ConvShape) -> Vec<f32> {
    let (k, n, co, wo) = (s.k(), s.n(), s.co, s.wo());
    let img = s.c * s.h * s.w;
    s.check(x.len(), co * k, g.len());
    let blocks = s.blocks();
    let partials: Vec<Vec<f32>> = x
        .par_chunks(img)
        .zip(g.par_chunks(co * n))
        .map(|(xb, gb)| {
            let mut dw = vec![0f32; co * k];
            let scratch = if s.is_pointwise() {
                0
            } else {
                k * s.rows_per_block() * wo
            };
            with_scratch(scratch, |buf| {
                for (i, &(oy0, oy1)) in blocks.iter().enumerate() {
                    let nb = (oy1 - oy0) * wo;
                    let patches: &[f32] = if s.is_pointwise() {
                        xb
                    } else {
                        im2col_block(xb, s, oy0, oy1, &mut buf[..k * nb]);
                        &buf[..k * nb]
                    };
                    gemm(
                        &mut dw,
                        Mat::row_major(co, k, k),
                        &gb[oy0 * wo..],
                        Mat::row_major(co, nb, n),
                        patches,
                        Mat::row_major(k, nb, nb).transposed(),
                        i > 0,
                    );
                }
            });
            dw
        })
        .collect();
    let mut parts = partials.into_iter();
    let mut dw = parts.next().unwrap_or_else(|| vec![0f32; co * k]);
    for p in parts {
        for (a, b) in dw.iter_mut().zip(&p) {
            *a += b;
        }
    }
    dw
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Direct seven-loop convolution: the reference.
    fn naive(x: &[f32], w: &[f32], s: &ConvShape) -> Vec<f32> {
        let (ho, wo) = (s.ho(), s.wo());
        let mut y = vec![0f32; s.b * s.co * ho * wo];
        for b in 0..s.b {
            for o in 0..s.co {
                for oy in 0..ho {
                    for ox in 0..wo {
                        let mut acc = 0f64;
                        for c in 0..s.c {
                            for di in 0..s.kh {
                                for dj in 0..s.kw {
                                    let iy = (oy * s.stride + di) as isize - s.pad as isize;
                                    let ix = (ox * s.stride + dj) as isize - s.pad as isize;
                                    if iy < 0 || ix < 0 || iy >= s.h as isize || ix >= s.w as isize
                                    {
                                        continue;
                                    }
                                    let xv =
                                        x[((b * s.c + c) * s.h + iy as usize) * s.w + ix as usize];
                                    let wv = w[((o * s.c + c) * s.kh + di) * s.kw + dj];
                                    acc += xv as f64 * wv as f64;
                                }
                            }
                        }
                        y[((b * s.co + o) * ho + oy) * wo + ox] = acc as f32;
                    }
                }
            }
        }
        y
    }

    fn values(len: usize, seed: u64) -> Vec<f32> {
        let mut rng = arkit_core::Rng::new(seed);
        (0..len)
            .map(|_| rng.next_f64() as f32 * 2.0 - 1.0)
            .collect()
    }

    fn dot(a: &[f32], b: &[f32]) -> f64 {
        a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum()
    }

    fn shapes() -> Vec<ConvShape> {
        let mk = |b, c, h, w, co, k, stride, pad| ConvShape {
            b,
            c,
            h,
            w,
            co,
            kh: k,
            kw: k,
            stride,
            pad,
        };
        vec![
            mk(2, 3, 9, 7, 4, 3, 1, 1),
            mk(3, 2, 12, 11, 5, 3, 2, 1),
            mk(1, 3, 16, 16, 2, 7, 2, 3),
            mk(2, 4, 8, 8, 3, 1, 2, 0),
            mk(2, 4, 5, 6, 3, 1, 1, 0),
            mk(2, 2, 7, 9, 3, 3, 2, 1),
            mk(1, 2, 4, 3, 2, 3, 1, 0),
        ]
    }

    #[test]
    fn forward_matches_the_direct_sum() {
        for (i, s) in shapes().into_iter().enumerate() {
            let x = values(s.b * s.c * s.h * s.w, i as u64);
            let w = values(s.co * s.k(), 100 + i as u64);
            let (a, b) = (forward(&x, &w, &s), naive(&x, &w, &s));
            let d = a
                .iter()
                .zip(&b)
                .map(|(p, q)| (p - q).abs())
                .fold(0f32, f32::max);
            assert!(d < 1e-5, "{s:?}: {d}");
        }
    }

    /// The two gradients are the adjoints of the forward map:
    /// `<conv(x, w), g> = <x, input_grad(g, w)> = <w, kernel_grad(x, g)>`.
    #[test]
    fn gradients_are_the_adjoints_of_the_forward_map() {
        for (i, s) in shapes().into_iter().enumerate() {
            let x = values(s.b * s.c * s.h * s.w, i as u64);
            let w = values(s.co * s.k(), 100 + i as u64);
            let g = values(s.b * s.co * s.n(), 200 + i as u64);
            let lhs = dot(&naive(&x, &w, &s), &g);
            let via_x = dot(&x, &input_grad(&g, &w, &s));
            let via_w = dot(&w, &kernel_grad(&x, &g, &s));
            assert!(
                (lhs - via_x).abs() < 1e-4 * lhs.abs().max(1.0),
                "{s:?}: {lhs} {via_x}"
            );
            assert!(
                (lhs - via_w).abs() < 1e-4 * lhs.abs().max(1.0),
                "{s:?}: {lhs} {via_w}"
            );
        }
    }

    #[test]
    fn blocks_cover_the_output_rows_once_and_small_blocks_agree() {
        let s = ConvShape {
            b: 2,
            c: 64,
            h: 40,
            w: 40,
            co: 3,
            kh: 3,
            kw: 3,
            stride: 1,
            pad: 1,
        };
        let blocks = s.blocks();
        assert!(blocks.len() > 1, "this shape must need several blocks");
        assert_eq!(blocks[0].0, 0);
        assert_eq!(blocks.last().unwrap().1, s.ho());
        assert!(blocks.windows(2).all(|p| p[0].1 == p[1].0));
        let x = values(s.b * s.c * s.h * s.w, 7);
        let w = values(s.co * s.k(), 8);
        let g = values(s.b * s.co * s.n(), 9);
        let y = forward(&x, &w, &s);
        let d = y
            .iter()
            .zip(&naive(&x, &w, &s))
            .map(|(p, q)| (p - q).abs())
            .fold(0f32, f32::max);
        assert!(d < 1e-4, "{d}");
        let lhs = dot(&y, &g);
        assert!((lhs - dot(&x, &input_grad(&g, &w, &s))).abs() < 1e-3 * lhs.abs());
        assert!((lhs - dot(&w, &kernel_grad(&x, &g, &s))).abs() < 1e-3 * lhs.abs());
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        // A batch of several blocks, and a deep layer of one image (one block, fewer
        // tasks than threads: its product is split over the threads).
        let deep = ConvShape {
            b: 1,
            c: 96,
            h: 6,
            w: 6,
            co: 160,
            kh: 3,
            kw: 3,
            stride: 1,
            pad: 1,
        };
        for s in [shapes()[1], deep] {
            let x = values(s.b * s.c * s.h * s.w, 1);
            let w = values(s.co * s.k(), 2);
            let g = values(s.b * s.co * s.n(), 3);
            let run = |threads| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap()
                    .install(|| {
                        (
                            forward(&x, &w, &s),
                            input_grad(&g, &w, &s),
                            kernel_grad(&x, &g, &s),
                        )
                    })
            };
            let one = run(1);
            assert_eq!(one, run(3), "{s:?}");
            assert_eq!(one.0, run(2).0, "{s:?}");
            let d = one
                .0
                .iter()
                .zip(&naive(&x, &w, &s))
                .map(|(p, q)| (p - q).abs())
                .fold(0f32, f32::max);
            assert!(d < 1e-4, "{s:?}: {d}");
        }
    }
}
