//! `client`: the object-store client ([`RemoteStore`]), built from the URL, the
//! standard environment and the AWS config files; one per process (made again in a
//! forked child, whose parent's threads and sockets it cannot use); every request
//! retried with backoff, then failed with an error that names the object and no secret.
//! [`RemoteObject`] is one object read by ranges, pinned to its ETag.

use super::cache::RecordCache;
use super::location::RemoteUrl;
use crate::store::ReadAt;
use arkit_core::{Error, Result};
use bytes::Bytes;
use futures::StreamExt;
use object_store::{
    Attribute, Attributes, GetOptions, GetRange, ObjectMeta, ObjectStore, ObjectStoreExt,
    PutOptions, PutPayload, path::Path as ObjectPath,
};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The user metadata key under which `push` stores each object's SHA-256.
pub(crate) const SHA256_METADATA: &str = "arkit-sha256";

/// How requests are retried: `attempts` tries in all, the waits doubling from `base` to
/// at most `max`; each request given up after `timeout`.
#[derive(Clone, Copy, Debug)]
struct RetryPolicy {
    attempts: u32,
    base: Duration,
    max: Duration,
    timeout: Duration,
}

impl RetryPolicy {
    /// The defaults (6 tries, 100 ms doubling to 3 s, 30 s a request), changed by
    /// `ARKIT_STORAGE_RETRIES` (tries) and `ARKIT_STORAGE_TIMEOUT_MS`, in the settings
    /// (lower-case) or the environment.
    fn from_env(settings: &[(String, String)]) -> Self {
        let num = |name: &str| {
            let key = name.to_ascii_lowercase();
            settings
                .iter()
                .find(|(k, _)| *k == key)
                .map(|(_, v)| v.clone())
                .or_else(|| std::env::var(name).ok())
                .and_then(|v| v.trim().parse::<u64>().ok())
        };
        RetryPolicy {
            attempts: num("ARKIT_STORAGE_RETRIES").map_or(6, |n| n.clamp(1, 100) as u32),
            base: Duration::from_millis(100),
            max: Duration::from_secs(3),
            timeout: Duration::from_millis(num("ARKIT_STORAGE_TIMEOUT_MS").unwrap_or(30_000)),
        }
    }

    fn wait(&self, attempt: u32) -> Duration {
        self.base
            .saturating_mul(1u32 << attempt.min(16))
            .min(self.max)
    }
}

/// The client of one process: its runtime and its store.
struct ProcessClient {
    pid: u32,
    runtime: Arc<tokio::runtime::Runtime>,
    store: Arc<dyn ObjectStore>,
}

/// A bucket prefix and the client that reads and writes it.
pub struct RemoteStore {
    url: RemoteUrl,
    /// The configuration the client is built from (may hold secrets; never printed).
    config: Vec<(String, String)>,
    /// Values redacted from every message.
    secrets: Vec<String>,
    retry: RetryPolicy,
    client: Mutex<Option<ProcessClient>>,
}

impl std::fmt::Debug for RemoteStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RemoteStore({})", self.url)
    }
}

/// Why one try failed.
enum Failure {
    Store(object_store::Error),
    Short { got: u64, want: u64 },
    Changed { was: String, now: String },
    Timeout,
}

impl Failure {
    fn retryable(&self) -> bool {
        match self {
            Failure::Store(e) => matches!(
                e,
                object_store::Error::Generic { .. } | object_store::Error::JoinError { .. }
            ),
            Failure::Short { .. } | Failure::Timeout => true,
            Failure::Changed { .. } => false,
        }
    }
}

impl RemoteStore {
    /// A client of `url`, configured from the environment and the AWS config files (see
    /// the module's docs). Nothing is requested yet.
    pub fn new(url: &RemoteUrl) -> Result<Arc<Self>> {
        Self::with_settings(url, &[])
    }

