//! Test infrastructure for arkit-tool's object-storage reading.
//!
//! The crate runs, inside a test or a benchmark, a **real** S3-protocol server and a
//! fault-injecting HTTP proxy in front of it, so that the client arkit-tool ships (the
//! `object_store` crate) is exercised over the network exactly as against a cloud
//! bucket, never mocked:
//!
//! - [`S3Server`]: [s3s-fs](https://crates.io/crates/s3s-fs) (an S3 server whose
//!   buckets are the subfolders of a directory) over HTTP/1.1, with AWS Signature
//!   Version 4 authentication enforced (a request signed with another secret gets
//!   403). Object reads (`GetObject`) are answered by a path of ours with one file
//!   read each, and honour `If-Match` (412); s3s-fs 0.14 reads an object in 4 KiB
//!   pieces, each a hop to a blocking thread, which on a small machine takes from the
//!   client under test the CPU a cloud bucket would not.
//! - [`FaultProxy`]: an HTTP/1.1 reverse proxy that forwards every request unchanged
//!   (headers, `Host` and the SigV4 `Authorization` included, so signatures stay
//!   valid) and streams the answer back, adding a per-request latency, a bandwidth
//!   cap shared by all connections, and scripted faults ([`Fault`]): an error status,
//!   a connection reset, a truncated body, a stall. It keeps counters ([`ProxyStats`])
//!   and is steered at run time from Rust through a [`FaultControl`] handle, or from
//!   any language through its JSON control endpoints under `/__testbed/` (see
//!   [`FaultProxy`]).
//!
//! The binary `arkit-s3-testbed` starts both and prints their endpoints as one line
//! of JSON, for tests written in other languages.
//!
//! ```
//! use std::time::Duration;
//! use arkit_s3_testbed::{Fault, FaultPlan, FaultProxy, FaultRule, S3Server};
//!
//! let root = tempfile::tempdir()?;
//! let server = S3Server::start(root.path(), "access", "secret")?;
//! server.create_bucket("faces")?;
//! let plan = FaultPlan {
//!     latency: Duration::from_millis(20),
//!     bandwidth_bytes_per_sec: 125_000_000, // 1 Gbit/s
//!     ..FaultPlan::default()
//! };
//! let proxy = FaultProxy::start(server.addr(), plan)?;
//! // The next two GETs of a key containing "part-0" fail with 503.
//! proxy.control().push_rule(
//!     FaultRule::new(Fault::Status(503), 2).method("GET").key_contains("part-0"),
//! );
//! // Point the S3 client (path style, region us-east-1, these keys) at
//! // proxy.endpoint(), or at server.endpoint() to bypass the proxy.
//! assert!(proxy.endpoint().starts_with("http://127.0.0.1:"));
//! assert_eq!(proxy.control().stats().requests, 0);
//! # Ok::<(), std::io::Error>(())
//! ```
//!
//! Everything binds the loopback address `127.0.0.1` on a port the system picks,
//! never another address: nothing here is reachable from outside the machine. Each
//! server runs on its own thread with its own tokio runtime, so it serves callers
//! that are synchronous or run any async runtime, and stops (its port freed) when it
//! is dropped.

#![warn(missing_docs)]

mod backend;

use std::collections::{BTreeMap, VecDeque};
use std::convert::Infallible;
use std::io;
use std::net::{Ipv4Addr, SocketAddr, TcpListener as StdTcpListener};
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::task::{Context, Poll};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use bytes::Bytes;
use http::{HeaderValue, Method, Request, Response, StatusCode, header};
use http_body_util::{BodyExt, Full};
use hyper::body::{Body, Frame, Incoming, SizeHint};
use hyper::service::service_fn;
use hyper_util::client::legacy::Client;
use hyper_util::client::legacy::connect::HttpConnector;
use hyper_util::rt::{TokioExecutor, TokioIo};
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, oneshot};

/// The error of the proxy's bodies and services (a concrete type: hyper's bounds on
/// a boxed `dyn Error` trip the compiler's higher-ranked lifetime checks in spawned
/// futures).
type ProxyError = io::Error;

/// How long a stopping server waits for its in-flight blocking file operations.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);

