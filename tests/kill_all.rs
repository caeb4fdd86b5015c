//! The kill harness for the writers tests/kill.rs does not cover: `synth`,
//! `convert --shard I/N`, `merge`, `split`, `augment`, `import-arkit`,
//! `convert --format biwi`, `train` (its checkpoints) and `export-weights`.
//!
//! Each command is killed (SIGKILL) twice over: at points drawn from a seed over its
//! measured uninterrupted run, and at the moments between writing and renaming each
//! kind of output it writes (`ARKIT_PAUSE_BEFORE_RENAME=PART` stops the writer once the
//! temporary of the first file whose path contains `PART` is complete, just before the
//! rename; the harness kills it there). While the folder is torn, every reader that
//! applies must refuse with an error naming a file or folder of it, or read the last
//! complete state; then the same command rerun completes, its outputs equal an
//! uninterrupted run's byte for byte, and no temporary is left.
//!
//! The readers: a release layout (`synth`, `augment`, `import-arkit`) is read by
//! `convert`; a converted dataset (`convert --shard`, `merge`, `convert --format biwi`,
//! `split`) by `inspect --json` and `predict --mean-pose`; a model folder (`train`) by
//! `train --resume`, `predict --model` and `export-weights`; an exported weights file
//! by its bytes (absent or whole). The Python readers are python/tests/test_kill.py.
//!
//! `ARKIT_KILL_POINTS` (default 3) sets the seeded points per command, `ARKIT_KILL_SEED`
//! (default 53) the seed; the between-write-and-rename points are always all tried.

use crate::kill::{Points, await_pause, differences, env_number, run_ok, temporaries, text, tree};
use crate::support::tool;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// The inputs every case reads, made once.
struct Fixture {
    /// A small synthetic release.
    release: PathBuf,
    /// It converted (4 rows per shard), rendered for the tiny network.
    dataset: PathBuf,
    /// Its two `convert --shard I/2` parts, not merged.
    parts: PathBuf,
    /// A synthetic BIWI head-pose database.
    hpdb: PathBuf,
    /// A synthetic ARKit capture.
    capture: PathBuf,
    /// A model trained for one step (for `export-weights`).
    #[cfg(feature = "model")]
    model: PathBuf,
}

fn convert_args(c: &mut Command, input: &Path, output: &Path) {
    c.args(["convert", "--input"])
        .arg(input)
        .arg("--output")
        .arg(output)
        .args(["--rows-per-shard", "4"]);
}

impl Fixture {
    fn make(root: &Path) -> Self {
        let release = root.join("release");
        run_ok(tool().arg("synth").arg("--output").arg(&release).args([
            "--subjects",
            "4",
            "--images-per-subject",
            "4",
            "--size",
            "160x160",
            "--seed",
            "5",
        ]));
        let dataset = root.join("dataset");
        run_ok(&mut {
            let mut c = tool();
            convert_args(&mut c, &release, &dataset);
            c
        });
        #[cfg(feature = "model")]
        run_ok(
            tool()
                .args(["render", "--dataset"])
                .arg(&dataset)
                .args(["--size", "64", "--points", "256"]),
        );
        let parts = root.join("parts");
        for shard in ["0/2", "1/2"] {
            let mut c = tool();
            convert_args(&mut c, &release, &parts);
            run_ok(c.args(["--shard", shard]));
        }
        let hpdb = root.join("hpdb");
        crate::support::biwi_writer::write_hpdb(&hpdb);
        let capture = root.join("capture");
        for (i, yaw) in [-10.0, 0.0, 12.0].into_iter().enumerate() {
            crate::import_arkit::write_frame(
                &capture,
                &format!("f{i}"),
                &crate::import_arkit::scene(
                    arkit_data::ingest::InterfaceOrientation::LandscapeRight,
                    yaw,
                    4.0,
                    0.0,
                ),
            );
        }
        #[cfg(feature = "model")]
        let model = {
            let model = root.join("model");
            run_ok(
                tool()
                    .args(["train", "--dataset"])
                    .arg(&dataset)
                    .args(["--split", "all", "--steps", "1", "--batch", "2", "--output"])
                    .arg(&model),
            );
            model
        };
        Self {
            release,
            dataset,
            parts,
            hpdb,
            capture,
            #[cfg(feature = "model")]
            model,
        }
    }
}

/// The commands of this harness.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Case {
    Synth,
    ShardConvert,
    Merge,
    Split,
    Augment,
    ImportArkit,
    Biwi,
    #[cfg(feature = "model")]
    Train,
    #[cfg(feature = "model")]
    ExportWeights,
    #[cfg(feature = "model")]
    ExportOnnx,
}

/// What a reader made of a torn folder.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Verdict {
    /// Refused with an error naming a file or folder of the output.
    Refused,
    /// Read the last complete state.
    LastComplete,
}

impl Case {
    fn all() -> Vec<Case> {
        vec![
            Case::Synth,
            Case::ShardConvert,
            Case::Merge,
            Case::Split,
            Case::Augment,
            Case::ImportArkit,
            Case::Biwi,
            #[cfg(feature = "model")]
            Case::Train,
            #[cfg(feature = "model")]
            Case::ExportWeights,
            #[cfg(feature = "model")]
            Case::ExportOnnx,
        ]
    }

