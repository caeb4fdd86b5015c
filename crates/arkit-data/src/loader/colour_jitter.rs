//! `colour_jitter`: torchvision's `ColorJitter(0.3, 0.3, 0.2, 0.01)` (the official
//! loader's training augmentation) on an interleaved RGB crop, byte for byte as PIL
//! computes it: brightness, contrast, saturation and hue in a drawn order, each rounded
//! back to bytes. The one colour jitter of the workspace: the loader (the Python
//! package's) draws it in the official ranges, `train` in ranges of its
//! `--colour-jitter` strength ([`ColourJitterRanges::of_strength`]; the official ones
//! by default).
//!
//! Invariants: every operation gives the bytes of its textbook definition (PIL's
//! enhancers, the HSV hue rotation with `f32` arithmetic and `round`); the fast paths
//! (byte tables, library-free roundings, SSE2 and AVX2 lanes) do the same operations
//! and give the same bits. Tested below: each operation against values derived by hand,
//! the scalar hue path against the textbook conversion, and each lane path (SSE2, AVX2
//! where the CPU has it) against the scalar path on every one of the 2^24 RGB triples.

use crate::lanes::jitter::{blend_bytes, luma_sum, saturate_all, shift_hue_all};
use arkit_core::Rng;

/// torchvision's `ColorJitter(0.3, 0.3, 0.2, 0.01)`: brightness, contrast and saturation
/// factors uniform in [0.7, 1.3], [0.7, 1.3], [0.8, 1.2], a hue shift uniform in
/// [-0.01, 0.01] of a turn, applied in a random order ([`ColourJitter::apply`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColourJitter {
    /// Brightness factor (1: unchanged).
    pub brightness: f32,
    /// Contrast factor.
    pub contrast: f32,
    /// Saturation factor.
    pub saturation: f32,
    /// Hue shift in turns.
    pub hue: f32,
    /// The order of the four operations (0 brightness, 1 contrast, 2 saturation, 3 hue).
    pub order: [usize; 4],
}

/// The ranges a [`ColourJitter`] is drawn from: torchvision's `ColorJitter(b, c, s, h)`
/// draws its brightness, contrast and saturation factors uniform in `[1-b, 1+b]`,
/// `[1-c, 1+c]`, `[1-s, 1+s]` and its hue shift in `[-h, h]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColourJitterRanges {
    /// Brightness factor range.
    pub brightness: (f64, f64),
    /// Contrast factor range.
    pub contrast: (f64, f64),
    /// Saturation factor range.
    pub saturation: (f64, f64),
    /// Hue shift range, turns.
    pub hue: (f64, f64),
}

impl ColourJitterRanges {
    /// The official loader's `ColorJitter(0.3, 0.3, 0.2, 0.01)`.
    pub const OFFICIAL: ColourJitterRanges = ColourJitterRanges {
        brightness: (0.7, 1.3),
        contrast: (0.7, 1.3),
        saturation: (0.8, 1.2),
        hue: (-0.01, 0.01),
    };

    /// `ColorJitter(c, c, 2c/3, c/30)`: the official ranges scaled to strength `c`
    /// (`train --colour-jitter c`). At `c = 0.3` (as `f32`) they are
    /// [`ColourJitterRanges::OFFICIAL`] exactly, so the same generator state draws the
    /// same jitter as the loader's.
    pub fn of_strength(c: f32) -> Self {
        if c == 0.3 {
            return Self::OFFICIAL;
        }
        let c = c as f64;
        let around_one = |r: f64| (1.0 - r, 1.0 + r);
        ColourJitterRanges {
            brightness: around_one(c),
            contrast: around_one(c),
            saturation: around_one(c * 2.0 / 3.0),
            hue: (-c / 30.0, c / 30.0),
        }
    }
}

impl ColourJitter {
    /// One draw from `rng` in the official ranges ([`ColourJitterRanges::OFFICIAL`]).
    pub fn draw(rng: &mut Rng) -> Self {
        Self::draw_in(rng, &ColourJitterRanges::OFFICIAL)
    }

    /// One draw from `rng` in `ranges`: brightness, contrast, saturation, hue, then the
    /// order of the four operations.
    pub fn draw_in(rng: &mut Rng, ranges: &ColourJitterRanges) -> Self {
        let mut uniform = |(lo, hi): (f64, f64)| rng.uniform(lo, hi) as f32;
        let brightness = uniform(ranges.brightness);
        let contrast = uniform(ranges.contrast);
        let saturation = uniform(ranges.saturation);
        let hue = uniform(ranges.hue);
        let mut order = [0usize, 1, 2, 3];
        for k in (1..4).rev() {
            order.swap(k, rng.below(k as u64 + 1) as usize);
        }
        ColourJitter {
            brightness,
            contrast,
            saturation,
            hue,
            order,
        }
    }

