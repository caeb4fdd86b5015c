//! Readers beside writers (issue 62, part 3): each CLI reader (`train`,
//! `predict --dataset` with `--oracle`, `--mean-pose` and `--model`, `eval`) is stopped
//! at a pause point while a writer replaces what it reads (`convert --overwrite` of
//! another release, `render --overwrite` with another seed, `crops`), then resumed.
//!
//! The rule (as the Python loader's): a reader keeps serving what it opened (the shard,
//! targets and errors files it opened stay open), and where it must open something
//! again it stops with an error naming the dataset folder as changed. So each verdict
//! must be one of:
//! - "last complete state": it succeeded and its output equals, byte for byte, an
//!   undisturbed run's on the folder as it was before the writer, or as the writer left
//!   it (a reader that had not yet opened the targets reads the new complete ones);
//! - "clear refusal naming the folder": it failed, its error names the dataset folder,
//!   and it wrote no output.
//!
//! Anything else (an output of two generations, a crash without the folder's name) fails
//! the test. The pause points (`ARKIT_PAUSE_READER`): `opened` (dataset.json read, its
//! shards opened, nothing else yet) and `reading` (everything opened, the first rows
//! being read). The table of verdicts is printed (`--nocapture`) and is in
//! docs/testing.md.

use crate::kill::{run_ok, text, tree};
use crate::support::tool;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Reader {
    #[cfg(feature = "model")]
    Train,
    Oracle,
    MeanPose,
    #[cfg(feature = "model")]
    Model,
    Eval,
}

const READERS: &[Reader] = &[
    #[cfg(feature = "model")]
    Reader::Train,
    Reader::Oracle,
    Reader::MeanPose,
    #[cfg(feature = "model")]
    Reader::Model,
    Reader::Eval,
];

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Writer {
    ConvertOverwrite,
    RenderOverwrite,
    Crops,
}

const WRITERS: &[Writer] = &[
    Writer::ConvertOverwrite,
    Writer::RenderOverwrite,
    Writer::Crops,
];

const POINTS: &[&str] = &["opened", "reading"];

/// The fixed paths every run uses (outputs may record the dataset's path).
struct Bed {
    root: PathBuf,
    /// The pristine dataset (release A converted, rendered).
    base: PathBuf,
    /// Where each run's dataset is (a copy of `base`).
    dataset: PathBuf,
    /// Release B, for `convert --overwrite`.
    other_release: PathBuf,
    /// Oracle predictions on `base`, for `eval`.
    predictions: PathBuf,
    #[cfg(feature = "model")]
    model: PathBuf,
}

fn synth(out: &Path, seed: &str) {
    run_ok(tool().arg("synth").arg("--output").arg(out).args([
        "--subjects",
        "4",
        "--images-per-subject",
        "3",
        "--size",
        "160x160",
        "--seed",
        seed,
    ]));
}

fn copy_tree(from: &Path, to: &Path) {
    if to.exists() {
        std::fs::remove_dir_all(to).unwrap();
    }
    for (rel, bytes) in tree(from) {
        let path = to.join(&rel);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(path, bytes).unwrap();
    }
}

impl Bed {
    fn make(root: &Path) -> Bed {
        let (release, other_release) = (root.join("release-a"), root.join("release-b"));
        synth(&release, "5");
        synth(&other_release, "6");
        let base = root.join("base");
        run_ok(
            tool()
                .args(["convert", "--input"])
                .arg(&release)
                .arg("--output")
                .arg(&base)
                .args(["--rows-per-shard", "4"]),
        );
        run_ok(
            tool()
                .args(["render", "--dataset"])
                .arg(&base)
                .args(["--size", "64", "--points", "256"]),
        );
        let predictions = root.join("oracle.parquet");
        run_ok(
            tool()
                .args(["predict", "--oracle", "--dataset"])
                .arg(&base)
                .arg("--output")
                .arg(&predictions),
        );
        #[cfg(feature = "model")]
        let model = {
            let model = root.join("model");
            run_ok(
                tool()
                    .args(["train", "--dataset"])
                    .arg(&base)
                    .args(["--split", "all", "--steps", "1", "--batch", "2", "--output"])
                    .arg(&model),
            );
            model
        };
        Bed {
            root: root.to_path_buf(),
            base,
            dataset: root.join("work").join("dataset"),
            other_release,
            predictions,
            #[cfg(feature = "model")]
            model,
        }
    }

