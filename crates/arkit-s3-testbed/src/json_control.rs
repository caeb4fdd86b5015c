//! The proxy's JSON control endpoints under `/__testbed/`, for tests in other languages.

use crate::body::{ProxyBody, full};
use crate::control::{FaultControl, Shared};
use crate::faults::{Fault, FaultRule};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use http::{HeaderValue, Method, Request, Response, StatusCode, header};
use http_body_util::BodyExt;
use hyper::body::Incoming;
use serde::{Deserialize, Serialize};

/// A fault as JSON: exactly one of the fields.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct JsonFault {
    pub(crate) status: Option<u16>,
    pub(crate) reset: Option<bool>,
    pub(crate) truncate: Option<u64>,
    pub(crate) stall_ms: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct JsonRule {
    pub(crate) method: Option<String>,
    pub(crate) key_contains: Option<String>,
    #[serde(default = "one")]
    pub(crate) times: u32,
    pub(crate) fault: JsonFault,
}

pub(crate) fn one() -> u32 {
    1
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct JsonRules {
    pub(crate) rules: Vec<JsonRule>,
}

#[derive(Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct JsonConfig {
    pub(crate) latency_ms: Option<u64>,
    pub(crate) bandwidth_bytes_per_sec: Option<u64>,
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

pub(crate) fn json_response(status: StatusCode, value: &impl Serialize) -> Response<ProxyBody> {
    let body = serde_json::to_vec(value).unwrap_or_default();
    let mut response = Response::new(full(body));
    *response.status_mut() = status;
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    response
}

pub(crate) fn json_error(status: StatusCode, message: &str) -> Response<ProxyBody> {
    json_response(status, &serde_json::json!({ "error": message }))
}

pub(crate) async fn control_request(
    req: Request<Incoming>,
    shared: &Arc<Shared>,
) -> Response<ProxyBody> {
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
