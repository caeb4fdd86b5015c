//! Charts for people to read, as SVG text: titled axes with tick values and units,
//! legends, and text the viewer (a browser, an image viewer, Inkscape) draws with its
//! own fonts, so no font files or plotting libraries are needed. The report inlines
//! them in its HTML; `inspect --plot FILE.svg` writes one.
//!
//! Every chart is one `<svg>` element with a `viewBox` (it scales to its container),
//! `<title>` for screen readers, and `class` names on its parts (`bar`, `series`,
//! `tick`, ...) with the plotted value in `data-value`, so tests can check what was drawn.

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

/// Escapes text for XML (SVG, HTML).
fn xml_escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            _ => out.push(c),
        }
    }
    out
}

/// Evenly spaced "nice" tick values (steps of 1, 2 or 5 times a power of ten) covering
/// `[lo, hi]`: the first tick is at or below `lo`, the last at or above `hi`, about
/// `target` intervals between them. `lo == hi` gets a unit-wide range.
fn nice_ticks(lo: f64, hi: f64, target: usize) -> Vec<f64> {
    ticks_with_min_step(lo, hi, target, 0.0)
}

/// [`nice_ticks`] with a step of at least `min_step` (1 for counts and step numbers).
fn ticks_with_min_step(lo: f64, hi: f64, target: usize, min_step: f64) -> Vec<f64> {
    let (lo, hi) = if lo.is_finite() && hi.is_finite() && lo < hi {
        (lo, hi)
    } else if lo.is_finite() {
        (lo, lo + 1.0)
    } else {
        (0.0, 1.0)
    };
    let step = nice_step((hi - lo) / target.max(1) as f64).max(min_step);
    let first = (lo / step + 1e-9).floor() as i64;
    let last = (hi / step - 1e-9).ceil() as i64;
    // Multiples of the step, so 0.1 * 3 prints as 0.3 and not 0.30000000000000004.
    (first..=last).map(|k| clean(k as f64 * step)).collect()
}

fn nice_step(raw: f64) -> f64 {
    let p = 10f64.powf(raw.log10().floor());
    let m = raw / p;
    let n = if m <= 1.0 + 1e-9 {
        1.0
    } else if m <= 2.0 + 1e-9 {
        2.0
    } else if m <= 5.0 + 1e-9 {
        5.0
    } else {
        10.0
    };
    n * p
}

fn clean(v: f64) -> f64 {
    let r = (v * 1e9).round() / 1e9;
    if r == 0.0 { 0.0 } else { r }
}

/// A tick value as text with as many decimals as the tick step needs (`0.2` -> one).
fn tick_label(v: f64, step: f64) -> String {
    let decimals = if step >= 1.0 || step <= 0.0 || !step.is_finite() {
        0
    } else {
        (-step.log10() - 1e-9).ceil().max(0.0) as usize
    };
    let s = format!("{:.*}", decimals, v);
    if s.starts_with('-') && s[1..].chars().all(|c| c == '0' || c == '.') {
        s[1..].to_string()
    } else {
        s
    }
}

/// One bar chart: a value per equal-width bin over `[lo, hi)`.
#[derive(Clone, Debug, PartialEq)]
pub struct Bars {
    /// Title drawn above the chart.
    pub title: String,
    /// The x axis's label, with its unit (`yaw (deg)`).
    pub x_label: String,
    /// The y axis's label, with its unit (`samples`, `mean rotation error (deg)`).
    pub y_label: String,
    /// Left edge of the first bin.
    pub lo: f64,
    /// Right edge of the last bin.
    pub hi: f64,
    /// Bar heights (NaN draws no bar: an empty bin).
    pub values: Vec<f64>,
    /// Samples per bin (shown on hover; for a histogram the values themselves).
    pub counts: Vec<usize>,
    /// A note under the title, e.g. how many values fell outside the range.
    pub note: String,
    /// The x axis's tick step (default: a nice step for about 6 ticks); 30 suits
    /// angles over -90..90.
    pub x_step: Option<f64>,
    /// Whether the values are counts (y ticks at whole numbers).
    pub counts_axis: bool,
}

impl Bars {
    /// The bars of a histogram (counts of samples).
    pub fn of_histogram(title: &str, x_label: &str, h: &Histogram) -> Self {
        Bars {
            title: title.to_string(),
            x_label: x_label.to_string(),
            y_label: "samples".to_string(),
            lo: h.lo,
            hi: h.hi,
            values: h.counts.iter().map(|&c| c as f64).collect(),
            counts: h.counts.clone(),
            note: if h.outside > 0 {
                format!("{} outside the range", h.outside)
            } else {
                String::new()
            },
            x_step: None,
            counts_axis: true,
        }
    }