// ---------------------------------------------------------------------------------
// The background thread shared by the two servers.

/// A listener served on its own thread and tokio runtime until dropped.
struct Background {
    addr: SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    thread: Option<JoinHandle<()>>,
}

impl Background {
    /// Binds `127.0.0.1:0` and serves each accepted connection with `serve` (called
    /// inside the runtime, where it may spawn tasks) until the value is dropped.
    fn start<F>(name: &str, mut serve: F) -> io::Result<Self>
    where
        F: FnMut(TcpStream) + Send + 'static,
    {
        let listener = StdTcpListener::bind((Ipv4Addr::LOCALHOST, 0))?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        // One thread: on a small machine that also runs the client under test, a
        // work-stealing runtime's cross-thread wake-ups cost the client CPU.
        let runtime = tokio::runtime::Builder::new_current_thread()
            .thread_name(format!("{name}-blocking"))
            .enable_all()
            .build()?;
        let (stop, mut stopped) = oneshot::channel::<()>();
        let thread = std::thread::Builder::new()
            .name(name.to_owned())
            .spawn(move || {
                runtime.block_on(async move {
                    let listener = match TcpListener::from_std(listener) {
                        Ok(listener) => listener,
                        Err(err) => {
                            eprintln!("arkit-s3-testbed: {err}");
                            return;
                        }
                    };
                    loop {
                        tokio::select! {
                            accepted = listener.accept() => match accepted {
                                Ok((socket, _)) => {
                                    let _ = socket.set_nodelay(true);
                                    serve(socket);
                                }
                                // Out of descriptors and the like: wait, then go on.
                                Err(_) => tokio::time::sleep(Duration::from_millis(10)).await,
                            },
                            _ = &mut stopped => break,
                        }
                    }
                    // The listener drops here: the port is free before the drop returns.
                });
                // Drops every connection task (closing its socket).
                runtime.shutdown_timeout(SHUTDOWN_GRACE);
            })?;
        Ok(Self {
            addr,
            stop: Some(stop),
            thread: Some(thread),
        })
    }
}

impl Drop for Background {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

// ---------------------------------------------------------------------------------
// The S3 server.

/// A real S3 server (s3s-fs) on `127.0.0.1`, with SigV4 authentication enforced.
///
/// Each bucket is a subfolder of the root directory; objects are files below it
/// (s3s-fs keeps their metadata, such as the ETag, in side files). The server runs
/// on its own thread and tokio runtime and stops, freeing its port, when dropped.
pub struct S3Server {
    root: PathBuf,
    background: Background,
}

impl S3Server {
    /// Serves the directory `root` (which must exist) on `127.0.0.1` at a port the
    /// system picks, accepting only requests signed (AWS SigV4) with this access key
    /// and secret key.
    pub fn start(root: &Path, access_key: &str, secret_key: &str) -> io::Result<S3Server> {
        let backend = backend::Backend::new(root)?;
        let service = {
            let mut builder = s3s::service::S3ServiceBuilder::new(backend);
            builder.set_auth(s3s::auth::SimpleAuth::from_single(access_key, secret_key));
            builder.build()
        };
        let background = Background::start("arkit-s3-server", move |socket| {
            let service = service.clone();
            tokio::spawn(async move {
                let _ = hyper::server::conn::http1::Builder::new()
                    .serve_connection(TokioIo::new(socket), service)
                    .await;
            });
        })?;
        Ok(S3Server {
            root: root.to_path_buf(),
            background,
        })
    }

    /// The server's address (`127.0.0.1:PORT`).
    pub fn addr(&self) -> SocketAddr {
        self.background.addr
    }

    /// The server's endpoint URL, `http://127.0.0.1:PORT` (path-style requests).
    pub fn endpoint(&self) -> String {
        format!("http://{}", self.addr())
    }

    /// The directory served.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Creates the bucket `name` (its folder under the root); creating one that
    /// exists is not an error. The name must be a plain S3 bucket name (lowercase
    /// letters, digits, `-` and `.`, 3 to 63 characters).
    pub fn create_bucket(&self, name: &str) -> io::Result<()> {
        let valid = (3..=63).contains(&name.len())
            && name
                .bytes()
                .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'-' || b == b'.')
            && !name.starts_with(['.', '-'])
            && !name.contains("..");
        if !valid {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("not an S3 bucket name: {name:?}"),
            ));
        }
        std::fs::create_dir_all(self.root.join(name))
    }
}

