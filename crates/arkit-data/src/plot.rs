//! Small PNG charts (histograms) for people to look at, with a built-in 5x7 pixel font
//! so no font files or plotting libraries are needed.

use image::{Rgb, RgbImage};

/// A histogram over `[lo, hi)` with equal-width bins.
#[derive(Clone, Debug, PartialEq)]
pub struct Histogram {
    /// Left edge of the first bin.
    pub lo: f64,
    /// Right edge of the last bin.
    pub hi: f64,
    /// Counts per bin.
    pub counts: Vec<usize>,
    /// Values outside `[lo, hi)`.
    pub outside: usize,
}

impl Histogram {
    /// Counts `values` into `bins` bins over `[lo, hi)`.
    pub fn new(values: impl IntoIterator<Item = f64>, lo: f64, hi: f64, bins: usize) -> Self {
        let mut counts = vec![0; bins.max(1)];
        let mut outside = 0;
        let width = (hi - lo) / counts.len() as f64;
        for v in values {
            let k = ((v - lo) / width).floor();
            if v.is_finite() && k >= 0.0 && (k as usize) < counts.len() {
                counts[k as usize] += 1;
            } else {
                outside += 1;
            }
        }
        Histogram {
            lo,
            hi,
            counts,
            outside,
        }
    }

    /// Lines of text: one per bin, `[lo, hi)  count  ####`.
    pub fn text_lines(&self, width: usize) -> Vec<String> {
        let max = self.counts.iter().copied().max().unwrap_or(0).max(1);
        let step = (self.hi - self.lo) / self.counts.len() as f64;
        self.counts
            .iter()
            .enumerate()
            .map(|(i, &c)| {
                let a = self.lo + step * i as f64;
                let bar = "#".repeat((c * width).div_ceil(max));
                format!("{:>8.2} .. {:<8.2} {:>8}  {}", a, a + step, c, bar)
            })
            .collect()
    }
}

/// 5x7 glyphs, one `u8` per row (low 5 bits, leftmost pixel in bit 4).
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_lowercase() {
        '0' => [14, 17, 19, 21, 25, 17, 14],
        '1' => [4, 12, 4, 4, 4, 4, 14],
        '2' => [14, 17, 1, 2, 4, 8, 31],
        '3' => [31, 2, 4, 2, 1, 17, 14],
        '4' => [2, 6, 10, 18, 31, 2, 2],
        '5' => [31, 16, 30, 1, 1, 17, 14],
        '6' => [6, 8, 16, 30, 17, 17, 14],
        '7' => [31, 1, 2, 4, 8, 8, 8],
        '8' => [14, 17, 17, 14, 17, 17, 14],
        '9' => [14, 17, 17, 15, 1, 2, 12],
        'a' => [0, 0, 14, 1, 15, 17, 15],
        'b' => [16, 16, 22, 25, 17, 17, 30],
        'c' => [0, 0, 14, 16, 16, 17, 14],
        'd' => [1, 1, 13, 19, 17, 17, 15],
        'e' => [0, 0, 14, 17, 31, 16, 14],
        'f' => [6, 9, 8, 28, 8, 8, 8],
        'g' => [0, 0, 15, 17, 15, 1, 14],
        'h' => [16, 16, 22, 25, 17, 17, 17],
        'i' => [4, 0, 12, 4, 4, 4, 14],
        'j' => [2, 0, 6, 2, 2, 18, 12],
        'k' => [16, 16, 18, 20, 24, 20, 18],
        'l' => [12, 4, 4, 4, 4, 4, 14],
        'm' => [0, 0, 26, 21, 21, 17, 17],
        'n' => [0, 0, 22, 25, 17, 17, 17],
        'o' => [0, 0, 14, 17, 17, 17, 14],
        'p' => [0, 0, 30, 17, 30, 16, 16],
        'q' => [0, 0, 13, 19, 15, 1, 1],
        'r' => [0, 0, 22, 25, 16, 16, 16],
        's' => [0, 0, 14, 16, 14, 1, 30],
        't' => [8, 8, 28, 8, 8, 9, 6],
        'u' => [0, 0, 17, 17, 17, 19, 13],
        'v' => [0, 0, 17, 17, 17, 10, 4],
        'w' => [0, 0, 17, 17, 21, 21, 10],
        'x' => [0, 0, 17, 10, 4, 10, 17],
        'y' => [0, 0, 17, 17, 15, 1, 14],
        'z' => [0, 0, 31, 2, 4, 8, 31],
        '-' => [0, 0, 0, 31, 0, 0, 0],
        '.' => [0, 0, 0, 0, 0, 12, 12],
        ',' => [0, 0, 0, 0, 12, 4, 8],
        ':' => [0, 12, 12, 0, 12, 12, 0],
        '(' => [2, 4, 8, 8, 8, 4, 2],
        ')' => [8, 4, 2, 2, 2, 4, 8],
        '/' => [0, 1, 2, 4, 8, 16, 0],
        '%' => [24, 25, 2, 4, 8, 19, 3],
        _ => [0; 7],
    }
}

