//! [`FaultProxy`]: the forwarding proxy and the faults it injects.

use crate::background::Background;
use crate::body::{ProxyBody, ProxyError, full};
use crate::control::{FaultControl, Shared, Throttle, lock};
use crate::faults::{Fault, FaultPlan, ProxyStats};
use crate::json_control::control_request;
use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use bytes::Bytes;
use http::{HeaderValue, Request, Response, StatusCode, header};
use http_body_util::BodyExt;
use hyper::body::{Body, Frame, Incoming, SizeHint};
use hyper::service::service_fn;
use hyper_util::client::legacy::Client;
use hyper_util::client::legacy::connect::HttpConnector;
use hyper_util::rt::{TokioExecutor, TokioIo};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio::sync::mpsc;

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
    pub(crate) control: FaultControl,
    pub(crate) background: Background,
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
pub(crate) struct ResettableSocket {
    pub(crate) socket: TcpStream,
    pub(crate) reset: Arc<AtomicBool>,
}

impl ResettableSocket {
    pub(crate) fn check(&self) -> io::Result<()> {
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
pub(crate) struct PumpedBody {
    pub(crate) frames: mpsc::Receiver<Result<Frame<Bytes>, ProxyError>>,
    pub(crate) size: SizeHint,
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

pub(crate) async fn serve_proxy_connection(
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
pub(crate) fn s3_error(status: StatusCode, message: &str) -> Response<ProxyBody> {
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

pub(crate) async fn proxy_request(
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
