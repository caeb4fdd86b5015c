//! Datasets in object storage, against a real S3 server (s3s-fs with SigV4 on, from
//! `arkit-s3-testbed`) behind a fault-injecting proxy: `push` (incremental, resumed
//! after a kill, refusing another dataset), the readers from a bucket (`inspect`, the
//! loader: the same items bit for bit, one request a sample), and every fault ending in
//! retries then an error that names the bucket and key and no secret.

use crate::support::{converted_by_the_command, tool};
use arkit_data::crop::RuleSet;
use arkit_data::loader::{FaceLoader, LoaderMode, LoaderOptions};
use arkit_data::storage::{MirrorSet, RemoteOptions, RemoteUrl, open_remote};
use arkit_s3_testbed::{Fault, FaultControl, FaultPlan, FaultProxy, FaultRule, S3Server};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

const ACCESS: &str = "arkit-test-access";
const SECRET: &str = "arkit-test-secret-Zq81pLw";
const BUCKET: &str = "arkit";

/// A server, a proxy in front of it, and a cache folder.
struct Cloud {
    _server: S3Server,
    proxy: FaultProxy,
    cache: tempfile::TempDir,
    _root: tempfile::TempDir,
}

impl Cloud {
    fn start() -> Cloud {
        let root = tempfile::tempdir().unwrap();
        let server = S3Server::start(root.path(), ACCESS, SECRET).unwrap();
        server.create_bucket(BUCKET).unwrap();
        let proxy = FaultProxy::start(server.addr(), FaultPlan::default()).unwrap();
        Cloud {
            _server: server,
            proxy,
            cache: tempfile::tempdir().unwrap(),
            _root: root,
        }
    }

    fn control(&self) -> FaultControl {
        self.proxy.control()
    }

    fn url(&self, prefix: &str) -> String {
        format!("s3://{BUCKET}/{prefix}")
    }

    /// The client settings of this server (what the environment gives the commands).
    fn settings(&self, secret: &str) -> Vec<(String, String)> {
        vec![
            ("aws_endpoint".into(), self.proxy.endpoint()),
            ("aws_access_key_id".into(), ACCESS.into()),
            ("aws_secret_access_key".into(), secret.into()),
            ("aws_region".into(), "us-east-1".into()),
            ("arkit_storage_retries".into(), "4".into()),
            ("arkit_storage_timeout_ms".into(), "2000".into()),
        ]
    }

    /// Options with the mirror in this cache folder and no record cache (every read a
    /// request).
    fn options(&self) -> RemoteOptions {
        RemoteOptions {
            cache_dir: Some(self.cache.path().to_path_buf()),
            cache_bytes: Some(0),
            settings: self.settings(SECRET),
        }
    }

    /// The command with this server's environment (and no AWS config files).
    fn tool(&self) -> Command {
        let mut c = tool();
        c.env("AWS_ENDPOINT_URL", self.proxy.endpoint())
            .env("AWS_ACCESS_KEY_ID", ACCESS)
            .env("AWS_SECRET_ACCESS_KEY", SECRET)
            .env("AWS_REGION", "us-east-1")
            .env("ARKIT_STORAGE_RETRIES", "4")
            .env("ARKIT_STORAGE_TIMEOUT_MS", "2000")
            .env("ARKIT_CACHE_DIR", self.cache.path())
            .env("HOME", self.cache.path())
            .env_remove("AWS_PROFILE")
            .env_remove("AWS_SESSION_TOKEN");
        c
    }
}

