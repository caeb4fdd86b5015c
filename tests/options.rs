//! Hostile options and stale output: every numeric option is checked when the command
//! line is parsed (a clap error naming the option, exit status 2, nothing written);
//! the checks between options come before any file is read or written; `render` keeps
//! old targets only when they were made from the same dataset with the same options and
//! topology.

use crate::support::tool;
use arkit_core::conventions::Camera;
use arkit_data::render::FaceRenderer;
use arkit_data::render::RenderOptions;
use arkit_data::store;
use std::path::{Path, PathBuf};
use std::process::Output;

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn run_ok(args: &[&str]) -> Output {
    let out = tool().args(args).output().unwrap();
    assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    out
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A converted dataset of `subjects` x 2 tiny images (96x96), from `seed`.
fn dataset(root: &Path, name: &str, subjects: usize, seed: u64) -> PathBuf {
    let raw = root.join(format!("{name}-raw"));
    let pq = root.join(name);
    run_ok(&[
        "synth",
        "--subjects",
        &subjects.to_string(),
        "--images-per-subject",
        "2",
        "--size",
        "96x96",
        "--seed",
        &seed.to_string(),
        "--output",
        s(&raw),
    ]);
    run_ok(&["convert", "--input", s(&raw), "--output", s(&pq)]);
    pq
}

/// `render` at the smallest sizes (fast), plus `extra` arguments.
fn render(dataset: &Path, output: &Path, extra: &[&str]) -> Output {
    tool()
        .args([
            "render",
            "--size",
            "16",
            "--uv-size",
            "16",
            "--points",
            "16",
        ])
        .args(["--dataset", s(dataset), "--output", s(output)])
        .args(extra)
        .output()
        .unwrap()
}

#[test]
fn out_of_range_options_are_clap_errors_naming_the_option() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("never");
    let o = s(&out);
    let cases: &[(&[&str], &str)] = &[
        (&["render", "--dataset", o, "--size", "20000"], "--size"),
        (&["render", "--dataset", o, "--size", "0"], "--size"),
        (&["render", "--dataset", o, "--size", "15"], "--size"),
        (&["render", "--dataset", o, "--uv-size", "0"], "--uv-size"),
        (&["render", "--dataset", o, "--uv-size", "513"], "--uv-size"),
        (&["render", "--dataset", o, "--points", "0"], "--points"),
        (
            &["render", "--dataset", o, "--points", "100000000"],
            "--points",
        ),
        (&["render", "--dataset", o, "--jobs", "0"], "--jobs"),
        (
            &["render", "--dataset", o, "--shard", "0/1000000"],
            "--shard",
        ),
        (
            &["train", "--dataset", o, "--output", o, "--lr", "-1"],
            "--lr",
        ),
        (&["train", "--dataset", o, "--output", o, "--lr=-1"], "--lr"),
        (&["render", "--dataset", o, "--size", "-5"], "--size"),
        (
            &["train", "--dataset", o, "--output", o, "--lr", "0"],
            "--lr",
        ),
        (
            &["train", "--dataset", o, "--output", o, "--lr", "NaN"],
            "--lr",
        ),
        (
            &["train", "--dataset", o, "--output", o, "--batch", "0"],
            "--batch",
        ),
        (
            &["train", "--dataset", o, "--output", o, "--epochs", "0"],
            "--epochs",
        ),
        (
            &["train", "--dataset", o, "--output", o, "--steps", "0"],
            "--steps",
        ),
        (
            &["train", "--dataset", o, "--output", o, "--lr-hold", "2"],
            "--lr-hold",
        ),
        (
            &[
                "train",
                "--dataset",
                o,
                "--output",
                o,
                "--colour-jitter",
                "1.5",
            ],
            "--colour-jitter",
        ),
        (
            &["train", "--dataset", o, "--output", o, "--shift-px", "1000"],
            "--shift-px",
        ),
        (
            &[
                "augment",
                "--input",
                o,
                "--output",
                o,
                "--jpeg-quality",
                "0",
            ],
            "--jpeg-quality",
        ),
        (
            &[
                "augment",
                "--input",
                o,
                "--output",
                o,
                "--max-angle",
                "1000",
            ],
            "--max-angle",
        ),
        (
            &["augment", "--input", o, "--output", o, "--min-change", "-5"],
            "--min-change",
        ),
        (
            &[
                "augment",
                "--input",
                o,
                "--output",
                o,
                "--per-sample",
                "1000",
            ],
            "--per-sample",
        ),
        (&["synth", "--output", o, "--subjects", "0"], "--subjects"),
        (
            &["synth", "--output", o, "--images-per-subject", "0"],
            "--images-per-subject",
        ),
        (
            &["synth", "--output", o, "--jpeg-quality", "101"],
            "--jpeg-quality",
        ),
        (
            &["synth", "--output", o, "--test-fraction", "1.5"],
            "--test-fraction",
        ),
        (&["synth", "--output", o, "--size", "20000x800"], "--size"),
        (
            &[
                "convert",
                "--input",
                o,
                "--output",
                o,
                "--rows-per-shard",
                "0",
            ],
            "--rows-per-shard",
        ),
        (
            &["split", "--dataset", o, "--test-fraction", "1"],
            "--test-fraction",
        ),
        (
            &["split", "--dataset", o, "--test-subjects", "0"],
            "--test-subjects",
        ),
        (
            &[
                "predict",
                "--oracle",
                "--dataset",
                o,
                "--output",
                o,
                "--outliers",
                "1",
            ],
            "--outliers",
        ),
        (
            &[
                "predict",
                "--oracle",
                "--dataset",
                o,
                "--output",
                o,
                "--noise-px",
                "-1",
            ],
            "--noise-px",
        ),
        (
            &[
                "predict",
                "--oracle",
                "--dataset",
                o,
                "--output",
                o,
                "--threshold-px",
                "0",
            ],
            "--threshold-px",
        ),
        (&["demo", "--output", o, "--jobs", "5000"], "--jobs"),
    ];
    for (args, option) in cases {
        let r = tool().args(*args).output().unwrap();
        let e = stderr(&r);
        assert_eq!(r.status.code(), Some(2), "{args:?}: {e}");
        assert!(
            e.contains("invalid value") && e.contains(option),
            "{args:?} does not name {option}: {e}"
        );
        assert!(!out.exists(), "{args:?} wrote {}", out.display());
    }
}