    fn name(self) -> &'static str {
        match self {
            Case::Synth => "synth",
            Case::ShardConvert => "convert --shard 0/2",
            Case::Merge => "merge",
            Case::Split => "split",
            Case::Augment => "augment",
            Case::ImportArkit => "import-arkit",
            Case::Biwi => "convert --format biwi",
            #[cfg(feature = "model")]
            Case::Train => "train (2 epochs)",
            #[cfg(feature = "model")]
            Case::ExportWeights => "export-weights",
            #[cfg(feature = "model")]
            Case::ExportOnnx => "export-onnx",
        }
    }

    /// The parts of output paths the harness pauses the writer before renaming (one
    /// kill each).
    fn pauses(self) -> &'static [&'static str] {
        match self {
            Case::Synth => &["_info.npz", "ARKitFace_test.csv", "out/ARKitFace_list"],
            Case::ShardConvert => &[
                "conversion.json",
                "samples/part-",
                "manifest/part-0000-of-0002.json",
            ],
            Case::Merge => &["dataset.json"],
            Case::Split => &[
                "ARKitFace_test.csv",
                "splits/ARKitFace_list",
                "splits.parquet",
            ],
            Case::Augment => &["_info.npz", "ARKitFace_test.csv", "out/ARKitFace_list"],
            Case::ImportArkit => &["_info.npz", "ARKitFace_test.csv"],
            Case::Biwi => &["ARKitFace_test.csv", "samples/part-", "dataset.json"],
            #[cfg(feature = "model")]
            Case::Train => &[
                "model.safetensors",
                "adam.safetensors",
                "loss.csv",
                "perspnet.json",
                "checkpoint.json",
            ],
            #[cfg(feature = "model")]
            Case::ExportWeights => &["official.safetensors"],
            #[cfg(feature = "model")]
            Case::ExportOnnx => &["dense.onnx", "points.onnx", "onnx.json"],
        }
    }

    /// The output of the case run in `dir`.
    fn output(self, dir: &Path) -> PathBuf {
        match self {
            #[cfg(feature = "model")]
            Case::ExportWeights => dir.join("out").join("official.safetensors"),
            _ => dir.join("out"),
        }
    }

    /// Sets up `dir` as the command finds it.
    fn prepare(self, fx: &Fixture, dir: &Path) {
        std::fs::create_dir_all(dir).unwrap();
        let copy = |from: &Path| {
            for (rel, bytes) in tree(from) {
                let p = dir.join("out").join(rel);
                std::fs::create_dir_all(p.parent().unwrap()).unwrap();
                std::fs::write(p, bytes).unwrap();
            }
        };
        match self {
            Case::Merge => copy(&fx.parts),
            Case::Split => copy(&fx.dataset),
            _ => {}
        }
    }

    fn command(self, fx: &Fixture, dir: &Path) -> Command {
        let out = self.output(dir);
        let mut c = tool();
        match self {
            Case::Synth => {
                c.arg("synth").arg("--output").arg(&out).args([
                    "--subjects",
                    "3",
                    "--images-per-subject",
                    "4",
                    "--size",
                    "160x160",
                    "--seed",
                    "9",
                ]);
            }
            Case::ShardConvert => {
                convert_args(&mut c, &fx.release, &out);
                c.args(["--shard", "0/2"]);
            }
            Case::Merge => {
                c.args(["merge", "--dataset"]).arg(&out);
            }
            Case::Split => {
                c.args(["split", "--dataset"]).arg(&out).args([
                    "--test-subjects",
                    "1",
                    "--val-subjects",
                    "1",
                    "--seed",
                    "3",
                ]);
            }
            Case::Augment => {
                c.args(["augment", "--input"])
                    .arg(&fx.dataset)
                    .arg("--output")
                    .arg(&out)
                    .args(["--flip", "--seed", "2"]);
            }
            Case::ImportArkit => {
                c.args(["import-arkit", "--input"])
                    .arg(&fx.capture)
                    .arg("--output")
                    .arg(&out)
                    .args(["--subject", "me"]);
            }
            Case::Biwi => {
                c.args(["convert", "--format", "biwi", "--input"])
                    .arg(&fx.hpdb)
                    .arg("--output")
                    .arg(&out);
            }
            #[cfg(feature = "model")]
            Case::Train => {
                c.args(["train", "--dataset"])
                    .arg(&fx.dataset)
                    .args([
                        "--split", "all", "--epochs", "2", "--batch", "4", "--seed", "1",
                        "--resume", "--output",
                    ])
                    .arg(&out);
            }
            #[cfg(feature = "model")]
            Case::ExportWeights => {
                c.arg("export-weights")
                    .arg(&fx.model)
                    .arg("--output")
                    .arg(&out);
            }
            #[cfg(feature = "model")]
            Case::ExportOnnx => {
                c.args(["export-onnx", "--model"])
                    .arg(&fx.model)
                    .arg("--output")
                    .arg(&out);
            }
        }
        c
    }

    /// What is compared with the uninterrupted run: the output's files, with the
    /// folder's own path (which `conversion.json` and `dataset.json` record for the
    /// BIWI staging folder under it) written `<DIR>`.
    fn outputs(self, dir: &Path) -> BTreeMap<String, Vec<u8>> {
        let out = self.output(dir);
        if out.is_file() {
            return BTreeMap::from([(String::new(), std::fs::read(&out).unwrap())]);
        }
        let own = dir.display().to_string().into_bytes();
        tree(&out)
            .into_iter()
            .map(|(k, v)| {
                let v = replace_bytes(&v, &own, b"<DIR>");
                // The BIWI staging folder is rewritten by the rerun, and a shard's
                // fingerprint holds its input files' modification times: those JSON
                // files are compared field by field without their fingerprints.
                if self == Case::Biwi && k.ends_with(".json") {
                    let mut j: serde_json::Value = serde_json::from_slice(&v).unwrap();
                    drop_fingerprints(&mut j);
                    return (k, j.to_string().into_bytes());
                }
                (k, v)
            })
            .collect()
    }
}

/// Removes every field whose name holds "fingerprint", at any depth.
fn drop_fingerprints(v: &mut serde_json::Value) {
    match v {
        serde_json::Value::Object(m) => {
            m.retain(|k, _| !k.contains("fingerprint"));
            m.values_mut().for_each(drop_fingerprints);
        }
        serde_json::Value::Array(a) => a.iter_mut().for_each(drop_fingerprints),
        _ => {}
    }
}

/// `bytes` with every `from` replaced by `to`.
fn replace_bytes(bytes: &[u8], from: &[u8], to: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i..].starts_with(from) {
            out.extend_from_slice(to);
            i += from.len();
        } else {
            out.push(bytes[i]);
            i += 1;
        }
    }
    out
}

/// How a killed writer ends, and what its process id then says.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Death {
    /// Killed and reaped: its process id names no process.
    Reaped,
    /// Killed and left a zombie (its parent, the harness, does not reap it until the
    /// rerun and the check for leftovers are done): its process id still names a
    /// process, as in a container whose PID 1 reaps nothing.
    Zombie,
    /// Run as PID 1 of a PID namespace of its own (`unshare --pid`), then killed: the
    /// process id it knew itself by names a live process here (PID 1 always runs), as
    /// another node's or another container's would.
    OtherPidNamespace,
}

impl Death {
    const ALL: [Death; 3] = [Death::Reaped, Death::Zombie, Death::OtherPidNamespace];

    fn name(self) -> &'static str {
        match self {
            Death::Reaped => "reaped",
            Death::Zombie => "zombie",
            Death::OtherPidNamespace => "own PID namespace",
        }
    }
}

