//! The kill harness: `convert`, `render` and `crops` are each killed (SIGKILL, as a
//! cluster pre-empts a job) at points drawn from a seed over their measured
//! uninterrupted run. While the folder is torn, the readers (`inspect`, its `--json`,
//! `train`, `predict --oracle`, the loader's crop store) must either refuse with an
//! error naming the file or folder, or read the last complete state; `inspect`'s state
//! line must name the torn output and the command that completes it. The same command
//! rerun must then complete, its outputs equal byte for byte to an uninterrupted run's,
//! and no temporary (`.NAME.tmp-TOKEN`) left anywhere in the folder. Every other kill
//! leaves the writer a zombie (not reaped until the rerun has cleaned up), as in a
//! container whose PID 1 reaps nothing.
//!
//! `ARKIT_KILL_POINTS` (default 3) sets the points per command, `ARKIT_KILL_SEED`
//! (default 53) the seed. The full run (docs/testing.md):
//!
//! ```text
//! ARKIT_KILL_POINTS=20 cargo test --release --locked --test tests kill -- --nocapture
//! ```
//!
//! A table of the verdicts is printed to stdout (`--nocapture` shows it).

use crate::support::tool;
use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::Instant;

/// The crop side of the stores (small: the harness measures states, not pixels).
const CROP_SIZE: &str = "64";

/// A small deterministic generator (splitmix64) for the kill points.
pub(crate) struct Points(pub(crate) u64);

impl Points {
    pub(crate) fn next_unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

pub(crate) fn env_number(name: &str, default: u64) -> u64 {
    match std::env::var(name) {
        Ok(v) => v
            .parse()
            .unwrap_or_else(|_| panic!("{name}={v}: not a whole number")),
        Err(_) => default,
    }
}

/// Reads the stderr of `child`, a writer run with `ARKIT_PAUSE_BEFORE_RENAME`, until it
/// reports its pause (`... paused before renaming TMP to PATH`) and returns that line,
/// then drains the rest on a thread (a writer whose stderr is closed would die of its
/// next line instead of waiting for its kill). `Err` holds what it printed when it
/// ended without pausing, or says so after 300 s.
pub(crate) fn await_pause(child: &mut std::process::Child) -> Result<String, String> {
    use std::io::{BufRead, BufReader};
    let stderr = child.stderr.take().expect("stderr piped");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut lines = BufReader::new(stderr).lines().map_while(|l| l.ok());
        let mut seen = Vec::new();
        while let Some(line) = lines.next() {
            if line.contains("paused before renaming") {
                let _ = tx.send(Ok(line));
                for _ in lines.by_ref() {}
                return;
            }
            seen.push(line);
        }
        let _ = tx.send(Err(seen.join("\n")));
    });
    rx.recv_timeout(std::time::Duration::from_secs(300))
        .map_err(|e| format!("no pause in 300 s: {e}"))?
}

pub(crate) fn run_ok(command: &mut Command) -> Output {
    let out = command.output().expect("run arkit-tool");
    assert!(
        out.status.success(),
        "{command:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

pub(crate) fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// Every regular file under `dir` (relative path -> bytes), lock files left out (they
/// are empty and only ever held by a live writer).
pub(crate) fn tree(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries {
            let e = e.unwrap();
            let path = e.path();
            if e.file_type().unwrap().is_dir() {
                stack.push(path);
                continue;
            }
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') && name.ends_with(".lock") {
                continue;
            }
            let rel = path.strip_prefix(dir).unwrap().display().to_string();
            out.insert(rel, std::fs::read(&path).unwrap());
        }
    }
    out
}

/// The temporaries under `dir` (files, and files in temporary folders).
pub(crate) fn temporaries(dir: &Path) -> Vec<String> {
    tree(dir)
        .into_keys()
        .filter(|k| k.split('/').any(arkit_core::atomic_file::is_temporary_name))
        .collect()
}

/// Where two trees differ (first few), empty when equal.
pub(crate) fn differences(
    expected: &BTreeMap<String, Vec<u8>>,
    got: &BTreeMap<String, Vec<u8>>,
) -> Vec<String> {
    let mut out = Vec::new();
    for (k, v) in expected {
        match got.get(k) {
            None => out.push(format!("{k}: missing")),
            Some(g) if g != v => out.push(format!(
                "{k}: {} bytes, expected {} (different)",
                g.len(),
                v.len()
            )),
            _ => {}
        }
    }
    for k in got.keys().filter(|k| !expected.contains_key(*k)) {
        out.push(format!("{k}: not in the uninterrupted run"));
    }
    out.truncate(8);
    out
}

