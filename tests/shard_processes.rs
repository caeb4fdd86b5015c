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

/// Runs `deploy/slurm/local-cluster.sh` with the environment `env`; its stdout, or
/// `None` (SKIPPED printed) without Slurm, root or the release's resources.
fn local_cluster(env: &[(&str, &str)]) -> Option<String> {
    let have = |tool: &str| {
        Command::new("sh")
            .args(["-c", &format!("command -v {tool}")])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if !["sbatch", "slurmctld", "slurmd", "munged"]
        .iter()
        .all(|t| have(t))
    {
        eprintln!("SKIPPED: Slurm is not installed (apt-get install slurm-wlm munge)");
        return None;
    }
    let root = Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| o.stdout.trim_ascii() == b"0");
    if !root {
        eprintln!("SKIPPED: starting slurmd needs root");
        return None;
    }
    let resources = std::env::var_os("ARKIT_RESOURCES")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/arkitface-resources")
        });
    if !resources.is_dir() {
        eprintln!("SKIPPED: no release resources at {}", resources.display());
        return None;
    }
    // One cluster at a time on this host (the tests of this file run in parallel).
    static ONE_CLUSTER: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _one = ONE_CLUSTER.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/slurm/local-cluster.sh");
    let out = Command::new("bash")
        .arg(script)
        .arg(dir.path())
        .env("ARKIT_TOOL", BIN)
        .env("ARKIT_RESOURCES", &resources)
        .envs(env.iter().copied())
        .output()
        .expect("run deploy/slurm/local-cluster.sh");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "local Slurm run failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("slurm: samples:") && stdout.contains("slurm: targets:"),
        "{stdout}"
    );
    assert!(stdout.lines().any(|l| l == "slurm: ok"), "{stdout}");
    Some(stdout)
}

/// The Slurm recipe under a real Slurm: `deploy/slurm/local-cluster.sh` starts a
/// one-node cluster (munged, slurmctld, slurmd on this host), submits
/// `deploy/slurm/submit.sh` (a convert array of 3 tasks, the merge, a render array of
/// 3 tasks) with sbatch, waits, and compares every Parquet file and `inspect --json`
/// with a single-machine run byte for byte. Skipped without Slurm, root or the
/// release's resources (CI installs Debian's slurm-wlm and munge).
#[test]
fn slurm_job_arrays_equal_a_single_run() {
    if let Some(stdout) = local_cluster(&[]) {
        assert!(stdout.contains("slurm: 7 job tasks done"), "{stdout}");
    }
}

/// The same recipe under faults (`SLURM_FAULTS=1`): convert task 1 cancelled (merge
/// refuses, naming part 1; resubmitted alone), render task 1 killed with SIGKILL once
/// it has written its first shard (its other shards missing, `train` refuses;
/// resubmitted alone), render task 2 re-queued; then every Parquet file and `inspect
/// --json` equal a single-machine run's, byte for byte. Skipped as above.
#[test]
fn slurm_recipe_survives_a_cancelled_a_killed_and_a_requeued_task() {
    let Some(stdout) = local_cluster(&[("SLURM_FAULTS", "1")]) else {
        return;
    };
    for line in [
        "slurm: fault 1: convert task",
        "merge refused:",
        "DependencyNeverSatisfied",
        "slurm: fault 2: render task",
        "train refused:",
        "slurm: fault 3: render task",
    ] {
        assert!(stdout.contains(line), "no '{line}' in:\n{stdout}");
    }
    assert!(stdout.contains("part 1 of 3 is missing"), "{stdout}");
}