    /// [`RemoteStore::new`] with `settings` (`object_store`'s configuration keys, e.g.
    /// `aws_endpoint`, `aws_access_key_id`, `aws_secret_access_key`, `aws_region`)
    /// taking precedence over the environment's.
    pub fn with_settings(url: &RemoteUrl, settings: &[(String, String)]) -> Result<Arc<Self>> {
        let (mut config, mut secrets) = environment_config(url.scheme());
        for (k, v) in settings {
            let k = k.to_ascii_lowercase();
            if ["secret", "token", "key", "password", "sas", "credential"]
                .iter()
                .any(|w| k.contains(w))
            {
                secrets.push(v.clone());
            }
            config.retain(|(ck, _)| *ck != k);
            config.push((k, v.clone()));
        }
        let retry = RetryPolicy::from_env(&config);
        config.retain(|(k, _)| !k.starts_with("arkit_"));
        let u = url.secret_url();
        if !u.password().unwrap_or_default().is_empty() {
            secrets.push(u.password().unwrap_or_default().to_string());
        }
        if let Some(q) = u.query() {
            secrets.extend(
                q.split('&')
                    .filter_map(|kv| kv.split_once('='))
                    .map(|(_, v)| v.to_string()),
            );
        }
        secrets.retain(|s| s.len() >= 4);
        let store = Arc::new(RemoteStore {
            url: url.clone(),
            config,
            secrets,
            retry,
            client: Mutex::new(None),
        });
        store.client()?;
        Ok(store)
    }

    /// The prefix this store reads and writes.
    pub fn url(&self) -> &RemoteUrl {
        &self.url
    }

    /// This process's runtime and store, made on first use and again after a fork.
    fn client(&self) -> Result<(Arc<tokio::runtime::Runtime>, Arc<dyn ObjectStore>)> {
        let pid = std::process::id();
        let mut slot = self.client.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(c) = slot.as_ref()
            && c.pid == pid
        {
            return Ok((c.runtime.clone(), c.store.clone()));
        }
        if let Some(old) = slot.take() {
            // Made by the parent of this forked process: its threads are not here, so
            // dropping it would wait for them forever.
            std::mem::forget(old);
        }
        let runtime = Arc::new(
            // A runtime driven by the thread that waits on it: no thread of its own, so
            // the process stays single-threaded for a later fork (DataLoader workers);
            // the blocking pool (name look-ups) lets its threads go after a second.
            tokio::runtime::Builder::new_current_thread()
                .thread_name("arkit-storage")
                .thread_keep_alive(Duration::from_secs(1))
                .enable_all()
                .build()
                .map_err(|e| Error::io(self.url.shown_path(""), e))?,
        );
        let store = self.build_store()?;
        *slot = Some(ProcessClient {
            pid,
            runtime: runtime.clone(),
            store: store.clone(),
        });
        Ok((runtime, store))
    }

    fn build_store(&self) -> Result<Arc<dyn ObjectStore>> {
        let url = self.url.secret_url();
        let mut opts: Vec<(String, String)> = self.config.clone();
        let endpoint_is_http = opts
            .iter()
            .any(|(k, v)| k.contains("endpoint") && v.starts_with("http://"));
        if endpoint_is_http || url.scheme() == "http" {
            opts.push(("allow_http".into(), "true".into()));
        }
        opts.push((
            "timeout".into(),
            format!("{}ms", self.retry.timeout.as_millis()),
        ));
        opts.push(("connect_timeout".into(), "5s".into()));
        // Our own retries (`retrying`) are the only ones: the crate's would multiply them.
        let no_retry = object_store::RetryConfig {
            max_retries: 0,
            ..Default::default()
        };
        let fail = |e: object_store::Error| {
            Error::invalid("dataset URL", self.redact(&format!("{}: {e}", self.url)))
        };
        macro_rules! build {
            ($builder:expr, $key:ty) => {{
                let mut b = $builder.with_url(url.as_str()).with_retry(no_retry.clone());
                for (k, v) in &opts {
                    if let Ok(key) = k.parse::<$key>() {
                        b = b.with_config(key, v.clone());
                    }
                }
                Arc::new(b.build().map_err(fail)?) as Arc<dyn ObjectStore>
            }};
        }
        Ok(match url.scheme() {
            "s3" | "s3a" => build!(
                object_store::aws::AmazonS3Builder::new(),
                object_store::aws::AmazonS3ConfigKey
            ),
            "gs" => build!(
                object_store::gcp::GoogleCloudStorageBuilder::new(),
                object_store::gcp::GoogleConfigKey
            ),
            "az" | "abfs" | "abfss" => build!(
                object_store::azure::MicrosoftAzureBuilder::new(),
                object_store::azure::AzureConfigKey
            ),
            _ => {
                let (store, _) = object_store::parse_url_opts(url, opts).map_err(fail)?;
                Arc::from(store)
            }
        })
    }