#[test]
fn help_states_the_ranges() {
    for (command, ranges) in [
        (
            "render",
            &["16..=1024", "16..=512", "1..=65536", "--size squared"][..],
        ),
        ("train", &["(0, 1]", "[0, 1]", "1..=1024", "1..=100000"][..]),
        ("augment", &["(0, 90]", "1..=100", "0..=100"][..]),
        (
            "predict",
            &["[0, 1)", "[0, 100]", "(0, 1000]", "1..=10000", "[0, 1000]"][..],
        ),
        ("synth", &["1..=100000", "32..=8192", "1..=100"][..]),
    ] {
        let out = run_ok(&[command, "--help"]);
        let text = String::from_utf8_lossy(&out.stdout);
        for r in ranges {
            assert!(text.contains(r), "`{command} --help` lacks {r}");
        }
    }
}

#[test]
fn checks_between_options_come_before_any_output() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    // More points than a 16-pixel crop has: refused before the (absent) dataset is read.
    let r = tool()
        .args([
            "render",
            "--dataset",
            "/nonexistent",
            "--size",
            "16",
            "--points",
            "257",
        ])
        .args(["--output", s(&out)])
        .output()
        .unwrap();
    assert_eq!(r.status.code(), Some(2));
    let e = stderr(&r);
    assert!(
        e.contains("invalid --points") && e.contains("--size 16"),
        "{e}"
    );
    assert!(!out.exists());
    // The same through the library, which does not rely on the command line.
    for (size, uv_size, points, option) in [
        (20000, 16, 16, "--size"),
        (0, 16, 16, "--size"),
        (16, 0, 16, "--uv-size"),
        (16, 16, 0, "--points"),
        (16, 16, 257, "--points"),
        (1024, 16, 100_000_000, "--points"),
    ] {
        let ro = RenderOptions {
            size,
            uv_size,
            points,
            seed: 0,
            output: out.clone(),
            shard: (0, 1),
            full_mask: false,
        };
        let renderer = FaceRenderer::new(
            arkit_data::mesh::builtin().topology.clone(),
            Camera::release_projection(),
        )
        .unwrap();
        let e =
            arkit_data::render::render_dataset(Path::new("/nonexistent"), &renderer, &ro, &|_| {})
                .unwrap_err()
                .to_string();
        assert!(e.contains(&format!("invalid {option}")), "{e}");
        assert!(!out.exists());
    }
    // train: --lowered-start belongs to the official loss's schedule.
    let r = tool()
        .args(["train", "--dataset", "/nonexistent", "--output", s(&out)])
        .args(["--loss", "paper", "--lowered-start"])
        .output()
        .unwrap();
    assert_eq!(r.status.code(), Some(2));
    assert!(
        stderr(&r).contains("invalid --lowered-start"),
        "{}",
        stderr(&r)
    );
    assert!(!out.exists());
    // augment: --min-change above --max-change, and nothing to write.
    for (extra, option) in [
        (
            &["--min-change", "40", "--max-change", "30"][..],
            "--min-change",
        ),
        (
            &[
                "--min-change",
                "40",
                "--max-angle",
                "30",
                "--max-change",
                "50",
            ][..],
            "--min-change",
        ),
        (&["--per-sample", "0"][..], "--per-sample"),
    ] {
        let r = tool()
            .args(["augment", "--input", "/nonexistent", "--output", s(&out)])
            .args(extra)
            .output()
            .unwrap();
        assert_eq!(r.status.code(), Some(2));
        assert!(
            stderr(&r).contains(&format!("invalid {option}")),
            "{}",
            stderr(&r)
        );
        assert!(!out.exists());
    }
}