fn ok(out: Output, what: &str) -> String {
    assert!(
        out.status.success(),
        "{what}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// A converted dataset with an official-rules crop store of side 64.
fn dataset(base: &Path, seed: u64) -> PathBuf {
    let dir = base.join("converted");
    converted_by_the_command(&base.join("release"), &dir, 3, 4, 256, seed);
    ok(
        tool()
            .args(["crops", "--dataset"])
            .arg(&dir)
            .args(["--compat", "official", "--size", "64"])
            .output()
            .unwrap(),
        "crops",
    );
    dir
}

fn push_json(cloud: &Cloud, dir: &Path, url: &str, extra: &[&str]) -> serde_json::Value {
    let out = cloud
        .tool()
        .arg("push")
        .arg(dir)
        .arg(url)
        .arg("--json")
        .args(extra)
        .output()
        .unwrap();
    serde_json::from_str(&ok(out, "push")).unwrap()
}

fn loader_options() -> LoaderOptions {
    LoaderOptions {
        split: None,
        mode: LoaderMode::Train,
        rules: RuleSet::Official,
        img_size: 64,
        n_pts: 32,
        seed: 5,
    }
}

fn topology() -> arkit_data::FaceTopology {
    arkit_data::mesh::builtin().topology.clone()
}

fn local_loader(dir: &Path) -> FaceLoader {
    let mut l = FaceLoader::open(dir, topology(), None, loader_options()).unwrap();
    l.open_crop_store(&dir.join("crops").join("official-64"))
        .unwrap();
    l
}

fn remote_loader(cloud: &Cloud, url: &str) -> (FaceLoader, arkit_data::storage::RemoteDataset) {
    let url = RemoteUrl::parse(url).unwrap();
    let set = MirrorSet::Loader {
        crop_store: Some("crops/official-64".into()),
    };
    let remote = open_remote(&url, &set, &cloud.options()).unwrap();
    let mut l = FaceLoader::open(remote.local_dir(), topology(), None, loader_options()).unwrap();
    l.open_remote_crop_store(
        &remote.local_dir().join("crops/official-64"),
        &remote,
        "crops/official-64",
    )
    .unwrap();
    (l, remote)
}

#[test]
fn a_pushed_dataset_reads_as_its_folder_does_one_request_a_sample() {
    let base = tempfile::tempdir().unwrap();
    let dir = dataset(base.path(), 3);
    let cloud = Cloud::start();
    let url = cloud.url("v1/arkit");
    let pushed = push_json(&cloud, &dir, &url, &[]);
    assert_eq!(pushed["uploaded"], pushed["objects"], "{pushed}");
    assert!(pushed["objects"].as_u64().unwrap() >= 6, "{pushed}");

    // inspect --json from the bucket says what it says of the folder.
    let local = ok(
        tool()
            .args(["inspect", "--json", "--dataset"])
            .arg(&dir)
            .output()
            .unwrap(),
        "inspect local",
    );
    let remote = ok(
        cloud
            .tool()
            .args(["inspect", "--json", "--dataset", &url])
            .output()
            .unwrap(),
        "inspect remote",
    );
    let (l, r): (serde_json::Value, serde_json::Value) = (
        serde_json::from_str(&local).unwrap(),
        serde_json::from_str(&remote).unwrap(),
    );
    for key in ["samples", "subjects", "yaw", "pitch", "roll", "distance"] {
        if l.get(key).is_some() {
            assert_eq!(l[key], r[key], "inspect's {key}");
        }
    }

    // The loader: the same items, bit for bit, in two epochs; batches fetched together.
    let from_disk = local_loader(&dir);
    let (from_bucket, _remote) = remote_loader(&cloud, &url);
    assert_eq!(from_disk.len(), from_bucket.len());
    let n = from_disk.len();
    assert!(n >= 8, "{n} samples");
    cloud.control().reset_stats();
    let indices: Vec<usize> = (0..n).rev().collect();
    for epoch in [0u64, 1] {
        from_bucket.prefetch(&indices);
        for &i in &indices {
            assert_eq!(
                from_disk.item(i, epoch).unwrap(),
                from_bucket.item(i, epoch).unwrap(),
                "sample {i}, epoch {epoch}"
            );
        }
    }
    let stats = cloud.control().stats();
    let gets = stats.requests_by_method.get("GET").copied().unwrap_or(0);
    assert!(
        gets <= 2 * n as u64,
        "{gets} GETs for {n} samples in 2 epochs: more than one request a sample ({stats:?})"
    );
    // Bytes: the records, within 10%.
    let store = from_disk.crop_store().unwrap();
    let records: u64 = (0..n)
        .map(|i| {
            let (shard, row) = from_disk.location(i).unwrap();
            store.record_span(shard, row).unwrap().1
        })
        .sum();
    assert!(
        stats.response_body_bytes as f64 <= 1.1 * (2 * records) as f64,
        "{} bytes read for {} bytes of records",
        stats.response_body_bytes,
        2 * records
    );
}

#[test]
fn push_is_incremental_and_refuses_another_dataset_without_overwrite() {
    let base = tempfile::tempdir().unwrap();
    let dir = dataset(&base.path().join("a"), 3);
    let other = dataset(&base.path().join("b"), 4);
    let cloud = Cloud::start();
    let url = cloud.url("arkit");
    let first = push_json(&cloud, &dir, &url, &[]);
    let again = push_json(&cloud, &dir, &url, &[]);
    assert_eq!(again["uploaded"], 0, "{again}");
    assert_eq!(again["unchanged"], first["objects"], "{again}");

    // Another dataset: refused, naming the URL, and nothing changed.
    let out = cloud
        .tool()
        .arg("push")
        .arg(&other)
        .arg(&url)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--overwrite") && err.contains(&url), "{err}");
    let (l, _r) = remote_loader(&cloud, &url);
    assert_eq!(
        l.item(0, 0).unwrap(),
        local_loader(&dir).item(0, 0).unwrap(),
        "the refused push changed the published dataset"
    );
    let replaced = push_json(&cloud, &other, &url, &["--overwrite"]);
    assert!(replaced["uploaded"].as_u64().unwrap() > 0, "{replaced}");
    let (l, _r) = remote_loader(&cloud, &url);
    assert_eq!(
        l.item(0, 0).unwrap(),
        local_loader(&other).item(0, 0).unwrap()
    );
}

#[test]
fn a_killed_push_is_never_read_and_its_rerun_uploads_only_what_is_missing() {
    let base = tempfile::tempdir().unwrap();
    let dir = dataset(base.path(), 3);
    let cloud = Cloud::start();
    let url = cloud.url("killed");
    // Slow enough to be killed after a few objects.
    cloud.control().set_latency(Duration::from_millis(150));
    let mut child = cloud
        .tool()
        .arg("push")
        .arg(&dir)
        .arg(&url)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while cloud
        .control()
        .stats()
        .requests_by_method
        .get("PUT")
        .copied()
        .unwrap_or(0)
        < 3
    {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "push never uploaded"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    cloud.control().set_latency(Duration::ZERO);
    // A half-published dataset is refused, naming the URL.
    let out = cloud
        .tool()
        .args(["inspect", "--dataset", &url])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no published dataset") && err.contains(&url),
        "{err}"
    );
    let rerun = push_json(&cloud, &dir, &url, &[]);
    let (uploaded, objects) = (
        rerun["uploaded"].as_u64().unwrap(),
        rerun["objects"].as_u64().unwrap(),
    );
    assert!(
        uploaded < objects && rerun["unchanged"].as_u64().unwrap() >= 2,
        "the rerun uploaded {uploaded} of {objects}: {rerun}"
    );
    let (l, _r) = remote_loader(&cloud, &url);
    assert_eq!(
        l.item(1, 0).unwrap(),
        local_loader(&dir).item(1, 0).unwrap()
    );
}

#[test]
fn faults_end_in_retries_then_an_error_naming_the_bucket_and_key_and_no_secret() {
    let base = tempfile::tempdir().unwrap();
    let dir = dataset(base.path(), 3);
    let cloud = Cloud::start();
    let url = cloud.url("faults");
    push_json(&cloud, &dir, &url, &[]);
    let expected = local_loader(&dir);
    let (l, _remote) = remote_loader(&cloud, &url);
    let c = cloud.control();
    let part = "crops/official-64/part-";
    // Passing faults: retried, and the item is right.
    for (fault, what) in [
        (Fault::Status(503), "503"),
        (Fault::Status(500), "500"),
        (Fault::Reset, "a reset"),
        (Fault::Truncate { after_bytes: 7 }, "a truncated body"),
        (
            Fault::Stall(Duration::from_millis(2500)),
            "a stall past the time-out",
        ),
    ] {
        c.reset_stats();
        c.set_rules(vec![
            FaultRule::new(fault, 2).method("GET").key_contains(part),
        ]);
        let got = l.item(2, 0).unwrap_or_else(|e| panic!("after {what}: {e}"));
        assert_eq!(got, expected.item(2, 0).unwrap(), "after {what}");
        let s = c.stats();
        assert_eq!(s.faults_fired, 2, "{what}: {s:?}");
        assert!(s.requests >= 3, "{what}: not retried: {s:?}");
    }
    // Lasting faults: an error naming the bucket and key, after the tries.
    for (fault, says) in [
        (Fault::Status(503), "after 4 tries"),
        (Fault::Truncate { after_bytes: 5 }, "after 4 tries"),
    ] {
        c.set_rules(vec![
            FaultRule::new(fault, 1000).method("GET").key_contains(part),
        ]);
        let started = Instant::now();
        let err = l.item(3, 0).unwrap_err().to_string();
        assert!(
            err.contains(&format!("s3://{BUCKET}/faults/{part}")) && err.contains(says),
            "{err}"
        );
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "took {:?}",
            started.elapsed()
        );
        assert!(!err.contains(SECRET), "{err}");
    }
    c.clear_rules();
    assert_eq!(l.item(3, 0).unwrap(), expected.item(3, 0).unwrap());

    // A missing object: at once, naming it.
    let missing = open_remote(
        &RemoteUrl::parse(&cloud.url("nothing-here")).unwrap(),
        &MirrorSet::Tables,
        &cloud.options(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        missing.contains("no published dataset") && missing.contains("s3://arkit/nothing-here"),
        "{missing}"
    );
    // Wrong credentials: refused, the error says so and names no secret.
    let wrong = "WRONG-secret-value-9d2c";
    let mut options = cloud.options();
    options.settings = cloud.settings(wrong);
    let err = open_remote(
        &RemoteUrl::parse(&url).unwrap(),
        &MirrorSet::Tables,
        &options,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("s3://arkit/faults/"), "{err}");
    assert!(err.contains("credentials"), "{err}");
    assert!(!err.contains(wrong) && !err.contains(SECRET), "{err}");
}

#[test]
fn a_dataset_published_again_under_a_running_job_stops_it_naming_the_object() {
    let base = tempfile::tempdir().unwrap();
    let dir = dataset(&base.path().join("a"), 3);
    let other = dataset(&base.path().join("b"), 4);
    let cloud = Cloud::start();
    let url = cloud.url("moving");
    push_json(&cloud, &dir, &url, &[]);
    let (l, _remote) = remote_loader(&cloud, &url);
    let before = l.item(0, 0).unwrap();
    assert_eq!(before, local_loader(&dir).item(0, 0).unwrap());
    push_json(&cloud, &other, &url, &["--overwrite"]);
    let err = l.item(1, 0).unwrap_err().to_string();
    assert!(
        err.contains("changed since this job opened it")
            && err.contains("s3://arkit/moving/crops/official-64/part-"),
        "{err}"
    );
}