    /// `message` with every known secret replaced by `***`.
    pub(crate) fn redact(&self, message: &str) -> String {
        let mut out = message.to_string();
        for s in &self.secrets {
            out = out.replace(s.as_str(), "***");
        }
        super::location::redact_url_text_in(&out)
    }

    fn path(&self, relative: &str) -> ObjectPath {
        ObjectPath::from(self.url.key(relative))
    }

    /// The error of `op` on the object `relative` after its last try.
    fn error(&self, relative: &str, op: &str, f: Failure, tries: u32) -> Error {
        let shown = self.url.shown_path(relative);
        let after = if tries > 1 {
            format!(" (after {tries} tries)")
        } else {
            String::new()
        };
        let message = match f {
            Failure::Store(object_store::Error::NotFound { .. }) => {
                format!("{op}: no such object in the bucket")
            }
            Failure::Store(e @ object_store::Error::PermissionDenied { .. })
            | Failure::Store(e @ object_store::Error::Unauthenticated { .. }) => format!(
                "{op}: the server refused the credentials ({e}); check AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_PROFILE and AWS_ENDPOINT_URL"
            ),
            Failure::Store(object_store::Error::Precondition { .. }) => format!(
                "{op}: the object changed since this job opened it (another ETag): the dataset was published again under a running job; start the job again"
            ),
            Failure::Store(e) => format!("{op} failed{after}: {e}"),
            Failure::Short { got, want } => {
                format!("{op}: the body came back with {got} bytes, {want} were asked for{after}")
            }
            Failure::Changed { was, now } => format!(
                "{op}: the object changed since this job opened it (ETag {was}, now {now}): the dataset was published again under a running job; start the job again"
            ),
            Failure::Timeout => format!(
                "{op}: no answer within {} ms{after}",
                self.retry.timeout.as_millis()
            ),
        };
        let message = self.redact(&message);
        Error::io(shown, std::io::Error::other(message))
    }

    /// Runs `attempt` until it succeeds, fails for good or runs out of tries.
    async fn retrying<T, F, Fut>(&self, relative: &str, op: &str, attempt: F) -> Result<T>
    where
        F: Fn() -> Fut,
        Fut: std::future::Future<Output = std::result::Result<T, Failure>>,
    {
        let mut tries = 0;
        loop {
            tries += 1;
            let result = match tokio::time::timeout(self.retry.timeout, attempt()).await {
                Ok(r) => r,
                Err(_) => Err(Failure::Timeout),
            };
            match result {
                Ok(v) => return Ok(v),
                Err(f) if f.retryable() && tries < self.retry.attempts => {
                    tokio::time::sleep(self.retry.wait(tries - 1)).await;
                }
                Err(f) => return Err(self.error(relative, op, f, tries)),
            }
        }
    }

    fn block_on<T>(&self, f: impl std::future::Future<Output = Result<T>>) -> Result<T> {
        let (runtime, _) = self.client()?;
        runtime.block_on(f)
    }

    /// The size and ETag of `relative`.
    pub fn head(&self, relative: &str) -> Result<ObjectMeta> {
        let (_, store) = self.client()?;
        let path = self.path(relative);
        self.block_on(self.retrying(relative, "HEAD", || {
            let (store, path) = (store.clone(), path.clone());
            async move { store.head(&path).await.map_err(Failure::Store) }
        }))
    }

    /// The size, ETag and stored SHA-256 (user metadata `arkit-sha256`, written by
    /// `push`) of `relative`; `None` when there is no such object.
    pub(crate) fn head_with_sha(
        &self,
        relative: &str,
    ) -> Result<Option<(ObjectMeta, Option<String>)>> {
        let (_, store) = self.client()?;
        let path = self.path(relative);
        let r = self.block_on(async {
            let got = self
                .retrying(relative, "HEAD", || {
                    let (store, path) = (store.clone(), path.clone());
                    async move {
                        let opts = GetOptions {
                            head: true,
                            ..Default::default()
                        };
                        match store.get_opts(&path, opts).await {
                            Ok(r) => Ok(Some(r)),
                            Err(object_store::Error::NotFound { .. }) => Ok(None),
                            Err(e) => Err(Failure::Store(e)),
                        }
                    }
                })
                .await?;
            Ok(got.map(|r| {
                let sha = r
                    .attributes
                    .get(&Attribute::Metadata(SHA256_METADATA.into()))
                    .map(|v| v.to_string());
                (r.meta, sha)
            }))
        })?;
        Ok(r)
    }

