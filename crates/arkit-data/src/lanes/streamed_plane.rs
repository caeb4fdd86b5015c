//! `streamed_plane`: a plane of `f32` or `i64` written 64 bytes at a time with
//! streaming stores, in AVX-512 (the loader's batch planes: the normalised image, the
//! mask, the UV map). Tested through its users, at every alignment of the plane.

/// A plane of `f32` or `i64` written 64 bytes at a time, in order, with streaming
/// stores (which do not read the lines they fill first, where a plain store does): the
/// vectors pushed are realigned to the plane's 64-byte lines by one two-register permute
/// of their 32-bit lanes each, the part before the first line and after the last
/// written by masked plain stores. [`StreamedPlane::finish`] fences the streaming
/// stores (`_mm_sfence`: they are weakly ordered) before anything reads the plane.
pub(crate) struct StreamedPlane<'a, T> {
    plane: &'a mut [T],
    /// 32-bit lanes before the first 64-byte line (0 to 15).
    head: usize,
    /// `head..head + 16`: lanes `head..` of one vector, then `..head` of the next.
    shift: std::arch::x86_64::__m512i,
    /// The last vector pushed, and how many were.
    last: std::arch::x86_64::__m512i,
    pushed: usize,
}

impl<'a, T: Copy> StreamedPlane<'a, T> {
    /// A writer of `plane`, which holds a whole number of 64-byte vectors of `T`
    /// (4 or 8 bytes a value).
    #[target_feature(enable = "avx512f")]
    pub(crate) fn new(plane: &'a mut [T]) -> Self {
        use std::arch::x86_64::*;
        let size = std::mem::size_of::<T>();
        assert!(size == 4 || size == 8, "f32 or i64 lanes");
        assert_eq!(std::mem::size_of_val(plane) % 64, 0, "whole vectors");
        // A `T` of 4 or 8 bytes is at least 4-aligned, so whole 32-bit lanes.
        let head = (plane.as_ptr() as usize).wrapping_neg() % 64 / 4;
        StreamedPlane {
            plane,
            head,
            shift: _mm512_add_epi32(
                _mm512_set1_epi32(head as i32),
                _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15),
            ),
            last: _mm512_setzero_si512(),
            pushed: 0,
        }
    }

    /// Writes the plane's next 64 bytes.
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub(crate) fn push(&mut self, v: std::arch::x86_64::__m512i) {
        use std::arch::x86_64::*;
        let k = self.pushed;
        let lanes = std::mem::size_of_val(self.plane) / 4;
        assert!(16 * (k + 1) <= lanes, "no more than the plane holds");
        let p = self.plane.as_mut_ptr().cast::<i32>();
        // SAFETY: the first vector's lanes below `head` go to lanes `0..head` (masked
        // plain store); a later one completes the line at lane `head + 16 (k - 1)`,
        // which is 64-byte aligned and ends at `head + 16 k <= 16 k`, inside the plane.
        unsafe {
            if k == 0 {
                _mm512_mask_storeu_epi32(p, ((1u32 << self.head) - 1) as __mmask16, v);
            } else {
                let line = _mm512_permutex2var_epi32(self.last, self.shift, v);
                _mm512_stream_si512(p.add(self.head + 16 * (k - 1)).cast(), line);
            }
        }
        self.last = v;
        self.pushed = k + 1;
    }

    /// Writes what is left of the last vector (its lanes from `head`), plainly;
    /// checks that the plane was written whole; fences the streaming stores.
    #[target_feature(enable = "avx512f")]
    pub(crate) fn finish(self) {
        use std::arch::x86_64::*;
        assert_eq!(
            16 * self.pushed,
            std::mem::size_of_val(self.plane) / 4,
            "the whole plane"
        );
        if self.pushed == 0 {
            return;
        }
        let rest = _mm512_permutex2var_epi32(self.last, self.shift, _mm512_setzero_si512());
        let lanes = ((1u32 << (16 - self.head)) - 1) as __mmask16;
        let p = self.plane.as_mut_ptr().cast::<i32>();
        // SAFETY: lanes `head + 16 (pushed - 1) .. 16 pushed`, the plane's last.
        unsafe { _mm512_mask_storeu_epi32(p.add(self.head + 16 * (self.pushed - 1)), lanes, rest) };
        // Streaming stores are weakly ordered: fenced before anything reads the plane.
        _mm_sfence();
    }
}