impl std::fmt::Debug for S3Server {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("S3Server")
            .field("addr", &self.addr())
            .field("root", &self.root)
            .finish()
    }
}

// ---------------------------------------------------------------------------------
// The fault plan.

/// A fault the proxy injects into a request matched by a [`FaultRule`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Fault {
    /// Answer this HTTP status (e.g. 500 or 503) with an S3-style XML error body,
    /// without forwarding the request.
    Status(u16),
    /// Close the client's connection abruptly (a TCP reset), without an answer and
    /// without forwarding the request.
    Reset,
    /// Forward the request, send the upstream's status and headers (its
    /// `Content-Length` included), then only the first `after_bytes` bytes of the
    /// body, and close the connection.
    Truncate {
        /// How many body bytes to send before closing.
        after_bytes: u64,
    },
    /// Hold the request this long (on top of the latency), then forward it.
    Stall(Duration),
}

/// A scripted fault: it fires on the next `times` requests that match, then is spent.
///
/// A request matches when its method equals `method` (any method if `None`,
/// compared case-insensitively) and its path (as sent, percent-encoded, without the
/// query; for path-style S3 requests `/bucket/key`) contains `key_contains` (any path
/// if `None`). The first live rule of the queue that matches a request fires.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FaultRule {
    /// The HTTP method to match (`"GET"`, `"PUT"`, ...), or any.
    pub method: Option<String>,
    /// A substring of the request path to match, or any path.
    pub key_contains: Option<String>,
    /// On how many matching requests the rule fires.
    pub times: u32,
    /// The fault injected.
    pub fault: Fault,
}

impl FaultRule {
    /// A rule that fires `fault` on the next `times` requests, of any method and path.
    pub fn new(fault: Fault, times: u32) -> Self {
        FaultRule {
            method: None,
            key_contains: None,
            times,
            fault,
        }
    }

    /// The same rule, matching only requests of this method.
    pub fn method(mut self, method: &str) -> Self {
        self.method = Some(method.to_owned());
        self
    }

    /// The same rule, matching only request paths containing `needle`.
    pub fn key_contains(mut self, needle: &str) -> Self {
        self.key_contains = Some(needle.to_owned());
        self
    }

    fn matches(&self, method: &Method, path: &str) -> bool {
        self.times > 0
            && self
                .method
                .as_deref()
                .is_none_or(|m| m.eq_ignore_ascii_case(method.as_str()))
            && self
                .key_contains
                .as_deref()
                .is_none_or(|k| path.contains(k))
    }
}

/// What a [`FaultProxy`] does to the traffic it forwards.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct FaultPlan {
    /// A fixed delay added to each request before it is forwarded (e.g. 20 ms, like
    /// a cloud bucket). Zero: none.
    pub latency: Duration,
    /// A cap on the response body bytes per second, shared by all connections (a
    /// token bucket), e.g. `125_000_000` for 1 Gbit/s. Zero: no cap.
    pub bandwidth_bytes_per_sec: u64,
    /// The scripted faults, in order of precedence.
    pub rules: Vec<FaultRule>,
}

/// The proxy's counters (see [`FaultControl::stats`]).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ProxyStats {
    /// Requests received (control requests under `/__testbed/` excepted), faulted or
    /// not.
    pub requests: u64,
    /// The same, per HTTP method.
    pub requests_by_method: BTreeMap<String, u64>,
    /// Response body bytes sent to clients (the error bodies of [`Fault::Status`]
    /// excepted).
    pub response_body_bytes: u64,
    /// How many times a rule fired.
    pub faults_fired: u64,
    /// Client connections accepted (a client reusing keep-alive connections opens
    /// few).
    pub connections: u64,
}

// ---------------------------------------------------------------------------------
// The proxy's shared state and its control handle.

/// A token bucket shared by all connections: each chunk reserves its transfer time
/// on a common timeline, with a small burst allowance.
struct Throttle {
    /// The instant until which the bandwidth is reserved.
    next_free: Mutex<Instant>,
}

