//! The order in which calls reached the server. The transport stamps each request when it hands
//! it to the routes, in its connection's order of streams, before any handler runs; handlers may
//! then run in any order, and a session applies a step only if no step that arrived after it was
//! applied first (a client that gave up on a step and sent the next must not see the first
//! applied behind the second).

use std::sync::atomic::{AtomicU64, Ordering};

static NEXT: AtomicU64 = AtomicU64::new(1);

/// A call's place in the server's order of arrivals.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord)]
pub struct Arrival(u64);

impl Arrival {
    /// The next place: for a request arriving now.
    pub fn next() -> Arrival {
        Arrival(NEXT.fetch_add(1, Ordering::Relaxed))
    }

    /// The place the transport stamped on a request, or the next one for a request that did not
    /// come through it.
    pub(crate) fn of(extensions: &http::Extensions) -> Arrival {
        extensions.get().copied().unwrap_or_else(Arrival::next)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrivals_are_ordered_and_a_stamp_is_kept() {
        let (first, second) = (Arrival::next(), Arrival::next());
        assert!(first < second);
        let mut extensions = http::Extensions::new();
        extensions.insert(first);
        assert_eq!(Arrival::of(&extensions), first);
        assert!(Arrival::of(&http::Extensions::new()) > second);
    }
}