    /// The whole object `relative` and its ETag; `Ok(None)` when there is no such object
    /// and `missing_ok`.
    pub fn get(&self, relative: &str) -> Result<(Bytes, Option<String>)> {
        self.get_opt(relative)?.ok_or_else(|| {
            self.error(
                relative,
                "GET",
                Failure::Store(object_store::Error::NotFound {
                    path: relative.into(),
                    source: "not found".into(),
                }),
                1,
            )
        })
    }

    /// [`RemoteStore::get`], `None` when there is no such object.
    pub fn get_opt(&self, relative: &str) -> Result<Option<(Bytes, Option<String>)>> {
        let (_, store) = self.client()?;
        let path = self.path(relative);
        self.block_on(self.retrying(relative, "GET", || {
            let (store, path) = (store.clone(), path.clone());
            async move {
                let r = match store.get_opts(&path, GetOptions::default()).await {
                    Ok(r) => r,
                    Err(object_store::Error::NotFound { .. }) => return Ok(None),
                    Err(e) => return Err(Failure::Store(e)),
                };
                let want = r.meta.size;
                let etag = r.meta.e_tag.clone();
                let bytes = r.bytes().await.map_err(Failure::Store)?;
                if bytes.len() as u64 != want {
                    return Err(Failure::Short {
                        got: bytes.len() as u64,
                        want,
                    });
                }
                Ok(Some((bytes, etag)))
            }
        }))
    }

    /// Spans of several objects, `(relative, etag, offset, length)` each, fetched
    /// concurrently (at most 64 in flight), in order.
    pub(crate) fn get_spans_of(
        &self,
        wanted: &[(&str, Option<&str>, u64, u64)],
    ) -> Result<Vec<Bytes>> {
        let (_, store) = self.client()?;
        self.block_on(async {
            let fetches = wanted.iter().map(|&(relative, etag, at, len)| {
                let path = self.path(relative);
                let etag = etag.map(str::to_string);
                let store = store.clone();
                async move {
                    self.retrying(relative, &format!("GET bytes {at}..{}", at + len), || {
                        let (store, path, etag) = (store.clone(), path.clone(), etag.clone());
                        async move { get_span(&*store, &path, etag, at, len).await }
                    })
                    .await
                }
            });
            let results: Vec<Result<Bytes>> =
                futures::stream::iter(fetches).buffered(64).collect().await;
            results.into_iter().collect()
        })
    }

    /// Uploads `bytes` as `relative` with its SHA-256 as user metadata; its new ETag.
    pub(crate) fn put(&self, relative: &str, bytes: Bytes, sha256: &str) -> Result<Option<String>> {
        let (_, store) = self.client()?;
        let path = self.path(relative);
        self.block_on(self.retrying(relative, "PUT", || {
            let (store, path, bytes) = (store.clone(), path.clone(), bytes.clone());
            let mut attributes = Attributes::new();
            attributes.insert(
                Attribute::Metadata(SHA256_METADATA.into()),
                sha256.to_string().into(),
            );
            async move {
                let opts = PutOptions {
                    attributes,
                    ..Default::default()
                };
                store
                    .put_opts(&path, PutPayload::from_bytes(bytes), opts)
                    .await
                    .map(|r| r.e_tag)
                    .map_err(Failure::Store)
            }
        }))
    }

