//! The cluster recipe on one machine: N tasks of `deploy/shard-task.sh` (the script
//! the Slurm array and the Kubernetes Indexed Job run) side by side on the same folder,
//! `convert` then `merge` then `render`, give the same files as single runs.

use std::path::Path;
use std::process::{Child, Command};

const BIN: &str = env!("CARGO_BIN_EXE_arkit-tool");

fn run(args: &[&str]) {
    let out = Command::new(BIN)
        .args(args)
        .output()
        .expect("run arkit-tool");
    assert!(
        out.status.success(),
        "arkit-tool {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// `deploy/shard-task.sh ARGS` with the task's index and count in the variables a
/// scheduler sets: Slurm's for even parts, a Kubernetes Indexed Job's for odd ones.
fn spawn_task(i: usize, n: usize, args: &[String]) -> Child {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/shard-task.sh");
    let mut c = Command::new("bash");
    c.arg(script).args(args).env("ARKIT_TOOL", BIN);
    if i.is_multiple_of(2) {
        c.env("SLURM_ARRAY_TASK_ID", i.to_string())
            .env("SLURM_ARRAY_TASK_COUNT", n.to_string());
    } else {
        c.env("JOB_COMPLETION_INDEX", i.to_string())
            .env("SHARD_COUNT", n.to_string());
    }
    c.stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn arkit-tool")
}

fn side_by_side(n: usize, args: impl Fn(usize) -> Vec<String>) {
    let children: Vec<Child> = (0..n).map(|i| spawn_task(i, n, &args(i))).collect();
    for (i, c) in children.into_iter().enumerate() {
        let out = c.wait_with_output().unwrap();
        assert!(
            out.status.success(),
            "part {i}/{n}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

fn parquet_files(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .filter(|n| n.ends_with(".parquet"))
        .collect();
    v.sort();
    v
}

#[test]
fn shard_processes_side_by_side_equal_a_single_run() {
    let dir = tempfile::tempdir().unwrap();
    let p = |s: &str| dir.path().join(s).to_string_lossy().to_string();
    run(&[
        "synth",
        "--output",
        &p("rel"),
        "--subjects",
        "5",
        "--images-per-subject",
        "8",
        "--size",
        "160x160",
        "--seed",
        "4",
    ]);
    // One process for everything.
    run(&[
        "convert",
        "--input",
        &p("rel"),
        "--output",
        &p("single"),
        "--rows-per-shard",
        "6",
    ]);
    run(&[
        "render",
        "--dataset",
        &p("single"),
        "--size",
        "48",
        "--points",
        "64",
        "--uv-size",
        "16",
    ]);
    // Three processes at once per stage, one merge.
    let n = 3;
    side_by_side(n, |_| {
        [
            "convert",
            &p("rel"),
            &p("parts"),
            "--rows-per-shard",
            "6",
            "--jobs",
            "1",
        ]
        .map(String::from)
        .to_vec()
    });
    run(&["merge", "--dataset", &p("parts")]);
    side_by_side(n, |_| {
        [
            "render",
            &p("parts"),
            "--size",
            "48",
            "--points",
            "64",
            "--uv-size",
            "16",
            "--jobs",
            "1",
        ]
        .map(String::from)
        .to_vec()
    });
    for sub in ["samples", "targets"] {
        let (a, b) = (
            dir.path().join("single").join(sub),
            dir.path().join("parts").join(sub),
        );
        let files = parquet_files(&a);
        assert!(files.len() >= 6, "{sub}: {files:?}");
        assert_eq!(files, parquet_files(&b), "{sub}");
        for f in &files {
            assert!(
                std::fs::read(a.join(f)).unwrap() == std::fs::read(b.join(f)).unwrap(),
                "{sub}/{f} differs between the single run and the parts"
            );
        }
    }
    let manifest = |d: &str| -> serde_json::Value {
        serde_json::from_str(
            &std::fs::read_to_string(dir.path().join(d).join("dataset.json")).unwrap(),
        )
        .unwrap()
    };
    let (a, b) = (manifest("single"), manifest("parts"));
    for key in ["converted", "skipped", "shards"] {
        assert_eq!(a[key], b[key], "{key}");
    }
    assert_eq!(a["converted"], 40);
}
