//! The binary: help that teaches, clear errors, exit codes, JSON output.

use crate::support::tool;

#[test]
fn help_lists_commands_and_conventions() {
    let out = tool().arg("--help").output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success());
    for word in ["synth", "topology", "info", "R_t", "yxz"] {
        assert!(text.contains(word), "--help lacks {word}: {text}");
    }
    let out = tool().args(["synth", "--help"]).output().unwrap();
    assert!(String::from_utf8_lossy(&out.stdout).contains("Example: arkit-tool synth"));
}

#[test]
fn bad_size_is_a_clear_error() {
    let out = tool()
        .args(["synth", "--output", "/tmp/never", "--size", "800by600"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("is not WIDTHxHEIGHT"));
    let out = tool()
        .args(["synth", "--output", "/tmp/never", "--size", "8x8"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("outside 32..8192"));
}

#[test]
fn synth_json_then_info_reads_every_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = tool()
        .args([
            "synth",
            "--subjects",
            "2",
            "--images-per-subject",
            "2",
            "--size",
            "96x96",
            "--seed",
            "4",
            "--json",
            "--output",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        summary["train_samples"].as_u64().unwrap() + summary["test_samples"].as_u64().unwrap(),
        4
    );
    let mut infos = Vec::new();
    for split in ["train", "test"] {
        let base = dir.path().join(format!("ARKitFace_info_{split}/info"));
        for s in std::fs::read_dir(&base).unwrap() {
            for a in std::fs::read_dir(s.unwrap().path()).unwrap() {
                for f in std::fs::read_dir(a.unwrap().path()).unwrap() {
                    infos.push(f.unwrap().path());
                }
            }
        }
    }
    assert_eq!(infos.len(), 4);
    // One broken file among good ones: all are reported, exit code 1, the file named.
    let broken = dir.path().join("broken_info.npz");
    std::fs::write(&broken, b"not a zip").unwrap();
    let out = tool()
        .arg("info")
        .arg("--json")
        .args(&infos)
        .arg(&broken)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 5);
    assert_eq!(lines.iter().filter(|l| l["ok"] == true).count(), 4);
    let bad = lines.iter().find(|l| l["ok"] == false).unwrap();
    assert!(bad["error"].as_str().unwrap().contains("broken_info.npz"));
}

#[test]
fn topology_reports_four_loops() {
    let out = tool().args(["topology", "--json"]).output().unwrap();
    assert!(out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["vertices"], 1220);
    assert_eq!(v["boundary_loops"].as_array().unwrap().len(), 4);
    let out = tool()
        .args(["topology", "--resources", "/nonexistent/dir"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/dir/triangles.npy"));
}

#[test]
fn convert_reports_skips_and_strict_fails_after_converting() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let out = tool()
        .args([
            "synth",
            "--subjects",
            "2",
            "--images-per-subject",
            "2",
            "--size",
            "96x96",
            "--output",
        ])
        .arg(&data)
        .output()
        .unwrap();
    assert!(out.status.success());
    // Break one image.
    let img_root = data.join("ARKitFace_image_train/image");
    let subject = std::fs::read_dir(&img_root)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let action = std::fs::read_dir(&subject)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let jpg = std::fs::read_dir(&action)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    std::fs::write(&jpg, b"garbage").unwrap();
    for (strict, code) in [(false, 0), (true, 1)] {
        let pq = dir.path().join(format!("pq-{strict}"));
        let mut cmd = tool();
        cmd.args(["convert", "--input"])
            .arg(&data)
            .arg("--output")
            .arg(&pq);
        if strict {
            cmd.arg("--strict");
        }
        let out = cmd.output().unwrap();
        assert_eq!(out.status.code(), Some(code));
        let stderr = String::from_utf8_lossy(&out.stderr);
        let last = stderr.lines().last().unwrap();
        assert!(last.starts_with("converted 3 samples, skipped 1"), "{last}");
        assert!(pq.join("dataset.json").exists());
    }
    let out = tool()
        .args(["convert", "--output", "/tmp/x", "--shard", "3/2", "--input"])
        .arg(&data)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("need 0 <= I < N"));
}