    /// Applies the jitter to an interleaved RGB image, each operation rounded back to
    /// bytes as PIL does between operations. Brightness blends with black, contrast with
    /// the grey of the image's mean luma (ITU-R 601 integer luma, as PIL's `L`),
    /// saturation with each pixel's luma; the hue shift rotates the HSV hue.
    ///
    /// Brightness and contrast map each byte alone (`blend_bytes`: 32 bytes at a time
    /// where the CPU has AVX2, else a 256-entry table of the same formula); every
    /// rounding is `round_half_away`, `f32::round`'s values without its library call.
    /// Saturation and hue run eight pixels at a time where the CPU has AVX2
    /// (`saturate_all`, `shift_hue_all`).
    pub fn apply(&self, rgb: &mut [u8]) {
        for op in self.order {
            match op {
                0 => blend_bytes(rgb, 0.0, self.brightness),
                1 => {
                    let n = (rgb.len() / 3).max(1) as f64;
                    // An integer sum: the same value as summing the lumas in f64 (every
                    // partial sum is an integer below 2^53), without its latency chain.
                    let sum = luma_sum(rgb);
                    let grey = (sum as f64 / n + 0.5).floor() as f32;
                    blend_bytes(rgb, grey, self.contrast);
                }
                2 => saturate_all(rgb, self.saturation),
                _ => {
                    if self.hue != 0.0 {
                        shift_hue_all(rgb, self.hue)
                    }
                }
            }
        }
    }
}