    /// The same bars with x ticks every `step`.
    pub fn with_x_step(mut self, step: f64) -> Self {
        self.x_step = Some(step);
        self
    }

    /// The mean of `y` per bin of `x` over `[lo, hi)` (NaN for an empty bin).
    pub fn binned_mean(
        title: &str,
        x_label: &str,
        y_label: &str,
        points: impl IntoIterator<Item = (f64, f64)>,
        lo: f64,
        hi: f64,
        bins: usize,
    ) -> Self {
        let bins = bins.max(1);
        let (mut sum, mut n) = (vec![0.0; bins], vec![0usize; bins]);
        let width = (hi - lo) / bins as f64;
        let mut outside = 0;
        for (x, y) in points {
            let k = ((x - lo) / width).floor();
            if x.is_finite() && y.is_finite() && k >= 0.0 && (k as usize) < bins {
                sum[k as usize] += y;
                n[k as usize] += 1;
            } else {
                outside += 1;
            }
        }
        let values: Vec<f64> = sum
            .iter()
            .zip(&n)
            .map(|(s, &c)| if c == 0 { f64::NAN } else { s / c as f64 })
            .collect();
        Bars {
            title: title.to_string(),
            x_label: x_label.to_string(),
            y_label: y_label.to_string(),
            lo,
            hi,
            values,
            counts: n,
            note: if outside > 0 {
                format!("{outside} outside the range")
            } else {
                String::new()
            },
            x_step: None,
            counts_axis: false,
        }
    }
}

const FONT: &str =
    "font-family=\"system-ui, -apple-system, 'Segoe UI', Helvetica, Arial, sans-serif\"";
const INK: &str = "#222";
const GRID: &str = "#e2e2e2";
const BAR: &str = "#4678c8";

/// Size of one bar chart panel in SVG units.
pub const PANEL_WIDTH: f64 = 380.0;
/// See [`PANEL_WIDTH`].
pub const PANEL_HEIGHT: f64 = 290.0;

/// Opens an `<svg>` of `w x h` units titled `title` (for screen readers and tooltips).
fn svg_open(w: f64, h: f64, title: &str) -> String {
    format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"0 0 {w} {h}\" width=\"{w}\" \
         height=\"{h}\" role=\"img\" {FONT} font-size=\"13\" fill=\"{INK}\">\n<title>{}</title>\n\
         <rect x=\"0\" y=\"0\" width=\"{w}\" height=\"{h}\" fill=\"#fff\"/>\n",
        xml_escape(title)
    )
}

fn text(x: f64, y: f64, anchor: &str, class: &str, extra: &str, body: &str) -> String {
    format!(
        "<text class=\"{class}\" x=\"{x:.1}\" y=\"{y:.1}\" text-anchor=\"{anchor}\"{extra}>{}</text>\n",
        xml_escape(body)
    )
}