impl Throttle {
    /// How much of the bandwidth may be used at once after an idle period.
    const BURST: Duration = Duration::from_millis(10);

    /// Waits until `bytes` more bytes may be sent at `rate` bytes per second.
    async fn take(&self, bytes: usize, rate: u64) {
        if rate == 0 || bytes == 0 {
            return;
        }
        let cost = Duration::from_secs_f64(bytes as f64 / rate as f64);
        let done = {
            let mut next_free = lock(&self.next_free);
            let now = Instant::now();
            let floor = now.checked_sub(Self::BURST).unwrap_or(now);
            let start = (*next_free).max(floor);
            *next_free = start + cost;
            *next_free
        };
        tokio::time::sleep_until(done.into()).await;
    }
}

struct Shared {
    upstream: SocketAddr,
    latency_ms: AtomicU64,
    bandwidth: AtomicU64,
    rules: Mutex<VecDeque<FaultRule>>,
    stats: Mutex<ProxyStats>,
    throttle: Throttle,
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Shared {
    /// Counts a request and takes the fault of the first live rule it matches.
    fn admit(&self, method: &Method, path: &str) -> Option<Fault> {
        let fault = {
            let mut rules = lock(&self.rules);
            rules.retain(|rule| rule.times > 0);
            let index = rules.iter().position(|rule| rule.matches(method, path));
            index.map(|i| {
                let rule = &mut rules[i];
                rule.times -= 1;
                let fault = rule.fault.clone();
                if rule.times == 0 {
                    rules.remove(i);
                }
                fault
            })
        };
        let mut stats = lock(&self.stats);
        stats.requests += 1;
        *stats
            .requests_by_method
            .entry(method.as_str().to_owned())
            .or_default() += 1;
        if fault.is_some() {
            stats.faults_fired += 1;
        }
        fault
    }

    fn add_body_bytes(&self, n: usize) {
        lock(&self.stats).response_body_bytes += n as u64;
    }
}

/// A cloneable handle that steers a running [`FaultProxy`] (from any thread, sync
/// or async) and reads its counters.
#[derive(Clone)]
pub struct FaultControl {
    shared: Arc<Shared>,
}

impl FaultControl {
    /// Appends a rule to the queue.
    pub fn push_rule(&self, rule: FaultRule) {
        lock(&self.shared.rules).push_back(rule);
    }

    /// Replaces the queue of rules.
    pub fn set_rules(&self, rules: Vec<FaultRule>) {
        *lock(&self.shared.rules) = rules.into();
    }

    /// Removes every rule.
    pub fn clear_rules(&self) {
        lock(&self.shared.rules).clear();
    }

    /// The rules not yet spent, with the number of times each has left.
    pub fn rules(&self) -> Vec<FaultRule> {
        lock(&self.shared.rules)
            .iter()
            .filter(|rule| rule.times > 0)
            .cloned()
            .collect()
    }

    /// Sets the delay added to each request (see [`FaultPlan::latency`]).
    pub fn set_latency(&self, latency: Duration) {
        let ms = u64::try_from(latency.as_millis()).unwrap_or(u64::MAX);
        self.shared.latency_ms.store(ms, Ordering::Relaxed);
    }

    /// The delay added to each request.
    pub fn latency(&self) -> Duration {
        Duration::from_millis(self.shared.latency_ms.load(Ordering::Relaxed))
    }

    /// Sets the response bandwidth cap in bytes per second, 0 for none (see
    /// [`FaultPlan::bandwidth_bytes_per_sec`]).
    pub fn set_bandwidth(&self, bytes_per_sec: u64) {
        self.shared
            .bandwidth
            .store(bytes_per_sec, Ordering::Relaxed);
    }

    /// The response bandwidth cap in bytes per second (0: none).
    pub fn bandwidth(&self) -> u64 {
        self.shared.bandwidth.load(Ordering::Relaxed)
    }

    /// The counters.
    pub fn stats(&self) -> ProxyStats {
        lock(&self.shared.stats).clone()
    }

    /// Sets the counters to zero.
    pub fn reset_stats(&self) {
        *lock(&self.shared.stats) = ProxyStats::default();
    }