/// Whether `unshare --pid` works here (root, or user namespaces allowed).
fn pid_namespaces() -> bool {
    static WORKS: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *WORKS.get_or_init(|| {
        Command::new("unshare")
            .args(["--pid", "--fork", "--kill-child", "--mount-proc", "true"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    })
}

/// `command` run as PID 1 of a new PID namespace (killed with `unshare`).
fn in_own_pid_namespace(command: &Command) -> Command {
    let mut c = Command::new("unshare");
    c.args(["--pid", "--fork", "--kill-child", "--mount-proc"])
        .arg(command.get_program())
        .args(command.get_args());
    for (k, v) in command.get_envs() {
        match v {
            Some(v) => c.env(k, v),
            None => c.env_remove(k),
        };
    }
    if let Some(d) = command.get_current_dir() {
        c.current_dir(d);
    }
    c
}

/// Runs `command` with the output's `what` paused before its rename, then kills it
/// the way `death` says. Returns the temporary the writer had completed (as it
/// reported it), and the killed process when it is left a zombie (the caller reaps it
/// once it has checked what the writer left).
fn kill_before_rename(
    command: Command,
    what: &str,
    death: Death,
) -> (String, Option<std::process::Child>) {
    let mut command = match death {
        Death::OtherPidNamespace => in_own_pid_namespace(&command),
        _ => command,
    };
    let mut child = command
        .env(arkit_core::atomic_file::PAUSE_BEFORE_RENAME, what)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let got = await_pause(&mut child);
    child.kill().unwrap();
    let zombie = match death {
        Death::Zombie => {
            // Dead but not reaped: /proc still lists it, in state Z.
            let stat = format!("/proc/{}/stat", child.id());
            let deadline = Instant::now() + Duration::from_secs(10);
            while !std::fs::read_to_string(&stat).is_ok_and(|s| s.contains(") Z ")) {
                assert!(
                    Instant::now() < deadline,
                    "the killed writer never became a zombie"
                );
                std::thread::sleep(Duration::from_millis(5));
            }
            Some(child)
        }
        _ => {
            child.wait().unwrap();
            None
        }
    };
    match got {
        Ok(line) => (line, zombie),
        Err(why) => panic!("{command:?} did not pause at '{what}': {why}"),
    }
}

/// Whether `err` names something under `dir`.
fn names(err: &str, dir: &Path) -> bool {
    err.contains(&dir.display().to_string())
}

/// The rows `convert` finds in a release layout, or its refusal.
fn converted_rows(release: &Path, scratch: &Path) -> Result<u64, String> {
    let pq = scratch.join("pq");
    let _ = std::fs::remove_dir_all(&pq);
    let mut c = tool();
    convert_args(&mut c, release, &pq);
    let out = c.arg("--json").output().unwrap();
    if !out.status.success() {
        return Err(text(&out.stderr));
    }
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    Ok(v["rows"]
        .as_u64()
        .or_else(|| v["converted"].as_u64())
        .unwrap_or_else(|| panic!("convert --json has no row count: {v}")))
}

/// The `predict --mean-pose` predictions of a dataset (`split`), or its refusal.
fn mean_pose(dataset: &Path, split: &str, scratch: &Path) -> Result<Vec<u8>, String> {
    let p = scratch.join("mean.parquet");
    let _ = std::fs::remove_file(&p);
    let out = tool()
        .args(["predict", "--mean-pose", "--split", split, "--dataset"])
        .arg(dataset)
        .arg("--output")
        .arg(&p)
        .output()
        .unwrap();
    if out.status.success() {
        Ok(std::fs::read(&p).unwrap())
    } else {
        assert!(!p.exists(), "predict refused but wrote {}", p.display());
        Err(text(&out.stderr))
    }
}

/// What the readers expect of a complete output: taken from the uninterrupted run.
#[derive(Default)]
struct Expected {
    /// Rows `convert` reads from a complete release layout.
    rows: Option<u64>,
    /// Test-split mean-pose predictions before `split` ran and after.
    split_states: Vec<Vec<u8>>,
    /// The exported weights.
    file: Vec<u8>,
    /// The files of an uninterrupted run's output folder (export-onnx).
    tree: BTreeMap<String, Vec<u8>>,
}

/// Runs the readers of the torn output of `case` in `dir`; panics on a reader that
/// reads a torn state as valid or refuses without naming it.
fn check_readers(
    case: Case,
    fx: &Fixture,
    dir: &Path,
    finished: bool,
    expected: &Expected,
) -> (Vec<Verdict>, String) {
    let out = case.output(dir);
    let scratch = dir.join("scratch");
    std::fs::create_dir_all(&scratch).unwrap();
    let mut verdicts = Vec::new();
    let state: String;
    match case {
        Case::Synth | Case::Augment | Case::ImportArkit => match converted_rows(&out, &scratch) {
            Ok(rows) => {
                assert_eq!(
                    Some(rows),
                    expected.rows,
                    "{}: convert read {rows} rows from a torn release layout (the whole has {:?})",
                    case.name(),
                    expected.rows
                );
                verdicts.push(Verdict::LastComplete);
                state = "complete".into();
            }
            Err(e) => {
                assert!(
                    !finished,
                    "{}: convert refused the finished output: {e}",
                    case.name()
                );
                assert!(
                    names(&e, &out),
                    "convert's refusal does not name {}: {e}",
                    out.display()
                );
                verdicts.push(Verdict::Refused);
                state = "refused".into();
            }
        },
        Case::ShardConvert | Case::Merge | Case::Biwi => {
            let o = tool()
                .args(["inspect", "--json", "--dataset"])
                .arg(&out)
                .output()
                .unwrap();
            let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap_or_else(|e| {
                panic!("inspect --json printed no JSON ({e}): {}", text(&o.stderr))
            });
            let s = &v["state"]["samples"];
            state = s["state"].as_str().unwrap_or("?").to_string();
            let message = s["message"].as_str().unwrap_or("").to_string();
            let complete = state == "complete";
            // A shard's conversion is whole only once merged.
            assert!(
                !finished || complete || case == Case::ShardConvert,
                "{}: finished but inspect says {s}",
                case.name()
            );
            if complete {
                assert!(o.status.success(), "inspect: {}", text(&o.stderr));
                verdicts.push(Verdict::LastComplete);
            } else {
                assert!(
                    !o.status.success()
                        && message.starts_with("samples: ")
                        && message.contains("arkit-tool "),
                    "inspect of a torn folder: {state}: {message}: {}",
                    text(&o.stderr)
                );
                assert!(names(&text(&o.stderr), &out), "{}", text(&o.stderr));
                verdicts.push(Verdict::Refused);
            }
            match mean_pose(&out, "all", &scratch) {
                Ok(_) => {
                    assert!(complete, "predict read a folder inspect calls {state}");
                    verdicts.push(Verdict::LastComplete);
                }
                // A BIWI conversion holds test samples only: the baseline has no training
                // split to fit on. predict says so after reading every sample, past the
                // folder's state checks, so this is a read of the complete state.
                Err(e) if case == Case::Biwi && e.contains("no samples in the \"train\" split") => {
                    assert!(complete, "predict read a folder inspect calls {state}: {e}");
                    verdicts.push(Verdict::LastComplete);
                }
                Err(e) => {
                    assert!(!complete, "predict refused a complete folder: {e}");
                    assert!(names(&e, &out), "predict's refusal names no file: {e}");
                    verdicts.push(Verdict::Refused);
                }
            }
        }
        Case::Split => match mean_pose(&out, "test", &scratch) {
            Ok(bytes) => {
                let which = expected.split_states.iter().position(|s| *s == bytes);
                assert!(
                    which.is_some(),
                    "split: predict --split test read a state that is neither the one before split nor after"
                );
                if finished {
                    assert_eq!(
                        which,
                        Some(1),
                        "split finished but its test split is not read"
                    );
                }
                state = ["before", "after"][which.unwrap()].to_string();
                verdicts.push(Verdict::LastComplete);
            }
            Err(e) => {
                assert!(names(&e, &out), "predict's refusal names no file: {e}");
                state = "refused".into();
                verdicts.push(Verdict::Refused);
            }
        },
        #[cfg(feature = "model")]
        Case::Train => {
            let p = scratch.join("model.parquet");
            let o = tool()
                .args(["predict", "--split", "all", "--model"])
                .arg(&out)
                .arg("--dataset")
                .arg(&fx.dataset)
                .arg("--output")
                .arg(&p)
                .output()
                .unwrap();
            if o.status.success() {
                verdicts.push(Verdict::LastComplete);
                state = "model".into();
            } else {
                assert!(
                    !finished,
                    "predict refused the finished model: {}",
                    text(&o.stderr)
                );
                assert!(
                    names(&text(&o.stderr), &out),
                    "predict's refusal names no file: {}",
                    text(&o.stderr)
                );
                verdicts.push(Verdict::Refused);
                state = "no model".into();
            }
            let w = scratch.join("w.safetensors");
            let o = tool()
                .arg("export-weights")
                .arg(&out)
                .arg("--output")
                .arg(&w)
                .output()
                .unwrap();
            if o.status.success() {
                verdicts.push(Verdict::LastComplete);
            } else {
                assert!(
                    names(&text(&o.stderr), &out),
                    "export-weights' refusal names no file: {}",
                    text(&o.stderr)
                );
                verdicts.push(Verdict::Refused);
            }
        }
        #[cfg(feature = "model")]
        Case::ExportOnnx => {
            // A user's reader opens onnx.json (written last) and the files it names: with
            // it, every file is the uninterrupted run's; without it, nothing is declared.
            if out.join("onnx.json").is_file() {
                let got = case.outputs(dir);
                assert!(
                    differences(&expected.tree, &got).is_empty(),
                    "onnx.json beside a torn export: {:?}",
                    differences(&expected.tree, &got)
                );
                verdicts.push(Verdict::LastComplete);
                state = "complete".into();
            } else {
                verdicts.push(Verdict::Refused);
                state = "no onnx.json".into();
            }
        }
        #[cfg(feature = "model")]
        Case::ExportWeights => match std::fs::read(&out) {
            Ok(bytes) => {
                assert_eq!(bytes, expected.file, "a torn {} is readable", out.display());
                verdicts.push(Verdict::LastComplete);
                state = "whole".into();
            }
            Err(_) => {
                verdicts.push(Verdict::Refused);
                state = "absent".into();
            }
        },
    }
    let _ = fx;
    std::fs::remove_dir_all(&scratch).unwrap();
    (verdicts, state)
}

/// Reruns the case in `dir` after a kill (the command as a job script reruns it).
fn rerun(case: Case, fx: &Fixture, dir: &Path) {
    let out = case
        .command(fx, dir)
        .stdout(Stdio::null())
        .output()
        .unwrap();
    if out.status.success() {
        return;
    }
    let err = text(&out.stderr);
    #[cfg(feature = "model")]
    if case == Case::Train && err.contains("the checkpoint is torn") {
        // As the refusal says: run again without --resume to start over.
        let mut c = case.command(fx, dir);
        let args: Vec<_> = c
            .get_args()
            .filter(|a| *a != "--resume")
            .map(|a| a.to_owned())
            .collect();
        run_ok(tool().args(args).stdout(Stdio::null()));
        let _ = &mut c;
        return;
    }
    if case == Case::ImportArkit && err.contains("pass --overwrite to replace it") {
        // import-arkit refuses to write over a layout, its own killed one included; as
        // the refusal says, --overwrite replaces it.
        run_ok(
            case.command(fx, dir)
                .arg("--overwrite")
                .stdout(Stdio::null()),
        );
        return;
    }
    panic!("{} rerun after a kill failed: {err}", case.name());
}

/// One line of the table.
#[derive(Default)]
struct Row {
    points: usize,
    pauses: usize,
    mid_run: usize,
    refused: usize,
    last_complete: usize,
    identical: usize,
    leftovers: usize,
    states: BTreeMap<String, usize>,
    deaths: BTreeMap<&'static str, usize>,
}

#[test]
fn every_other_writer_killed_leaves_readable_outputs_and_reruns_give_the_same_files() {
    let started = Instant::now();
    let points = env_number("ARKIT_KILL_POINTS", 3) as usize;
    let seed = env_number("ARKIT_KILL_SEED", 53);
    let root = tempfile::tempdir().unwrap();
    let fx = Fixture::make(root.path());
    let mut rng = Points(seed);
    let mut table = Vec::new();
    for case in Case::all() {
        // The uninterrupted run.
        let reference = root.path().join(format!("{case:?}-reference"));
        case.prepare(&fx, &reference);
        let mut expected = Expected::default();
        if case == Case::Split {
            expected
                .split_states
                .push(mean_pose(&case.output(&reference), "test", root.path()).unwrap());
        }
        let t = Instant::now();
        run_ok(case.command(&fx, &reference).stdout(Stdio::null()));
        let duration = t.elapsed();
        let want = case.outputs(&reference);
        match case {
            Case::Synth | Case::Augment | Case::ImportArkit => {
                expected.rows =
                    Some(converted_rows(&case.output(&reference), root.path()).unwrap());
            }
            Case::Split => expected
                .split_states
                .push(mean_pose(&case.output(&reference), "test", root.path()).unwrap()),
            #[cfg(feature = "model")]
            Case::ExportWeights => expected.file = std::fs::read(case.output(&reference)).unwrap(),
            #[cfg(feature = "model")]
            Case::ExportOnnx => expected.tree = case.outputs(&reference),
            _ => {}
        }
        // Every reader accepts the uninterrupted run's output: a reader that refuses a
        // complete folder shows up here, not only when a seeded kill comes too late.
        check_readers(case, &fx, &reference, true, &expected);
        let mut row = Row {
            points,
            pauses: case.pauses().len(),
            ..Row::default()
        };
        // Each pause is killed one way in turn; the first pause every other way too, so
        // that each writer dies each way.
        let deaths: Vec<Death> = Death::ALL
            .into_iter()
            .filter(|d| *d != Death::OtherPidNamespace || pid_namespaces())
            .collect();
        let mut kills: Vec<(Option<&str>, Death)> =
            (0..points).map(|_| (None, Death::Reaped)).collect();
        for (i, p) in case.pauses().iter().enumerate() {
            kills.push((Some(*p), deaths[i % deaths.len()]));
        }
        for d in deaths.iter().skip(1) {
            kills.push((Some(case.pauses()[0]), *d));
        }
        row.pauses = kills.iter().filter(|(p, _)| p.is_some()).count();
        for (k, (pause, death)) in kills.into_iter().enumerate() {
            let dir = root.path().join(format!("{case:?}-{k}"));
            case.prepare(&fx, &dir);
            let mut zombie = None;
            let finished = match pause {
                Some(what) => {
                    *row.deaths.entry(death.name()).or_default() += 1;
                    let (line, left_zombie) =
                        kill_before_rename(case.command(&fx, &dir), what, death);
                    zombie = left_zombie;
                    // The file the writer completed is under its temporary name only.
                    let tmp = line
                        .split("renaming ")
                        .nth(1)
                        .and_then(|s| s.split(" to ").next())
                        .unwrap()
                        .to_string();
                    assert!(Path::new(&tmp).exists(), "{line}: no temporary");
                    row.mid_run += 1;
                    false
                }
                None => {
                    let delay = duration.mul_f64(rng.next_unit());
                    let mut child = case
                        .command(&fx, &dir)
                        .stdout(Stdio::null())
                        .stderr(Stdio::null())
                        .spawn()
                        .unwrap();
                    std::thread::sleep(delay);
                    match child.try_wait().unwrap() {
                        Some(status) => {
                            assert!(status.success(), "{} failed by itself", case.name());
                            true
                        }
                        None => {
                            child.kill().unwrap();
                            child.wait().unwrap();
                            row.mid_run += 1;
                            false
                        }
                    }
                }
            };
            let (verdicts, state) = check_readers(case, &fx, &dir, finished, &expected);
            row.refused += verdicts.iter().filter(|v| **v == Verdict::Refused).count();
            row.last_complete += verdicts
                .iter()
                .filter(|v| **v == Verdict::LastComplete)
                .count();
            *row.states.entry(state).or_default() += 1;
            rerun(case, &fx, &dir);
            let diff = differences(&want, &case.outputs(&dir));
            assert!(
                diff.is_empty(),
                "{} killed (pause {pause:?}) then rerun: outputs differ from an uninterrupted run's: {diff:?}",
                case.name()
            );
            row.identical += 1;
            let left = temporaries(&dir);
            row.leftovers += left.len();
            assert!(
                left.is_empty(),
                "{} rerun after a kill ({}) left {left:?}",
                case.name(),
                death.name()
            );
            if let Some(mut z) = zombie {
                z.wait().unwrap();
            }
            std::fs::remove_dir_all(&dir).unwrap();
        }
        table.push((case, duration, row));
    }
    println!(
        "\nkill harness, other writers (seed {seed}, {points} seeded points + each pause before rename, {:.1} s)",
        started.elapsed().as_secs_f64()
    );
    println!(
        "| command | run (s) | seeded points | paused before rename | killed as | killed mid-run | readers said | refused | read last complete | reruns identical | leftovers |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for (case, d, r) in &table {
        println!(
            "| {} | {:.2} | {} | {} | {} | {} | {} | {} | {} | {}/{} | {} |",
            case.name(),
            d.as_secs_f64(),
            r.points,
            r.pauses,
            r.deaths
                .iter()
                .map(|(s, n)| format!("{s} x{n}"))
                .collect::<Vec<_>>()
                .join(", "),
            r.mid_run,
            r.states
                .iter()
                .map(|(s, n)| format!("{s} x{n}"))
                .collect::<Vec<_>>()
                .join(", "),
            r.refused,
            r.last_complete,
            r.identical,
            r.points + r.pauses,
            r.leftovers
        );
    }
}

/// Copies the files `convert` wrote in `from` (no targets, no crop stores) to `to`.
fn copy_samples(from: &Path, to: &Path) {
    for (rel, bytes) in tree(from) {
        if rel.starts_with("targets") || rel.starts_with("crops") {
            continue;
        }
        let p = to.join(rel);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, bytes).unwrap();
    }
}

#[test]
fn a_second_writer_of_the_same_outputs_is_refused_naming_the_lock_and_its_holder() {
    let started = Instant::now();
    let root = tempfile::tempdir().unwrap();
    let fx = Fixture::make(root.path());
    // (command, the output file the first run is held at, the lock it holds)
    type Make<'a> = Box<dyn Fn(&Path) -> Command + 'a>;
    let mut cases: Vec<(&str, Make<'_>, &str, &str)> = Vec::new();
    cases.push((
        "render",
        Box::new(|d: &Path| {
            let mut c = tool();
            c.args(["render", "--dataset"]).arg(d.join("out")).args([
                "--size",
                "48",
                "--points",
                "64",
                "--uv-size",
                "16",
            ]);
            c
        }),
        "targets/part-",
        "targets/.render-part-0-of-1.lock",
    ));
    cases.push((
        "crops",
        Box::new(|d: &Path| {
            let mut c = tool();
            c.args(["crops", "--dataset"])
                .arg(d.join("out"))
                .args(["--size", "64"]);
            c
        }),
        "crops/",
        ".crops.lock",
    ));
    for (case, pause, lock) in [
        (
            Case::ShardConvert,
            "samples/part-",
            ".convert-part-0-of-2.lock",
        ),
        (Case::Merge, "dataset.json", ".merge.lock"),
        (Case::Split, "splits.parquet", ".split.lock"),
        (Case::Synth, "_info.npz", ".synth.lock"),
        (Case::Augment, "_info.npz", ".augment.lock"),
        (Case::ImportArkit, "_info.npz", ".import-arkit.lock"),
        #[cfg(feature = "model")]
        (Case::Train, "model.safetensors", ".train.lock"),
    ] {
        let fx = &fx;
        cases.push((
            case.name(),
            Box::new(move |d: &Path| case.command(fx, d)),
            pause,
            lock,
        ));
    }
    let mut rows = Vec::new();
    for (k, (name, make, pause, lock)) in cases.iter().enumerate() {
        let dir = root.path().join(format!("lock-{k}"));
        match *name {
            "render" | "crops" => copy_samples(&fx.dataset, &dir.join("out")),
            "merge" => Case::Merge.prepare(&fx, &dir),
            "split" => Case::Split.prepare(&fx, &dir),
            _ => std::fs::create_dir_all(&dir).unwrap(),
        }
        // Held once it reports its pause (its lock is taken before any output).
        let (mut first, line, drain) = start_paused(&mut make(&dir), pause);
        assert!(line.is_some(), "{name} never paused at {pause}");
        let t = Instant::now();
        let second = make(&dir).output().unwrap();
        let refused_in = t.elapsed();
        first.kill().unwrap();
        first.wait().unwrap();
        drain.join().unwrap();
        let err = text(&second.stderr);
        let lock_path = dir.join("out").join(lock);
        assert!(
            !second.status.success()
                && err.contains(&dir.join("out").display().to_string())
                && err.contains(lock)
                && err.contains(&format!("held by pid {} on ", first.id()))
                && err.contains("arkit-tool"),
            "{name}: a second run beside a running one was not refused naming {} and pid {}: {err}",
            lock_path.display(),
            first.id()
        );
        // The killed holder's lock goes with it.
        let mut again = make(&dir);
        if *name == "import-arkit" {
            // It refuses to write over a layout, its own killed one included.
            again.arg("--overwrite");
        }
        let again = again.stdout(Stdio::null()).output().unwrap();
        assert!(
            again.status.success(),
            "{name} after the holder was killed: {}",
            text(&again.stderr)
        );
        rows.push((
            *name,
            refused_in,
            err.lines().last().unwrap_or("").to_string(),
        ));
    }
    println!(
        "\ntwo writers of the same outputs ({:.1} s)",
        started.elapsed().as_secs_f64()
    );
    println!("| command | second run refused in (ms) | its error |");
    println!("|---|---|---|");
    for (name, t, err) in rows {
        println!("| {name} | {} | {err} |", t.as_millis());
    }
}

/// Starts `command` held just before it renames a file whose path contains `part`
/// (`ARKIT_PAUSE_BEFORE_RENAME`): the running child, its "paused before renaming TMP to
/// PATH" line, and the thread draining its stderr until it is killed (a writer whose
/// stderr is closed would die of its next line and let go of its locks).
fn start_paused(
    command: &mut Command,
    part: &str,
) -> (
    std::process::Child,
    Option<String>,
    std::thread::JoinHandle<()>,
) {
    let mut child = command
        .env(arkit_core::atomic_file::PAUSE_BEFORE_RENAME, part)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stderr.take().unwrap())
        .lines()
        .map_while(|l| l.ok());
    let line = lines.find(|l| l.contains("paused before renaming"));
    let drain = std::thread::spawn(move || for _ in lines {});
    (child, line, drain)
}

/// `convert --overwrite` of another conversion into a folder whose conversion is still
/// being written (a part paused before it renames its first shard) is refused, naming
/// the writers' lock and the running part, and removes nothing; once that part is gone
/// the overwrite runs. A `split` of the folder is refused the same way while an
/// overwrite would remove it (each writer holds the lock shared).
#[test]
fn convert_overwrite_is_refused_while_another_writer_of_the_folder_runs() {
    let root = tempfile::tempdir().unwrap();
    let fx = Fixture::make(root.path());
    let dir = root.path().join("overwrite");
    std::fs::create_dir_all(&dir).unwrap();
    let out = Case::ShardConvert.output(&dir);
    let (mut first, line, drain) =
        start_paused(&mut Case::ShardConvert.command(&fx, &dir), "samples/part-");
    let line = line.expect("the part never paused");
    let tmp = line
        .split("renaming ")
        .nth(1)
        .and_then(|s| s.split(" to ").next())
        .unwrap()
        .to_string();
    // The folder's files, less the lock files (which name their last holder).
    let files = || {
        let mut t = tree(&out);
        t.retain(|k, _| !k.ends_with(".lock"));
        t
    };
    let before = files();
    // Another conversion (other shard sizes) over it, with --overwrite.
    let overwrite = || {
        let mut c = tool();
        c.args(["convert", "--input"])
            .arg(&fx.release)
            .arg("--output")
            .arg(&out)
            .args(["--rows-per-shard", "5", "--overwrite"]);
        c
    };
    let second = overwrite().output().unwrap();
    let err = text(&second.stderr);
    let refused = !second.status.success()
        && err.contains(".convert.lock")
        && err.contains(&format!("held by pid {} on ", first.id()));
    let after = files();
    let tmp_kept = Path::new(&tmp).exists();
    first.kill().unwrap();
    first.wait().unwrap();
    drain.join().unwrap();
    assert!(
        refused,
        "convert --overwrite beside a running part was not refused naming the lock and pid {}: {err}",
        first.id()
    );
    assert!(
        tmp_kept && before == after,
        "the refused overwrite changed the running part's folder"
    );
    // The part gone, the overwrite runs, and its folder is a whole conversion.
    run_ok(overwrite().stdout(Stdio::null()));
    let o = tool()
        .args(["inspect", "--json", "--dataset"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o.stderr));
    // While an overwrite holds the lock, split (a writer of the folder) is refused.
    let held = arkit_core::atomic_file::FolderLock::acquire(&out, "convert", "test").unwrap();
    let split = tool()
        .args(["split", "--dataset"])
        .arg(&out)
        .args(["--test-subjects", "1", "--seed", "3"])
        .output()
        .unwrap();
    drop(held);
    let err = text(&split.stderr);
    assert!(
        !split.status.success()
            && err.contains("another convert --overwrite is writing")
            && err.contains(".convert.lock"),
        "split beside an overwrite: {err}"
    );
    assert!(!out.join("splits").exists(), "the refused split wrote");
}

/// A tmpfs mounted for a test (root only), unmounted when dropped.
struct SmallDisk {
    dir: PathBuf,
}

impl SmallDisk {
    /// Mounts a tmpfs of `mib` MiB at `dir`, or says why it cannot.
    fn mount(dir: &Path, mib: u64) -> Result<Self, String> {
        std::fs::create_dir_all(dir).unwrap();
        let out = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mib}m"), "tmpfs"])
            .arg(dir)
            .output()
            .map_err(|e| format!("no mount command: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "cannot mount a tmpfs (needs root): {}",
                text(&out.stderr).trim()
            ));
        }
        Ok(Self {
            dir: dir.to_path_buf(),
        })
    }

    /// Bytes free.
    fn available(&self) -> u64 {
        let out = Command::new("df")
            .args(["--output=avail", "-B1"])
            .arg(&self.dir)
            .output()
            .unwrap();
        text(&out.stdout)
            .lines()
            .nth(1)
            .and_then(|l| l.trim().parse().ok())
            .unwrap_or_else(|| panic!("df: {}", text(&out.stdout)))
    }

    /// Fills the file system until `free` bytes are left.
    fn leave(&self, free: u64) -> PathBuf {
        let filler = self.dir.join("filler");
        let n = self.available().saturating_sub(free);
        std::fs::write(&filler, vec![0u8; n as usize]).unwrap();
        filler
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(&self.dir).status();
    }
}

