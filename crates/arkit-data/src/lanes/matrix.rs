//! The dense correspondence matrix's writer lanes ([`crate::loader::correspondence_matrix`]):
//! a mostly-zero matrix written in order, eight values at a time with streaming
//! (non-temporal) stores where the CPU has AVX ([`write_streaming`]), or plainly
//! ([`write_plain`], the definition beside it).

use super::{Level, level};

/// The definition: zeros, then the weights.
pub(crate) fn write_plain(out: &mut [f32], entries: &[(usize, f32)]) {
    out.fill(0.0);
    for &(at, w) in entries {
        out[at] = w;
    }
}

/// [`write_plain`]'s values written in order, eight at a time with streaming stores
/// over the 32-byte aligned body (each group of eight made in registers: zeros, or the
/// weights that fall in it), plainly before and after it.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn write_streaming(out: &mut [f32], entries: &[(usize, f32)]) {
    use std::arch::x86_64::*;
    let len = out.len();
    let head = out.as_ptr().align_offset(32).min(len);
    let body_end = head + (len - head) / 8 * 8;
    let mut next = 0;
    // The plain values of `range`: zeros and the entries in it.
    let plain = |out: &mut [f32], range: std::ops::Range<usize>, next: &mut usize| {
        out[range.clone()].fill(0.0);
        while *next < entries.len() && entries[*next].0 < range.end {
            out[entries[*next].0] = entries[*next].1;
            *next += 1;
        }
    };
    plain(out, 0..head, &mut next);
    let zeros = _mm256_setzero_ps();
    let base = out.as_mut_ptr();
    let mut at = head;
    while at < body_end {
        let group = if next < entries.len() && entries[next].0 < at + 8 {
            let mut g = [0f32; 8];
            while next < entries.len() && entries[next].0 < at + 8 {
                g[entries[next].0 - at] = entries[next].1;
                next += 1;
            }
            // SAFETY: `g` is eight floats.
            unsafe { _mm256_loadu_ps(g.as_ptr()) }
        } else {
            zeros
        };
        // SAFETY: `at..at + 8` is inside `out` (below `body_end <= len`) and `at` is
        // 32-byte aligned (`head` is, and `at` steps by eight floats).
        unsafe { _mm256_stream_ps(base.add(at), group) };
        at += 8;
    }
    // Streaming stores are weakly ordered: fenced before anything else reads `out`.
    _mm_sfence();
    plain(out, body_end..len, &mut next);
    debug_assert_eq!(next, entries.len());
}

/// Writes `out` as [`write_plain`] does (zeros, then `entries`: increasing positions,
/// one each, inside `out`), with streaming stores at the workspace's SIMD level
/// ([`write_streamed_at`]).
pub(crate) fn write_streamed(out: &mut [f32], entries: &[(usize, f32)]) {
    write_streamed_at(level(), out, entries)
}

/// [`write_streamed`] at `level` (lowered to the CPU's): from [`Level::Avx2`] up (which
/// includes AVX) [`write_streaming`], else [`write_plain`]. The same values either way
/// (tested).
pub(crate) fn write_streamed_at(level: Level, out: &mut [f32], entries: &[(usize, f32)]) {
    #[cfg(target_arch = "x86_64")]
    if level.supported() >= Level::Avx2 {
        // SAFETY: the CPU has AVX (part of `Level::Avx2`).
        unsafe { write_streaming(out, entries) };
        return;
    }
    let _ = level;
    write_plain(out, entries);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streaming_writes_the_plain_values_at_every_level_length_and_alignment() {
        // Lengths 0 to 40 (below, at and around the eight-float groups) and a few
        // larger ones, at every float offset from a 32-byte boundary, over old values
        // that are not zero, with random entries (negative zeros among the weights):
        // bit for bit the definition at every level the CPU has.
        let mut r = arkit_core::Rng::new(5);
        let mut backing = vec![0f32; 1100];
        for len in (0..=40).chain([63, 64, 65, 1000, 1061]) {
            let mut entries: Vec<(usize, f32)> = Vec::new();
            for at in 0..len {
                if r.below(5) == 0 {
                    let w = if r.below(9) == 0 {
                        -0.0
                    } else {
                        r.uniform(-1.0, 1.0) as f32
                    };
                    entries.push((at, w));
                }
            }
            let mut want = vec![f32::NAN; len];
            write_plain(&mut want, &entries);
            for level in super::super::available() {
                for shift in 0..8 {
                    backing.fill(f32::NAN);
                    let out = &mut backing[shift..shift + len];
                    write_streamed_at(level, out, &entries);
                    assert!(
                        out.iter()
                            .zip(&want)
                            .all(|(a, b)| a.to_bits() == b.to_bits()),
                        "{level}: {len} values at +{shift}"
                    );
                }
            }
        }
    }
}