    /// Removes every rule and sets the counters to zero (the latency and bandwidth
    /// stay).
    pub fn reset(&self) {
        self.clear_rules();
        self.reset_stats();
    }
}

impl std::fmt::Debug for FaultControl {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FaultControl")
            .field("upstream", &self.shared.upstream)
            .field("latency", &self.latency())
            .field("bandwidth", &self.bandwidth())
            .field("rules", &self.rules())
            .finish()
    }
}

// ---------------------------------------------------------------------------------
// The proxy.

/// A fault-injecting HTTP/1.1 reverse proxy on `127.0.0.1`, in front of an
/// [`S3Server`] (or any HTTP server).
///
/// Every request is forwarded unchanged (method, path, query, all headers, `Host`
/// and `Authorization` included, and the body) over a pool of keep-alive connections
/// to the upstream, and the answer is streamed back; client connections are kept
/// alive and served concurrently. The [`FaultPlan`] adds latency, a bandwidth cap and
/// scripted faults; steer it at run time with [`FaultProxy::control`].
///
/// # Control endpoints
///
/// Requests whose path starts with `/__testbed/` are answered by the proxy itself,
/// never forwarded nor counted, for tests in other languages (JSON bodies):
///
/// - `POST /__testbed/faults` appends rules to the queue:
///   `{"rules":[{"method":"GET","key_contains":"part-0","times":2,"fault":{"status":503}}]}`;
///   `method` and `key_contains` may be left out, `times` defaults to 1, and the
///   fault is one of `{"status":N}`, `{"reset":true}`, `{"truncate":N}` (bytes) or
///   `{"stall_ms":N}`.
/// - `GET /__testbed/stats` answers the counters, [`ProxyStats`] as JSON:
///   `{"requests":N,"requests_by_method":{"GET":N},"response_body_bytes":N,"faults_fired":N,"connections":N}`.
/// - `POST /__testbed/reset` removes every rule and zeroes the counters.
/// - `POST /__testbed/config` sets `{"latency_ms":N,"bandwidth_bytes_per_sec":N}`
///   (either may be left out; `GET` answers the current values).
///
/// The proxy stops, freeing its port, when dropped.
pub struct FaultProxy {
    control: FaultControl,
    background: Background,
}

impl FaultProxy {
    /// Starts the proxy on `127.0.0.1` at a port the system picks, forwarding to
    /// `upstream` (which must be a loopback address) with this plan.
    pub fn start(upstream: SocketAddr, plan: FaultPlan) -> io::Result<FaultProxy> {
        if !upstream.ip().is_loopback() {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("the fault proxy forwards to loopback addresses only, not {upstream}"),
            ));
        }
        let shared = Arc::new(Shared {
            upstream,
            latency_ms: AtomicU64::new(0),
            bandwidth: AtomicU64::new(plan.bandwidth_bytes_per_sec),
            rules: Mutex::new(plan.rules.into()),
            stats: Mutex::new(ProxyStats::default()),
            throttle: Throttle {
                next_free: Mutex::new(Instant::now()),
            },
        });
        let control = FaultControl { shared };
        control.set_latency(plan.latency);
        let shared = control.shared.clone();
        let mut client: Option<Client<HttpConnector, Incoming>> = None;
        let background = Background::start("arkit-s3-proxy", move |socket| {
            // Built inside the runtime, shared by every connection (one pool).
            let client = client
                .get_or_insert_with(|| {
                    let mut connector = HttpConnector::new();
                    connector.set_nodelay(true);
                    Client::builder(TokioExecutor::new())
                        .pool_idle_timeout(Duration::from_secs(30))
                        .build(connector)
                })
                .clone();
            let shared = shared.clone();
            tokio::spawn(serve_proxy_connection(socket, shared, client));
        })?;
        Ok(FaultProxy {
            control,
            background,
        })
    }

    /// The proxy's address (`127.0.0.1:PORT`).
    pub fn addr(&self) -> SocketAddr {
        self.background.addr
    }

    /// The proxy's endpoint URL, `http://127.0.0.1:PORT`: give it to the client in
    /// place of the server's.
    pub fn endpoint(&self) -> String {
        format!("http://{}", self.addr())
    }

    /// The address requests are forwarded to.
    pub fn upstream(&self) -> SocketAddr {
        self.control.shared.upstream
    }

    /// A handle that changes the plan and reads the counters while the proxy runs.
    pub fn control(&self) -> FaultControl {
        self.control.clone()
    }
}