/// Draws `text` with its top-left corner at `(x, y)`, each font pixel `scale` pixels.
pub fn draw_text(img: &mut RgbImage, x: i64, y: i64, text: &str, scale: u32, colour: Rgb<u8>) {
    for (k, c) in text.chars().enumerate() {
        let g = glyph(c);
        for (row, bits) in g.iter().enumerate() {
            for col in 0..5 {
                if bits >> (4 - col) & 1 == 1 {
                    for dy in 0..scale as i64 {
                        for dx in 0..scale as i64 {
                            let px = x + (k as i64 * 6 + col) * scale as i64 + dx;
                            let py = y + row as i64 * scale as i64 + dy;
                            if px >= 0
                                && py >= 0
                                && (px as u32) < img.width()
                                && (py as u32) < img.height()
                            {
                                img.put_pixel(px as u32, py as u32, colour);
                            }
                        }
                    }
                }
            }
        }
    }
}

fn fill(img: &mut RgbImage, x0: i64, y0: i64, x1: i64, y1: i64, c: Rgb<u8>) {
    for y in y0.max(0)..y1.min(img.height() as i64) {
        for x in x0.max(0)..x1.min(img.width() as i64) {
            img.put_pixel(x as u32, y as u32, c);
        }
    }
}

/// One bar chart: a value per equal-width bin over `[lo, hi)`.
#[derive(Clone, Debug, PartialEq)]
pub struct Bars {
    /// Title drawn above the chart.
    pub title: String,
    /// Left edge of the first bin.
    pub lo: f64,
    /// Right edge of the last bin.
    pub hi: f64,
    /// Bar heights (NaN draws no bar).
    pub values: Vec<f64>,
    /// What the top of the scale means, e.g. `max 12`.
    pub scale_label: String,
}

impl Bars {
    /// The bars of a histogram (counts).
    pub fn of_histogram(title: &str, h: &Histogram) -> Self {
        let max = h.counts.iter().copied().max().unwrap_or(0).max(1);
        Bars {
            title: title.to_string(),
            lo: h.lo,
            hi: h.hi,
            values: h.counts.iter().map(|&c| c as f64).collect(),
            scale_label: format!("max {max}"),
        }
    }

    /// The mean of `y` per bin of `x` over `[lo, hi)` (NaN for an empty bin).
    pub fn binned_mean(
        title: &str,
        points: impl IntoIterator<Item = (f64, f64)>,
        lo: f64,
        hi: f64,
        bins: usize,
        unit: &str,
    ) -> Self {
        let bins = bins.max(1);
        let (mut sum, mut n) = (vec![0.0; bins], vec![0usize; bins]);
        let width = (hi - lo) / bins as f64;
        for (x, y) in points {
            let k = ((x - lo) / width).floor();
            if x.is_finite() && y.is_finite() && k >= 0.0 && (k as usize) < bins {
                sum[k as usize] += y;
                n[k as usize] += 1;
            }
        }
        let values: Vec<f64> = sum
            .iter()
            .zip(&n)
            .map(|(s, &c)| if c == 0 { f64::NAN } else { s / c as f64 })
            .collect();
        let max = values
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max);
        Bars {
            title: title.to_string(),
            lo,
            hi,
            values,
            scale_label: format!("max {max:.2} {unit}"),
        }
    }
}