/// One bar chart drawn into the box `(ox, oy, PANEL_WIDTH, PANEL_HEIGHT)`.
fn bars_group(b: &Bars, ox: f64, oy: f64) -> String {
    let (left, right, top, bottom) = (64.0, 14.0, 44.0, 50.0);
    let (x0, x1) = (ox + left, ox + PANEL_WIDTH - right);
    let (y0, y1) = (oy + top, oy + PANEL_HEIGHT - bottom);
    let max = b
        .values
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max);
    let min_step = if b.counts_axis { 1.0 } else { 0.0 };
    let yticks = ticks_with_min_step(0.0, if max > 0.0 { max } else { 1.0 }, 5, min_step);
    let ystep = yticks[1] - yticks[0];
    let ytop = *yticks.last().expect("two ticks at least");
    let py = |v: f64| y1 - (y1 - y0) * v / ytop;
    let span = b.hi - b.lo;
    let px = |v: f64| x0 + (x1 - x0) * (v - b.lo) / span;
    let mut g = format!(
        "<g class=\"chart\" data-title=\"{}\">\n",
        xml_escape(&b.title)
    );
    g += &text(
        ox + PANEL_WIDTH / 2.0,
        oy + 20.0,
        "middle",
        "title",
        " font-size=\"15\" font-weight=\"600\"",
        &b.title,
    );
    if !b.note.is_empty() {
        g += &text(
            ox + PANEL_WIDTH / 2.0,
            oy + 36.0,
            "middle",
            "note",
            " font-size=\"11\" fill=\"#666\"",
            &b.note,
        );
    }
    for &t in &yticks {
        let y = py(t);
        g += &format!(
            "<line x1=\"{x0:.1}\" y1=\"{y:.1}\" x2=\"{x1:.1}\" y2=\"{y:.1}\" stroke=\"{GRID}\"/>\n"
        );
        g += &text(
            x0 - 6.0,
            y + 4.0,
            "end",
            "tick y",
            &format!(" data-value=\"{t}\""),
            &tick_label(t, ystep),
        );
    }
    let n = b.values.len().max(1);
    let bw = (x1 - x0) / n as f64;
    for (k, &v) in b.values.iter().enumerate() {
        // No bar for an empty bin (NaN) or a zero (a bar of no height).
        if !(v.is_finite() && v > 0.0) {
            continue;
        }
        let top = py(v);
        let a = b.lo + span * k as f64 / n as f64;
        let count = b.counts.get(k).copied().unwrap_or(0);
        g += &format!(
            "<rect class=\"bar\" x=\"{:.2}\" y=\"{top:.2}\" width=\"{:.2}\" height=\"{:.2}\" \
             fill=\"{BAR}\" data-value=\"{v}\" data-count=\"{count}\"><title>{}</title></rect>\n",
            x0 + k as f64 * bw + 0.5,
            (bw - 1.0).max(0.5),
            y1 - top,
            xml_escape(&format!(
                "{} .. {}: {} ({count} samples)",
                tick_label(a, span / n as f64 / 10.0),
                tick_label(a + span / n as f64, span / n as f64 / 10.0),
                tick_label(v, ystep / 10.0)
            ))
        );
    }
    let xticks = match b.x_step {
        Some(step) if step > 0.0 && (b.hi - b.lo) / step <= 100.0 => {
            let first = (b.lo / step - 1e-9).ceil() as i64;
            let last = (b.hi / step + 1e-9).floor() as i64;
            (first..=last).map(|k| clean(k as f64 * step)).collect()
        }
        _ => nice_ticks(b.lo, b.hi, 6),
    };
    let xstep = b
        .x_step
        .unwrap_or_else(|| xticks.get(1).map_or(1.0, |s| s - xticks[0]));
    for &t in xticks
        .iter()
        .filter(|&&t| t >= b.lo - 1e-9 && t <= b.hi + 1e-9)
    {
        let x = px(t);
        g += &format!(
            "<line x1=\"{x:.1}\" y1=\"{y1:.1}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"{INK}\"/>\n",
            y1 + 5.0
        );
        g += &text(
            x,
            y1 + 19.0,
            "middle",
            "tick x",
            &format!(" data-value=\"{t}\""),
            &tick_label(t, xstep),
        );
    }
    g +=
        &format!("<path d=\"M{x0:.1},{y0:.1}V{y1:.1}H{x1:.1}\" fill=\"none\" stroke=\"{INK}\"/>\n");
    g += &text(
        (x0 + x1) / 2.0,
        y1 + 40.0,
        "middle",
        "axis-label x",
        "",
        &b.x_label,
    );
    let (lx, ly) = (ox + 16.0, (y0 + y1) / 2.0);
    g += &text(
        lx,
        ly,
        "middle",
        "axis-label y",
        &format!(" transform=\"rotate(-90 {lx:.1} {ly:.1})\""),
        &b.y_label,
    );
    g += "</g>\n";
    g
}

/// Bar charts in one SVG, `columns` per row, each with its title, axes, tick values
/// and the axes' labels.
pub fn bars_svg(title: &str, panels: &[Bars], columns: usize) -> String {
    let columns = columns.clamp(1, panels.len().max(1));
    let rows = panels.len().div_ceil(columns).max(1);
    let mut s = svg_open(
        PANEL_WIDTH * columns as f64,
        PANEL_HEIGHT * rows as f64,
        title,
    );
    for (i, b) in panels.iter().enumerate() {
        s += &bars_group(
            b,
            (i % columns) as f64 * PANEL_WIDTH,
            (i / columns) as f64 * PANEL_HEIGHT,
        );
    }
    s += "</svg>\n";
    s
}

/// One named series of a line chart.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    /// Legend name.
    pub name: String,
    /// `y` per step (`x` is the index); non-finite or non-positive values (on a log
    /// scale) are skipped.
    pub values: Vec<f64>,
    /// Line colour, RGB.
    pub colour: [u8; 3],
}

/// Size of a line chart in SVG units.
pub(crate) const LINE_WIDTH: f64 = 760.0;
/// See [`LINE_WIDTH`].
pub(crate) const LINE_HEIGHT: f64 = 340.0;
/// The line chart's plot area: left, right, top and bottom edges in SVG units.
pub const LINE_PLOT: [f64; 4] = [78.0, LINE_WIDTH - 150.0, 44.0, LINE_HEIGHT - 56.0];

