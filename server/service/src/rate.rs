//! Rate limits: a token bucket per client address for requests (gRPC calls, HTTP requests,
//! WebSocket upgrades), and one per stream for the messages inside it (tool commands,
//! viewer requests). One client over its rate is refused; nobody else notices.
//! Behind a trusted proxy the client is the address the proxy says it forwards for.

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

/// A block of addresses: `10.0.0.0/8`, `fd00::/8`, or one address (`192.0.2.7`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IpBlock {
    base: IpAddr,
    prefix: u8,
}

impl IpBlock {
    pub fn parse(text: &str) -> Result<Self, String> {
        let bad = |why: &str| format!("{text:?} is not an address or a CIDR block ({why}); e.g. 10.0.0.0/8, 192.0.2.7 or fd00::/8");
        let (address, prefix) = match text.split_once('/') {
            Some((a, p)) => (a, Some(p)),
            None => (text, None),
        };
        let base: IpAddr = address.trim().parse().map_err(|_| bad("no IP address"))?;
        let bits = if base.is_ipv4() { 32 } else { 128 };
        let prefix = match prefix {
            Some(p) => p.trim().parse::<u8>().ok().filter(|&p| p <= bits).ok_or_else(|| bad(&format!("the prefix length must be 0 to {bits}")))?,
            None => bits,
        };
        Ok(Self { base, prefix })
    }

    pub fn contains(&self, ip: IpAddr) -> bool {
        match (self.base, ip.to_canonical()) {
            (IpAddr::V4(b), IpAddr::V4(a)) => prefix_matches(u32::from(b).into(), u32::from(a).into(), 32, self.prefix),
            (IpAddr::V6(b), IpAddr::V6(a)) => prefix_matches(u128::from(b), u128::from(a), 128, self.prefix),
            _ => false,
        }
    }
}

fn prefix_matches(base: u128, address: u128, bits: u8, prefix: u8) -> bool {
    let shift = bits - prefix;
    shift >= bits || (base >> shift) == (address >> shift)
}

/// Requests per client address (all ports of one host share a bucket).
pub struct ClientRates {
    rate: f64,
    burst: f64,
    /// Proxies whose `X-Forwarded-For` is believed.
    trusted_proxies: Vec<IpBlock>,
    buckets: Mutex<HashMap<IpAddr, TokenBucket>>,
}

impl ClientRates {
    pub fn new(rate: f64, burst: f64, trusted_proxies: Vec<IpBlock>) -> Self {
        Self { rate, burst, trusted_proxies, buckets: Mutex::new(HashMap::new()) }
    }

    fn trusted(&self, ip: IpAddr) -> bool {
        self.trusted_proxies.iter().any(|b| b.contains(ip))
    }

    /// Who sent a request: its peer, unless the peer is a trusted proxy; then the nearest
    /// address in `X-Forwarded-For` (comma-separated, nearest last) that is not a trusted
    /// proxy. A hop that is not an address ends the walk: what lies beyond it is not
    /// believed.
    pub fn client(&self, peer: Option<SocketAddr>, forwarded_for: &[&str]) -> Option<IpAddr> {
        let mut client = peer?.ip().to_canonical();
        let hops = forwarded_for.iter().rev().flat_map(|header| header.rsplit(','));
        for hop in hops {
            if !self.trusted(client) {
                break;
            }
            let hop = hop.trim();
            match hop.parse::<IpAddr>().or_else(|_| hop.parse::<SocketAddr>().map(|a| a.ip())) {
                Ok(ip) => client = ip.to_canonical(),
                Err(_) => break,
            }
        }
        Some(client)
    }

    /// Admits one request from the client behind `peer` and `forwarded_for` (the
    /// `X-Forwarded-For` values, in order), or refuses it with `RESOURCE_EXHAUSTED` / 429
    /// saying the limit and when to retry. An unknown peer (not TCP) is admitted.
    pub fn admit(&self, peer: Option<SocketAddr>, forwarded_for: &[&str]) -> Result<(), ApiError> {
        let Some(client) = self.client(peer, forwarded_for) else { return Ok(()) };
        let now = Instant::now();
        let mut buckets = self.buckets.lock().unwrap_or_else(|e| e.into_inner());
        if buckets.len() > SWEEP_ABOVE {
            buckets.retain(|_, b| !b.full(now));
        }
        let bucket = buckets.entry(client).or_insert_with(|| TokenBucket::new(self.rate, self.burst, now));
        bucket.take(now).map_err(|wait| ApiError::RateLimited {
            message: format!(
                "rate limit: {} sends more than {} requests per second (burst {}); retry in {} ms",
                client,
                self.rate,
                self.burst,
                wait.as_millis().max(1)
            ),
            retry_after: wait,
        })
    }
}

