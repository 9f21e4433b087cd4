//! Latency statistics without allocation: a log-linear histogram of durations.
//!
//! Recording is O(1) and never allocates, so it can sit inside the 1 kHz loop. Values
//! are kept with about 3 % relative precision from 10 ns to about 40 s.

/// The machine a benchmark or report ran on, for its header: the CPU model (from
/// /proc/cpuinfo where there is one) and the logical CPUs. Timings from different hosts
/// differ by about 2x on this project's machines; a number without its host misleads.
pub fn machine_description() -> String {
    let cpus = std::thread::available_parallelism().map_or(0, |n| n.get());
    let model = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|info| {
        info.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split_once(':')).map(|(_, name)| name.trim().to_string())
    });
    match model {
        Some(model) => format!("{model}, {cpus} logical CPUs"),
        None => format!("{cpus} logical CPUs"),
    }
}

/// Sub-buckets per power of two: 32 gives a relative bucket width of 1/32 ≈ 3 %.
const SUB_BUCKETS: usize = 32;
const SUB_BITS: u32 = 5;
const OCTAVES: usize = 40;

/// A histogram of durations in nanoseconds.
#[derive(Clone)]
pub struct LatencyHistogram {
    counts: Box<[u64]>,
    total: u64,
    max_ns: u64,
    sum_ns: u128,
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        Self::new()
    }
}

impl std::fmt::Debug for LatencyHistogram {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LatencyHistogram")
            .field("count", &self.total)
            .field("p50_ns", &self.quantile_ns(0.5))
            .field("p99_ns", &self.quantile_ns(0.99))
            .field("max_ns", &self.max_ns)
            .finish()
    }
}

impl LatencyHistogram {
    pub fn new() -> Self {
        Self { counts: vec![0; SUB_BUCKETS * OCTAVES].into_boxed_slice(), total: 0, max_ns: 0, sum_ns: 0 }
    }

    fn bucket_of(ns: u64) -> usize {
        if ns < SUB_BUCKETS as u64 {
            return ns as usize;
        }
        let octave = 63 - ns.leading_zeros() - SUB_BITS + 1; // ≥ 1
        let sub = (ns >> (octave - 1)) as usize & (SUB_BUCKETS - 1);
        ((octave as usize) * SUB_BUCKETS + sub).min(SUB_BUCKETS * OCTAVES - 1)
    }

    /// Upper edge of a bucket, in ns: what a quantile reports (never an underestimate).
    fn bucket_upper_ns(bucket: usize) -> u64 {
        let octave = bucket / SUB_BUCKETS;
        let sub = (bucket % SUB_BUCKETS) as u64;
        if octave == 0 {
            return sub;
        }
        ((SUB_BUCKETS as u64 + sub + 1) << (octave - 1)) - 1
    }

    pub fn record_ns(&mut self, ns: u64) {
        self.counts[Self::bucket_of(ns)] += 1;
        self.total += 1;
        self.max_ns = self.max_ns.max(ns);
        self.sum_ns += u128::from(ns);
    }

    pub fn record(&mut self, d: std::time::Duration) {
        self.record_ns(d.as_nanos().min(u128::from(u64::MAX)) as u64);
    }

    pub fn count(&self) -> u64 {
        self.total
    }

    pub fn max_ns(&self) -> u64 {
        self.max_ns
    }

    pub fn mean_ns(&self) -> f64 {
        if self.total == 0 { 0.0 } else { self.sum_ns as f64 / self.total as f64 }
    }

    /// The q-quantile (0 ≤ q ≤ 1) in ns; 0 when empty. Reported values are bucket upper
    /// edges clamped to the observed maximum.
    pub fn quantile_ns(&self, q: f64) -> u64 {
        if self.total == 0 {
            return 0;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.total as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (bucket, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return Self::bucket_upper_ns(bucket).min(self.max_ns);
            }
        }
        self.max_ns
    }

    pub fn merge(&mut self, other: &Self) {
        for (a, b) in self.counts.iter_mut().zip(other.counts.iter()) {
            *a += b;
        }
        self.total += other.total;
        self.max_ns = self.max_ns.max(other.max_ns);
        self.sum_ns += other.sum_ns;
    }

    pub fn clear(&mut self) {
        self.counts.fill(0);
        self.total = 0;
        self.max_ns = 0;
        self.sum_ns = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_within_bucket_precision() {
        let mut h = LatencyHistogram::new();
        for ns in 1..=100_000u64 {
            h.record_ns(ns);
        }
        let p50 = h.quantile_ns(0.5) as f64;
        let p99 = h.quantile_ns(0.99) as f64;
        assert!((p50 / 50_000.0 - 1.0).abs() < 0.035, "p50 {p50}");
        assert!((p99 / 99_000.0 - 1.0).abs() < 0.035, "p99 {p99}");
        assert_eq!(h.quantile_ns(1.0), 100_000);
        assert_eq!(h.count(), 100_000);
    }

    #[test]
    fn small_values_are_exact() {
        let mut h = LatencyHistogram::new();
        h.record_ns(7);
        assert_eq!(h.quantile_ns(0.5), 7);
    }
}