/// Copies the files `convert` wrote (no targets, no crop stores, no locks).
fn copy_converted(from: &Path, to: &Path) {
    for (rel, bytes) in tree(from) {
        if rel.starts_with("targets") || rel.starts_with("crops") {
            continue;
        }
        let path = to.join(&rel);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, bytes).unwrap();
    }
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Stage {
    Convert,
    Render,
    Crops,
}

impl Stage {
    fn name(self) -> &'static str {
        match self {
            Stage::Convert => "convert",
            Stage::Render => "render",
            Stage::Crops => "crops",
        }
    }

    fn command(self, release: &Path, dir: &Path) -> Command {
        let mut c = tool();
        match self {
            Stage::Convert => {
                c.args(["convert", "--input"])
                    .arg(release)
                    .arg("--output")
                    .arg(dir)
                    .args(["--rows-per-shard", "6"]);
            }
            Stage::Render => {
                c.args(["render", "--dataset"]).arg(dir).args([
                    "--size",
                    "48",
                    "--points",
                    "64",
                    "--uv-size",
                    "16",
                ]);
            }
            Stage::Crops => {
                c.args(["crops", "--dataset"])
                    .arg(dir)
                    .args(["--size", CROP_SIZE]);
            }
        }
        c
    }

    /// What the stage writes, relative to the dataset folder (the whole folder for
    /// `convert`).
    fn output(self) -> Option<&'static str> {
        match self {
            Stage::Convert => None,
            Stage::Render => Some("targets"),
            Stage::Crops => Some("crops"),
        }
    }

    fn outputs(self, dir: &Path) -> BTreeMap<String, Vec<u8>> {
        match self.output() {
            // What `convert` writes: everything but the later stages' folders.
            None => tree(dir)
                .into_iter()
                .filter(|(k, _)| !k.starts_with("targets") && !k.starts_with("crops"))
                .collect(),
            Some(sub) => tree(&dir.join(sub)),
        }
    }
}

/// What the readers made of one torn folder.
#[derive(Default)]
struct Verdicts {
    /// Readers that refused with an error naming the file or folder.
    refused: usize,
    /// Readers that read the last complete state.
    last_complete: usize,
    /// The state `inspect` reported for the stage's output.
    state: String,
}

/// The state `inspect --json` reports for the stage's output.
fn inspect_state(dir: &Path, stage: Stage) -> (Output, String, serde_json::Value) {
    let out = tool()
        .arg("inspect")
        .arg("--dataset")
        .arg(dir)
        .arg("--json")
        .output()
        .unwrap();
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "inspect --json on {} printed no JSON ({e}): {}{}",
            dir.display(),
            text(&out.stdout),
            text(&out.stderr)
        )
    });
    let state = &json["state"];
    let of = match stage {
        Stage::Convert => state["samples"].clone(),
        Stage::Render => state["targets"].clone(),
        Stage::Crops => state["crop_stores"]
            .as_array()
            .and_then(|a| a.first().cloned())
            .unwrap_or_else(|| serde_json::json!({"state": "absent", "message": ""})),
    };
    let name = of["state"].as_str().unwrap_or("?").to_string();
    (out, name, of)
}

