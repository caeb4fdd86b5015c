//! The binary: help that teaches, clear errors, exit codes, JSON output.

use std::process::Command;

fn tool() -> Command {
    Command::new(env!("CARGO_BIN_EXE_arkit-tool"))
}

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