/// A panel of histograms side by side, each titled, with its range and peak count.
pub fn histogram_panel(panels: &[(&str, &Histogram)]) -> RgbImage {
    let bars: Vec<Bars> = panels
        .iter()
        .map(|(t, h)| Bars::of_histogram(t, h))
        .collect();
    bars_panel(&bars)
}

/// Bar charts side by side, each titled, with its range and the top of its scale.
pub fn bars_panel(panels: &[Bars]) -> RgbImage {
    let (pw, ph) = (360i64, 260i64);
    let mut img = RgbImage::from_pixel(
        (pw * panels.len() as i64) as u32,
        ph as u32,
        Rgb([255, 255, 255]),
    );
    let ink = Rgb([30, 30, 30]);
    for (i, b) in panels.iter().enumerate() {
        let ox = i as i64 * pw;
        draw_text(&mut img, ox + 20, 10, &b.title, 2, ink);
        let (x0, x1, y0, y1) = (ox + 30, ox + pw - 20, 50, ph - 40);
        fill(&mut img, x0, y1, x1, y1 + 1, ink);
        fill(&mut img, x0, y0, x0 + 1, y1, ink);
        let max = b
            .values
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max);
        let max = if max > 0.0 { max } else { 1.0 };
        let n = b.values.len() as i64;
        let bw = (x1 - x0) / n.max(1);
        for (k, &v) in b.values.iter().enumerate() {
            if !v.is_finite() {
                continue;
            }
            let top = y1 - ((y1 - y0) as f64 * v.max(0.0) / max).round() as i64;
            fill(
                &mut img,
                x0 + 1 + k as i64 * bw,
                top,
                x0 + (k as i64 + 1) * bw,
                y1,
                Rgb([70, 120, 200]),
            );
        }
        draw_text(&mut img, x0, y1 + 8, &format!("{}", b.lo), 1, ink);
        let hi = format!("{}", b.hi);
        draw_text(&mut img, x1 - 6 * hi.len() as i64, y1 + 8, &hi, 1, ink);
        draw_text(&mut img, x0 + 6, y0 - 12, &b.scale_label, 1, ink);
    }
    img
}

/// One named series of a line chart.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    /// Legend name.
    pub name: String,
    /// `y` per step (`x` is the index); non-finite or non-positive values (on a log
    /// scale) are skipped.
    pub values: Vec<f64>,
    /// Line colour.
    pub colour: Rgb<u8>,
}