/// [`ColourJitter::draw`] then [`ColourJitter::apply`].
pub fn jitter_colour(rgb: &mut [u8], rng: &mut Rng) {
    ColourJitter::draw(rng).apply(rgb)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lanes::jitter::*;
    use crate::lanes::{Level, available};

    #[test]
    fn colour_jitter_operations_match_their_definitions() {
        let pixels = [200u8, 100, 50, 10, 20, 30];
        let none = ColourJitter {
            brightness: 1.0,
            contrast: 1.0,
            saturation: 1.0,
            hue: 0.0,
            order: [0, 1, 2, 3],
        };
        let mut p = pixels;
        none.apply(&mut p);
        assert_eq!(p, pixels);
        let mut p = pixels;
        ColourJitter {
            brightness: 0.5,
            ..none
        }
        .apply(&mut p);
        assert_eq!(p, [100, 50, 25, 5, 10, 15]);
        // Saturation 0: each pixel its integer luma (299 R + 587 G + 114 B) / 1000.
        let mut p = pixels;
        ColourJitter {
            saturation: 0.0,
            ..none
        }
        .apply(&mut p);
        let l0 = (200 * 299 + 100 * 587 + 50 * 114) / 1000;
        let l1 = (10 * 299 + 20 * 587 + 30 * 114) / 1000;
        assert_eq!(p, [l0, l0, l0, l1, l1, l1].map(|v| v as u8));
        // Contrast 0: every value the rounded mean luma.
        let mut p = pixels;
        ColourJitter {
            contrast: 0.0,
            ..none
        }
        .apply(&mut p);
        let mean = ((l0 + l1) as f64 / 2.0 + 0.5).floor() as u8;
        assert_eq!(p, [mean; 6]);
        // A third of a turn takes pure red to pure green.
        let mut p = [255u8, 0, 0];
        ColourJitter {
            hue: 1.0 / 3.0,
            ..none
        }
        .apply(&mut p);
        assert_eq!(p, [0, 255, 0]);
    }

    /// The HSV hue rotation as the textbook writes it, with the library's roundings.
    fn shift_hue_reference(p: &mut [u8], h: f32) {
        let [r, g, b] = [p[0], p[1], p[2]].map(|v| v as f32 / 255.0);
        let max = r.max(g).max(b);
        let min = r.min(g).min(b);
        let d = max - min;
        if d == 0.0 {
            return;
        }
        let hue = if max == r {
            ((g - b) / d).rem_euclid(6.0)
        } else if max == g {
            (b - r) / d + 2.0
        } else {
            (r - g) / d + 4.0
        } / 6.0;
        let hue = (hue + h).rem_euclid(1.0);
        let (sat, val) = (d / max, max);
        let i = (hue * 6.0).floor();
        let f = hue * 6.0 - i;
        let (pp, q, t) = (
            val * (1.0 - sat),
            val * (1.0 - sat * f),
            val * (1.0 - sat * (1.0 - f)),
        );
        let (r, g, b) = match i as i32 % 6 {
            0 => (val, t, pp),
            1 => (q, val, pp),
            2 => (pp, val, t),
            3 => (pp, q, val),
            4 => (t, pp, val),
            _ => (val, pp, q),
        };
        for (o, v) in p.iter_mut().zip([r, g, b]) {
            *o = (v * 255.0).round().clamp(0.0, 255.0) as u8;
        }
    }

    #[test]
    fn the_hue_rotation_gives_the_textbook_bytes() {
        let mut rng = Rng::new(8);
        for k in 0..300_000 {
            let p: [u8; 3] = if k < 4096 {
                // Every corner-ish and grey case: channels from a coarse grid.
                [
                    (k % 16 * 17) as u8,
                    (k / 16 % 16 * 17) as u8,
                    (k / 256 * 17) as u8,
                ]
            } else {
                [0; 3].map(|_| rng.below(256) as u8)
            };
            let h = match k % 4 {
                0 => rng.uniform(-0.01, 0.01) as f32,
                1 => rng.uniform(-0.5, 0.5) as f32,
                2 => 1.0 / 3.0,
                _ => -0.01,
            };
            let (mut a, mut b) = (p, p);
            shift_hue(&mut a, h);
            shift_hue_reference(&mut b, h);
            assert_eq!(a, b, "{p:?} {h}");
        }
        // The coarse grid (greys, ties between channels) through the lanes.
        let grid: Vec<u8> = (0..4096)
            .flat_map(|k| [k % 16 * 17, k / 16 % 16 * 17, k / 256 * 17].map(|v| v as u8))
            .collect();
        for h in [0.01f32, -0.01, 1.0 / 3.0, -0.5] {
            let (mut a, mut b) = (grid.clone(), grid.clone());
            shift_hue_all(&mut a, h);
            b.chunks_exact_mut(3)
                .for_each(|p| shift_hue_reference(p, h));
            assert_eq!(a, b, "grid, hue {h}");
        }
        // Whole images through the lanes (and the remainder), against pixel by pixel.
        for n in [1usize, 7, 8, 9, 64, 1001] {
            let h = rng.uniform(-0.02, 0.02) as f32;
            let img: Vec<u8> = (0..3 * n).map(|_| rng.below(256) as u8).collect();
            let (mut a, mut b) = (img.clone(), img);
            shift_hue_all(&mut a, h);
            b.chunks_exact_mut(3)
                .for_each(|p| shift_hue_reference(p, h));
            assert_eq!(a, b, "{n} pixels");
        }
    }

    #[test]
    fn the_fast_roundings_equal_the_library_ones() {
        let mut rng = Rng::new(3);
        let mut values: Vec<f32> = vec![0.0, -0.0, 0.5, -0.5, 1.5, 2.5, -2.5, 254.5, 255.49998];
        values.push(0.5f32.next_down()); // 0.49999997: rounds to 0, though + 0.5 gives 1
        values.push((-0.5f32).next_up());
        for _ in 0..200_000 {
            values.push(rng.uniform(-400.0, 700.0) as f32);
            let k = rng.below(512) as f32;
            values.push(k + 0.5);
            values.push(-k - 0.5);
        }
        for v in values {
            assert_eq!(round_half_away(v).to_bits(), v.round().to_bits(), "{v}");
        }
        for _ in 0..200_000 {
            let x = rng.uniform(-1.0, 2.0) as f32;
            assert_eq!(
                wrap_once(x, 1.0).to_bits(),
                x.rem_euclid(1.0).to_bits(),
                "{x}"
            );
            let y = rng.uniform(-6.0, 12.0) as f32;
            assert_eq!(
                wrap_once(y, 6.0).to_bits(),
                y.rem_euclid(6.0).to_bits(),
                "{y}"
            );
        }
    }

    #[test]
    fn strength_ranges_are_the_official_ones_scaled() {
        assert_eq!(
            ColourJitterRanges::of_strength(0.3),
            ColourJitterRanges::OFFICIAL
        );
        // The same generator state, the same draw as the loader's.
        assert_eq!(
            ColourJitter::draw_in(&mut Rng::new(4), &ColourJitterRanges::of_strength(0.3)),
            ColourJitter::draw(&mut Rng::new(4))
        );
        let r = ColourJitterRanges::of_strength(0.15);
        let c = 0.15f32 as f64;
        assert_eq!(r.brightness, (1.0 - c, 1.0 + c));
        assert_eq!(r.contrast, (1.0 - c, 1.0 + c));
        assert!((r.saturation.1 - 1.1).abs() < 1e-7 && (r.hue.1 - 0.005).abs() < 1e-8);
        // Strength 0: every factor 1 and no hue shift, so the bytes are unchanged.
        let zero = ColourJitter::draw_in(&mut Rng::new(9), &ColourJitterRanges::of_strength(0.0));
        let pixels = [200u8, 100, 50, 10, 20, 30, 0, 255, 128];
        let mut p = pixels;
        zero.apply(&mut p);
        assert_eq!(p, pixels);
    }

    #[test]
    fn colour_jitter_draws_stay_in_torchvision_ranges() {
        let mut rng = Rng::new(5);
        for _ in 0..1000 {
            let j = ColourJitter::draw(&mut rng);
            assert!((0.7..1.3).contains(&j.brightness) && (0.7..1.3).contains(&j.contrast));
            assert!((0.8..1.2).contains(&j.saturation) && (-0.01..0.01).contains(&j.hue));
            let mut o = j.order;
            o.sort();
            assert_eq!(o, [0, 1, 2, 3]);
        }
    }

    #[test]
    fn the_luma_sum_lanes_give_the_integer_sum() {
        // The lanes' multiply and shifts are the integer division on every weighted
        // sum, and no product passes 2^31.
        for s in 0..=255_000u32 {
            let product = (s >> 3) * LUMA_BY_125 as u32;
            assert!(product < 1 << 31, "{s}");
            assert_eq!(product >> 22, s / 1000, "{s}");
        }
        // The lanes themselves, on pixels whose sums run over the whole range.
        #[cfg(target_arch = "x86_64")]
        if arkit_core::lanes::detected() >= Level::Avx2 {
            use crate::lanes::rgb::load_rgb8;
            let mut rng = Rng::new(29);
            let mut px: Vec<u8> = (0..65_536 * 3).map(|_| rng.below(256) as u8).collect();
            px.extend([255u8; 24].iter().chain(&[0u8; 24]));
            for group in px.chunks_exact(24) {
                let group: &[u8; 24] = group.try_into().unwrap();
                let mut out = [0u32; 8];
                // SAFETY: the CPU has AVX2; a store of eight u32 into `out`.
                unsafe {
                    let lanes = luma_lanes(load_rgb8(group));
                    std::arch::x86_64::_mm256_storeu_si256(out.as_mut_ptr().cast(), lanes);
                }
                for (k, p) in group.chunks_exact(3).enumerate() {
                    assert_eq!(out[k], luma(p), "pixel {p:?}");
                }
            }
        }
        // Images of any length, lanes and remainder, against pixel by pixel.
        let mut rng = Rng::new(23);
        for n in (0..=40).chain([100, 65_536 + 13]) {
            let img: Vec<u8> = (0..3 * n).map(|_| rng.below(256) as u8).collect();
            let plain: u64 = img.chunks_exact(3).map(|p| luma(p) as u64).sum();
            assert_eq!(luma_sum(&img), plain, "{n} pixels");
            for level in available() {
                assert_eq!(luma_sum_at(level, &img), plain, "{level}: {n} pixels");
            }
        }
        let white = vec![255u8; 3 * 70_000];
        assert_eq!(luma_sum(&white), 255 * 70_000);
    }

    #[test]
    fn the_byte_blend_lanes_give_blends_bytes_for_every_byte() {
        let mut rng = Rng::new(21);
        // Every byte value in several places of the 32-byte groups, then a remainder.
        let bytes: Vec<u8> = (0..256 * 5 + 17).map(|k| (k * 7 % 256) as u8).collect();
        let mut factors = vec![(0.0f32, 0.7f32), (0.0, 1.3), (128.0, 0.0), (0.0, 1.0)];
        factors.extend([(255.0, 1.3), (0.0, 0.5), (3.0, 1.2999)]);
        for _ in 0..200 {
            factors.push((rng.below(256) as f32, rng.uniform(0.0, 2.0) as f32));
        }
        for (grey, f) in factors {
            let mut fast = bytes.clone();
            blend_bytes(&mut fast, grey, f);
            let by_formula: Vec<u8> = bytes.iter().map(|&v| blend(v as f32, grey, f)).collect();
            assert_eq!(fast, by_formula, "grey {grey}, factor {f}");
            // Each level the CPU has on its own (AVX-512 with and without VBMI),
            // whichever `blend_bytes` took, on every length up to 70 bytes too.
            for level in available() {
                for vbmi in [false, true] {
                    let mut lanes = bytes.clone();
                    blend_bytes_at(level, vbmi, &mut lanes, grey, f);
                    assert_eq!(lanes, by_formula, "{level} {vbmi}, grey {grey}, factor {f}");
                    for n in 0..=70 {
                        let mut lanes = bytes[..n].to_vec();
                        blend_bytes_at(level, vbmi, &mut lanes, grey, f);
                        assert_eq!(lanes, by_formula[..n], "{level} {vbmi}: {n} bytes");
                    }
                }
            }
        }
        // Brightness 0.5 by hand: 200 -> 100, 3 -> 1.5 -> 2 (halves away from zero).
        let mut p = [200u8; 40];
        p[33] = 3;
        blend_bytes(&mut p, 0.0, 0.5);
        assert_eq!((p[0], p[31], p[32], p[33]), (100, 100, 100, 2));
    }

    /// Every RGB triple, interleaved.
    fn every_triple() -> Vec<u8> {
        (0..1u32 << 24)
            .flat_map(|k| [(k >> 16) as u8, (k >> 8) as u8, k as u8])
            .collect()
    }

    #[test]
    fn the_hue_lanes_give_the_scalar_bytes_for_every_triple() {
        let all = every_triple();
        for h in [0.0093f32, -0.01, 0.5] {
            let mut scalar = all.clone();
            scalar.chunks_exact_mut(3).for_each(|p| shift_hue(p, h));
            // Every level the CPU has (SSE2 at `Scalar` on x86-64, then AVX2, then
            // AVX-512), each called directly; then every length up to 40 pixels
            // (the groups of sixteen, eight and four and their tails) from the
            // triples.
            for level in available() {
                let mut lanes = all.clone();
                shift_hue_all_at(level, &mut lanes, h);
                assert!(lanes == scalar, "{level}, hue {h}");
                for n in 0..=40 {
                    let at = 3 * (n * 40_503 % (1 << 24) / 3 * 3);
                    let mut lanes = all[at..at + 3 * n].to_vec();
                    shift_hue_all_at(level, &mut lanes, h);
                    assert!(
                        lanes == scalar[at..at + 3 * n],
                        "{level}, {n} pixels, hue {h}"
                    );
                }
            }
            if arkit_core::lanes::detected() < Level::Avx512 {
                eprintln!("SKIPPED: AVX-512 hue lanes (this CPU has no AVX-512)");
            }
            let mut dispatched = all.clone();
            shift_hue_all(&mut dispatched, h);
            assert!(dispatched == scalar, "shift_hue_all, hue {h}");
        }
    }

    #[test]
    fn the_saturation_lanes_give_the_scalar_bytes_for_every_triple() {
        let all = every_triple();
        for f in [0.8f32, 1.1999, 0.0, 1.0] {
            let mut scalar = all.clone();
            scalar.chunks_exact_mut(3).for_each(|p| saturate(p, f));
            for level in available() {
                let mut lanes = all.clone();
                saturate_all_at(level, &mut lanes, f);
                assert!(lanes == scalar, "{level}, factor {f}");
            }
            if arkit_core::lanes::detected() < Level::Avx2 {
                eprintln!("SKIPPED: AVX2 saturation lanes (this CPU has no AVX2)");
            }
            let mut dispatched = all.clone();
            saturate_all(&mut dispatched, f);
            assert!(dispatched == scalar, "saturate_all, factor {f}");
        }
        // The scalar path is PIL's blend with the integer luma, derived by hand.
        let mut p = [200u8, 100, 50];
        saturate(&mut p, 1.2);
        let l = (200 * 299 + 100 * 587 + 50 * 114) / 1000; // 123
        let by_hand = [200, 100, 50]
            .map(|v: i32| (l as f32 + 1.2 * (v - l) as f32).round().clamp(0.0, 255.0) as u8);
        assert_eq!(p, by_hand);
        assert_eq!(by_hand, [215, 95, 35]);
        // Images of any length: lanes and remainder.
        let mut rng = Rng::new(11);
        for n in (0..=40).chain([1001]) {
            let img: Vec<u8> = (0..3 * n).map(|_| rng.below(256) as u8).collect();
            let mut b = img.clone();
            b.chunks_exact_mut(3).for_each(|p| saturate(p, 0.9));
            for level in available() {
                let mut a = img.clone();
                saturate_all_at(level, &mut a, 0.9);
                assert_eq!(a, b, "{level}: {n} pixels");
            }
            let mut a = img;
            saturate_all(&mut a, 0.9);
            assert_eq!(a, b, "{n} pixels");
        }
    }
}
