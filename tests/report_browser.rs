//! The demo end to end at its smallest size, and its report page opened in a real
//! headless browser (Debian's Chromium). The browser part skips, saying so, when no
//! Chromium is installed; set `ARKIT_CHROMIUM` to use another binary.

use arkit_tool::demo::{self, DemoPlan, DemoProgress, STAGES};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicU64, Ordering};

struct Count {
    units: AtomicU64,
    stages: std::sync::Mutex<Vec<String>>,
}

impl DemoProgress for Count {
    fn stage(&self, index: usize, name: &str) {
        assert_eq!(STAGES[index - 1], name);
        self.stages.lock().unwrap().push(name.to_string());
    }
    fn advance(&self, units: u64) {
        self.units.fetch_add(units, Ordering::Relaxed);
    }
}

fn chromium() -> Option<PathBuf> {
    if let Ok(p) = std::env::var("ARKIT_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    [
        "/usr/bin/chromium",
        "/usr/bin/chromium-browser",
        "/usr/bin/google-chrome",
    ]
    .iter()
    .map(PathBuf::from)
    .find(|p| p.exists())
}

/// The page's `<body>` after load, as the browser's DOM dump shows it.
fn body_tag(browser: &Path, page: &Path, profile: &Path) -> String {
    let out = Command::new(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--virtual-time-budget=10000",
            "--dump-dom",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("file://{}", page.display()))
        .output()
        .expect("run chromium");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let dom = String::from_utf8_lossy(&out.stdout).to_string();
    let start = dom.find("<body").expect("a body in the DOM dump");
    dom[start..start + dom[start..].find('>').unwrap() + 1].to_string()
}

#[test]
fn demo_runs_every_stage_and_its_report_opens_in_a_browser() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let plan = DemoPlan::smoke(3);
    let topology = arkit_data::mesh::builtin().topology.clone();
    let progress = Count {
        units: AtomicU64::new(0),
        stages: Default::default(),
    };
    let summary = demo::run_demo(&out, &plan, &topology, &progress).unwrap();
    // Every stage ran, in order, and the single progress display reached its end.
    assert_eq!(*progress.stages.lock().unwrap(), STAGES.to_vec());
    assert_eq!(progress.units.load(Ordering::Relaxed), plan.units());
    let names: Vec<&str> = summary.stages.iter().map(|s| s.stage.as_str()).collect();
    assert_eq!(names, STAGES.to_vec());
    // Both predictors were scored on the held-out subject's images only.
    let test_images = plan.test_subjects * plan.images_per_subject;
    assert_eq!(summary.model.samples, test_images);
    assert_eq!(summary.baseline.samples, test_images);
    assert!(summary.model.recon_mean_mm.is_some() && summary.baseline.recon_mean_mm.is_none());
    for f in [
        "demo.json",
        "predictions.parquet",
        "baseline.parquet",
        "model/model.safetensors",
        "dataset/splits/splits.parquet",
        "report/index.html",
    ] {
        assert!(out.join(f).exists(), "{f}");
    }
    // A second run into the same folder is refused rather than mixed in.
    let e = demo::run_demo(&out, &plan, &topology, &progress)
        .unwrap_err()
        .to_string();
    assert!(e.contains("not empty"), "{e}");

    let html = std::fs::read_to_string(out.join("report/index.html")).unwrap();
    let images: Vec<&str> = html
        .split("<img src=\"")
        .skip(1)
        .map(|s| &s[..s.find('"').unwrap()])
        .collect();
    assert!(images.len() >= 3, "{images:?}");
    for i in &images {
        assert!(out.join("report").join(i).exists(), "{i}");
    }
    // The charts are inline SVG (the browser draws their text), each also a file; the
    // worst predictions' captions are an SVG laid over their picture.
    let charts = html.matches("<svg ").count();
    assert_eq!(
        charts, 4,
        "poses, loss, errors by pose, captions of the worst"
    );
    for f in ["poses.svg", "loss.svg", "errors_by_pose.svg", "worst.svg"] {
        let svg = std::fs::read_to_string(out.join("report").join(f)).unwrap();
        assert!(
            svg.starts_with("<svg ") && svg.trim_end().ends_with("</svg>"),
            "{f}"
        );
    }
    for label in [
        "yaw (deg)",
        "distance (m)",
        "training step",
        "mean rotation error (deg)",
    ] {
        assert!(html.contains(label), "{label}");
    }
    // Only the SVG namespace's name, never a fetch.
    let without_ns = html.replace("xmlns=\"http://www.w3.org/2000/svg\"", "");
    assert!(!without_ns.contains("http://") && !without_ns.contains("https://"));

    let Some(browser) = chromium() else {
        eprintln!(
            "SKIPPED browser check: no Chromium (apt-get install chromium, or set ARKIT_CHROMIUM)"
        );
        return;
    };
    let body = body_tag(
        &browser,
        &out.join("report/index.html"),
        &dir.path().join("profile"),
    );
    let n = images.len();
    assert!(
        body.contains(&format!("data-images=\"{n}/{n}\"")),
        "not every image loaded: {body}"
    );
    assert!(
        body.contains(&format!("data-charts=\"{charts}/{charts}\"")),
        "not every chart was drawn: {body}"
    );
    assert!(body.contains("data-errors=\"0\""), "{body}");
    // The check itself can fail: a page with a broken image and a chart that is not
    // drawn reports both.
    let broken = out.join("report/broken.html");
    let html = html
        .replacen("targets.png", "no-such-file.png", 1)
        .replacen("<svg ", "<svg style=\"display:none\" ", 1);
    std::fs::write(&broken, html).unwrap();
    let body = body_tag(&browser, &broken, &dir.path().join("profile2"));
    assert!(
        body.contains(&format!("data-images=\"{}/{n}\"", n - 1)),
        "{body}"
    );
    assert!(
        body.contains(&format!("data-charts=\"{}/{charts}\"", charts - 1)),
        "{body}"
    );
    assert!(!body.contains("data-errors=\"0\""), "{body}");
}
