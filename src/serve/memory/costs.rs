//! What each item a client can make the server hold costs in resident memory, as measured by
//! `cargo test --release --test integration memory::measure_item_costs -- --ignored --nocapture`
//! into `results/memory/item-costs.json` (docs/operations.md, "Memory budget"). Each constant is
//! the measured figure rounded up, so the budget errs toward counting too much.

use crate::policy::Policy;

/// An open HTTP/2 connection past its handshake, with no call: hyper's and h2's state, the
/// connection task, its read and write buffers (measured 20.7 KiB).
pub(crate) const CONNECTION: u64 = 24 * 1024;

/// A TLS connection's extra: rustls' record buffers and session state (measured 14.9 KiB).
pub(crate) const TLS_EXTRA: u64 = 20 * 1024;

/// A call in flight (a StepStream that sent only its HEADERS is the costliest): h2's stream,
/// hyper's stream task, tonic's decoder and encoder, the handler's task and its answer channel
/// (measured 7.2 KiB).
pub(crate) const CALL: u64 = 8 * 1024;

/// A WatchPlan watcher beyond its call, whose charge already covers it (a started watcher,
/// call included, measured 0.15 KiB): counted apart so the metrics show watchers.
pub(crate) const WATCHER: u64 = 1024;

/// A session beyond its plan: ids, settings, rng, watch channel, map slot (measured 3.0 KiB).
const SESSION_BASE: u64 = 3584;

/// Bytes a session holds per planned action and per float of its observation and action: the
/// committed plan and the copy its watchers see (measured 8; counted as 10).
const SESSION_BYTES_PER_FLOAT: u64 = 10;

/// A session of `policy` whose plans hold at most `max_horizon` actions (the Humanoid's at
/// max_horizon 32 measured 18.8 KiB, counted as 24.2 KiB).
pub(crate) fn session(policy: &Policy, max_horizon: usize) -> u64 {
    let floats = (policy.obs_dim() + policy.act_dim()) as u64;
    SESSION_BASE + (max_horizon as u64 + 1) * (floats * SESSION_BYTES_PER_FLOAT + 16)
}

/// The server with no client: the runtime, its threads' stacks, the allocator's arenas, the
/// metrics, health and reflection services (measured 10.5 MiB with no bundle) and what the
/// first bundle served brings with it (1.5 MiB).
pub(crate) const RUNTIME: u64 = 14 << 20;

/// Each replanning thread's workspace for one bundle.
const WORKSPACE: u64 = 128 * 1024;

/// A loaded bundle: its weights, held as loaded and transposed for the kernels (about twice
/// the file: 2.2 MB each for the shipped bundles), and each replanning thread's workspace.
pub(crate) fn bundle(policy: &Policy, threads: usize) -> u64 {
    2 * policy.weight_bytes() + threads as u64 * WORKSPACE
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The costs counted cover what `measure_item_costs` last measured
    /// (results/memory/item-costs.json): a change that makes an item costlier fails here until
    /// it is measured again and counted.
    #[test]
    fn the_counted_costs_cover_the_measured_ones() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let text = std::fs::read_to_string(root.join("results/memory/item-costs.json")).unwrap();
        let measured: serde_json::Value = serde_json::from_str(&text).unwrap();
        let kib = |key: &str| (measured[key].as_f64().unwrap() * 1024.0) as u64;
        assert!(CONNECTION >= kib("connection_kib"));
        assert!(CONNECTION + TLS_EXTRA >= kib("tls_connection_kib"));
        assert!(CALL >= kib("header_only_call_kib"));
        assert!(CALL + WATCHER >= kib("watcher_kib"));
        let runtime = kib("runtime_kib");
        // Two runtime threads and two batch workers, as on the machine that measured.
        let threads = 4;
        for (name, entry) in measured["bundles"].as_object().unwrap() {
            let policy =
                crate::bundle::load(&root.join(format!("bundles/{name}.safetensors"))).unwrap();
            let session_kib = entry["session_kib"].as_f64().unwrap();
            assert!(
                session(&policy, 32) as f64 >= session_kib * 1024.0,
                "{name}: a session counted {} bytes, measured {session_kib} KiB",
                session(&policy, 32)
            );
            let served = runtime + entry["bundle_kib"].as_u64().unwrap() * 1024;
            assert!(
                RUNTIME + bundle(&policy, threads) >= served,
                "{name}: the server with it counted {} bytes, measured {served}",
                RUNTIME + bundle(&policy, threads)
            );
        }
    }
}
