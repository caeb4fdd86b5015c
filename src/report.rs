//! The pipeline report: pictures of what each stage made (crops with their masks,
//! correspondences and UV maps, augmented samples, the worst predictions), charts (the
//! poses, the loss curve, the errors by pose) and one `index.html` that shows them
//! beside the eval table.
//!
//! The page is self-contained and works offline: relative image links, the charts as
//! inline SVG (the browser draws their text; each is also written as its own `.svg`
//! file), inline CSS, and one small inline script that records, in `<body
//! data-images="loaded/total" data-charts="drawn/total" data-errors="N">`, whether
//! every image decoded, whether every chart's text was laid out and whether any script
//! error happened, so a headless browser can check the page without a driver
//! (`tests/report_browser.rs`).

use arkit_core::{Error, Result};
use arkit_data::eval::Summary;
use arkit_data::picture::{Bars, Histogram, bars_svg};
#[cfg(feature = "model")]
use arkit_data::picture::{Series, log_line_svg};
use arkit_data::store::SampleRecord;
use arkit_data::store::TargetsRecord;
use image::{Rgb, RgbImage};
use std::path::{Path, PathBuf};

/// The four panels of one sample's targets, each `crop x crop` pixels (the UV map at
/// its own size).
pub struct TargetPanels {
    /// The network's input crop.
    pub crop: RgbImage,
    /// The crop with face pixels tinted green and the rest darkened.
    pub mask: RgbImage,
    /// Each face pixel coloured by the canonical point it shows (x, y, z -> R, G, B
    /// over the mesh's bounding box): the correspondences as a picture.
    pub correspondences: RgbImage,
    /// The UV position map coloured the same way (texels outside the face black).
    pub uv_map: RgbImage,
}

/// Maps canonical positions to colours over the bounding box of `verts` (flat xyz).
struct PositionColours {
    lo: [f32; 3],
    span: [f32; 3],
}

impl PositionColours {
    fn of(verts: &[f32]) -> Self {
        let mut lo = [f32::MAX; 3];
        let mut hi = [f32::MIN; 3];
        for c in verts.chunks(3) {
            for k in 0..3 {
                lo[k] = lo[k].min(c[k]);
                hi[k] = hi[k].max(c[k]);
            }
        }
        let span = std::array::from_fn(|k| (hi[k] - lo[k]).max(1e-9));
        PositionColours { lo, span }
    }

    fn colour(&self, p: [f32; 3]) -> Rgb<u8> {
        Rgb(std::array::from_fn(|k| {
            (((p[k] - self.lo[k]) / self.span[k]).clamp(0.0, 1.0) * 235.0 + 20.0) as u8
        }))
    }
}

/// Draws a sample's stored targets.
pub fn target_panels(
    sample: &SampleRecord,
    targets: &TargetsRecord,
    image: &RgbImage,
) -> Result<TargetPanels> {
    let crop = targets.crop.crop_image(image);
    let mask = targets.mask()?;
    let s = targets.crop.size;
    let colours = PositionColours::of(&sample.verts);
    let mut tinted = crop.clone();
    for (i, p) in tinted.pixels_mut().enumerate() {
        *p = if mask[i] {
            Rgb([p[0] / 2, p[1] / 2 + 110, p[2] / 2])
        } else {
            Rgb([p[0] / 3, p[1] / 3, p[2] / 3])
        };
    }
    let mut corr = RgbImage::new(s, s);
    let weights = targets.weights();
    let pixels = arkit_data::store::mask_pixel_indices(&mask);
    for ((&px, ids), w) in pixels.iter().zip(&targets.corr_vertices).zip(&weights) {
        let mut q = [0f32; 3];
        for k in 0..3 {
            let v = 3 * ids[k] as usize;
            let Some(vert) = sample.verts.get(v..v + 3) else {
                return Err(Error::invalid(
                    "targets",
                    format!("{}: vertex id {} out of range", sample.key, ids[k]),
                ));
            };
            for a in 0..3 {
                q[a] += w[k] * vert[a];
            }
        }
        corr.put_pixel(px % s, px / s, colours.colour(q));
    }
    let u = targets.uv_size;
    let mut uv = RgbImage::new(u, u);
    for (i, p) in targets.uv_positions().into_iter().enumerate() {
        if p.iter().all(|v| v.is_finite()) && p != [0.0; 3] {
            uv.put_pixel(i as u32 % u, i as u32 / u, colours.colour(p));
        }
    }
    Ok(TargetPanels {
        crop,
        mask: tinted,
        correspondences: corr,
        uv_map: uv,
    })
}