    /// Uploads the local file `file` as `relative` in parts of `part_bytes` (a multipart
    /// upload; aborted if it fails); its new ETag.
    pub(crate) fn put_multipart(
        &self,
        relative: &str,
        file: &Path,
        sha256: &str,
        part_bytes: usize,
        on_bytes: &(dyn Fn(u64) + Sync),
    ) -> Result<Option<String>> {
        use std::io::Read;
        let (_, store) = self.client()?;
        let path = self.path(relative);
        let mut attributes = Attributes::new();
        attributes.insert(
            Attribute::Metadata(SHA256_METADATA.into()),
            sha256.to_string().into(),
        );
        self.block_on(async {
            let opts = object_store::PutMultipartOptions {
                attributes,
                ..Default::default()
            };
            let mut upload = self
                .retrying(relative, "multipart upload (create)", || {
                    let (store, path, opts) = (store.clone(), path.clone(), opts.clone());
                    async move {
                        store
                            .put_multipart_opts(&path, opts)
                            .await
                            .map_err(Failure::Store)
                    }
                })
                .await?;
            let mut f = std::fs::File::open(file).map_err(|e| Error::io(file, e))?;
            let mut part = 0;
            loop {
                let mut buf = vec![0u8; part_bytes];
                let mut n = 0;
                while n < part_bytes {
                    let got = f.read(&mut buf[n..]).map_err(|e| Error::io(file, e))?;
                    if got == 0 {
                        break;
                    }
                    n += got;
                }
                if n == 0 && part > 0 {
                    break;
                }
                buf.truncate(n);
                let payload = PutPayload::from(buf);
                part += 1;
                let r = upload.put_part(payload).await;
                if let Err(e) = r {
                    let _ = upload.abort().await;
                    return Err(self.error(
                        relative,
                        &format!("multipart upload (part {part})"),
                        Failure::Store(e),
                        1,
                    ));
                }
                on_bytes(n as u64);
                if n < part_bytes {
                    break;
                }
            }
            match upload.complete().await {
                Ok(r) => Ok(r.e_tag),
                Err(e) => {
                    let _ = upload.abort().await;
                    Err(self.error(
                        relative,
                        "multipart upload (complete)",
                        Failure::Store(e),
                        1,
                    ))
                }
            }
        })
    }

    /// Deletes `relative` (nothing when it is not there).
    pub(crate) fn delete(&self, relative: &str) -> Result<()> {
        let (_, store) = self.client()?;
        let path = self.path(relative);
        self.block_on(self.retrying(relative, "DELETE", || {
            let (store, path) = (store.clone(), path.clone());
            async move {
                match store.delete(&path).await {
                    Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
                    Err(e) => Err(Failure::Store(e)),
                }
            }
        }))
    }
}

/// One ranged GET of `len` bytes at `at`, checked for its length and ETag.
async fn get_span(
    store: &dyn ObjectStore,
    path: &ObjectPath,
    etag: Option<String>,
    at: u64,
    len: u64,
) -> std::result::Result<Bytes, Failure> {
    if len == 0 {
        return Ok(Bytes::new());
    }
    let opts = GetOptions {
        range: Some(GetRange::Bounded(at..at + len)),
        if_match: etag.clone(),
        ..Default::default()
    };
    let r = store.get_opts(path, opts).await.map_err(Failure::Store)?;
    if let (Some(was), Some(now)) = (&etag, &r.meta.e_tag)
        && was != now
    {
        return Err(Failure::Changed {
            was: was.clone(),
            now: now.clone(),
        });
    }
    let bytes = r.bytes().await.map_err(Failure::Store)?;
    if bytes.len() as u64 != len {
        return Err(Failure::Short {
            got: bytes.len() as u64,
            want: len,
        });
    }
    Ok(bytes)
}

/// The client's configuration from the environment (every `AWS_*`, `GOOGLE_*` or
/// `AZURE_*` variable, lower-cased, as `object_store` names its keys) and, for S3, the
/// AWS config files' profile for what the environment does not set; and the values to
/// redact.
fn environment_config(scheme: &str) -> (Vec<(String, String)>, Vec<String>) {
    let mut config = Vec::new();
    let mut secrets = Vec::new();
    let family = match scheme {
        "s3" | "s3a" => "AWS_",
        "gs" => "GOOGLE_",
        "az" | "abfs" | "abfss" => "AZURE_",
        _ => "",
    };
    for (k, v) in std::env::vars() {
        let upper = k.to_ascii_uppercase();
        let secret_like = ["SECRET", "TOKEN", "KEY", "PASSWORD", "SAS", "CREDENTIAL"]
            .iter()
            .any(|w| upper.contains(w));
        if secret_like
            && (upper.starts_with("AWS_")
                || upper.starts_with("GOOGLE_")
                || upper.starts_with("AZURE_"))
        {
            secrets.push(v.clone());
        }
        if !family.is_empty() && upper.starts_with(family) {
            config.push((k.to_ascii_lowercase(), v));
        }
    }
    if family == "AWS_" {
        let profile = aws_profile();
        for (k, v) in profile {
            if k.contains("secret") || k.contains("token") || k.contains("key_id") {
                secrets.push(v.clone());
            }
            if !config.iter().any(|(ck, _)| ck == &k) {
                config.push((k, v));
            }
        }
        if !config
            .iter()
            .any(|(k, _)| k == "aws_region" || k == "aws_default_region")
        {
            config.push(("aws_region".into(), "us-east-1".into()));
        }
    }
    (config, secrets)
}

