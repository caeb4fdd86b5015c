//! The SVG charts (report, `inspect --plot`, `eval --report`): each parses as XML, and
//! its titles, axis labels, tick values and bars are the ones derived by hand from
//! the data.

use arkit_data::picture::{Bars, Histogram, LINE_PLOT, PANEL_HEIGHT, PANEL_WIDTH, Series};
use quick_xml::events::Event;
use std::collections::HashMap;
use std::process::Command;

/// One element of a parsed SVG: its name, attributes and direct text.
#[derive(Debug)]
struct Elem {
    name: String,
    attrs: HashMap<String, String>,
    text: String,
}

/// Parses `svg` as XML (panics on malformed XML), every element in document order.
fn parse(svg: &str) -> Vec<Elem> {
    let mut reader = quick_xml::Reader::from_str(svg);
    let mut out: Vec<Elem> = Vec::new();
    let mut open: Vec<usize> = Vec::new();
    loop {
        match reader.read_event().expect("well-formed XML") {
            ev @ (Event::Start(_) | Event::Empty(_)) => {
                let (e, is_start) = match &ev {
                    Event::Start(e) => (e, true),
                    Event::Empty(e) => (e, false),
                    _ => unreachable!(),
                };
                let name = String::from_utf8(e.name().as_ref().to_vec()).unwrap();
                let attrs = e
                    .attributes()
                    .map(|a| {
                        let a = a.expect("a well-formed attribute");
                        (
                            String::from_utf8(a.key.as_ref().to_vec()).unwrap(),
                            a.unescape_value().unwrap().into_owned(),
                        )
                    })
                    .collect();
                out.push(Elem {
                    name,
                    attrs,
                    text: String::new(),
                });
                if is_start {
                    open.push(out.len() - 1);
                }
            }
            Event::Text(t) => {
                if let Some(&i) = open.last() {
                    out[i].text += &t.decode().unwrap();
                }
            }
            Event::GeneralRef(r) => {
                if let Some(&i) = open.last() {
                    let name = r.decode().unwrap();
                    let c = quick_xml::escape::resolve_predefined_entity(&name)
                        .expect("a predefined entity");
                    out[i].text += c;
                }
            }
            Event::End(_) => {
                open.pop();
            }
            Event::Eof => break,
            _ => {}
        }
    }
    assert!(open.is_empty(), "unclosed elements");
    assert_eq!(out.first().map(|e| e.name.as_str()), Some("svg"));
    out
}

fn texts<'a>(elems: &'a [Elem], class: &str) -> Vec<&'a str> {
    elems
        .iter()
        .filter(|e| e.name == "text" && e.attrs.get("class").map(String::as_str) == Some(class))
        .map(|e| e.text.as_str())
        .collect()
}

fn num(e: &Elem, a: &str) -> f64 {
    e.attrs[a].parse().unwrap()
}

#[test]
fn a_histogram_chart_has_the_hand_derived_axes_ticks_and_bars() {
    // 18 bins of 10 degrees over -90..90: -85 in bin 0, -10 and -5 in bin 8, 0 and 5 in
    // bin 9, 44 in bin 13, 89 in bin 17; 95 is outside.
    let values = [-85.0, -10.0, -5.0, 0.0, 5.0, 44.0, 89.0, 95.0];
    let h = Histogram::new(values, -90.0, 90.0, 18);
    let chart = arkit_tool::report::pose_chart("Poses", &[("yaw (deg)", h)]);
    let e = parse(&chart);
    assert_eq!(texts(&e, "title"), ["yaw of 8 samples"]);
    assert_eq!(texts(&e, "note"), ["1 outside the range"]);
    assert_eq!(texts(&e, "axis-label x"), ["yaw (deg)"]);
    assert_eq!(texts(&e, "axis-label y"), ["samples"]);
    // Angles every 30 degrees; counts up to the peak of 2, in whole samples.
    assert_eq!(
        texts(&e, "tick x"),
        ["-90", "-60", "-30", "0", "30", "60", "90"]
    );
    assert_eq!(texts(&e, "tick y"), ["0", "1", "2"]);
    let bars: Vec<&Elem> = e
        .iter()
        .filter(|b| b.attrs.get("class").map(String::as_str) == Some("bar"))
        .collect();
    let counts: Vec<f64> = bars.iter().map(|b| num(b, "data-value")).collect();
    assert_eq!(counts, [1.0, 2.0, 2.0, 1.0, 1.0]);
    // Plot area: x 64..366 (18 bins of 302/18), y 44..240 (196 units for 2 samples).
    let bw = (PANEL_WIDTH - 14.0 - 64.0) / 18.0;
    let plot_h = PANEL_HEIGHT - 44.0 - 50.0;
    for (b, (bin, count)) in bars
        .iter()
        .zip([(0, 1.0), (8, 2.0), (9, 2.0), (13, 1.0), (17, 1.0)])
    {
        assert!(
            (num(b, "x") - (64.0 + bin as f64 * bw + 0.5)).abs() < 0.01,
            "{b:?}"
        );
        assert!(
            (num(b, "height") - plot_h * count / 2.0).abs() < 0.01,
            "{b:?}"
        );
        assert!((num(b, "y") + num(b, "height") - (PANEL_HEIGHT - 50.0)).abs() < 0.02);
    }
}

