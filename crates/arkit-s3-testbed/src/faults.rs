//! The fault plan: [`Fault`], [`FaultRule`], [`FaultPlan`] and the counters
//! ([`ProxyStats`]).

use std::collections::BTreeMap;
use std::time::Duration;

use http::Method;
use serde::{Deserialize, Serialize};

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

    pub(crate) fn matches(&self, method: &Method, path: &str) -> bool {
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

/// What a [`FaultProxy`](crate::FaultProxy) does to the traffic it forwards.
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

/// The proxy's counters (see [`FaultControl::stats`](crate::FaultControl::stats)).
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
