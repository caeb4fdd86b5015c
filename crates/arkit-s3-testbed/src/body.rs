//! The body and error types the proxy and its control endpoints answer with.

use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use std::convert::Infallible;
use std::io;

/// The error of the proxy's bodies and services (a concrete type: hyper's bounds on
/// a boxed `dyn Error` trip the compiler's higher-ranked lifetime checks in spawned
/// futures).
pub(crate) type ProxyError = io::Error;

/// A response body of the proxy: a forwarded answer or one of its own.
pub(crate) type ProxyBody = http_body_util::combinators::BoxBody<Bytes, ProxyError>;

/// A whole body from bytes in memory.
pub(crate) fn full(body: impl Into<Bytes>) -> ProxyBody {
    Full::new(body.into())
        .map_err(|never: Infallible| match never {})
        .boxed()
}
