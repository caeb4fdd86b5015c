//! `lanes`: the one place that decides which SIMD instructions the workspace uses. The
//! core crate's lane kernels (the rasterizers') are in `raster::lanes`, each beside its
//! scalar definition, as tiny-skia's `wide`; the pipeline's are in arkit-data's `lanes`.
//!
//! The [`Level`] is detected once from the CPU and capped by the environment variable
//! `ARKIT_SIMD` (read once, at the first dispatch):
//!
//! - `auto` (or unset, or empty): the highest level the CPU has;
//! - `avx512`, `avx2`, `scalar`: at most that level (never above the CPU's: `avx512` on a
//!   CPU without AVX-512 runs AVX2).
//!
//! Any other value prints a warning naming `ARKIT_SIMD` and its accepted values on stderr
//! and runs `auto`: a typo never stops a training run, and the results are the same
//! at every level (bit for bit: each kernel computes exactly its scalar definition).
//!
//! Every SIMD dispatch in the workspace asks [`level`] (or [`avx512_vbmi`]); no other
//! code detects CPU features. Builds for other architectures than x86-64 run the scalar
//! definitions.

use std::sync::OnceLock;

/// The environment variable that caps the SIMD level.
pub const ENV: &str = "ARKIT_SIMD";

/// A set of SIMD instructions the kernels may use, in increasing order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Level {
    /// No SIMD beyond the target's baseline (SSE2 on x86-64): the scalar definitions,
    /// and the kernels written in SSE2 alone.
    Scalar,
    /// AVX, AVX2 and FMA (Haswell, 2013, and later; AMD Zen).
    Avx2,
    /// [`Level::Avx2`] and AVX-512 F, VL, DQ and BW (Skylake-SP, 2017, and later; AMD
    /// Zen 4). The byte permutes of AVX-512 VBMI are used when the CPU has them too
    /// ([`avx512_vbmi`]).
    Avx512,
}

impl Level {
    /// Every level, lowest first.
    pub const ALL: [Level; 3] = [Level::Scalar, Level::Avx2, Level::Avx512];

    /// The value of `ARKIT_SIMD` that caps at this level.
    pub fn name(self) -> &'static str {
        match self {
            Level::Scalar => "scalar",
            Level::Avx2 => "avx2",
            Level::Avx512 => "avx512",
        }
    }

    /// This level, lowered to the highest one the CPU has: what a kernel asked to run at
    /// `self` may safely run at.
    pub fn supported(self) -> Level {
        self.min(cpu().level)
    }
}

impl std::fmt::Display for Level {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// What the CPU has, detected once.
#[derive(Clone, Copy, Debug)]
struct Cpu {
    level: Level,
    vbmi: bool,
}

fn cpu() -> Cpu {
    static CPU: OnceLock<Cpu> = OnceLock::new();
    *CPU.get_or_init(detect)
}

#[cfg(target_arch = "x86_64")]
fn detect() -> Cpu {
    use std::arch::is_x86_feature_detected as has;
    let avx2 = has!("avx") && has!("avx2") && has!("fma");
    let avx512 =
        avx2 && has!("avx512f") && has!("avx512vl") && has!("avx512dq") && has!("avx512bw");
    let level = match (avx2, avx512) {
        (_, true) => Level::Avx512,
        (true, false) => Level::Avx2,
        _ => Level::Scalar,
    };
    Cpu {
        level,
        vbmi: avx512 && has!("avx512vbmi"),
    }
}

#[cfg(not(target_arch = "x86_64"))]
fn detect() -> Cpu {
    Cpu {
        level: Level::Scalar,
        vbmi: false,
    }
}

/// The value of `ARKIT_SIMD`: `Ok(None)` for `auto`, unset or empty; `Ok(Some(cap))` for
/// a level's name (case and surrounding spaces ignored); `Err` with a message naming the
/// variable and its accepted values otherwise.
pub fn parse_cap(value: Option<&str>) -> Result<Option<Level>, String> {
    let Some(value) = value else { return Ok(None) };
    let v = value.trim().to_ascii_lowercase();
    if v.is_empty() || v == "auto" {
        return Ok(None);
    }
    Level::ALL
        .into_iter()
        .find(|l| l.name() == v)
        .map(Some)
        .ok_or_else(|| format!("{ENV}={value:?}: expected one of scalar, avx2, avx512 or auto"))
}

/// The highest level the CPU has, whatever `ARKIT_SIMD` says.
pub fn detected() -> Level {
    cpu().level
}

/// The level every SIMD dispatch uses: [`detected`], capped by `ARKIT_SIMD`. Decided once
/// per process.
pub fn level() -> Level {
    static LEVEL: OnceLock<Level> = OnceLock::new();
    *LEVEL.get_or_init(|| {
        let value = std::env::var(ENV).ok();
        let cap = parse_cap(value.as_deref()).unwrap_or_else(|message| {
            eprintln!("warning: {message}; using auto");
            None
        });
        cap.map_or(detected(), Level::supported)
    })
}

/// Whether the kernels may use AVX-512 VBMI's byte permutes: [`level`] is
/// [`Level::Avx512`] and the CPU has VBMI.
pub fn avx512_vbmi() -> bool {
    level() == Level::Avx512 && cpu().vbmi
}

/// Whether the CPU has AVX-512 VBMI beside [`Level::Avx512`], whatever `ARKIT_SIMD` says:
/// for tests that run a VBMI kernel directly.
pub fn detected_avx512_vbmi() -> bool {
    cpu().level == Level::Avx512 && cpu().vbmi
}

/// The levels this CPU can run, lowest first: what a test compares each kernel at.
pub fn available() -> impl Iterator<Item = Level> {
    Level::ALL.into_iter().filter(|l| *l <= detected())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_variable_parses_every_level_and_auto() {
        assert_eq!(parse_cap(None), Ok(None));
        assert_eq!(parse_cap(Some("")), Ok(None));
        assert_eq!(parse_cap(Some(" Auto ")), Ok(None));
        assert_eq!(parse_cap(Some("scalar")), Ok(Some(Level::Scalar)));
        assert_eq!(parse_cap(Some("AVX2")), Ok(Some(Level::Avx2)));
        assert_eq!(parse_cap(Some("avx512")), Ok(Some(Level::Avx512)));
        let e = parse_cap(Some("sse4")).unwrap_err();
        assert!(e.contains("ARKIT_SIMD") && e.contains("\"sse4\""), "{e}");
        assert!(e.contains("scalar, avx2, avx512 or auto"), "{e}");
    }

    #[test]
    fn a_cap_never_raises_above_the_cpu() {
        for l in Level::ALL {
            assert!(l.supported() <= detected());
            assert_eq!(l.supported(), l.min(detected()));
        }
        assert!(level() <= detected());
        assert_eq!(available().last(), Some(detected()));
        assert_eq!(available().next(), Some(Level::Scalar));
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn detection_agrees_with_the_features() {
        use std::arch::is_x86_feature_detected as has;
        assert_eq!(
            detected() >= Level::Avx2,
            has!("avx") && has!("avx2") && has!("fma")
        );
        assert_eq!(
            detected() == Level::Avx512,
            has!("avx2")
                && has!("fma")
                && has!("avx512f")
                && has!("avx512vl")
                && has!("avx512dq")
                && has!("avx512bw")
        );
        assert_eq!(
            detected_avx512_vbmi(),
            detected() == Level::Avx512 && has!("avx512vbmi")
        );
    }
}