/// A decade tick as text: `0.01`, `1`, `100`, or `1e-5` beyond that.
fn decade_label(d: i64) -> String {
    if (-3..=4).contains(&d) {
        tick_label(10f64.powi(d as i32), 10f64.powi(d as i32))
    } else {
        format!("1e{d}")
    }
}

/// A line chart of `series` against their index on a log-10 `y` scale (losses span
/// decades): a grid line and value at every decade, `x` ticks at nice steps, both axes
/// labelled, and a legend.
pub fn log_line_svg(title: &str, x_label: &str, y_label: &str, series: &[Series]) -> String {
    let [x0, x1, y0, y1] = LINE_PLOT;
    let positive = series
        .iter()
        .flat_map(|s| s.values.iter().copied())
        .filter(|v| v.is_finite() && *v > 0.0);
    let (lo, hi) = positive.fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
    let (dlo, dhi) = if lo <= hi {
        let dlo = lo.log10().floor();
        (dlo, hi.log10().ceil().max(dlo + 1.0))
    } else {
        (0.0, 1.0)
    };
    let n = series
        .iter()
        .map(|s| s.values.len())
        .max()
        .unwrap_or(0)
        .max(2);
    let px = |i: f64| x0 + (x1 - x0) * i / (n - 1) as f64;
    let py = |v: f64| y1 - (y1 - y0) * (v.log10() - dlo) / (dhi - dlo);
    let mut s = svg_open(LINE_WIDTH, LINE_HEIGHT, title);
    s += &text(
        (x0 + x1) / 2.0,
        24.0,
        "middle",
        "title",
        " font-size=\"15\" font-weight=\"600\"",
        title,
    );
    let mut d = dlo as i64;
    while d as f64 <= dhi + 1e-9 {
        let y = py(10f64.powi(d as i32));
        s += &format!(
            "<line x1=\"{x0:.1}\" y1=\"{y:.1}\" x2=\"{x1:.1}\" y2=\"{y:.1}\" stroke=\"{GRID}\"/>\n"
        );
        s += &text(
            x0 - 6.0,
            y + 4.0,
            "end",
            "tick y",
            &format!(" data-value=\"{}\"", 10f64.powi(d as i32)),
            &decade_label(d),
        );
        d += 1;
    }
    let xticks = ticks_with_min_step(0.0, (n - 1) as f64, 8, 1.0);
    let xstep = xticks[1] - xticks[0];
    for &t in xticks.iter().filter(|&&t| t <= (n - 1) as f64 + 1e-9) {
        let x = px(t);
        s += &format!(
            "<line x1=\"{x:.1}\" y1=\"{y1:.1}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"{INK}\"/>\n",
            y1 + 5.0
        );
        s += &text(
            x,
            y1 + 19.0,
            "middle",
            "tick x",
            &format!(" data-value=\"{t}\""),
            &tick_label(t, xstep),
        );
    }
    for (k, line) in series.iter().enumerate() {
        let colour = format!(
            "#{:02x}{:02x}{:02x}",
            line.colour[0], line.colour[1], line.colour[2]
        );
        // One path; a gap (a value a log scale cannot show) starts a new piece.
        let mut path = String::new();
        let mut pen_down = false;
        for (i, &v) in line.values.iter().enumerate() {
            if !(v.is_finite() && v > 0.0) {
                pen_down = false;
                continue;
            }
            path += &format!(
                "{}{:.2},{:.2}",
                if pen_down { "L" } else { "M" },
                px(i as f64),
                py(v)
            );
            pen_down = true;
        }
        s += &format!(
            "<path class=\"series\" data-name=\"{}\" d=\"{path}\" fill=\"none\" stroke=\"{colour}\" \
             stroke-width=\"1.6\" stroke-linejoin=\"round\"/>\n",
            xml_escape(&line.name)
        );
        let ly = y0 + 8.0 + 20.0 * k as f64;
        s += &format!(
            "<line class=\"legend-key\" x1=\"{:.1}\" y1=\"{ly:.1}\" x2=\"{:.1}\" y2=\"{ly:.1}\" \
             stroke=\"{colour}\" stroke-width=\"3\"/>\n",
            x1 + 18.0,
            x1 + 44.0
        );
        s += &text(x1 + 52.0, ly + 4.5, "start", "legend", "", &line.name);
    }
    s +=
        &format!("<path d=\"M{x0:.1},{y0:.1}V{y1:.1}H{x1:.1}\" fill=\"none\" stroke=\"{INK}\"/>\n");
    s += &text(
        (x0 + x1) / 2.0,
        y1 + 42.0,
        "middle",
        "axis-label x",
        "",
        x_label,
    );
    let (lx, ly) = (20.0, (y0 + y1) / 2.0);
    s += &text(
        lx,
        ly,
        "middle",
        "axis-label y",
        &format!(" transform=\"rotate(-90 {lx:.1} {ly:.1})\""),
        y_label,
    );
    s += "</svg>\n";
    s
}