impl std::fmt::Debug for FaultProxy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FaultProxy")
            .field("addr", &self.addr())
            .field("control", &self.control)
            .finish()
    }
}

/// A client socket that can be reset: once `reset` is set, reads and writes fail and
/// dropping the socket sends a TCP reset (SO_LINGER 0) instead of an orderly close.
struct ResettableSocket {
    socket: TcpStream,
    reset: Arc<AtomicBool>,
}

impl ResettableSocket {
    fn check(&self) -> io::Result<()> {
        if self.reset.load(Ordering::Relaxed) {
            Err(io::Error::new(
                io::ErrorKind::ConnectionReset,
                "connection reset by the fault plan",
            ))
        } else {
            Ok(())
        }
    }
}

impl Drop for ResettableSocket {
    fn drop(&mut self) {
        if self.reset.load(Ordering::Relaxed) {
            let _ = self.socket.set_zero_linger();
        }
    }
}

impl AsyncRead for ResettableSocket {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        this.check()?;
        Pin::new(&mut this.socket).poll_read(cx, buf)
    }
}

impl AsyncWrite for ResettableSocket {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        this.check()?;
        Pin::new(&mut this.socket).poll_write(cx, buf)
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        this.check()?;
        Pin::new(&mut this.socket).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        this.check()?;
        Pin::new(&mut this.socket).poll_shutdown(cx)
    }
}

/// The proxy's response body: frames pumped by a task (which applies the bandwidth
/// cap and the truncation) through a small channel.
struct PumpedBody {
    frames: mpsc::Receiver<Result<Frame<Bytes>, ProxyError>>,
    size: SizeHint,
}

impl Body for PumpedBody {
    type Data = Bytes;
    type Error = ProxyError;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, ProxyError>>> {
        self.get_mut().frames.poll_recv(cx)
    }

    fn size_hint(&self) -> SizeHint {
        self.size
    }
}

type ProxyBody = http_body_util::combinators::BoxBody<Bytes, ProxyError>;

async fn serve_proxy_connection(
    socket: TcpStream,
    shared: Arc<Shared>,
    client: Client<HttpConnector, Incoming>,
) {
    lock(&shared.stats).connections += 1;
    let reset = Arc::new(AtomicBool::new(false));
    let io = ResettableSocket {
        socket,
        reset: reset.clone(),
    };
    let service = service_fn(move |req: Request<Incoming>| {
        let shared = shared.clone();
        let client = client.clone();
        let reset = reset.clone();
        async move {
            if req.uri().path().starts_with("/__testbed/") {
                return Ok::<_, ProxyError>(control_request(req, &shared).await);
            }
            proxy_request(req, shared, client, reset).await
        }
    });
    // A service error (a reset) ends the connection; the socket is then dropped.
    let _ = hyper::server::conn::http1::Builder::new()
        .keep_alive(true)
        .serve_connection(TokioIo::new(io), service)
        .await;
}

/// The S3-style XML error answer of [`Fault::Status`] and of an unreachable upstream.
fn s3_error(status: StatusCode, message: &str) -> Response<ProxyBody> {
    let code = match status.as_u16() {
        500 => "InternalError",
        502 => "BadGateway",
        503 => "SlowDown",
        403 => "AccessDenied",
        404 => "NoSuchKey",
        _ => "InjectedFault",
    };
    let body = format!(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<Error><Code>{code}</Code><Message>{message}</Message><RequestId>arkit-s3-testbed</RequestId></Error>"
    );
    let mut response = Response::new(full(body));
    *response.status_mut() = status;
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/xml"),
    );
    response
}

fn full(body: impl Into<Bytes>) -> ProxyBody {
    Full::new(body.into())
        .map_err(|never: Infallible| match never {})
        .boxed()
}