#[test]
fn render_keeps_targets_only_from_the_same_dataset_and_options() {
    let dir = tempfile::tempdir().unwrap();
    let a = dataset(dir.path(), "a", 2, 1);
    let b = dataset(dir.path(), "b", 2, 2);
    let out = dir.path().join("t");
    let r = render(&a, &out, &[]);
    assert!(r.status.success(), "{}", stderr(&r));
    let shard = store::shard_path(&out, 0);
    let made_from_a = std::fs::read(&shard).unwrap();
    // Another dataset into the same folder: refused, the old targets left alone.
    let r = render(&b, &out, &[]);
    assert_eq!(r.status.code(), Some(2));
    let e = stderr(&r);
    assert!(
        e.contains("another dataset") && e.contains("--overwrite") && e.contains("render.json"),
        "{e}"
    );
    assert_eq!(std::fs::read(&shard).unwrap(), made_from_a);
    // Other options: refused, naming the option that differs.
    let r = render(&a, &out, &["--seed", "7"]);
    assert_eq!(r.status.code(), Some(2));
    assert!(stderr(&r).contains("seed 0 there, 7 now"), "{}", stderr(&r));
    // The same dataset and options: kept (same bytes).
    let r = render(&a, &out, &[]);
    assert!(r.status.success(), "{}", stderr(&r));
    assert_eq!(std::fs::read(&shard).unwrap(), made_from_a);
    // --overwrite replaces them with exactly what a fresh folder gets.
    let r = render(&b, &out, &["--overwrite"]);
    assert!(r.status.success(), "{}", stderr(&r));
    let fresh = dir.path().join("fresh");
    assert!(render(&b, &fresh, &[]).status.success());
    let made_from_b = std::fs::read(store::shard_path(&fresh, 0)).unwrap();
    assert_ne!(made_from_a, made_from_b);
    assert_eq!(std::fs::read(&shard).unwrap(), made_from_b);
    assert_eq!(
        std::fs::read(out.join("targets/render.json")).unwrap(),
        std::fs::read(fresh.join("targets/render.json")).unwrap()
    );
    // --overwrite is for a single process.
    let r = render(&b, &out, &["--overwrite", "--shard", "0/2"]);
    assert_eq!(r.status.code(), Some(2));
    assert!(stderr(&r).contains("--overwrite"), "{}", stderr(&r));
}