/// The four pose histograms `inspect` prints and plots: yaw, pitch, roll (degrees,
/// -90..90) and distance (metres, 0..1.2).
pub fn pose_histograms(
    yaw: &[f64],
    pitch: &[f64],
    roll: &[f64],
    distance: &[f64],
) -> [(&'static str, Histogram); 4] {
    [
        (
            "yaw (deg)",
            Histogram::new(yaw.iter().copied(), -90.0, 90.0, 18),
        ),
        (
            "pitch (deg)",
            Histogram::new(pitch.iter().copied(), -90.0, 90.0, 18),
        ),
        (
            "roll (deg)",
            Histogram::new(roll.iter().copied(), -90.0, 90.0, 18),
        ),
        (
            "distance (m)",
            Histogram::new(distance.iter().copied(), 0.0, 1.2, 12),
        ),
    ]
}

/// The four pose histograms as one chart (two by two): titled, the x axes in degrees
/// or metres with their tick values, the y axes in samples.
pub fn pose_chart(title: &str, hists: &[(&str, Histogram)]) -> String {
    let bars: Vec<Bars> = hists
        .iter()
        .map(|(name, h)| {
            let what = name.split(" (").next().unwrap_or(name);
            let b = Bars::of_histogram(&format!("{what} of {} samples", total(h)), name, h);
            if name.ends_with("(deg)") {
                b.with_x_step(30.0)
            } else {
                b
            }
        })
        .collect();
    bars_svg(title, &bars, 2)
}

fn total(h: &Histogram) -> usize {
    h.counts.iter().sum::<usize>() + h.outside
}

/// The pose histograms of a set of samples as one chart ([`pose_chart`]).
pub fn pose_svg(samples: &[SampleRecord]) -> String {
    let col = |f: &dyn Fn(&SampleRecord) -> f64| samples.iter().map(f).collect::<Vec<f64>>();
    let h = pose_histograms(
        &col(&|s| s.yaw_deg),
        &col(&|s| s.pitch_deg),
        &col(&|s| s.roll_deg),
        &col(&|s| -s.translation_m[2]),
    );
    pose_chart("Pose histograms", &h)
}

/// The loss curve of a training log (`loss.csv` rows): total and each term, on a log
/// scale against the training step.
#[cfg(feature = "model")]
pub fn loss_svg(log: &[arkit_perspnet::StepLoss]) -> String {
    let series = |name: &str, f: &dyn Fn(&arkit_perspnet::StepLoss) -> f32, c: [u8; 3]| Series {
        name: name.to_string(),
        values: log.iter().map(|s| f(s) as f64).collect(),
        colour: c,
    };
    log_line_svg(
        "Training loss",
        "training step",
        "weighted loss (log scale)",
        &[
            series("total", &|s| s.total, [20, 20, 20]),
            series("corr", &|s| s.corr, [200, 40, 40]),
            series("shape", &|s| s.shape, [40, 110, 200]),
            series("kl", &|s| s.kl, [40, 160, 60]),
            series("seg", &|s| s.seg, [200, 140, 20]),
        ],
    )
}

/// One picture or chart on the page.
#[derive(Clone, Debug, Default)]
pub struct Figure {
    /// File name inside the report folder (a PNG, or the chart's `.svg`).
    pub file: String,
    /// Heading.
    pub title: String,
    /// What to look at.
    pub caption: String,
    /// A chart's SVG, inlined in the page (then `file` holds the same SVG).
    pub svg: Option<String>,
    /// Captions laid over the picture (an SVG of the picture's size, inlined).
    pub overlay: Option<String>,
}

/// One stage's line in the timing table.
#[derive(Clone, Debug, serde::Serialize)]
pub struct StageTiming {
    /// Stage name (`synth`, `convert`, ...).
    pub stage: String,
    /// Wall time, seconds.
    pub seconds: f64,
    /// What it did, in words.
    pub detail: String,
}

/// What the page shows.
pub struct Page<'a> {
    /// Page title.
    pub title: &'a str,
    /// A paragraph under the title (plain text).
    pub intro: &'a str,
    /// Stage timings.
    pub stages: &'a [StageTiming],
    /// Named eval summaries (model, baselines), in table order.
    pub results: &'a [(&'a str, &'a Summary)],
    /// Pictures, in page order.
    pub figures: &'a [Figure],
}

