//! The parsers of option values the subcommands share (`--jobs`, `--shard`, shares,
//! angles, pixel thresholds, rates), each naming the range it accepts.

use arkit_core::Result;

/// Parses `WxH` (each side 32..=8192 pixels, as `synth` draws them).
pub(super) fn parse_size(s: &str) -> std::result::Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("'{s}' is not WIDTHxHEIGHT (for example 800x800)"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| format!("'{v}' in '{s}' is not a whole number of pixels"))
    };
    let (w, h) = (parse(w)?, parse(h)?);
    if !(32..=8192).contains(&w) || !(32..=8192).contains(&h) {
        return Err(format!("{w}x{h} is outside 32..8192 pixels a side"));
    }
    Ok((w, h))
}

/// Parses `--shard I/N` (0 <= I < N, N <= 100000).
pub(super) fn parse_shard(s: &str) -> std::result::Result<(usize, usize), String> {
    let (i, n) = s
        .split_once('/')
        .ok_or_else(|| format!("'{s}' is not I/N (for example 0/8)"))?;
    let (i, n): (usize, usize) = (
        i.trim()
            .parse()
            .map_err(|_| format!("'{i}' is not a number"))?,
        n.trim()
            .parse()
            .map_err(|_| format!("'{n}' is not a number"))?,
    );
    if n == 0 || i >= n {
        return Err(format!("shard {i}/{n}: need 0 <= I < N"));
    }
    if n > 100_000 {
        return Err(format!("shard {i}/{n}: N is at most 100000"));
    }
    Ok((i, n))
}

/// A float in a range, for options: `lo`/`hi` with whether each end is included.
/// The error names the range (clap adds the option's name and value).
pub(super) fn float_in(s: &str, lo: f64, lo_in: bool, hi: f64, hi_in: bool) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("'{s}' is not a number"))?;
    let above = if lo_in { v >= lo } else { v > lo };
    let below = if hi_in { v <= hi } else { v < hi };
    if v.is_finite() && above && below {
        Ok(v)
    } else {
        Err(format!(
            "must be in {}{lo}, {hi}{}",
            if lo_in { '[' } else { '(' },
            if hi_in { ']' } else { ')' }
        ))
    }
}

/// A share in [0, 1] (`--lr-hold`, `--test-fraction`, `--colour-jitter`).
pub(super) fn unit_interval(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, true, 1.0, true)
}

/// A share in [0, 1) (`--outliers`: some points must stay).
pub(super) fn unit_interval_open(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, true, 1.0, false)
}

/// A share strictly inside (0, 1) (`split --test-fraction`: both sides non-empty).
pub(super) fn open_unit_interval(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, false, 1.0, false)
}

/// A learning rate in (0, 1].
#[cfg(feature = "model")]
pub(super) fn learning_rate(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, false, 1.0, true)
}

/// An angle in degrees in (0, 90] (`augment --max-angle`, `--min-change`, `--max-change`).
pub(super) fn degrees_up_to_90(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, false, 90.0, true)
}

/// A pixel noise level in [0, 100].
pub(super) fn noise_px(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, true, 100.0, true)
}

/// A pixel threshold in (0, 1000].
pub(super) fn threshold_px(s: &str) -> Result<f64, String> {
    float_in(s, 0.0, false, 1000.0, true)
}

/// `--jobs`: 1..=1024 worker threads.
pub(super) fn jobs(s: &str) -> Result<usize, String> {
    let n: usize = s
        .trim()
        .parse()
        .map_err(|_| format!("'{s}' is not a whole number"))?;
    if (1..=1024).contains(&n) {
        Ok(n)
    } else {
        Err("must be in 1..=1024 (leave --jobs out for all cores)".into())
    }
}

/// Frames a second in (0, 1000] (`--fps`).
pub(super) fn frame_rate(s: &str) -> std::result::Result<f64, String> {
    float_in(s, 0.0, false, 1000.0, true)
}

/// A One-Euro cutoff in (0, 1000] Hz.
pub(super) fn cutoff_hz(s: &str) -> std::result::Result<f64, String> {
    float_in(s, 0.0, false, 1000.0, true)
}

/// A One-Euro beta in [0, 1000].
pub(super) fn smoothing_beta(s: &str) -> std::result::Result<f64, String> {
    float_in(s, 0.0, true, 1000.0, true)
}