#[test]
fn a_run_that_wrote_no_shard_does_not_block_a_corrected_rerun() {
    let dir = tempfile::tempdir().unwrap();
    let a = dataset(dir.path(), "a", 1, 3);
    let out = dir.path().join("t");
    // A bad option: nothing at all is written.
    let r = tool()
        .args([
            "render",
            "--size",
            "16",
            "--points",
            "1000",
            "--dataset",
            s(&a),
        ])
        .args(["--output", s(&out)])
        .output()
        .unwrap();
    assert_eq!(r.status.code(), Some(2));
    assert!(stderr(&r).contains("invalid --points"), "{}", stderr(&r));
    assert!(!out.exists());
    // A run that died after writing render.json but before any shard (as an older
    // version's `--size 20000` did): its render.json is replaced.
    std::fs::create_dir_all(out.join("targets")).unwrap();
    std::fs::write(out.join("targets/render.json"), r#"{"size": 20000}"#).unwrap();
    let r = render(&a, &out, &[]);
    assert!(r.status.success(), "{}", stderr(&r));
    assert!(store::shard_path(&out, 0).exists());
    let settings: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("targets/render.json")).unwrap()).unwrap();
    assert_eq!(settings["size"], 16);
    assert_eq!(settings["dataset"].as_str().unwrap().len(), 64);
    // Shards but no render.json: nobody can say how they were made, so refused.
    std::fs::remove_file(out.join("targets/render.json")).unwrap();
    let r = render(&a, &out, &[]);
    assert_eq!(r.status.code(), Some(2));
    assert!(stderr(&r).contains("no render.json"), "{}", stderr(&r));
}

