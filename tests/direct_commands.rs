//! The "Direct 6DoF Regress" baseline through the commands: a model `train
//! --architecture direct` writes is predicted and scored by `predict --model` and
//! `eval` (`-` for 3DRecon, no mask line), and what does not apply to it is refused by
//! name. (The library's side, shapes to a trained model's predictions, is tested in
//! `crates/arkit-perspnet/tests/direct.rs`.)

use std::path::Path;
use std::process::Command;

#[test]
fn a_direct_model_through_predict_eval_and_the_refusals() {
    let dir = tempfile::tempdir().unwrap();
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (release, pq, model, pred) = (
        dir.path().join("release"),
        dir.path().join("pq"),
        dir.path().join("model"),
        dir.path().join("pred.parquet"),
    );
    let run = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_arkit-tool"))
            .args(args)
            .env("ARKIT_INPUT_ROOT", &release)
            .output()
            .unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stdout).to_string()
                + &String::from_utf8_lossy(&out.stderr),
        )
    };
    let ok = |args: &[&str]| {
        let (ok, text) = run(args);
        assert!(ok, "{args:?}: {text}");
        text
    };
    ok(&[
        "synth",
        "--subjects",
        "2",
        "--images-per-subject",
        "4",
        "--size",
        "256x256",
        "--seed",
        "5",
        "--output",
        &s(&release),
    ]);
    ok(&["convert", "--input", &s(&release), "--output", &s(&pq)]);
    ok(&[
        "render",
        "--dataset",
        &s(&pq),
        "--size",
        "64",
        "--points",
        "256",
        "--uv-size",
        "16",
        "--output",
        &s(&pq),
    ]);
    ok(&[
        "train",
        "--dataset",
        &s(&pq),
        "--architecture",
        "direct",
        "--split",
        "all",
        "--steps",
        "2",
        "--output",
        &s(&model),
    ]);
    ok(&[
        "predict",
        "--model",
        &s(&model),
        "--dataset",
        &s(&pq),
        "--split",
        "all",
        "--output",
        &s(&pred),
    ]);
    let text = ok(&[
        "eval",
        "--dataset",
        &s(&pq),
        "--predictions",
        &s(&pred),
        "--split",
        "all",
    ]);
    let header = text.lines().find(|l| l.contains("3DRecon")).unwrap();
    let values = text
        .lines()
        .skip_while(|l| !l.contains("3DRecon"))
        .nth(1)
        .unwrap();
    assert_eq!(
        header.split_whitespace().count(),
        values.split_whitespace().count()
    );
    assert_eq!(values.split_whitespace().last(), Some("-"), "{text}");
    assert!(!text.contains("mask:"), "{text}");
    let (ok, text) = run(&[
        "predict",
        "--model",
        &s(&model),
        "--dataset",
        &s(&pq),
        "--mask",
        "truth",
        "--output",
        &s(&pred),
    ]);
    assert!(!ok && text.contains("--mask truth"), "{text}");
    let (ok, text) = run(&[
        "export-weights",
        &s(&model),
        "--output",
        &s(&dir.path().join("w.safetensors")),
    ]);
    assert!(!ok && text.contains("direct"), "{text}");
    let (ok, text) = run(&[
        "train",
        "--dataset",
        &s(&pq),
        "--architecture",
        "direct",
        "--loss",
        "paper",
        "--output",
        &s(&dir.path().join("m2")),
    ]);
    assert!(!ok && text.contains("--loss"), "{text}");
}
