//! Timing shared by the benches that time a closure (`mod timing;` in each).

use std::time::Instant;

/// The median wall-clock time of `n` calls of `f`, in milliseconds.
pub fn median_ms(mut f: impl FnMut(), n: usize) -> f64 {
    let mut t: Vec<f64> = (0..n)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[n / 2]
}
