//! Who owns a temporary, as writers on several "nodes" of one shared folder see it:
//! each node a PID and UTS namespace of its own (`unshare --pid --uts`), so both
//! writers are PID 1 and their host names differ, as on two machines. A temporary is
//! owned by its writer's lock, never by a process id: `arkit-tool clean` (and every
//! writer's own sweep) removes the killed node's temporary and keeps the live node's,
//! though the two writers' process ids are the same number; `inspect` lists both with
//! their sizes and states.

use crate::kill::{await_pause, run_ok, temporaries, text};
use crate::support::tool;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// Whether `unshare --pid --uts` works here (root, or user namespaces allowed).
fn namespaces() -> bool {
    Command::new("unshare")
        .args([
            "--pid",
            "--uts",
            "--fork",
            "--kill-child",
            "--mount-proc",
            "true",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

/// A writer started on "node" `host`: `args` of arkit-tool as PID 1 of its own PID and
/// UTS namespaces, paused before renaming the first file whose path contains `pause`.
/// Returns the process (`unshare`; killing it kills the writer) and the temporary the
/// writer holds.
fn paused_on_node(host: &str, args: &[&str], pause: &str) -> (Child, PathBuf) {
    let program = tool().get_program().to_owned();
    let script = format!("hostname {host} && exec \"$0\" \"$@\"");
    let mut child = Command::new("unshare")
        .args(["--pid", "--uts", "--fork", "--kill-child", "--mount-proc"])
        .args(["sh", "-c", &script])
        .arg(program)
        .args(args)
        .env(arkit_core::atomic_file::PAUSE_BEFORE_RENAME, pause)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    match await_pause(&mut child) {
        Ok(line) => {
            let rest = line
                .split("paused before renaming ")
                .nth(1)
                .unwrap_or_default();
            let tmp = PathBuf::from(rest.split(" to ").next().unwrap_or_default());
            (child, tmp)
        }
        Err(why) => panic!("the writer on {host} never paused at '{pause}': {why}"),
    }
}

/// Waits (up to 30 s) until no process holds the lock of the temporary `tmp`.
fn gone(tmp: &Path) {
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    loop {
        let file = std::fs::File::open(tmp).unwrap();
        if file.try_lock().is_ok() {
            return;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "{}: still locked 30 s after its writer was killed",
            tmp.display()
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}

fn clean_json(dir: &Path) -> serde_json::Value {
    let out = run_ok(tool().arg("clean").arg(dir).arg("--json"));
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn two_nodes_in_one_folder_a_killed_nodes_temporary_goes_and_a_live_ones_stays() {
    if !namespaces() {
        println!(
            "SKIPPED: unshare --pid --uts is not permitted here (needs root or user namespaces)"
        );
        return;
    }
    let root = tempfile::tempdir().unwrap();
    let release = root.path().join("release");
    run_ok(tool().arg("synth").arg("--output").arg(&release).args([
        "--subjects",
        "4",
        "--images-per-subject",
        "4",
        "--size",
        "160x160",
        "--seed",
        "3",
    ]));
    let out = root.path().join("dataset");
    let shard = |i: &str| {
        vec![
            "convert".to_string(),
            "--input".into(),
            release.display().to_string(),
            "--output".into(),
            out.display().to_string(),
            "--rows-per-shard".into(),
            "4".into(),
            "--shard".into(),
            i.into(),
        ]
    };
    let a_args = shard("0/2");
    let b_args = shard("1/2");
    let a_args: Vec<&str> = a_args.iter().map(String::as_str).collect();
    let b_args: Vec<&str> = b_args.iter().map(String::as_str).collect();
    let (mut node_a, a_tmp) = paused_on_node("node-a", &a_args, "samples/part-");
    let (mut node_b, b_tmp) = paused_on_node("node-b", &b_args, "samples/part-");
    assert_ne!(a_tmp, b_tmp);
    assert!(a_tmp.exists() && b_tmp.exists());

    // Node B dies; its writer was PID 1 there, as node A's still running one is.
    node_b.kill().unwrap();
    node_b.wait().unwrap();
    // `unshare --kill-child` kills the node's writer as it dies; that takes an instant.
    gone(&b_tmp);
    // A torn folder: inspect exits 1, with the state and the temporaries.
    let inspect = tool()
        .args(["inspect", "--dataset"])
        .arg(&out)
        .output()
        .unwrap();
    let shown = format!("{}{}", text(&inspect.stdout), text(&inspect.stderr));
    assert!(
        shown.contains("1 abandoned by killed runs") && shown.contains("1 being written"),
        "{shown}"
    );
    let report = clean_json(&out);
    let items = report["temporaries"].as_array().unwrap();
    let state = |tmp: &Path| {
        let rel = tmp.strip_prefix(&out).unwrap().display().to_string();
        let item = items
            .iter()
            .find(|i| i["path"] == rel.as_str())
            .unwrap_or_else(|| panic!("{rel} not listed: {report}"));
        (
            item["abandoned"].clone(),
            item["removed"].clone(),
            item["bytes"].as_u64().unwrap(),
        )
    };
    let (a_abandoned, a_removed, a_bytes) = state(&a_tmp);
    let (b_abandoned, b_removed, b_bytes) = state(&b_tmp);
    assert_eq!(
        (a_abandoned, a_removed),
        (false.into(), false.into()),
        "{report}"
    );
    assert_eq!(
        (b_abandoned, b_removed),
        (true.into(), true.into()),
        "{report}"
    );
    assert!(a_bytes > 0 && b_bytes > 0);
    assert_eq!(report["bytes_freed"].as_u64(), Some(b_bytes));
    assert!(a_tmp.exists() && !b_tmp.exists());

    // Node A dies too, and is left a zombie of nobody's (its unshare not reaped yet):
    // its temporary goes with the next sweep.
    node_a.kill().unwrap();
    gone(&a_tmp);
    let report = clean_json(&out);
    assert_eq!(report["removed"].as_u64(), Some(1), "{report}");
    node_a.wait().unwrap();
    assert!(temporaries(&out).is_empty(), "{:?}", temporaries(&out));

    // The shards rerun and merged give a complete dataset.
    for args in [&a_args, &b_args] {
        run_ok(tool().args(args.iter()).stdout(Stdio::null()));
    }
    run_ok(
        tool()
            .args(["merge", "--dataset"])
            .arg(&out)
            .stdout(Stdio::null()),
    );
    let inspect = run_ok(tool().args(["inspect", "--json", "--dataset"]).arg(&out));
    let v: serde_json::Value = serde_json::from_slice(&inspect.stdout).unwrap();
    assert_eq!(v["state"]["temporaries"], serde_json::json!([]), "{v}");
}

#[test]
fn clean_keeps_a_running_writers_temporary_and_dry_run_removes_nothing() {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path();
    // A killed writer's leftovers of every kind (a file, a folder with its owner file,
    // an old folder set aside, a name from older versions with a process id) and a
    // file a live writer (this test) holds.
    let files = [
        dir.join("samples/.part-00000.parquet.tmp-00c0ffee00c0ffee"),
        dir.join(".lists.tmp-abcdef0123456789.owner"),
        dir.join(format!(".x.tmp-{}", std::process::id())),
    ];
    for f in &files {
        std::fs::create_dir_all(f.parent().unwrap()).unwrap();
        std::fs::write(f, b"12345").unwrap();
    }
    let folder = dir.join(".lists.tmp-abcdef0123456789");
    std::fs::create_dir_all(folder.join("list")).unwrap();
    std::fs::write(folder.join("list/a.csv"), b"abc").unwrap();
    let aside = dir.join(".lists.tmp-abcdef0123456789.aside");
    std::fs::create_dir_all(&aside).unwrap();
    let live = dir.join("samples/.part-00001.parquet.tmp-1111222233334444");
    std::fs::write(&live, b"live").unwrap();
    let held = std::fs::File::open(&live).unwrap();
    held.try_lock().unwrap();

    let dry = run_ok(tool().arg("clean").arg(dir).args(["--dry-run", "--json"]));
    let dry: serde_json::Value = serde_json::from_slice(&dry.stdout).unwrap();
    assert_eq!(dry["removed"].as_u64(), Some(0));
    assert_eq!(dry["temporaries"].as_array().unwrap().len(), 6, "{dry}");
    assert!(files.iter().all(|f| f.exists()) && folder.exists() && aside.exists());

    let report = clean_json(dir);
    assert_eq!(report["removed"].as_u64(), Some(5), "{report}");
    assert_eq!(report["bytes_freed"].as_u64(), Some(3 * 5 + 3), "{report}");
    assert!(live.exists() && !folder.exists() && !aside.exists());
    assert!(files.iter().all(|f| !f.exists()));
    let human = run_ok(tool().arg("clean").arg(dir));
    assert!(
        text(&human.stdout).contains("kept: a running writer holds it"),
        "{}",
        text(&human.stdout)
    );
    drop(held);
    let report = clean_json(dir);
    assert_eq!(report["removed"].as_u64(), Some(1), "{report}");
    // A folder that is not one is refused, naming it.
    let missing = tool()
        .arg("clean")
        .arg(dir.join("absent"))
        .output()
        .unwrap();
    assert!(!missing.status.success());
    assert!(
        text(&missing.stderr).contains("absent"),
        "{}",
        text(&missing.stderr)
    );
}

/// `render --output ELSEWHERE` holds that folder's writers' lock too: while one render
/// writes its targets into a converted folder, a `convert --overwrite` of that folder
/// and a second render into it are refused, naming the folder; killed there, it leaves
/// nothing that its rerun does not clean, and the rerun equals a render of that dataset
/// into a fresh folder.
#[test]
fn render_elsewhere_holds_the_output_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (release, other) = (root.join("release"), root.join("other"));
    for (out, seed) in [(&release, "5"), (&other, "6")] {
        run_ok(tool().arg("synth").arg("--output").arg(out).args([
            "--subjects",
            "2",
            "--images-per-subject",
            "3",
            "--size",
            "160x160",
            "--seed",
            seed,
        ]));
    }
    let (a, b, shared) = (root.join("a"), root.join("b"), root.join("shared"));
    for (input, out) in [(&release, &a), (&release, &b), (&other, &shared)] {
        run_ok(
            tool()
                .args(["convert", "--input"])
                .arg(input)
                .arg("--output")
                .arg(out)
                .args(["--rows-per-shard", "4"]),
        );
    }
    let render = |dataset: &Path, output: &Path| {
        let mut c = tool();
        c.args(["render", "--dataset"])
            .arg(dataset)
            .arg("--output")
            .arg(output)
            .args(["--size", "32", "--points", "64"]);
        c
    };
    // Render a into `shared` (another converted folder), paused before its first
    // targets file.
    let mut first = render(&a, &shared)
        .env(
            arkit_core::atomic_file::PAUSE_BEFORE_RENAME,
            "targets/part-",
        )
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    await_pause(&mut first).unwrap_or_else(|e| panic!("render never paused: {e}"));
    let shown = shared.display().to_string();
    // A convert --overwrite of that folder is refused while the render writes there.
    let out = tool()
        .args(["convert", "--input"])
        .arg(&release)
        .arg("--output")
        .arg(&shared)
        .args(["--rows-per-shard", "4", "--overwrite"])
        .output()
        .unwrap();
    let err = text(&out.stderr);
    assert!(
        !out.status.success() && err.contains(&shown) && err.contains("render"),
        "convert --overwrite beside a render into its folder: {err}"
    );
    // So is a second render into it, of the same dataset's copy or another.
    let out = render(&b, &shared).output().unwrap();
    let err = text(&out.stderr);
    assert!(
        !out.status.success() && err.contains(&shown),
        "a second render into one output folder: {err}"
    );
    first.kill().unwrap();
    first.wait().unwrap();
    // Rerun: complete, nothing left, the targets a render into a fresh folder makes.
    run_ok(&mut render(&a, &shared));
    assert_eq!(temporaries(&shared), Vec::<String>::new());
    let fresh = root.join("fresh");
    run_ok(&mut render(&a, &fresh));
    let targets = |d: &Path| crate::kill::tree(&d.join("targets"));
    assert_eq!(targets(&shared), targets(&fresh));
}