/// Captions for the cells of a contact sheet (`sheet` pixels, cells `cell` pixels,
/// `columns` per row, in order; a label's lines one under the other), drawn by the
/// viewer in its own font: an SVG of the
/// sheet's size. With `href` (the sheet's file name, relative) it shows the picture under
/// the captions (a file to open on its own); without, it holds only the captions, to lay
/// over the picture (the report does).
pub(crate) fn sheet_labels_svg(
    title: &str,
    href: Option<&str>,
    sheet: (u32, u32),
    cell: (u32, u32),
    columns: usize,
    labels: &[String],
) -> String {
    let (w, h) = (sheet.0 as f64, sheet.1 as f64);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"0 0 {w} {h}\" role=\"img\" \
         {FONT} font-size=\"15\" font-weight=\"600\">\n<title>{}</title>\n",
        xml_escape(title)
    );
    if let Some(href) = href {
        s += &format!(
            "<image href=\"{}\" x=\"0\" y=\"0\" width=\"{w}\" height=\"{h}\"/>\n",
            xml_escape(href)
        );
    }
    let columns = columns.max(1);
    for (k, label) in labels.iter().enumerate() {
        let x = (k % columns) as f64 * cell.0 as f64 + 6.0;
        let y = (k / columns) as f64 * cell.1 as f64 + 20.0;
        // One line per line of the label.
        let lines: String = label
            .lines()
            .enumerate()
            .map(|(i, line)| {
                format!(
                    "<tspan x=\"{x:.1}\" dy=\"{}\">{}</tspan>",
                    if i == 0 { "0" } else { "1.2em" },
                    xml_escape(line)
                )
            })
            .collect();
        s += &format!(
            "<text class=\"label\" x=\"{x:.1}\" y=\"{y:.1}\" fill=\"#ffe600\" stroke=\"#000\" \
             stroke-width=\"3\" paint-order=\"stroke\">{lines}</text>\n"
        );
    }
    s += "</svg>\n";
    s
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
            "x (deg)",
            "mean (deg)",
            [(0.5, 2.0), (0.7, 4.0), (2.5, 1.0), (9.0, 5.0)],
            0.0,
            3.0,
            3,
        );
        assert_eq!(b.values[0], 3.0);
        assert!(b.values[1].is_nan());
        assert_eq!(b.values[2], 1.0);
        assert_eq!(b.counts, vec![2, 0, 1]);
        assert_eq!(b.note, "1 outside the range");
    }

    #[test]
    fn ticks_are_nice_and_cover_the_range() {
        assert_eq!(
            nice_ticks(-90.0, 90.0, 6),
            vec![-100.0, -50.0, 0.0, 50.0, 100.0]
        );
        assert_eq!(
            nice_ticks(0.0, 1.2, 6),
            vec![0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2]
        );
        assert_eq!(nice_ticks(0.0, 7.0, 5), vec![0.0, 2.0, 4.0, 6.0, 8.0]);
        assert_eq!(nice_ticks(0.0, 3.1, 5), vec![0.0, 1.0, 2.0, 3.0, 4.0]);
        assert_eq!(nice_ticks(3.0, 3.0, 5).first(), Some(&3.0));
        assert_eq!(tick_label(0.6000000001, 0.2), "0.6");
        assert_eq!(tick_label(-0.0, 1.0), "0");
        assert_eq!(tick_label(25.0, 5.0), "25");
        assert_eq!(tick_label(0.05, 0.05), "0.05");
        assert_eq!(decade_label(-2), "0.01");
        assert_eq!(decade_label(2), "100");
        assert_eq!(decade_label(-5), "1e-5");
    }

    #[test]
    fn text_is_escaped() {
        let s = bars_svg(
            "a < b",
            &[Bars::binned_mean("x & y", "<x>", "\"y\"", [], 0.0, 1.0, 2)],
            1,
        );
        assert!(s.contains("a &lt; b") && s.contains("x &amp; y") && s.contains("&quot;y&quot;"));
        assert!(!s.contains("<x>"));
        // No bars for empty bins.
        assert!(!s.contains("class=\"bar\""));
    }
}