/// Runs every reader on the folder `dir` that `stage` was killed in (`finished`:
/// whether the command had exited by itself) and checks each either refuses, naming
/// the file, or reads a complete state. Panics otherwise.
fn check_readers(stage: Stage, dir: &Path, finished: bool, scratch: &Path) -> Verdicts {
    let (out, state, of) = inspect_state(dir, stage);
    let mut v = Verdicts {
        state: state.clone(),
        ..Verdicts::default()
    };
    let message = of["message"].as_str().unwrap_or("").to_string();
    let complete = state == "complete";
    if finished {
        assert!(
            complete,
            "{}: the run finished but inspect says {of}",
            stage.name()
        );
    }
    // inspect: a torn output is named, with the command that completes it.
    match (stage, complete) {
        (_, true) => {
            assert!(
                out.status.success(),
                "inspect of a complete folder failed: {}",
                text(&out.stderr)
            );
            v.last_complete += 1;
        }
        (Stage::Convert, false) => {
            assert!(
                !out.status.success()
                    && (state == "torn" || state == "absent")
                    && message.starts_with("samples: ")
                    && message.contains("arkit-tool convert"),
                "inspect of a torn conversion: {state}: {message}: {}",
                text(&out.stderr)
            );
            assert!(
                text(&out.stderr).contains(&dir.display().to_string()),
                "inspect's error does not name the folder: {}",
                text(&out.stderr)
            );
            v.refused += 1;
        }
        (Stage::Render, false) => {
            assert!(
                out.status.success(),
                "inspect (samples complete) failed: {}",
                text(&out.stderr)
            );
            assert!(
                (state == "torn"
                    && message.starts_with("targets: ")
                    && message.contains(" shards, rerun `arkit-tool render"))
                    || state == "absent",
                "inspect of a torn render: {state}: {message}"
            );
            v.refused += 1;
        }
        (Stage::Crops, false) => {
            assert!(
                out.status.success(),
                "inspect (samples complete) failed: {}",
                text(&out.stderr)
            );
            assert!(
                (state == "torn"
                    && message.starts_with("crops/exact-")
                    && message.contains("no crops.json")
                    && message.contains("rerun `arkit-tool crops"))
                    || state == "absent",
                "inspect of a torn crop store: {state}: {message}"
            );
            v.refused += 1;
        }
    }
    // The text report prints the same line.
    // (A crops run killed before it made its folder leaves no store to name.)
    let plain = tool()
        .arg("inspect")
        .arg("--dataset")
        .arg(dir)
        .output()
        .unwrap();
    assert!(
        message.is_empty() || text(&plain.stdout).contains(&message),
        "inspect's text does not say '{message}': {}",
        text(&plain.stdout)
    );
    // The stage's consumers.
    match stage {
        Stage::Convert | Stage::Render => {
            // predict --oracle reads the samples and every targets shard.
            let pred = scratch.join("oracle.parquet");
            let out = tool()
                .args(["predict", "--oracle", "--dataset"])
                .arg(dir)
                .arg("--output")
                .arg(&pred)
                .output()
                .unwrap();
            let whole = stage == Stage::Render && complete;
            if whole {
                assert!(
                    out.status.success(),
                    "predict on complete targets: {}",
                    text(&out.stderr)
                );
                v.last_complete += 1;
            } else {
                let err = text(&out.stderr);
                assert!(
                    !out.status.success(),
                    "predict --oracle read a torn {} folder as complete: {}",
                    stage.name(),
                    text(&out.stdout)
                );
                // A finished conversion has no targets yet: refused for those.
                let named = match stage {
                    Stage::Convert if !complete => "dataset.json",
                    _ => "targets/part-",
                };
                assert!(
                    err.contains(named),
                    "predict's refusal does not name {named}: {err}"
                );
                assert!(
                    !pred.exists(),
                    "predict refused but wrote {}",
                    pred.display()
                );
                v.refused += 1;
            }
            #[cfg(feature = "model")]
            if !whole {
                let out = tool()
                    .args(["train", "--dataset"])
                    .arg(dir)
                    .args(["--split", "all", "--steps", "1", "--batch", "1", "--output"])
                    .arg(scratch.join("model"))
                    .output()
                    .unwrap();
                let err = text(&out.stderr);
                assert!(
                    !out.status.success(),
                    "train accepted a torn {} folder",
                    stage.name()
                );
                let named = match stage {
                    Stage::Convert if !complete => "dataset.json",
                    _ => "targets/part-",
                };
                assert!(
                    err.contains(named),
                    "train's refusal does not name {named}: {err}"
                );
                v.refused += 1;
            }
        }
        Stage::Crops => {
            // The loader the Python package uses, given the store.
            use arkit_data::crop::RuleSet;
            use arkit_data::loader::{FaceLoader, LoaderMode, LoaderOptions};
            let options = LoaderOptions {
                split: None,
                mode: LoaderMode::Eval,
                rules: RuleSet::Exact,
                img_size: CROP_SIZE.parse().unwrap(),
                n_pts: 16,
                seed: 0,
            };
            let topology = arkit_data::mesh::builtin().topology.clone();
            let mut loader = FaceLoader::open(dir, topology, None, options).unwrap();
            let store =
                FaceLoader::default_crop_store(dir, RuleSet::Exact, CROP_SIZE.parse().unwrap());
            match loader.open_crop_store(&store) {
                Ok(()) => {
                    assert!(
                        complete,
                        "the loader opened a crop store inspect calls {state}"
                    );
                    for i in 0..loader.len() {
                        loader.item(i, 0).unwrap();
                    }
                    v.last_complete += 1;
                }
                Err(e) => {
                    assert!(!complete, "the loader refused a complete store: {e}");
                    let e = e.to_string();
                    assert!(
                        e.contains("crops.json") && e.contains(&store.display().to_string()),
                        "the loader's refusal does not name the store's crops.json: {e}"
                    );
                    v.refused += 1;
                }
            }
        }
    }
    v
}