/// The keys of the AWS profile in use (`AWS_PROFILE`, else `default`) from the shared
/// credentials file and the config file (`AWS_SHARED_CREDENTIALS_FILE`,
/// `AWS_CONFIG_FILE`, else `~/.aws/credentials` and `~/.aws/config`), as `object_store`
/// names them: access key, secret, session token, region, endpoint.
fn aws_profile() -> Vec<(String, String)> {
    let profile = std::env::var("AWS_PROFILE").unwrap_or_else(|_| "default".into());
    let home = std::env::var_os("HOME").map(PathBuf::from);
    let file = |var: &str, name: &str| {
        std::env::var_os(var)
            .map(PathBuf::from)
            .or_else(|| home.as_ref().map(|h| h.join(".aws").join(name)))
    };
    let mut out = Vec::new();
    let wanted = [
        ("aws_access_key_id", "aws_access_key_id"),
        ("aws_secret_access_key", "aws_secret_access_key"),
        ("aws_session_token", "aws_session_token"),
        ("region", "aws_region"),
        ("endpoint_url", "aws_endpoint_url"),
    ];
    for (path, section) in [
        (
            file("AWS_SHARED_CREDENTIALS_FILE", "credentials"),
            profile.clone(),
        ),
        (
            file("AWS_CONFIG_FILE", "config"),
            if profile == "default" {
                profile.clone()
            } else {
                format!("profile {profile}")
            },
        ),
    ] {
        let Some(text) = path.and_then(|p| std::fs::read_to_string(p).ok()) else {
            continue;
        };
        for (k, v) in ini_section(&text, &section) {
            if let Some((_, ours)) = wanted.iter().find(|(theirs, _)| *theirs == k)
                && !out.iter().any(|(o, _): &(String, String)| o == ours)
            {
                out.push((ours.to_string(), v));
            }
        }
    }
    out
}

/// The `key = value` pairs of `[section]` in an INI text.
fn ini_section(text: &str, section: &str) -> Vec<(String, String)> {
    let mut inside = false;
    let mut out = Vec::new();
    for line in text.lines() {
        let line = line.trim();
        if line.starts_with('#') || line.starts_with(';') || line.is_empty() {
            continue;
        }
        if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            inside = name.trim() == section;
            continue;
        }
        if inside && let Some((k, v)) = line.split_once('=') {
            out.push((k.trim().to_ascii_lowercase(), v.trim().to_string()));
        }
    }
    out
}

/// One object read by ranges ([`ReadAt`]): its size and ETag found when it was opened,
/// every read checked for its length and that ETag, and served from a
/// [`RecordCache`] when one is given.
#[derive(Debug)]
pub struct RemoteObject {
    store: Arc<RemoteStore>,
    relative: String,
    shown: PathBuf,
    len: u64,
    etag: Option<String>,
    cache: Option<Arc<RecordCache>>,
}

impl RemoteObject {
    /// Opens `relative` of `store` (one HEAD): its size and ETag pinned.
    pub fn open(
        store: Arc<RemoteStore>,
        relative: &str,
        cache: Option<Arc<RecordCache>>,
    ) -> Result<Self> {
        let meta = store.head(relative)?;
        Ok(RemoteObject {
            shown: store.url().shown_path(relative),
            relative: relative.to_string(),
            len: meta.size,
            etag: meta.e_tag,
            store,
            cache,
        })
    }

    /// The ETag it is pinned to.
    pub fn etag(&self) -> Option<&str> {
        self.etag.as_deref()
    }

