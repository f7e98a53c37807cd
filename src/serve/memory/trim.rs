//! Gives memory back to the system after a burst of calls or connections ends. glibc's malloc
//! keeps what such a burst freed in its arenas: 2,000 StepStreams cancelled at once left the
//! server 10 to 30 MB larger, round after round, though nothing of them was still held (a
//! `malloc_trim` after each round brought it back to within 0.6 MB over ten rounds). The trim runs
//! only when the calls in flight or the open connections have fallen well below their high-water
//! mark since the last trim, so a steady load never pays for it.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use tokio_util::sync::CancellationToken;

use super::super::transport::ConnectionStats;
use super::{BurstLog, MemoryBudget};

/// How often the counts are looked at.
const PERIOD: Duration = Duration::from_millis(250);

/// A fall of this many calls in flight, or of this many connections, is a burst worth a trim.
const CALLS_BURST: u64 = 256;
const CONNECTIONS_BURST: u64 = 64;

/// Trims after a burst, one a period: the tasks of the ended calls free their buffers over the
/// next moments, after the counts have fallen.
const TRIMS_PER_BURST: u32 = 8;

/// Trims the heap after each burst until `shutdown`, and logs the memory budget's bursts of
/// shedding.
pub(in crate::serve) async fn give_back_after_bursts(
    stats: Arc<ConnectionStats>,
    budget: Arc<MemoryBudget>,
    shutdown: CancellationToken,
) {
    let mut bursts = BurstLog::default();
    let mut tick = tokio::time::interval(PERIOD);
    let (mut calls_high, mut connections_high) = (0, 0);
    let mut trims_left = 0;
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = tick.tick() => {}
        }
        bursts.look(&budget);
        let calls = stats.calls_in_flight.load(Ordering::Relaxed);
        // The peak since the last look, however brief (the count now starts the next one's).
        calls_high = calls_high.max(stats.calls_in_flight_peak.swap(calls, Ordering::Relaxed));
        let connections = stats.open.load(Ordering::Relaxed);
        connections_high = connections_high.max(connections);
        if calls_high.saturating_sub(calls) >= CALLS_BURST
            || connections_high - connections >= CONNECTIONS_BURST
        {
            trims_left = TRIMS_PER_BURST;
            (calls_high, connections_high) = (calls, connections);
        }
        if trims_left > 0 {
            trims_left -= 1;
            let _ = tokio::task::spawn_blocking(trim).await;
        }
    }
}

/// Returns the free memory at the top of the heap and the free pages inside it to the system.
fn trim() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks glibc's own arenas under their locks.
    unsafe {
        libc::malloc_trim(0);
    }
}