    /// Where `reader` writes (outside the dataset).
    fn output(&self, reader: Reader) -> PathBuf {
        let name = match reader {
            #[cfg(feature = "model")]
            Reader::Train => "trained",
            #[cfg(feature = "model")]
            Reader::Model => "model.parquet",
            Reader::Oracle => "oracle.parquet",
            Reader::MeanPose => "mean.parquet",
            Reader::Eval => "eval.json",
        };
        self.root.join("work").join(name)
    }

    fn reader(&self, reader: Reader) -> Command {
        let mut c = tool();
        let d = &self.dataset;
        let out = self.output(reader);
        match reader {
            #[cfg(feature = "model")]
            Reader::Train => {
                c.args(["train", "--dataset"]).arg(d).args([
                    "--split",
                    "all",
                    "--steps",
                    "2",
                    "--batch",
                    "2",
                    "--stream",
                    // The points render stored: a render with another seed changes them.
                    "--stored-points",
                    "--output",
                ]);
                c.arg(out);
            }
            #[cfg(feature = "model")]
            Reader::Model => {
                c.args(["predict", "--split", "all", "--model"])
                    .arg(&self.model)
                    .arg("--dataset")
                    .arg(d)
                    .arg("--output")
                    .arg(out);
            }
            Reader::Oracle => {
                c.args(["predict", "--oracle", "--dataset"])
                    .arg(d)
                    .arg("--output")
                    .arg(out);
            }
            Reader::MeanPose => {
                c.args(["predict", "--mean-pose", "--split", "all", "--dataset"])
                    .arg(d)
                    .arg("--output")
                    .arg(out);
            }
            Reader::Eval => {
                c.args(["eval", "--split", "all", "--json", "--dataset"])
                    .arg(d)
                    .arg("--predictions")
                    .arg(&self.predictions);
            }
        }
        c
    }

    fn writer(&self, writer: Writer) -> Command {
        let mut c = tool();
        let d = &self.dataset;
        match writer {
            Writer::ConvertOverwrite => {
                c.args(["convert", "--input"])
                    .arg(&self.other_release)
                    .arg("--output")
                    .arg(d)
                    .args(["--rows-per-shard", "4", "--overwrite"]);
            }
            Writer::RenderOverwrite => {
                c.args(["render", "--dataset"]).arg(d).args([
                    "--size",
                    "64",
                    "--points",
                    "256",
                    "--seed",
                    "9",
                    "--overwrite",
                ]);
            }
            Writer::Crops => {
                c.args(["crops", "--dataset"]).arg(d).args(["--size", "64"]);
            }
        }
        c
    }

    /// What `reader` gave: `Ok(output)` (its files, or its stdout for `eval`) or
    /// `Err(stderr)`, with its output then checked absent.
    fn result(
        &self,
        reader: Reader,
        status_ok: bool,
        stdout: &[u8],
        stderr: &str,
    ) -> Result<BTreeMap<String, Vec<u8>>, String> {
        let out = self.output(reader);
        if !status_ok {
            assert!(
                !out.exists() || (out.is_dir() && tree(&out).is_empty()),
                "{reader:?} failed but left {}: {stderr}",
                out.display()
            );
            return Err(stderr.to_string());
        }
        let mut got = if out.is_dir() {
            tree(&out)
        } else if out.exists() {
            BTreeMap::from([(String::new(), std::fs::read(&out).unwrap())])
        } else {
            BTreeMap::new()
        };
        if reader == Reader::Eval {
            got.insert("stdout".into(), stdout.to_vec());
        }
        Ok(got)
    }

    fn clear_output(&self, reader: Reader) {
        let out = self.output(reader);
        if out.is_dir() {
            std::fs::remove_dir_all(&out).unwrap();
        } else if out.exists() {
            std::fs::remove_file(&out).unwrap();
        }
    }

    /// An undisturbed run of `reader` on the dataset as it is now.
    fn undisturbed(&self, reader: Reader) -> Result<BTreeMap<String, Vec<u8>>, String> {
        self.clear_output(reader);
        let out = self.reader(reader).output().unwrap();
        self.result(
            reader,
            out.status.success(),
            &out.stdout,
            &text(&out.stderr),
        )
    }
}