    /// Spans of several objects of one store, `(object, offset, length)` each: those
    /// cached served from the cache, the others fetched together (concurrently, one
    /// ranged GET a span), each checked for its length and its object's ETag.
    pub fn read_across(wanted: &[(&RemoteObject, u64, u64)]) -> Result<Vec<Vec<u8>>> {
        for &(o, at, len) in wanted {
            if at.checked_add(len).is_none_or(|end| end > o.len) {
                return Err(Error::format(
                    &o.shown,
                    format!(
                        "bytes {at}..{} asked of an object of {} bytes",
                        at.saturating_add(len),
                        o.len
                    ),
                ));
            }
        }
        let ids: Vec<String> = wanted.iter().map(|(o, _, _)| o.cache_id()).collect();
        let mut out: Vec<Option<Vec<u8>>> = wanted
            .iter()
            .zip(&ids)
            .map(|(&(o, at, len), id)| o.cache.as_ref().and_then(|c| c.get(id, at, len)))
            .collect();
        let missing: Vec<usize> = (0..wanted.len()).filter(|&i| out[i].is_none()).collect();
        if let Some(&first) = missing.first() {
            let store = &wanted[first].0.store;
            let requests: Vec<(&str, Option<&str>, u64, u64)> = missing
                .iter()
                .map(|&i| {
                    let (o, at, len) = wanted[i];
                    (o.relative.as_str(), o.etag.as_deref(), at, len)
                })
                .collect();
            let fetched = store.get_spans_of(&requests)?;
            for (&i, bytes) in missing.iter().zip(fetched) {
                let (o, at, _) = wanted[i];
                if let Some(c) = &o.cache {
                    c.put(&ids[i], at, &bytes);
                }
                out[i] = Some(bytes.to_vec());
            }
        }
        Ok(out
            .into_iter()
            .map(|b| b.expect("every span read"))
            .collect())
    }

    fn cache_id(&self) -> String {
        format!(
            "{}#{}#{}",
            self.shown.display(),
            self.len,
            self.etag.as_deref().unwrap_or("")
        )
    }
}

impl ReadAt for RemoteObject {
    fn name(&self) -> &Path {
        &self.shown
    }

    fn len(&self) -> u64 {
        self.len
    }

    fn read_exact_at(&self, buf: &mut [u8], offset: u64) -> Result<()> {
        let mut got = self.read_spans(&[(offset, buf.len() as u64)])?;
        buf.copy_from_slice(&got.pop().expect("one span"));
        Ok(())
    }

    fn read_spans(&self, spans: &[(u64, u64)]) -> Result<Vec<Vec<u8>>> {
        let wanted: Vec<(&RemoteObject, u64, u64)> =
            spans.iter().map(|&(at, len)| (self, at, len)).collect();
        RemoteObject::read_across(&wanted)
    }

    fn is_remote(&self) -> bool {
        true
    }

    fn read_across(&self, wanted: &[(&dyn ReadAt, u64, u64)]) -> Result<Vec<Vec<u8>>> {
        let objects: Option<Vec<(&RemoteObject, u64, u64)>> = wanted
            .iter()
            .map(|&(source, at, len)| {
                (source as &dyn std::any::Any)
                    .downcast_ref::<RemoteObject>()
                    .map(|o| (o, at, len))
            })
            .collect();
        match objects {
            Some(objects) => RemoteObject::read_across(&objects),
            None => Err(Error::invalid(
                "crop store",
                "a store of local and remote parts",
            )),
        }
    }

    fn forget(&self, offset: u64, len: u64) {
        if let Some(c) = &self.cache {
            c.forget(&self.cache_id(), offset, len);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profiles_are_read_from_their_section() {
        let text = "[default]\naws_access_key_id = A\n[profile x]\nregion = eu-west-1\nendpoint_url=http://h:1\n";
        assert_eq!(
            ini_section(text, "default"),
            vec![("aws_access_key_id".into(), "A".into())]
        );
        assert_eq!(
            ini_section(text, "profile x"),
            vec![
                ("region".into(), "eu-west-1".into()),
                ("endpoint_url".into(), "http://h:1".into())
            ]
        );
    }

    #[test]
    fn backoff_doubles_up_to_its_cap() {
        let p = RetryPolicy {
            attempts: 6,
            base: Duration::from_millis(100),
            max: Duration::from_secs(3),
            timeout: Duration::from_secs(1),
        };
        assert_eq!(p.wait(0), Duration::from_millis(100));
        assert_eq!(p.wait(3), Duration::from_millis(800));
        assert_eq!(p.wait(10), Duration::from_secs(3));
    }
}
