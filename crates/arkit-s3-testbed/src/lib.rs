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
mod background;
mod body;
mod control;
mod faults;
mod json_control;
mod proxy;
mod server;

pub use self::{
    control::FaultControl,
    faults::{Fault, FaultPlan, FaultRule, ProxyStats},
    proxy::FaultProxy,
    server::S3Server,
};