/// A line chart of `series` against their index on a log-10 `y` scale (losses span
/// decades), with a legend and the decade grid labelled.
pub fn log_line_chart(title: &str, x_label: &str, series: &[Series]) -> RgbImage {
    let (w, h) = (720i64, 320i64);
    let mut img = RgbImage::from_pixel(w as u32, h as u32, Rgb([255, 255, 255]));
    let ink = Rgb([30, 30, 30]);
    draw_text(&mut img, 20, 10, title, 2, ink);
    let (x0, x1, y0, y1) = (70i64, w - 150, 40i64, h - 40);
    let positive = series
        .iter()
        .flat_map(|s| s.values.iter().copied())
        .filter(|v| v.is_finite() && *v > 0.0);
    let (lo, hi) = positive.fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
    let (dlo, dhi) = if lo <= hi {
        (
            lo.log10().floor(),
            hi.log10().ceil().max(lo.log10().floor() + 1.0),
        )
    } else {
        (0.0, 1.0)
    };
    let n = series
        .iter()
        .map(|s| s.values.len())
        .max()
        .unwrap_or(0)
        .max(2);
    let px = |i: usize| x0 as f64 + (x1 - x0) as f64 * i as f64 / (n - 1) as f64;
    let py = |v: f64| y1 as f64 - (y1 - y0) as f64 * (v.log10() - dlo) / (dhi - dlo);
    let grid = Rgb([225, 225, 225]);
    let mut d = dlo;
    while d <= dhi + 1e-9 {
        let y = py(10f64.powf(d)).round() as i64;
        fill(&mut img, x0, y, x1, y + 1, grid);
        draw_text(&mut img, 8, y - 3, &format!("1e{}", d as i64), 1, ink);
        d += 1.0;
    }
    fill(&mut img, x0, y1, x1, y1 + 1, ink);
    fill(&mut img, x0, y0, x0 + 1, y1, ink);
    draw_text(&mut img, x0, y1 + 8, "0", 1, ink);
    let last = format!("{} {x_label}", n - 1);
    draw_text(&mut img, x1 - 6 * last.len() as i64, y1 + 8, &last, 1, ink);
    for (k, s) in series.iter().enumerate() {
        let mut prev: Option<(f64, f64)> = None;
        for (i, &v) in s.values.iter().enumerate() {
            if !(v.is_finite() && v > 0.0) {
                prev = None;
                continue;
            }
            let p = (px(i), py(v));
            if let Some(q) = prev {
                crate::overlay::draw_line(&mut img, q, p, s.colour);
            }
            prev = Some(p);
        }
        let ly = y0 + 14 * k as i64;
        fill(&mut img, x1 + 15, ly + 2, x1 + 35, ly + 5, s.colour);
        draw_text(&mut img, x1 + 42, ly, &s.name, 1, ink);
    }
    img
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histogram_counts_and_edges() {
        let h = Histogram::new([0.0, 0.5, 1.0, 9.99, 10.0, -0.1, f64::NAN], 0.0, 10.0, 10);
        assert_eq!(h.counts, vec![2, 1, 0, 0, 0, 0, 0, 0, 0, 1]);
        assert_eq!(h.outside, 3);
        let lines = h.text_lines(10);
        assert_eq!(lines.len(), 10);
        assert!(lines[0].ends_with("##########"));
    }

    #[test]
    fn binned_means_by_hand() {
        let b = Bars::binned_mean(
            "e",
            [(0.5, 2.0), (0.7, 4.0), (2.5, 1.0), (9.0, 5.0)],
            0.0,
            3.0,
            3,
            "deg",
        );
        assert_eq!(b.values[0], 3.0);
        assert!(b.values[1].is_nan());
        assert_eq!(b.values[2], 1.0);
        assert_eq!(b.scale_label, "max 3.00 deg");
        let img = bars_panel(&[b]);
        assert_eq!(img.width(), 360);
    }

    #[test]
    fn text_is_drawn_inside_the_image() {
        let mut img = RgbImage::from_pixel(60, 10, Rgb([0, 0, 0]));
        draw_text(&mut img, 0, 0, "yaw 90", 1, Rgb([255, 255, 255]));
        let lit = img.pixels().filter(|p| p.0[0] == 255).count();
        assert!(lit > 20);
        // Drawing past the edge does not panic.
        draw_text(&mut img, 55, 5, "long text", 2, Rgb([255, 255, 255]));
    }

    #[test]
    fn log_line_chart_puts_values_on_the_decade_scale() {
        // Values 1, 10, 100 over 3 steps: decades 1e0..1e2 span y 280..40, steps span
        // x 70..570, so 10 at step 1 is at (320, 160) by hand.
        let red = Rgb([200, 0, 0]);
        let img = log_line_chart(
            "loss",
            "steps",
            &[Series {
                name: "total".into(),
                values: vec![1.0, 10.0, 100.0],
                colour: red,
            }],
        );
        assert_eq!(*img.get_pixel(320, 160), red);
        // A straight line on the log scale: the point between steps 0 and 1 at 10^0.5.
        assert_eq!(*img.get_pixel(195, 220), red);
        assert_ne!(*img.get_pixel(320, 100), red);
    }
}