/// One line of the table.
struct Row {
    stage: Stage,
    points: usize,
    mid_run: usize,
    finished_first: usize,
    refused: usize,
    last_complete: usize,
    identical: usize,
    leftovers: usize,
    /// How often `inspect` reported each state while torn.
    states: BTreeMap<String, usize>,
}

#[test]
fn killed_writers_leave_readable_folders_and_reruns_give_the_same_files() {
    let started = Instant::now();
    let points = env_number("ARKIT_KILL_POINTS", 3) as usize;
    let seed = env_number("ARKIT_KILL_SEED", 53);
    let root = tempfile::tempdir().unwrap();
    let release = root.path().join("release");
    run_ok(tool().arg("synth").arg("--output").arg(&release).args([
        "--subjects",
        "6",
        "--images-per-subject",
        "12",
        "--size",
        "240x240",
        "--seed",
        "7",
    ]));
    // The uninterrupted runs: the reference outputs and each command's duration.
    let reference = root.path().join("reference");
    let mut durations = Vec::new();
    for stage in [Stage::Convert, Stage::Render, Stage::Crops] {
        let t = Instant::now();
        run_ok(stage.command(&release, &reference).stdout(Stdio::null()));
        durations.push((stage, t.elapsed()));
    }
    let mut rng = Points(seed);
    let mut rows = Vec::new();
    for (stage, duration) in durations {
        let expected = stage.outputs(&reference);
        let mut row = Row {
            stage,
            points,
            mid_run: 0,
            finished_first: 0,
            refused: 0,
            last_complete: 0,
            identical: 0,
            leftovers: 0,
            states: BTreeMap::new(),
        };
        for point in 0..points {
            let dir = root.path().join(format!("{}-{point}", stage.name()));
            let scratch = root
                .path()
                .join(format!("{}-{point}-scratch", stage.name()));
            std::fs::create_dir_all(&scratch).unwrap();
            if stage != Stage::Convert {
                copy_converted(&reference, &dir);
            }
            let delay = duration.mul_f64(rng.next_unit());
            let mut child = stage
                .command(&release, &dir)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .unwrap();
            std::thread::sleep(delay);
            let finished = match child.try_wait().unwrap() {
                Some(status) => {
                    assert!(
                        status.success(),
                        "{} exited with {status} before the kill",
                        stage.name()
                    );
                    true
                }
                None => {
                    // SIGKILL on Unix. Every other kill leaves a zombie: not reaped
                    // until the rerun has cleaned up, so its process id still names a
                    // process (a container whose PID 1 reaps nothing).
                    child.kill().unwrap();
                    if point % 2 == 0 {
                        child.wait().unwrap();
                    }
                    false
                }
            };
            if finished {
                row.finished_first += 1;
            } else {
                row.mid_run += 1;
            }
            let v = check_readers(stage, &dir, finished, &scratch);
            row.refused += v.refused;
            row.last_complete += v.last_complete;
            *row.states.entry(v.state).or_default() += 1;
            // The same command again completes, to the same files, and cleans up.
            run_ok(stage.command(&release, &dir).stdout(Stdio::null()));
            let diff = differences(&expected, &stage.outputs(&dir));
            assert!(
                diff.is_empty(),
                "{} killed after {delay:?} then rerun: its outputs differ from an uninterrupted run's: {diff:?}",
                stage.name()
            );
            row.identical += 1;
            let left = temporaries(&dir);
            row.leftovers += left.len();
            assert!(
                left.is_empty(),
                "{} rerun left temporaries: {left:?}",
                stage.name()
            );
            // The zombie (if any) reaped only now.
            child.wait().unwrap();
            std::fs::remove_dir_all(&dir).unwrap();
            std::fs::remove_dir_all(&scratch).unwrap();
        }
        rows.push((row, duration));
    }
    println!(
        "\nkill harness (seed {seed}, {points} points per command, {:.1} s)",
        started.elapsed().as_secs_f64()
    );
    println!(
        "| command | run (s) | kill points | killed mid-run | finished first | inspect said | readers refused | readers read last complete | reruns identical | leftovers |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for (r, d) in &rows {
        println!(
            "| {} | {:.2} | {} | {} | {} | {} | {} | {} | {}/{} | {} |",
            r.stage.name(),
            d.as_secs_f64(),
            r.points,
            r.mid_run,
            r.finished_first,
            r.states
                .iter()
                .map(|(s, n)| format!("{s} x{n}"))
                .collect::<Vec<_>>()
                .join(", "),
            r.refused,
            r.last_complete,
            r.identical,
            r.points,
            r.leftovers
        );
    }
}