/// Runs `reader` paused at `point`, runs `writer` to its end meanwhile, resumes it.
fn disturbed(
    bed: &Bed,
    reader: Reader,
    writer: Writer,
    point: &str,
) -> Result<BTreeMap<String, Vec<u8>>, String> {
    bed.clear_output(reader);
    let resume = bed.root.join("work").join("resume");
    let _ = std::fs::remove_file(&resume);
    let mut child = bed
        .reader(reader)
        .env(arkit_core::atomic_file::PAUSE_READER, point)
        .env(arkit_core::atomic_file::RESUME_READER, &resume)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let lines = std::thread::spawn(move || {
        let mut all = String::new();
        for line in BufReader::new(stderr).lines().map_while(|l| l.ok()) {
            if line.contains("ARKIT_PAUSE_READER: paused at") {
                // (Not kept: it names the folder, which the verdict asks of the error.)
                let _ = tx.send(());
                continue;
            }
            all.push_str(&line);
            all.push('\n');
        }
        all
    });
    rx.recv_timeout(std::time::Duration::from_secs(300))
        .unwrap_or_else(|_| {
            let _ = child.kill();
            panic!("{reader:?} never paused at {point}")
        });
    run_ok(&mut bed.writer(writer));
    std::fs::write(&resume, b"").unwrap();
    let mut stdout = Vec::new();
    std::io::Read::read_to_end(child.stdout.as_mut().unwrap(), &mut stdout).unwrap();
    let status = child.wait().unwrap();
    let stderr = lines.join().unwrap();
    bed.result(reader, status.success(), &stdout, &stderr)
}

#[test]
fn readers_beside_writers_serve_one_generation_or_refuse_naming_the_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let bed = Bed::make(tmp.path());
    // The outputs of undisturbed runs: before any writer, and after each.
    let mut before = BTreeMap::new();
    copy_tree(&bed.base, &bed.dataset);
    for &r in READERS {
        let got = bed.undisturbed(r);
        assert!(got.is_ok(), "{r:?} on the pristine dataset: {got:?}");
        before.insert(format!("{r:?}"), got);
    }
    let mut after = BTreeMap::new();
    for &w in WRITERS {
        copy_tree(&bed.base, &bed.dataset);
        run_ok(&mut bed.writer(w));
        for &r in READERS {
            after.insert(format!("{r:?} {w:?}"), bed.undisturbed(r));
        }
    }
    let mut table = Vec::new();
    let shown = bed.dataset.display().to_string();
    for &w in WRITERS {
        for &r in READERS {
            for &point in POINTS {
                copy_tree(&bed.base, &bed.dataset);
                let got = disturbed(&bed, r, w, point);
                let same = before[&format!("{r:?}")] == after[&format!("{r:?} {w:?}")];
                let verdict = match &got {
                    Ok(out) if same && Some(out) == before[&format!("{r:?}")].as_ref().ok() => {
                        "last complete state (the writer changed nothing it reads)".to_string()
                    }
                    Ok(out) if Some(out) == before[&format!("{r:?}")].as_ref().ok() => {
                        "last complete state (as opened)".to_string()
                    }
                    Ok(out) if Some(out) == after[&format!("{r:?} {w:?}")].as_ref().ok() => {
                        "last complete state (as the writer left it)".to_string()
                    }
                    Ok(_) => panic!(
                        "{r:?} paused at {point} beside {w:?}: an output that is neither the opened folder's nor the replaced folder's (two generations mixed)"
                    ),
                    Err(e) => {
                        assert!(
                            e.contains(&shown),
                            "{r:?} paused at {point} beside {w:?} failed without naming {shown}: {e}"
                        );
                        let why = if e.contains("the dataset changed while this command read it") {
                            "dataset changed"
                        } else if e.contains("the targets changed while this command read them") {
                            "targets changed"
                        } else {
                            e.lines()
                                .find(|l| {
                                    l.contains(&shown) && !l.starts_with("ARKIT_PAUSE_READER")
                                })
                                .unwrap_or_default()
                        };
                        format!(
                            "clear refusal naming the folder: {}",
                            why.replace(&shown, "DIR")
                        )
                    }
                };
                table.push(format!(
                    "{:<9} {:<16} {:<8} {verdict}",
                    format!("{r:?}"),
                    format!("{w:?}"),
                    point
                ));
            }
        }
    }
    println!("reader    writer           pause    verdict");
    for line in &table {
        println!("{line}");
    }
    // A reader paused once everything was opened keeps serving it: its output is the
    // opened folder's whatever replaced it.
    for line in table.iter().filter(|l| l.contains(" reading ")) {
        assert!(
            line.contains("last complete state (as opened)")
                || line.contains("last complete state (the writer changed nothing it reads)"),
            "a reader that had opened everything did not serve it: {line}"
        );
    }
}