#[test]
fn render_refuses_the_builtin_face_for_a_dataset_converted_with_resources() {
    let dir = tempfile::tempdir().unwrap();
    let a = dataset(dir.path(), "a", 1, 4);
    // As if converted with `--resources /data/resources` (the release's mesh has as many
    // vertices as the built-in face, so nothing else would notice).
    let path = a.join("dataset.json");
    let mut m: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    m["topology"] = "/data/resources".into();
    m["topology_sha256"] = "ab".repeat(32).into();
    std::fs::write(&path, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
    let out = dir.path().join("t");
    let r = render(&a, &out, &[]);
    assert_eq!(r.status.code(), Some(2));
    let e = stderr(&r);
    assert!(
        e.contains("invalid --resources") && e.contains("/data/resources"),
        "{e}"
    );
    assert!(!out.exists());
}

#[test]
fn rows_render_cannot_use_are_skipped_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    let a = dataset(dir.path(), "a", 3, 5);
    let m = arkit_data::store::read_manifest(&a.join("dataset.json")).unwrap();
    let file = a.join(&m.shards[0].samples_file);
    let rows = store::read_samples(&file).unwrap();
    assert!(rows.len() >= 4);
    // Readers refuse a shard that differs from the manifest; these rows are meant to be
    // read, as if convert had written them, so the manifest forgets the shard's size.
    let mut m = m;
    m.shards[0].bytes = 0;
    std::fs::write(
        a.join("dataset.json"),
        serde_json::to_string_pretty(&m).unwrap(),
    )
    .unwrap();
    // A row whose verts or landmarks are not whole points cannot be written any more
    // (fixed-size lists); in a file of the format before (variable-length lists) the
    // reader refuses it, naming the file and the column (it used to panic on chunks(3)).
    let mut bad = rows.clone();
    bad[0].verts.truncate(10);
    assert!(store::samples_frame(&bad, 1220).is_err());
    let mut odd = rows.clone();
    odd[1].landmarks_2d.pop();
    for (rows, column) in [(&bad, "verts"), (&odd, "landmarks_2d")] {
        store::write_parquet(&file, &mut store::samples_frame_format1(rows).unwrap()).unwrap();
        let e = store::read_samples(&file).unwrap_err().to_string();
        assert!(
            e.contains(&file.display().to_string()) && e.contains(&format!("column '{column}'")),
            "{e}"
        );
    }
    let mut rows = rows;
    rows[2].image_width = 20000; // beyond the rasterizer's buffer
    store::write_samples(&file, &rows, 1220).unwrap();
    let renderer = FaceRenderer::new(
        arkit_data::mesh::builtin().topology.clone(),
        Camera::release_projection(),
    )
    .unwrap();
    let out = dir.path().join("t");
    let ro = RenderOptions {
        size: 16,
        uv_size: 16,
        points: 16,
        seed: 0,
        output: out.clone(),
        shard: (0, 1),
        full_mask: true,
    };
    let summary = arkit_data::render::render_dataset(&a, &renderer, &ro, &|_| {}).unwrap();
    assert_eq!(summary.skipped, 1, "{:?}", summary.skipped_examples);
    let reasons = summary.skipped_examples.join("\n");
    assert!(reasons.contains("invalid image size"), "{reasons}");
    assert_eq!(
        store::parquet_row_count(&store::shard_path(&out, 0)).unwrap(),
        rows.len() - 1
    );
}

/// Every file of a folder, by path relative to it, with its bytes; not the writers'
/// lock files, which name their holder (a process id).
fn tree(root: &Path) -> std::collections::BTreeMap<PathBuf, Vec<u8>> {
    let mut files = std::collections::BTreeMap::new();
    let mut todo = vec![root.to_path_buf()];
    while let Some(dir) = todo.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                todo.push(path);
            } else if path.extension().is_some_and(|e| e == "lock") {
                continue;
            } else {
                let bytes = std::fs::read(&path).unwrap();
                files.insert(path.strip_prefix(root).unwrap().to_path_buf(), bytes);
            }
        }
    }
    files
}

#[test]
fn every_simd_level_writes_the_same_bytes_and_an_unknown_one_warns() {
    // `render` takes the rasterizer's, the crop's and the UV map's lanes: the same
    // files at every `ARKIT_SIMD` cap (levels above the CPU's run at the CPU's), and an
    // unknown value is a warning naming the variable and its values, then `auto`.
    let root = tempfile::tempdir().unwrap();
    let pq = dataset(root.path(), "pq", 2, 5);
    let render = |simd: &str| {
        let out = root.path().join(format!("render-{simd}"));
        let run = tool()
            .env("ARKIT_SIMD", simd)
            .args(["render", "--dataset", s(&pq), "--output", s(&out)])
            .args(["--size", "64", "--uv-size", "32", "--points", "64"])
            .output()
            .unwrap();
        assert!(run.status.success(), "{simd}: {}", stderr(&run));
        (tree(&out), stderr(&run))
    };
    let (auto, quiet) = render("auto");
    assert!(!quiet.contains("ARKIT_SIMD"), "{quiet}");
    assert!(!auto.is_empty());
    for level in ["scalar", "avx2", "avx512", "sse9"] {
        let (files, err) = render(level);
        assert!(files == auto, "ARKIT_SIMD={level}: other bytes than auto's");
        let warning = "warning: ARKIT_SIMD=\"sse9\": expected one of scalar, avx2, avx512 or auto; using auto";
        assert_eq!(err.contains(warning), level == "sse9", "{level}: {err}");
    }
}