/// Escapes text for HTML.
pub fn escape(text: &str) -> String {
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

const STYLE: &str = "body{font-family:system-ui,sans-serif;margin:2em auto;max-width:1200px;\
padding:0 1em;color:#222}table{border-collapse:collapse;margin:1em 0}\
td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}th:first-child,\
td:first-child{text-align:left}figure{margin:2em 0}img{max-width:100%;\
border:1px solid #ddd;image-rendering:pixelated;display:block}figcaption{color:#555;margin-top:.4em}\
figure>svg{max-width:100%;height:auto;display:block}.sheet{position:relative;display:inline-block;\
max-width:100%}.sheet>svg{position:absolute;left:0;top:0;width:100%;height:100%;pointer-events:none}";

// Records in data attributes whether every image decoded, whether every chart (inline
// SVG) has its text laid out with a width, and whether any error was thrown, so a
// headless browser's DOM dump tells without a driver.
const CHECK_SCRIPT: &str = "var errors=0;window.addEventListener('error',function(){errors++;\
document.body.dataset.errors=errors},true);window.addEventListener('load',function(){\
var imgs=document.images,ok=0;for(var i=0;i<imgs.length;i++){if(imgs[i].complete&&\
imgs[i].naturalWidth>0)ok++}document.body.dataset.images=ok+'/'+imgs.length;\
var svgs=document.querySelectorAll('svg'),drawn=0;for(var k=0;k<svgs.length;k++){\
var t=svgs[k].querySelectorAll('text'),good=t.length>0;for(var j=0;j<t.length;j++){\
if(!(t[j].getComputedTextLength()>0))good=false}if(good&&svgs[k].getBoundingClientRect()\
.width>0)drawn++}document.body.dataset.charts=drawn+'/'+svgs.length;\
document.body.dataset.errors=errors});";

/// The page's HTML.
pub fn page_html(page: &Page) -> String {
    let mut h = String::new();
    h += "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n";
    h += &format!("<title>{}</title>\n", escape(page.title));
    h += &format!("<style>{STYLE}</style>\n<script>{CHECK_SCRIPT}</script>\n");
    h += "</head>\n<body data-images=\"pending\" data-charts=\"pending\" data-errors=\"0\">\n";
    h += &format!(
        "<h1>{}</h1>\n<p>{}</p>\n",
        escape(page.title),
        escape(page.intro)
    );
    if let Some((_, first)) = page.results.first() {
        h += "<h2>Evaluation (held-out subjects)</h2>\n<table>\n<tr><th></th>";
        for (name, _) in first.columns() {
            h += &format!("<th>{}</th>", escape(name));
        }
        h += "<th>mask IoU</th></tr>\n";
        for (name, s) in page.results {
            h += &format!("<tr><td>{}</td>", escape(name));
            for (_, v) in s.columns() {
                h += &format!("<td>{}</td>", escape(&v));
            }
            h += &format!(
                "<td>{}</td></tr>\n",
                s.mask.map_or("-".to_string(), |m| format!("{:.3}", m.iou))
            );
        }
        h += "</table>\n<p>Angles in degrees (official Euler differences), distances in \
              mm, success rates in %. ADD is the mean distance between the true and \
              predicted placements of the true mesh.</p>\n";
    }
    if !page.stages.is_empty() {
        h += "<h2>Stages</h2>\n<table>\n<tr><th>stage</th><th>seconds</th><th>what it did</th></tr>\n";
        for s in page.stages {
            h += &format!(
                "<tr><td>{}</td><td>{:.1}</td><td style=\"text-align:left\">{}</td></tr>\n",
                escape(&s.stage),
                s.seconds,
                escape(&s.detail)
            );
        }
        let total: f64 = page.stages.iter().map(|s| s.seconds).sum();
        h += &format!("<tr><th>total</th><th>{total:.1}</th><th></th></tr>\n</table>\n");
    }
    for f in page.figures {
        h += &format!("<figure>\n<h2>{}</h2>\n", escape(&f.title));
        let img = format!(
            "<img src=\"{}\" alt=\"{}\">",
            escape(&f.file),
            escape(&f.title)
        );
        match (&f.svg, &f.overlay) {
            (Some(svg), _) => h += svg,
            (None, Some(overlay)) => h += &format!("<div class=\"sheet\">{img}\n{overlay}</div>\n"),
            (None, None) => h += &format!("{img}\n"),
        }
        h += &format!(
            "<figcaption>{}</figcaption>\n</figure>\n",
            escape(&f.caption)
        );
    }
    h += "</body>\n</html>\n";
    h
}

/// Writes `dir/index.html` (atomically); every figure's file must already be in `dir`.
pub fn write_page(dir: &Path, page: &Page) -> Result<PathBuf> {
    for f in page.figures {
        let p = dir.join(&f.file);
        if !p.exists() {
            return Err(Error::invalid(
                "report",
                format!("{} is listed on the page but not written", p.display()),
            ));
        }
    }
    let path = dir.join("index.html");
    arkit_core::atomic_file::write_bytes(&path, page_html(page).as_bytes())?;
    Ok(path)
}

/// Writes a picture as PNG into `dir` (atomically) and returns its figure entry.
pub fn write_figure(
    dir: &Path,
    file: &str,
    img: &RgbImage,
    title: &str,
    caption: &str,
) -> Result<Figure> {
    arkit_core::atomic_file::write_bytes(&dir.join(file), &arkit_data::eval::png_bytes(img)?)?;
    Ok(Figure {
        file: file.to_string(),
        title: title.to_string(),
        caption: caption.to_string(),
        ..Figure::default()
    })
}

/// Writes a chart (SVG text) into `dir` (atomically) and returns its figure entry, which
/// inlines the same SVG in the page.
pub fn write_chart(
    dir: &Path,
    file: &str,
    svg: String,
    title: &str,
    caption: &str,
) -> Result<Figure> {
    arkit_core::atomic_file::write_bytes(&dir.join(file), svg.as_bytes())?;
    Ok(Figure {
        file: file.to_string(),
        title: title.to_string(),
        caption: caption.to_string(),
        svg: Some(svg),
        overlay: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn html_is_escaped_and_lists_every_figure() {
        let figures = vec![Figure {
            file: "a b.png".into(),
            title: "x < y".into(),
            caption: "\"quoted\" & more".into(),
            ..Figure::default()
        }];
        let html = page_html(&Page {
            title: "t",
            intro: "<script>alert(1)</script>",
            stages: &[StageTiming {
                stage: "synth".into(),
                seconds: 1.25,
                detail: "made 3".into(),
            }],
            results: &[],
            figures: &figures,
        });
        assert!(html.contains("&lt;script&gt;alert(1)&lt;/script&gt;"));
        assert!(!html.contains("<script>alert"));
        assert!(html.contains("<img src=\"a b.png\" alt=\"x &lt; y\">"));
        assert!(html.contains("&quot;quoted&quot; &amp; more"));
        assert!(html.contains("<td>1.2</td>") || html.contains("<td>1.3</td>"));
        // Nothing is fetched from the network.
        assert!(!html.contains("http://") && !html.contains("https://"));
    }

    #[test]
    fn a_page_that_names_a_missing_file_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let figures = vec![Figure {
            file: "missing.png".into(),
            title: "m".into(),
            caption: String::new(),
            ..Figure::default()
        }];
        let page = Page {
            title: "t",
            intro: "",
            stages: &[],
            results: &[],
            figures: &figures,
        };
        let e = write_page(dir.path(), &page).unwrap_err().to_string();
        assert!(e.contains("missing.png"), "{e}");
        assert!(!dir.path().join("index.html").exists());
    }

    #[test]
    fn position_colours_span_the_box() {
        let c = PositionColours::of(&[0.0, 0.0, 0.0, 1.0, 2.0, 4.0]);
        assert_eq!(c.colour([0.0, 0.0, 0.0]), Rgb([20, 20, 20]));
        assert_eq!(c.colour([1.0, 2.0, 4.0]), Rgb([255, 255, 255]));
        assert_eq!(c.colour([0.5, 1.0, 2.0]), Rgb([137, 137, 137]));
    }
}
