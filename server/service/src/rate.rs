//! Rate limits: a token bucket per client address for requests (gRPC calls, HTTP requests,
//! WebSocket upgrades), and one per stream for the messages inside it (tool commands,
//! viewer requests). One client over its rate is refused; nobody else notices.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::error::ApiError;

/// `rate` tokens per second, at most `burst` saved up; each admitted event takes one.
#[derive(Debug, Clone, Copy)]
pub struct TokenBucket {
    rate: f64,
    burst: f64,
    tokens: f64,
    at: Instant,
}

impl TokenBucket {
    pub fn new(rate: f64, burst: f64, now: Instant) -> Self {
        Self { rate, burst, tokens: burst, at: now }
    }

    /// Takes a token, or says how long until one is there.
    pub fn take(&mut self, now: Instant) -> Result<(), Duration> {
        let elapsed = now.saturating_duration_since(self.at).as_secs_f64();
        self.tokens = (self.tokens + elapsed * self.rate).min(self.burst);
        self.at = now;
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            Ok(())
        } else {
            Err(Duration::from_secs_f64((1.0 - self.tokens) / self.rate))
        }
    }

    fn full(&self, now: Instant) -> bool {
        self.tokens + now.saturating_duration_since(self.at).as_secs_f64() * self.rate >= self.burst
    }
}

/// Buckets kept before the full ones (clients idle long enough to be back at their
/// burst, so forgetting them changes nothing) are swept out.
const SWEEP_ABOVE: usize = 4096;

/// Requests per client address (all ports of one host share a bucket).
pub struct ClientRates {
    rate: f64,
    burst: f64,
    buckets: Mutex<HashMap<IpAddr, TokenBucket>>,
}

impl ClientRates {
    pub fn new(rate: f64, burst: f64) -> Self {
        Self { rate, burst, buckets: Mutex::new(HashMap::new()) }
    }

    /// Admits one request from `client`, or refuses it with `RESOURCE_EXHAUSTED` / 429
    /// saying the limit and when to retry. An unknown address (not TCP) is admitted.
    pub fn admit(&self, client: Option<SocketAddr>) -> Result<(), ApiError> {
        let Some(client) = client else { return Ok(()) };
        let now = Instant::now();
        let mut buckets = self.buckets.lock().unwrap_or_else(|e| e.into_inner());
        if buckets.len() > SWEEP_ABOVE {
            buckets.retain(|_, b| !b.full(now));
        }
        let bucket = buckets.entry(client.ip()).or_insert_with(|| TokenBucket::new(self.rate, self.burst, now));
        bucket.take(now).map_err(|wait| {
            ApiError::ResourceExhausted(format!(
                "rate limit: {} sends more than {} requests per second (burst {}); retry in {} ms",
                client.ip(),
                self.rate,
                self.burst,
                wait.as_millis().max(1)
            ))
        })
    }
}

/// The gRPC side: an interceptor in front of every service (ours, health and reflection
/// alike), so each call and each stream opened counts against its client's rate.
pub fn admit_grpc(rates: Arc<ClientRates>) -> impl FnMut(tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> + Clone {
    move |request| {
        rates.admit(request.remote_addr())?;
        Ok(request)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bucket_admits_its_burst_then_its_rate() {
        let t0 = Instant::now();
        let mut b = TokenBucket::new(10.0, 3.0, t0);
        assert!((0..3).all(|_| b.take(t0).is_ok()));
        let wait = b.take(t0).unwrap_err();
        assert!((wait.as_secs_f64() - 0.1).abs() < 1e-9, "{wait:?}");
        assert!(b.take(t0 + Duration::from_millis(100)).is_ok());
        assert!(b.take(t0 + Duration::from_millis(150)).is_err());
        // Idle for long: back to the burst, never above.
        let later = t0 + Duration::from_secs(60);
        assert!((0..3).all(|_| b.take(later).is_ok()));
        assert!(b.take(later).is_err());
    }

    #[test]
    fn clients_are_limited_separately() {
        let rates = ClientRates::new(1.0, 2.0);
        let a: SocketAddr = "10.0.0.1:1000".parse().unwrap();
        let a_other_port: SocketAddr = "10.0.0.1:2000".parse().unwrap();
        let b: SocketAddr = "10.0.0.2:1000".parse().unwrap();
        assert!(rates.admit(Some(a)).is_ok());
        assert!(rates.admit(Some(a_other_port)).is_ok());
        let refused = rates.admit(Some(a)).unwrap_err().to_string();
        assert!(refused.contains("10.0.0.1") && refused.contains("more than 1 requests per second"), "{refused}");
        assert!(rates.admit(Some(b)).is_ok(), "another client is not affected");
        assert!(rates.admit(None).is_ok());
    }
}