#[test]
fn binned_means_chart_a_gap_for_an_empty_bin_and_decimal_ticks() {
    // Means 3.0 (bin 0..1) and 1.0 (bin 2..3); bin 1..2 is empty: no bar.
    let b = Bars::binned_mean(
        "Rotation error",
        "distance (m)",
        "mean rotation error (deg)",
        [(0.5, 2.0), (0.7, 4.0), (2.5, 1.0)],
        0.0,
        3.0,
        3,
    );
    let e = parse(&arkit_data::picture::bars_svg("Errors", &[b], 1));
    assert_eq!(texts(&e, "axis-label y"), ["mean rotation error (deg)"]);
    // Peak 3.0: ticks 0..3 in steps of 1 (3 / 5 = 0.6 rounds up to 1).
    assert_eq!(texts(&e, "tick y"), ["0", "1", "2", "3"]);
    assert_eq!(
        texts(&e, "tick x"),
        ["0.0", "0.5", "1.0", "1.5", "2.0", "2.5", "3.0"]
    );
    let values: Vec<f64> = e
        .iter()
        .filter(|b| b.attrs.get("class").map(String::as_str) == Some("bar"))
        .map(|b| num(b, "data-value"))
        .collect();
    assert_eq!(values, [3.0, 1.0]);
}

#[test]
fn the_loss_chart_puts_values_on_the_decade_scale_with_a_legend() {
    // 1, 10, 100 over steps 0..2: decades 1..100 span y 284..44, steps x 78..610, so
    // 10 at step 1 is at (344, 164) by hand.
    let svg = arkit_data::picture::log_line_svg(
        "Training loss",
        "training step",
        "weighted loss (log scale)",
        &[
            Series {
                name: "total".into(),
                values: vec![1.0, 10.0, 100.0],
                colour: [200, 0, 0],
            },
            Series {
                name: "kl".into(),
                values: vec![2.0, f64::NAN, 3.0],
                colour: [0, 0, 200],
            },
        ],
    );
    let e = parse(&svg);
    let [x0, x1, y0, y1] = LINE_PLOT;
    assert_eq!((x0, x1, y0, y1), (78.0, 610.0, 44.0, 284.0));
    assert_eq!(texts(&e, "tick y"), ["1", "10", "100"]);
    assert_eq!(texts(&e, "tick x"), ["0", "1", "2"]);
    assert_eq!(texts(&e, "legend"), ["total", "kl"]);
    assert_eq!(texts(&e, "axis-label x"), ["training step"]);
    let paths: Vec<&str> = e
        .iter()
        .filter(|p| p.attrs.get("class").map(String::as_str) == Some("series"))
        .map(|p| p.attrs["d"].as_str())
        .collect();
    assert_eq!(paths[0], "M78.00,284.00L344.00,164.00L610.00,44.00");
    // A value the log scale cannot show breaks the line: two separate points.
    assert!(
        paths[1].starts_with('M') && paths[1].matches('M').count() == 2 && !paths[1].contains('L')
    );
}

#[test]
fn inspect_plot_writes_an_svg_whose_bars_count_every_sample_and_refuses_png() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("pq");
    crate::support::converted_by_the_command(&dir.path().join("release"), &data, 2, 3, 160, 5);
    let bin = env!("CARGO_BIN_EXE_arkit-tool");
    let svg_path = dir.path().join("poses.svg");
    let out = Command::new(bin)
        .args(["inspect", "--json", "--dataset"])
        .arg(&data)
        .arg("--plot")
        .arg(&svg_path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let e = parse(&std::fs::read_to_string(&svg_path).unwrap());
    assert_eq!(
        texts(&e, "axis-label x"),
        ["yaw (deg)", "pitch (deg)", "roll (deg)", "distance (m)"]
    );
    // Each panel's bars add up to its histogram's counts, as `--json` prints them.
    let groups: Vec<usize> = e
        .iter()
        .enumerate()
        .filter(|(_, g)| g.attrs.get("class").map(String::as_str) == Some("chart"))
        .map(|(i, _)| i)
        .collect();
    assert_eq!(groups.len(), 4);
    for (k, &start) in groups.iter().enumerate() {
        let end = groups.get(k + 1).copied().unwrap_or(e.len());
        let drawn: f64 = e[start..end]
            .iter()
            .filter(|b| b.attrs.get("class").map(String::as_str) == Some("bar"))
            .map(|b| num(b, "data-value"))
            .sum();
        let counted: u64 = json["histograms"][k]["counts"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c.as_u64().unwrap())
            .sum();
        assert_eq!(drawn as u64, counted, "panel {k}");
    }
    assert_eq!(
        texts(&e, "title")[0],
        format!("yaw of {} samples", json["images"])
    );
    let out = Command::new(bin)
        .args(["inspect", "--dataset"])
        .arg(&data)
        .arg("--plot")
        .arg(dir.path().join("poses.png"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("poses.png") && err.contains("SVG"), "{err}");
    assert!(!dir.path().join("poses.png").exists());
}