async fn proxy_request(
    req: Request<Incoming>,
    shared: Arc<Shared>,
    client: Client<HttpConnector, Incoming>,
    reset: Arc<AtomicBool>,
) -> Result<Response<ProxyBody>, ProxyError> {
    let fault = shared.admit(req.method(), req.uri().path());
    let latency = shared.latency_ms.load(Ordering::Relaxed);
    if latency > 0 {
        tokio::time::sleep(Duration::from_millis(latency)).await;
    }
    let mut truncate = None;
    match fault {
        Some(Fault::Status(code)) => {
            // Read the request body first (as a server answering after it would), so
            // that the client, still sending, sees the answer and not a reset.
            let mut body = req.into_body();
            while let Some(Ok(_)) = body.frame().await {}
            let status = StatusCode::from_u16(code).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
            return Ok(s3_error(status, "fault injected by arkit-s3-testbed"));
        }
        Some(Fault::Reset) => {
            reset.store(true, Ordering::Relaxed);
            return Err(io::Error::new(
                io::ErrorKind::ConnectionReset,
                "connection reset by the fault plan",
            ));
        }
        Some(Fault::Stall(duration)) => tokio::time::sleep(duration).await,
        Some(Fault::Truncate { after_bytes }) => truncate = Some(after_bytes),
        None => {}
    }

    // The same request, to the upstream: only the URI gains the upstream's address
    // (for the connection); the client keeps the request's own Host header.
    let (mut parts, body) = req.into_parts();
    let path_and_query = parts
        .uri
        .path_and_query()
        .map_or("/", |pq| pq.as_str())
        .to_owned();
    parts.uri = format!("http://{}{}", shared.upstream, path_and_query)
        .parse()
        .map_err(io::Error::other)?;
    let upstream_response = match client.request(Request::from_parts(parts, body)).await {
        Ok(response) => response,
        Err(err) => {
            return Ok(s3_error(
                StatusCode::BAD_GATEWAY,
                &format!(
                    "arkit-s3-testbed proxy: upstream {}: {err}",
                    shared.upstream
                ),
            ));
        }
    };
    let (parts, mut upstream_body) = upstream_response.into_parts();
    let size = upstream_body.size_hint();
    let (tx, rx) = mpsc::channel(4);
    tokio::spawn(async move {
        // The largest piece sent at once, so that connections share the bandwidth.
        const SLICE: usize = 64 * 1024;
        let mut left = truncate.unwrap_or(u64::MAX);
        while let Some(frame) = upstream_body.frame().await {
            let frame = match frame {
                Ok(frame) => frame,
                Err(err) => {
                    let _ = tx.send(Err(io::Error::other(err))).await;
                    return;
                }
            };
            let mut data = match frame.into_data() {
                Ok(data) => data,
                Err(frame) => {
                    if tx.send(Ok(frame)).await.is_err() {
                        return;
                    }
                    continue;
                }
            };
            while !data.is_empty() && left > 0 {
                let n = data
                    .len()
                    .min(SLICE)
                    .min(usize::try_from(left).unwrap_or(SLICE));
                let piece = data.split_to(n);
                shared
                    .throttle
                    .take(n, shared.bandwidth.load(Ordering::Relaxed))
                    .await;
                if tx.send(Ok(Frame::data(piece))).await.is_err() {
                    return;
                }
                shared.add_body_bytes(n);
                left -= n as u64;
            }
            if left == 0 {
                break;
            }
        }
        if truncate.is_some() && left == 0 {
            // Let the connection flush what was sent, then fail the body: the server
            // closes the connection in the middle of the message.
            tokio::time::sleep(Duration::from_millis(50)).await;
            let truncated = io::Error::new(
                io::ErrorKind::UnexpectedEof,
                "body truncated by the fault plan",
            );
            let _ = tx.send(Err(truncated)).await;
        }
    });
    let body = PumpedBody { frames: rx, size };
    Ok(Response::from_parts(parts, body.boxed()))
}

// ---------------------------------------------------------------------------------
// The JSON control endpoints.

/// A fault as JSON: exactly one of the fields.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonFault {
    status: Option<u16>,
    reset: Option<bool>,
    truncate: Option<u64>,
    stall_ms: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonRule {
    method: Option<String>,
    key_contains: Option<String>,
    #[serde(default = "one")]
    times: u32,
    fault: JsonFault,
}

