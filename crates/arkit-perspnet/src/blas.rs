//! Matrix products on flat `f32` buffers: a thin, bounds-checked layer over the
//! `gemm` crate (the one candle's matmul uses), with strided views so that no
//! operand is transposed or copied before a product.

/// A strided view of a row-major matrix for [`gemm`].
#[derive(Clone, Copy)]
pub(crate) struct Mat {
    rows: usize,
    cols: usize,
    row_stride: usize,
    col_stride: usize,
}

impl Mat {
    pub(crate) fn row_major(rows: usize, cols: usize, row_stride: usize) -> Self {
        Self {
            rows,
            cols,
            row_stride,
            col_stride: 1,
        }
    }

    pub(crate) fn transposed(self) -> Self {
        Self {
            rows: self.cols,
            cols: self.rows,
            row_stride: self.col_stride,
            col_stride: self.row_stride,
        }
    }

    /// One past the largest index the view touches.
    fn extent(&self) -> usize {
        if self.rows == 0 || self.cols == 0 {
            return 0;
        }
        (self.rows - 1) * self.row_stride + (self.cols - 1) * self.col_stride + 1
    }
}

/// `dst = lhs rhs`, or `dst += lhs rhs` with `accumulate`, on one thread.
pub(crate) fn gemm(
    dst: &mut [f32],
    d: Mat,
    lhs: &[f32],
    l: Mat,
    rhs: &[f32],
    r: Mat,
    accumulate: bool,
) {
    // SAFETY: `dst` is borrowed mutably for the call: nothing else reads or
    // writes it, and it overlaps neither operand.
    unsafe { gemm_raw((dst.as_mut_ptr(), dst.len()), d, lhs, l, rhs, r, accumulate) }
}

/// [`gemm`] on rayon's threads (for one large product, not inside parallel tasks).
pub(crate) fn gemm_par(
    dst: &mut [f32],
    d: Mat,
    lhs: &[f32],
    l: Mat,
    rhs: &[f32],
    r: Mat,
    accumulate: bool,
) {
    // SAFETY: as in `gemm`.
    unsafe {
        gemm_with(
            (dst.as_mut_ptr(), dst.len()),
            (d, lhs, l, rhs, r),
            accumulate,
            gemm::Parallelism::Rayon(0),
        )
    }
}

/// [`gemm`] into `len` values at a raw pointer.
///
/// # Safety
/// The elements the view `d` describes must be valid for writes and touched by
/// no one else during the call, and must not overlap `lhs` or `rhs`.
pub(crate) unsafe fn gemm_raw(
    dst: (*mut f32, usize),
    d: Mat,
    lhs: &[f32],
    l: Mat,
    rhs: &[f32],
    r: Mat,
    accumulate: bool,
) {
    // SAFETY: the caller's promise, passed on.
    unsafe {
        gemm_with(
            dst,
            (d, lhs, l, rhs, r),
            accumulate,
            gemm::Parallelism::None,
        )
    }
}

/// [`gemm_raw`] whose product may itself run on rayon's threads (`parallel`): for a
/// task of a parallel loop with fewer tasks than threads. Each element of `dst` is the
/// same sum, in the same order, either way (the product is split by blocks of `dst`).
///
/// # Safety
/// As [`gemm_raw`].
pub(crate) unsafe fn gemm_raw_maybe_par(
    dst: (*mut f32, usize),
    d: Mat,
    lhs: &[f32],
    l: Mat,
    rhs: &[f32],
    r: Mat,
    parallel: bool,
) {
    let parallelism = if parallel {
        gemm::Parallelism::Rayon(0)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: the caller's promise, passed on.
    unsafe { gemm_with(dst, (d, lhs, l, rhs, r), false, parallelism) }
}

/// The product with the given parallelism.
///
/// # Safety
/// As [`gemm_raw`].
unsafe fn gemm_with(
    (dst, len): (*mut f32, usize),
    (d, lhs, l, rhs, r): (Mat, &[f32], Mat, &[f32], Mat),
    accumulate: bool,
    parallelism: gemm::Parallelism,
) {
    assert!(
        l.rows == d.rows && r.cols == d.cols && l.cols == r.rows,
        "gemm shapes"
    );
    assert!(
        d.extent() <= len && l.extent() <= lhs.len() && r.extent() <= rhs.len(),
        "gemm bounds"
    );
    if d.rows == 0 || d.cols == 0 || (l.cols == 0 && accumulate) {
        return;
    }
    if l.cols == 0 {
        for i in 0..d.rows {
            for j in 0..d.cols {
                // SAFETY: inside the view (extent checked); exclusive (caller).
                unsafe { *dst.add(i * d.row_stride + j * d.col_stride) = 0.0 };
            }
        }
        return;
    }
    // SAFETY: the asserts above keep every index the views describe inside their
    // buffers; exclusivity and no overlap are the caller's promise.
    unsafe {
        gemm::gemm(
            d.rows,
            d.cols,
            l.cols,
            dst,
            d.col_stride as isize,
            d.row_stride as isize,
            accumulate,
            lhs.as_ptr(),
            l.col_stride as isize,
            l.row_stride as isize,
            rhs.as_ptr(),
            r.col_stride as isize,
            r.row_stride as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
}
