//! The proxy's shared state (the plan, the throttle, the counters) and its Rust
//! handle, [`FaultControl`].

use crate::faults::{Fault, FaultRule, ProxyStats};
use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use http::Method;

/// A token bucket shared by all connections: each chunk reserves its transfer time
/// on a common timeline, with a small burst allowance.
pub(crate) struct Throttle {
    /// The instant until which the bandwidth is reserved.
    pub(crate) next_free: Mutex<Instant>,
}

impl Throttle {
    /// How much of the bandwidth may be used at once after an idle period.
    const BURST: Duration = Duration::from_millis(10);

    /// Waits until `bytes` more bytes may be sent at `rate` bytes per second.
    pub(crate) async fn take(&self, bytes: usize, rate: u64) {
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

pub(crate) struct Shared {
    pub(crate) upstream: SocketAddr,
    pub(crate) latency_ms: AtomicU64,
    pub(crate) bandwidth: AtomicU64,
    pub(crate) rules: Mutex<VecDeque<FaultRule>>,
    pub(crate) stats: Mutex<ProxyStats>,
    pub(crate) throttle: Throttle,
}

pub(crate) fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Shared {
    /// Counts a request and takes the fault of the first live rule it matches.
    pub(crate) fn admit(&self, method: &Method, path: &str) -> Option<Fault> {
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

    pub(crate) fn add_body_bytes(&self, n: usize) {
        lock(&self.stats).response_body_bytes += n as u64;
    }
}

/// A cloneable handle that steers a running [`FaultProxy`](crate::FaultProxy) (from any thread, sync
/// or async) and reads its counters.
#[derive(Clone)]
pub struct FaultControl {
    pub(crate) shared: Arc<Shared>,
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