/// Bytes of every file under `dir` (or of the file `dir`).
fn bytes_under(dir: &Path) -> u64 {
    if dir.is_file() {
        return std::fs::metadata(dir).unwrap().len();
    }
    tree(dir).values().map(|v| v.len() as u64).sum()
}

#[test]
fn every_writer_on_a_full_disk_names_the_file_leaves_nothing_readable_and_reruns_once_freed() {
    let started = Instant::now();
    let root = tempfile::tempdir().unwrap();
    let disk = match SmallDisk::mount(&root.path().join("disk"), 64) {
        Ok(d) => d,
        Err(why) => {
            eprintln!("SKIPPED: the full-disk test: {why}");
            return;
        }
    };
    let fx = Fixture::make(&root.path().join("inputs"));
    let mut rows = Vec::new();
    for case in Case::all() {
        let reference = root.path().join(format!("{case:?}-reference"));
        case.prepare(&fx, &reference);
        let mut expected = Expected::default();
        if case == Case::Split {
            expected
                .split_states
                .push(mean_pose(&case.output(&reference), "test", root.path()).unwrap());
        }
        let before = bytes_under(&case.output(&reference));
        run_ok(case.command(&fx, &reference).stdout(Stdio::null()));
        let written = bytes_under(&case.output(&reference)).saturating_sub(before);
        match case {
            Case::Synth | Case::Augment | Case::ImportArkit => {
                expected.rows =
                    Some(converted_rows(&case.output(&reference), root.path()).unwrap());
            }
            Case::Split => expected
                .split_states
                .push(mean_pose(&case.output(&reference), "test", root.path()).unwrap()),
            #[cfg(feature = "model")]
            Case::ExportWeights => expected.file = std::fs::read(case.output(&reference)).unwrap(),
            #[cfg(feature = "model")]
            Case::ExportOnnx => expected.tree = case.outputs(&reference),
            _ => {}
        }
        let want = case.outputs(&reference);
        let dir = disk.dir.join(format!("{case:?}"));
        case.prepare(&fx, &dir);
        // Room for half of what the command writes.
        let free = written / 2;
        let filler = disk.leave(free);
        let out = case
            .command(&fx, &dir)
            .stdout(Stdio::null())
            .output()
            .unwrap();
        let err = text(&out.stderr);
        assert!(
            !out.status.success(),
            "{} wrote {written} bytes into {free} free bytes and succeeded",
            case.name()
        );
        assert!(
            err.contains("No space left on device") && names(&err, &dir),
            "{}: the error does not say the disk is full, naming the file: {err}",
            case.name()
        );
        std::fs::remove_file(&filler).unwrap();
        let (verdicts, state) = check_readers(case, &fx, &dir, false, &expected);
        let left_full = temporaries(&dir);
        rerun(case, &fx, &dir);
        let diff = differences(&want, &case.outputs(&dir));
        assert!(
            diff.is_empty(),
            "{} rerun after a full disk differs: {diff:?}",
            case.name()
        );
        let left = temporaries(&dir);
        assert!(left.is_empty(), "{}: {left:?}", case.name());
        rows.push((
            case,
            written,
            free,
            err.lines()
                .find(|l| l.contains("No space"))
                .unwrap_or("")
                .replace(&dir.display().to_string(), "DIR"),
            verdicts,
            state,
            left_full.len(),
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }
    println!(
        "\nfull disk (a 64 MiB tmpfs filled to leave half of each command's output free, {:.1} s)",
        started.elapsed().as_secs_f64()
    );
    println!(
        "| command | writes (bytes) | free (bytes) | error | readers said | refused | read last complete | temporaries after the failure | rerun once freed |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for (case, written, free, err, verdicts, state, left) in rows {
        println!(
            "| {} | {written} | {free} | {err} | {state} | {} | {} | {left} | identical, no leftovers |",
            case.name(),
            verdicts.iter().filter(|v| **v == Verdict::Refused).count(),
            verdicts
                .iter()
                .filter(|v| **v == Verdict::LastComplete)
                .count(),
        );
    }
}

/// What a reader polling every file saw while a writer ran.
#[derive(Default, Debug)]
struct Seen {
    reads: usize,
    old: usize,
    new: usize,
    absent: usize,
}

/// Polls every file of `old` and `new` (relative to `dir`) until `done`; each read must
/// be the old file, the new one, or no file (a reader then refuses): never a mix.
fn poll_while(
    dir: &Path,
    old: &BTreeMap<String, Vec<u8>>,
    new: &BTreeMap<String, Vec<u8>>,
    done: &std::sync::atomic::AtomicBool,
) -> Seen {
    let mut seen = Seen::default();
    let paths: std::collections::BTreeSet<&String> = old.keys().chain(new.keys()).collect();
    while !done.load(std::sync::atomic::Ordering::SeqCst) {
        for rel in &paths {
            seen.reads += 1;
            match std::fs::read(dir.join(rel)) {
                Ok(bytes) if new.get(*rel) == Some(&bytes) => seen.new += 1,
                Ok(bytes) if old.get(*rel) == Some(&bytes) => seen.old += 1,
                Ok(bytes) => panic!(
                    "{rel}: read {} bytes that are neither the old file nor the new one",
                    bytes.len()
                ),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => seen.absent += 1,
                Err(e) => panic!("{rel}: {e}"),
            }
        }
    }
    seen
}

#[test]
fn a_reader_beside_a_writer_reads_each_file_old_or_new_never_a_mix() {
    let started = Instant::now();
    let root = tempfile::tempdir().unwrap();
    let fx = Fixture::make(root.path());
    let augment = |out: &Path, seed: &str| {
        let mut c = tool();
        c.args(["augment", "--input"])
            .arg(&fx.dataset)
            .arg("--output")
            .arg(out)
            .args(["--flip", "--per-sample", "2", "--seed", seed]);
        c
    };
    let render = |d: &Path| {
        let mut c = tool();
        c.args(["render", "--dataset"]).arg(d).args([
            "--size",
            "48",
            "--points",
            "64",
            "--uv-size",
            "16",
        ]);
        c
    };
    let crops = |d: &Path| {
        let mut c = tool();
        c.args(["crops", "--dataset"]).arg(d).args(["--size", "64"]);
        c
    };
    let mut rows = Vec::new();
    // augment over an older augmentation (another seed); render and crops over none.
    for name in ["augment", "render", "crops"] {
        let (work, reference) = (
            root.path().join(format!("{name}-work")),
            root.path().join(format!("{name}-reference")),
        );
        let command: Box<dyn Fn(&Path) -> Command> = match name {
            "augment" => {
                run_ok(augment(&work, "2").stdout(Stdio::null()));
                run_ok(augment(&reference, "4").stdout(Stdio::null()));
                Box::new(|d: &Path| augment(d, "4"))
            }
            "render" => {
                copy_samples(&fx.dataset, &work);
                copy_samples(&fx.dataset, &reference);
                run_ok(render(&reference).stdout(Stdio::null()));
                Box::new(render)
            }
            _ => {
                copy_samples(&fx.dataset, &work);
                copy_samples(&fx.dataset, &reference);
                run_ok(crops(&reference).stdout(Stdio::null()));
                Box::new(crops)
            }
        };
        let (old, new) = (tree(&work), tree(&reference));
        let done = std::sync::atomic::AtomicBool::new(false);
        let seen = std::thread::scope(|s| {
            let reader = s.spawn(|| poll_while(&work, &old, &new, &done));
            let t = Instant::now();
            let status = command(&work).stdout(Stdio::null()).status().unwrap();
            let took = t.elapsed();
            done.store(true, std::sync::atomic::Ordering::SeqCst);
            assert!(status.success(), "{name} beside a reader failed");
            (reader.join().unwrap(), took)
        });
        // Every new file is there (augment leaves the older run's other samples, which
        // its new lists do not name).
        let after = tree(&work);
        assert!(
            new.iter().all(|(k, v)| after.get(k) == Some(v)),
            "{name}: the rewritten folder is not the uninterrupted run's"
        );
        rows.push((name, seen));
    }
    println!(
        "\na reader polling every file while a writer runs ({:.1} s)",
        started.elapsed().as_secs_f64()
    );
    println!("| writer | run (s) | file reads | old file | new file | absent | torn |");
    println!("|---|---|---|---|---|---|---|");
    for (name, (s, took)) in rows {
        println!(
            "| {name} | {:.2} | {} | {} | {} | {} | 0 |",
            took.as_secs_f64(),
            s.reads,
            s.old,
            s.new,
            s.absent
        );
    }
}

/// A source file that fails while a command is reading it: a FIFO in one image's place,
/// so the command blocks on that file in the middle of its run, and then reads a few
/// bytes that are not an image. `convert`, `crops` and `augment` report that sample,
/// naming its file, and write every other one; nothing is substituted for it.
#[test]
fn a_source_failing_mid_run_is_reported_naming_it_and_the_rest_is_written() {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let root = tempfile::tempdir().unwrap();
    let release = root.path().join("release");
    run_ok(tool().arg("synth").arg("--output").arg(&release).args([
        "--subjects",
        "3",
        "--images-per-subject",
        "4",
        "--size",
        "160x160",
        "--seed",
        "5",
    ]));
    let dataset = root.path().join("dataset");
    run_ok(&mut {
        let mut c = tool();
        convert_args(&mut c, &release, &dataset);
        c
    });
    let mut images: Vec<PathBuf> = tree(&release)
        .keys()
        .filter(|k| k.ends_with(".jpg"))
        .map(|k| release.join(k))
        .collect();
    images.sort();
    let victim = images[5].clone();
    let good = std::fs::read(&victim).unwrap();
    let total = images.len();
    let mut rows = Vec::new();
    for name in ["convert", "crops", "augment"] {
        let mut c = tool();
        match name {
            "convert" => convert_args(&mut c, &release, &root.path().join("converted")),
            "crops" => {
                c.args(["crops", "--dataset"])
                    .arg(&dataset)
                    .args(["--size", "64"]);
            }
            _ => {
                c.args(["augment", "--input"])
                    .arg(&dataset)
                    .arg("--output")
                    .arg(root.path().join("augmented"))
                    .args(["--flip", "--seed", "2"]);
            }
        }
        std::fs::remove_file(&victim).unwrap();
        let made = Command::new("mkfifo").arg(&victim).status().unwrap();
        assert!(made.success(), "mkfifo {}", victim.display());
        let mut child = c
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // While the command has the file open, it gets these bytes and then the end
        // (each write connects while a reader has the FIFO open, so they are counted,
        // not the command's opens).
        let mut opened_mid_run = 0;
        let status = loop {
            if let Some(status) = child.try_wait().unwrap() {
                break status;
            }
            match std::fs::OpenOptions::new()
                .write(true)
                .custom_flags(libc_o_nonblock())
                .open(&victim)
            {
                Ok(mut w) => {
                    opened_mid_run += 1;
                    let _ = w.write_all(b"not a JPEG");
                }
                Err(_) => std::thread::sleep(Duration::from_millis(5)),
            }
        };
        let out = child.wait_with_output().unwrap();
        std::fs::remove_file(&victim).unwrap();
        std::fs::write(&victim, &good).unwrap();
        let said = format!("{}{}", text(&out.stdout), text(&out.stderr));
        assert!(
            opened_mid_run > 0,
            "{name} never read {} while running: {said}",
            victim.display()
        );
        let rel = victim.strip_prefix(&release).unwrap().display().to_string();
        let reported = match name {
            // The reason is in the errors table, the count on the terminal.
            "convert" => {
                let errors = tree(&root.path().join("converted").join("errors"));
                said.contains("skipped 1 ")
                    && errors
                        .values()
                        .any(|v| v.windows(rel.len()).any(|w| w == rel.as_bytes()))
            }
            _ => said.contains(&victim.display().to_string()),
        };
        assert!(
            reported,
            "{name} did not report {}: {said}",
            victim.display()
        );
        let written = match name {
            "convert" => said.contains(&format!("converted {} samples", total - 1)),
            "crops" => said.contains(&format!("stored {} of {total} samples", total - 1)),
            _ => said.contains("skipped 1 sample(s)"),
        };
        assert!(written, "{name} did not write the other samples: {said}");
        // crops says so in its exit status; convert and augment succeed with the
        // sample reported.
        assert_eq!(
            status.success(),
            name != "crops",
            "{name}: {status}: {said}"
        );
        rows.push((
            name,
            opened_mid_run,
            said.lines().last().unwrap_or("").to_string(),
        ));
    }
    println!("\na source failing mid-run (a FIFO in an image's place)");
    println!("| command | FIFO writes while the command ran | last line |");
    println!("|---|---|---|");
    for (name, n, line) in rows {
        println!("| {name} | {n} | {line} |");
    }
}

/// `O_NONBLOCK`: opening a FIFO for writing fails at once while no reader has it open.
fn libc_o_nonblock() -> i32 {
    0o4000
}