/// The gRPC side: an interceptor in front of every service (ours, health and reflection
/// alike), so each call and each stream opened counts against its client's rate.
pub fn admit_grpc(rates: Arc<ClientRates>) -> impl FnMut(tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> + Clone {
    move |request| {
        let forwarded: Vec<&str> = request.metadata().get_all("x-forwarded-for").iter().filter_map(|v| v.to_str().ok()).collect();
        rates.admit(request.remote_addr(), &forwarded)?;
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
        let rates = ClientRates::new(1.0, 2.0, Vec::new());
        let a: SocketAddr = "10.0.0.1:1000".parse().unwrap();
        let a_other_port: SocketAddr = "10.0.0.1:2000".parse().unwrap();
        let b: SocketAddr = "10.0.0.2:1000".parse().unwrap();
        assert!(rates.admit(Some(a), &[]).is_ok());
        assert!(rates.admit(Some(a_other_port), &[]).is_ok());
        let refused = rates.admit(Some(a), &[]).unwrap_err().to_string();
        assert!(refused.contains("10.0.0.1") && refused.contains("more than 1 requests per second"), "{refused}");
        assert!(rates.admit(Some(b), &[]).is_ok(), "another client is not affected");
        assert!(rates.admit(None, &[]).is_ok());
    }

    #[test]
    fn address_blocks_parse_and_match() {
        let block = |t: &str| IpBlock::parse(t).unwrap();
        let ip = |t: &str| t.parse::<IpAddr>().unwrap();
        assert!(block("10.0.0.0/8").contains(ip("10.200.3.4")));
        assert!(!block("10.0.0.0/8").contains(ip("11.0.0.1")));
        assert!(block("192.0.2.7").contains(ip("192.0.2.7")) && !block("192.0.2.7").contains(ip("192.0.2.8")));
        assert!(block("0.0.0.0/0").contains(ip("203.0.113.9")));
        assert!(block("10.0.0.0/8").contains(ip("::ffff:10.1.2.3")), "an IPv4-mapped peer is its IPv4 address");
        assert!(block("fd00::/8").contains(ip("fd12::1")) && !block("fd00::/8").contains(ip("fe80::1")));
        assert!(!block("fd00::/8").contains(ip("10.0.0.1")));
        for bad in ["10.0.0/8", "10.0.0.0/33", "fd00::/129", "proxy", "10.0.0.0/x", ""] {
            let e = IpBlock::parse(bad).unwrap_err();
            assert!(e.contains("not an address or a CIDR block"), "{bad}: {e}");
        }
    }

    #[test]
    fn a_trusted_proxy_is_believed_and_no_one_else() {
        let rates = ClientRates::new(1.0, 2.0, vec![IpBlock::parse("10.0.0.0/8").unwrap()]);
        let proxy: SocketAddr = "10.0.0.5:40000".parse().unwrap();
        let stranger: SocketAddr = "198.51.100.1:40000".parse().unwrap();
        let client = |peer, xff: &[&str]| rates.client(Some(peer), xff).unwrap().to_string();
        assert_eq!(client(proxy, &[]), "10.0.0.5", "no header: the proxy itself");
        assert_eq!(client(proxy, &["203.0.113.9"]), "203.0.113.9");
        // Nearest last; trusted hops (a second proxy) are skipped, the first stranger is the client.
        assert_eq!(client(proxy, &["192.0.2.1, 203.0.113.9, 10.1.1.1"]), "203.0.113.9");
        assert_eq!(client(proxy, &["192.0.2.1", "203.0.113.9:5555"]), "203.0.113.9", "several headers, a port");
        assert_eq!(client(proxy, &["[2001:db8::1]:443"]), "2001:db8::1");
        assert_eq!(client(proxy, &["192.0.2.1, garbage, 10.1.1.1"]), "10.1.1.1", "nothing beyond a bad hop is believed");
        assert_eq!(client(stranger, &["203.0.113.9"]), "198.51.100.1", "an untrusted peer's header is ignored");
        // Clients behind one proxy get a bucket each.
        let behind = |xff: &str| rates.admit(Some(proxy), &[xff]);
        assert!(behind("203.0.113.1").is_ok() && behind("203.0.113.1").is_ok());
        assert!(behind("203.0.113.1").unwrap_err().to_string().contains("203.0.113.1"));
        assert!(behind("203.0.113.2").is_ok(), "the proxy's other client is not affected");
    }
}
