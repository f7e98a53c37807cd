//! What prac-bench and prac-soak share: their own local server and latency histograms.

use std::path::Path;

/// A `prac serve` of its own on a random Hopper-sized bundle, with the folder it lives in.
pub struct LocalServer {
    pub server: prac::client::local::LocalServer,
    _dir: tempfile::TempDir,
}

impl LocalServer {
    /// Starts `prac serve ARGS...` (the binary beside this one unless `prac_bin`) on a fresh
    /// `hopper-bench` policy with random weights.
    pub async fn start(prac_bin: Option<&Path>, args: &[String]) -> anyhow::Result<LocalServer> {
        let dir = tempfile::tempdir()?;
        let policy = prac::testing::random_policy(prac::testing::hopper_sized_manifest(), 7);
        prac::bundle::save(&policy, &dir.path().join("hopper-bench.safetensors"))?;
        let bin = prac::client::local::prac_binary(prac_bin)?;
        let server = prac::client::local::LocalServer::start(&bin, dir.path(), args).await?;
        Ok(LocalServer { server, _dir: dir })
    }
}

/// Step latencies in microseconds: 1 us to 60 s at 3 significant digits.
pub fn latency_histogram() -> hdrhistogram::Histogram<u64> {
    hdrhistogram::Histogram::new_with_bounds(1, 60_000_000, 3).expect("valid histogram bounds")
}

/// Records one latency (at least 1 us; longer than the bounds counts as the maximum).
pub fn record_latency(histogram: &mut hdrhistogram::Histogram<u64>, latency: std::time::Duration) {
    histogram.saturating_record((latency.as_micros() as u64).max(1));
}