fn one() -> u32 {
    1
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonRules {
    rules: Vec<JsonRule>,
}

#[derive(Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct JsonConfig {
    latency_ms: Option<u64>,
    bandwidth_bytes_per_sec: Option<u64>,
}

impl TryFrom<JsonRule> for FaultRule {
    type Error = String;

    fn try_from(rule: JsonRule) -> Result<Self, String> {
        let f = rule.fault;
        let fault = match (f.status, f.reset, f.truncate, f.stall_ms) {
            (Some(code), None, None, None) => {
                StatusCode::from_u16(code).map_err(|_| format!("not an HTTP status: {code}"))?;
                Fault::Status(code)
            }
            (None, Some(true), None, None) => Fault::Reset,
            (None, None, Some(after_bytes), None) => Fault::Truncate { after_bytes },
            (None, None, None, Some(ms)) => Fault::Stall(Duration::from_millis(ms)),
            _ => {
                return Err(
                    "a fault is exactly one of {\"status\":N}, {\"reset\":true}, {\"truncate\":N}, {\"stall_ms\":N}"
                        .to_owned(),
                );
            }
        };
        Ok(FaultRule {
            method: rule.method,
            key_contains: rule.key_contains,
            times: rule.times,
            fault,
        })
    }
}

fn json_response(status: StatusCode, value: &impl Serialize) -> Response<ProxyBody> {
    let body = serde_json::to_vec(value).unwrap_or_default();
    let mut response = Response::new(full(body));
    *response.status_mut() = status;
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    response
}

fn json_error(status: StatusCode, message: &str) -> Response<ProxyBody> {
    json_response(status, &serde_json::json!({ "error": message }))
}

async fn control_request(req: Request<Incoming>, shared: &Arc<Shared>) -> Response<ProxyBody> {
    let control = FaultControl {
        shared: shared.clone(),
    };
    let method = req.method().clone();
    let path = req.uri().path().to_owned();
    let body = match req.into_body().collect().await {
        Ok(body) => body.to_bytes(),
        Err(err) => return json_error(StatusCode::BAD_REQUEST, &err.to_string()),
    };
    let ok = serde_json::json!({ "ok": true });
    match (method, path.as_str()) {
        (Method::POST, "/__testbed/faults") => {
            let rules: JsonRules = match serde_json::from_slice(&body) {
                Ok(rules) => rules,
                Err(err) => return json_error(StatusCode::BAD_REQUEST, &err.to_string()),
            };
            let rules: Result<Vec<FaultRule>, String> =
                rules.rules.into_iter().map(FaultRule::try_from).collect();
            match rules {
                Ok(rules) => {
                    let queued = rules.len();
                    for rule in rules {
                        control.push_rule(rule);
                    }
                    json_response(StatusCode::OK, &serde_json::json!({ "queued": queued }))
                }
                Err(err) => json_error(StatusCode::BAD_REQUEST, &err),
            }
        }
        (Method::GET, "/__testbed/stats") => json_response(StatusCode::OK, &control.stats()),
        (Method::POST, "/__testbed/reset") => {
            control.reset();
            json_response(StatusCode::OK, &ok)
        }
        (Method::POST, "/__testbed/config") => {
            let config: JsonConfig = match serde_json::from_slice(&body) {
                Ok(config) => config,
                Err(err) => return json_error(StatusCode::BAD_REQUEST, &err.to_string()),
            };
            if let Some(ms) = config.latency_ms {
                control.set_latency(Duration::from_millis(ms));
            }
            if let Some(rate) = config.bandwidth_bytes_per_sec {
                control.set_bandwidth(rate);
            }
            json_response(StatusCode::OK, &ok)
        }
        (Method::GET, "/__testbed/config") => json_response(
            StatusCode::OK,
            &JsonConfig {
                latency_ms: Some(shared.latency_ms.load(Ordering::Relaxed)),
                bandwidth_bytes_per_sec: Some(control.bandwidth()),
            },
        ),
        _ => json_error(
            StatusCode::NOT_FOUND,
            "unknown control request; see POST /__testbed/faults, GET /__testbed/stats, POST /__testbed/reset, POST /__testbed/config",
        ),
    }
}
