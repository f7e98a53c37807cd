//! One memory budget for everything a client can make the server hold, so that no client, hostile
//! or buggy, can push the server past its container's limit and get it killed.
//!
//! The server may use `--max-memory` bytes, by default its cgroup's limit ([`limit`]). From that,
//! [`costs::RUNTIME`] and the loaded bundles are set aside, and a tenth for the allocator's slack;
//! what is left is the clients' budget. Connections, calls in flight, WatchPlan watchers, sessions
//! and the bytes of unfinished requests are charged against it at their measured costs
//! ([`costs`]) and given back when they end.
//!
//! Past the high-water mark (80 % of the budget) room is made in a fixed order before anything
//! new is admitted: the oldest calls that never sent a first message are reset
//! (RESOURCE_EXHAUSTED), then the watchers of sessions that are not stepping; sessions are never
//! shed. Meanwhile a connection may hold only a few never-started calls: past that its new calls
//! are refused, and one found holding many is sent GOAWAY and its never-started calls reset.
//! Whatever cannot be made room for under the budget is refused: a call with RESOURCE_EXHAUSTED
//! from its headers, a connection closed when accepted. Each action is counted in the metrics
//! and logged once per burst.

pub(crate) mod costs;
pub(super) mod limit;
mod trim;

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;
use tonic::Status;

pub(super) use limit::{MemoryLimit, parse_size, show_size};

use crate::plan::DEFAULT_MAX_HORIZON;
use crate::policy::Policy;
pub(super) use trim::give_back_after_bursts;

/// The share of the total kept free for the allocator's slack and what is not counted.
const SLACK_PERCENT: u64 = 10;

/// Past this share of the clients' budget, room is made before anything new is admitted.
const HIGH_WATER_PERCENT: u64 = 80;

/// Shedding goes on until usage is back under this share.
const LOW_WATER_PERCENT: u64 = 70;

/// A connection holding this many never-started calls is sent GOAWAY when the server sheds.
pub(super) const HOARDING_CALLS: usize = 32;

/// Past the high-water mark, a connection may hold at most this many never-started calls: a
/// client sends its first message at once, so its new calls still get in while a flood's
/// connections, each holding many, are refused.
const NEVER_STARTED_PAST_HIGH_WATER: usize = 4;

/// The least the clients' budget may be: a few connections, calls and sessions.
const MIN_CLIENT_BYTES: u64 = 4 << 20;

/// A watcher whose session has not changed its plan for this long is idle.
const IDLE_WATCHER: Duration = Duration::from_secs(1);

/// What a charge is for, as the metrics name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Item {
    Connection,
    Call,
    Watcher,
    Session,
    Request,
}

impl Item {
    pub(super) const ALL: [Item; 5] = [
        Item::Connection,
        Item::Call,
        Item::Watcher,
        Item::Session,
        Item::Request,
    ];

    pub(super) fn name(self) -> &'static str {
        match self {
            Item::Connection => "connection",
            Item::Call => "call",
            Item::Watcher => "watcher",
            Item::Session => "session",
            Item::Request => "request",
        }
    }
}

/// What the server did to stay within its budget, as the metrics name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Shed {
    /// A new call answered RESOURCE_EXHAUSTED from its headers.
    CallRefused,
    /// A call that never sent a first message, reset with RESOURCE_EXHAUSTED.
    CallReset,
    /// A watcher of a session not stepping, ended with RESOURCE_EXHAUSTED.
    WatcherReset,
    /// A connection holding many never-started calls, sent GOAWAY.
    Goaway,
    /// An OpenSession answered RESOURCE_EXHAUSTED.
    SessionRefused,
    /// A WatchPlan answered RESOURCE_EXHAUSTED.
    WatcherRefused,
    /// A new connection closed when accepted.
    ConnectionRefused,
}

impl Shed {
    pub(super) const ALL: [Shed; 7] = [
        Shed::CallRefused,
        Shed::CallReset,
        Shed::WatcherReset,
        Shed::Goaway,
        Shed::SessionRefused,
        Shed::WatcherRefused,
        Shed::ConnectionRefused,
    ];

    pub(super) fn name(self) -> &'static str {
        match self {
            Shed::CallRefused => "call_refused",
            Shed::CallReset => "call_reset",
            Shed::WatcherReset => "watcher_reset",
            Shed::Goaway => "goaway",
            Shed::SessionRefused => "session_refused",
            Shed::WatcherRefused => "watcher_refused",
            Shed::ConnectionRefused => "connection_refused",
        }
    }
}

/// A call admitted but not yet past its first message, in the order of admission.
struct Pending {
    cancel: CancellationToken,
    connection: Arc<ConnectionShare>,
    bytes: u64,
}

/// A watcher, in the order it began.
struct Watching {
    cancel: CancellationToken,
    /// When its session's plan last changed (ms since the budget's epoch).
    last_change: Arc<AtomicU64>,
    bytes: u64,
}

/// One connection's part in the budget: its never-started calls and its GOAWAY.
#[derive(Default)]
pub(super) struct ConnectionShare {
    never_started: AtomicUsize,
    /// Cancelled to reset every never-started call of the connection.
    reset_pending: CancellationToken,
    /// Cancelled to send the connection GOAWAY.
    goaway: CancellationToken,
}

impl ConnectionShare {
    /// Resolves when the connection is to be sent GOAWAY.
    pub(super) fn goaway(&self) -> CancellationToken {
        self.goaway.clone()
    }
}

/// The budget's numbers now, for the metrics.
#[derive(Clone, Debug, Default)]
pub(super) struct Snapshot {
    pub(crate) total: u64,
    pub(crate) reserved: u64,
    pub(crate) budget: u64,
    pub(crate) high_water: u64,
    pub(crate) used: [u64; 5],
    pub(crate) shed: [u64; 7],
}

pub(super) struct MemoryBudget {
    total: MemoryLimit,
    /// Runtime and bundles: set aside before the clients' budget.
    reserved: AtomicU64,
    /// Charged now, by item.
    used: [AtomicU64; 5],
    /// Bytes of calls reset but not yet ended: left out when deciding how much more to shed, so
    /// that one burst is shed once (admission still counts them until they let go).
    shedding: AtomicU64,
    pending: Mutex<BTreeMap<u64, Pending>>,
    watchers: Mutex<BTreeMap<u64, Watching>>,
    next: AtomicU64,
    shed: [AtomicU64; 7],
    epoch: Instant,
}

impl MemoryBudget {
    pub(super) fn new(total: MemoryLimit) -> Arc<MemoryBudget> {
        Arc::new(MemoryBudget {
            total,
            reserved: AtomicU64::new(costs::RUNTIME),
            used: Default::default(),
            shedding: AtomicU64::new(0),
            pending: Mutex::new(BTreeMap::new()),
            watchers: Mutex::new(BTreeMap::new()),
            next: AtomicU64::new(0),
            shed: Default::default(),
            epoch: Instant::now(),
        })
    }

    /// Sets aside the runtime and the loaded bundles (`bundles` bytes).
    pub(super) fn reserve_for_bundles(&self, bundles: u64) {
        self.reserved
            .store(costs::RUNTIME + bundles, Ordering::Relaxed);
    }

    /// Checks that `bundles` (name and policy) fit with `max_sessions` sessions of the largest
    /// at the default plan length, and returns what they need set aside; else says which
    /// numbers do not fit and which flag to change.
    pub(super) fn check_fit<'a>(
        &self,
        bundles: impl Iterator<Item = (&'a str, &'a Policy)>,
        max_sessions: usize,
        threads: usize,
    ) -> anyhow::Result<u64> {
        let mut needed = 0;
        let mut largest: Option<(&str, u64)> = None;
        for (name, policy) in bundles {
            needed += costs::bundle(policy, threads);
            let session = costs::session(policy, DEFAULT_MAX_HORIZON);
            if largest.is_none_or(|(_, s)| session > s) {
                largest = Some((name, session));
            }
        }
        let reserved = costs::RUNTIME + needed;
        let budget = self.budget_with(reserved);
        let total = &self.total;
        let floor = reserved + MIN_CLIENT_BYTES;
        let total_floor = floor + floor / (100 - SLACK_PERCENT) * SLACK_PERCENT;
        anyhow::ensure!(
            budget >= MIN_CLIENT_BYTES,
            "the server may use {} ({}), but the runtime and the loaded bundles need {} ({} \
             runtime, {} bundles), and {} are kept as allocator slack, leaving {} of the {} \
             the fewest clients need: raise --max-memory (or the container's memory limit) to \
             at least {}",
            show_size(total.bytes),
            total.source,
            show_size(reserved),
            show_size(costs::RUNTIME),
            show_size(needed),
            show_size(total.bytes / 100 * SLACK_PERCENT),
            show_size(budget),
            show_size(MIN_CLIENT_BYTES),
            show_size(total_floor)
        );
        if let Some((name, session)) = largest {
            let sessions = session * max_sessions as u64;
            let fitting = budget / session;
            anyhow::ensure!(
                sessions <= budget,
                "--max-sessions {max_sessions} sessions of bundle '{name}' ({} each at the \
                 default max_horizon {DEFAULT_MAX_HORIZON}) need {}, over the {} the memory \
                 budget leaves for clients (--max-memory {} from {}, less {} for the runtime \
                 and bundles and a tenth as slack): lower --max-sessions to at most {fitting}, \
                 or raise --max-memory to at least {}",
                show_size(session),
                show_size(sessions),
                show_size(budget),
                show_size(total.bytes),
                total.source,
                show_size(reserved),
                show_size((reserved + sessions) / (100 - SLACK_PERCENT) * 100 + 1)
            );
        }
        Ok(needed)
    }

    /// The clients' budget with `reserved` set aside: 0 when nothing is left.
    pub(super) fn budget_with(&self, reserved: u64) -> u64 {
        let usable = self.total.bytes - self.total.bytes / 100 * SLACK_PERCENT;
        usable.saturating_sub(reserved)
    }

    /// The clients' budget now.
    pub(super) fn budget(&self) -> u64 {
        self.budget_with(self.reserved.load(Ordering::Relaxed))
    }

    fn high_water(&self) -> u64 {
        self.budget() / 100 * HIGH_WATER_PERCENT
    }

    fn low_water(&self) -> u64 {
        self.budget() / 100 * LOW_WATER_PERCENT
    }

    /// Charged now: what is held, including what is being shed but has not yet let go.
    fn charged(&self) -> u64 {
        self.used.iter().map(|u| u.load(Ordering::Relaxed)).sum()
    }

    /// Charged now, less what is being shed: what shedding goes by, so that one burst is shed
    /// once, while admission goes by [`Self::charged`] until the shed calls have let go.
    fn used(&self) -> u64 {
        self.charged()
            .saturating_sub(self.shedding.load(Ordering::Relaxed))
    }

    fn count(&self, shed: Shed, by: u64) {
        self.shed[shed as usize].fetch_add(by, Ordering::Relaxed);
    }

    pub(super) fn snapshot(&self) -> Snapshot {
        Snapshot {
            total: self.total.bytes,
            reserved: self.reserved.load(Ordering::Relaxed),
            budget: self.budget(),
            high_water: self.high_water(),
            used: std::array::from_fn(|i| self.used[i].load(Ordering::Relaxed)),
            shed: std::array::from_fn(|i| self.shed[i].load(Ordering::Relaxed)),
        }
    }

    /// Charges `bytes` for `item` unconditionally (what is already held, such as a request's
    /// declared bytes, bounded by their own limits).
    pub(super) fn charge(self: &Arc<Self>, item: Item, bytes: u64) -> Charge {
        self.used[item as usize].fetch_add(bytes, Ordering::Relaxed);
        Charge {
            budget: self.clone(),
            item,
            bytes,
        }
    }

    /// Whether `bytes` more fit: under the high-water mark at once; past it, once shedding
    /// never-started calls and then idle watchers down to the low-water mark has begun, if what
    /// is still held leaves room under the budget.
    fn make_room(&self, bytes: u64) -> bool {
        if self.charged() + bytes <= self.high_water() {
            return true;
        }
        let target = self.low_water().saturating_sub(bytes);
        self.shed_pending(target);
        if self.used() > target {
            self.shed_idle_watchers(target);
        }
        self.charged() + bytes <= self.budget()
    }

    /// Charges `bytes` for `item` if room can be made, else counts `refused` and says why.
    pub(super) fn try_charge(
        self: &Arc<Self>,
        item: Item,
        bytes: u64,
        refused: Shed,
    ) -> Result<Charge, Status> {
        if self.make_room(bytes) {
            return Ok(self.charge(item, bytes));
        }
        self.count(refused, 1);
        Err(self.exhausted(item))
    }

    fn exhausted(&self, item: Item) -> Status {
        Status::resource_exhausted(format!(
            "the server's memory budget is spent ({} of {} for clients, of {} in all from {}); \
             no {} can be added now: retry shortly",
            show_size(self.used()),
            show_size(self.budget()),
            show_size(self.total.bytes),
            self.total.source,
            item.name()
        ))
    }

    /// A new connection, charged at `bytes`; None (counted) when no room can be made.
    pub(super) fn admit_connection(self: &Arc<Self>, bytes: u64) -> Option<Charge> {
        self.try_charge(Item::Connection, bytes, Shed::ConnectionRefused)
            .ok()
    }

    /// A new call on `connection`: charged and registered as never-started until its first
    /// message. Past the high-water mark a connection that already holds
    /// [`NEVER_STARTED_PAST_HIGH_WATER`] never-started calls has the call refused, and one that
    /// holds [`HOARDING_CALLS`] is sent GOAWAY too.
    pub(super) fn admit_call(
        self: &Arc<Self>,
        connection: &Arc<ConnectionShare>,
    ) -> Result<Admission, Status> {
        let bytes = costs::CALL;
        let never_started = connection.never_started.load(Ordering::Relaxed);
        if self.charged() + bytes > self.high_water()
            && never_started >= NEVER_STARTED_PAST_HIGH_WATER
        {
            if never_started >= HOARDING_CALLS {
                self.goaway(connection);
            }
            self.count(Shed::CallRefused, 1);
            return Err(Status::resource_exhausted(
                "this connection holds many calls that never sent a message while the server's \
                 memory is short: send on them or close them",
            ));
        }
        let charge = self.try_charge(Item::Call, bytes, Shed::CallRefused)?;
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let cancel = connection.reset_pending.child_token();
        connection.never_started.fetch_add(1, Ordering::Relaxed);
        self.lock_pending().insert(
            id,
            Pending {
                cancel: cancel.clone(),
                connection: connection.clone(),
                bytes,
            },
        );
        Ok(Admission {
            charge,
            pending: Some(PendingCall {
                budget: self.clone(),
                id,
                connection: connection.clone(),
                cancel,
                bytes,
            }),
        })
    }

    /// A watcher of a session, charged; idle until [`WatcherTicket::active`].
    pub(super) fn admit_watcher(self: &Arc<Self>) -> Result<WatcherTicket, Status> {
        let bytes = costs::WATCHER;
        let charge = self.try_charge(Item::Watcher, bytes, Shed::WatcherRefused)?;
        let id = self.next.fetch_add(1, Ordering::Relaxed);
        let cancel = CancellationToken::new();
        // Idle until its session's plan changes: watchers of a session that never steps are
        // the first to go.
        let last_change = Arc::new(AtomicU64::new(0));
        self.lock_watchers().insert(
            id,
            Watching {
                cancel: cancel.clone(),
                last_change: last_change.clone(),
                bytes,
            },
        );
        Ok(WatcherTicket {
            budget: self.clone(),
            id,
            cancel,
            last_change,
            _charge: charge,
        })
    }

    fn now_ms(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    fn lock_pending(&self) -> MutexGuard<'_, BTreeMap<u64, Pending>> {
        self.pending.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn lock_watchers(&self) -> MutexGuard<'_, BTreeMap<u64, Watching>> {
        self.watchers.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Resets never-started calls, oldest first, until usage is at `target` or none is left;
    /// a connection found holding many is sent GOAWAY.
    fn shed_pending(&self, target: u64) {
        let mut reset = 0;
        let mut hoarders = Vec::new();
        {
            let mut pending = self.lock_pending();
            while self.used() > target {
                let Some((_, call)) = pending.pop_first() else {
                    break;
                };
                self.shedding.fetch_add(call.bytes, Ordering::Relaxed);
                call.cancel.cancel();
                reset += 1;
                if call.connection.never_started.load(Ordering::Relaxed) >= HOARDING_CALLS {
                    hoarders.push(call.connection);
                }
            }
        }
        self.count(Shed::CallReset, reset);
        for connection in hoarders {
            self.goaway(&connection);
        }
    }

    /// Ends watchers whose session has not stepped for [`IDLE_WATCHER`], oldest first, until
    /// usage is at `target`.
    fn shed_idle_watchers(&self, target: u64) {
        let idle_since = self
            .now_ms()
            .saturating_sub(IDLE_WATCHER.as_millis() as u64);
        let mut ended = 0;
        let mut watchers = self.lock_watchers();
        let idle: Vec<u64> = watchers
            .iter()
            .filter(|(_, w)| w.last_change.load(Ordering::Relaxed) <= idle_since)
            .map(|(id, _)| *id)
            .collect();
        for id in idle {
            if self.used() <= target {
                break;
            }
            if let Some(watcher) = watchers.remove(&id) {
                self.shedding.fetch_add(watcher.bytes, Ordering::Relaxed);
                watcher.cancel.cancel();
                ended += 1;
            }
        }
        drop(watchers);
        self.count(Shed::WatcherReset, ended);
    }

    /// Sends `connection` GOAWAY (once) and resets its never-started calls.
    fn goaway(&self, connection: &ConnectionShare) {
        if connection.goaway.is_cancelled() {
            return;
        }
        connection.goaway.cancel();
        connection.reset_pending.cancel();
        self.count(Shed::Goaway, 1);
    }
}

/// Logs each burst of shedding twice: when it starts, and once it has been quiet for a second,
/// with what it shed. Looked at periodically by the memory keeper.
#[derive(Default)]
pub(super) struct BurstLog {
    seen: [u64; 7],
    /// The counts when the burst began, and when they last changed.
    burst: Option<([u64; 7], Instant)>,
}

impl BurstLog {
    pub(super) fn look(&mut self, budget: &MemoryBudget) {
        let now: [u64; 7] = std::array::from_fn(|i| budget.shed[i].load(Ordering::Relaxed));
        if now != self.seen {
            match &mut self.burst {
                Some((_, changed)) => *changed = Instant::now(),
                None => {
                    tracing::warn!(
                        used = %show_size(budget.used()),
                        budget = %show_size(budget.budget()),
                        total = %show_size(budget.total.bytes),
                        "memory budget past its high-water mark: resetting never-started calls \
                         and idle watchers, refusing what does not fit"
                    );
                    self.burst = Some((self.seen, Instant::now()));
                }
            }
            self.seen = now;
        }
        if let Some((start, changed)) = self.burst
            && changed.elapsed() >= Duration::from_secs(1)
        {
            let shed: Vec<String> = Shed::ALL
                .iter()
                .filter(|s| now[**s as usize] > start[**s as usize])
                .map(|s| format!("{} {}", s.name(), now[*s as usize] - start[*s as usize]))
                .collect();
            tracing::warn!(
                shed = %shed.join(", "),
                used = %show_size(budget.used()),
                budget = %show_size(budget.budget()),
                "memory shedding burst over"
            );
            self.burst = None;
        }
    }
}

/// Bytes charged against the budget, given back when dropped.
pub(crate) struct Charge {
    budget: Arc<MemoryBudget>,
    item: Item,
    bytes: u64,
}

impl Drop for Charge {
    fn drop(&mut self) {
        self.budget.used[self.item as usize].fetch_sub(self.bytes, Ordering::Relaxed);
    }
}

/// A call admitted: its charge (held until its response ends) and its never-started mark.
pub(super) struct Admission {
    pub(crate) charge: Charge,
    pub(crate) pending: Option<PendingCall>,
}

/// A call that has not yet sent a first message: `reset()` resolves if it is shed.
pub(super) struct PendingCall {
    budget: Arc<MemoryBudget>,
    id: u64,
    connection: Arc<ConnectionShare>,
    cancel: CancellationToken,
    bytes: u64,
}

impl PendingCall {
    /// Cancelled if the call is reset to make room.
    pub(super) fn reset(&self) -> CancellationToken {
        self.cancel.clone()
    }
}

impl Drop for PendingCall {
    /// Started (its first message complete) or ended.
    fn drop(&mut self) {
        self.connection
            .never_started
            .fetch_sub(1, Ordering::Relaxed);
        let removed = self.budget.lock_pending().remove(&self.id).is_some();
        if !removed {
            // Shed (or reset with its connection): its bytes were counted as gone. A call
            // reset with its connection was still in the map and counts normally.
            self.budget
                .shedding
                .fetch_sub(self.bytes, Ordering::Relaxed);
        }
    }
}

/// A watcher admitted: ended with RESOURCE_EXHAUSTED when `reset()` resolves.
pub(super) struct WatcherTicket {
    budget: Arc<MemoryBudget>,
    id: u64,
    cancel: CancellationToken,
    last_change: Arc<AtomicU64>,
    _charge: Charge,
}

impl WatcherTicket {
    pub(super) fn reset(&self) -> CancellationToken {
        self.cancel.clone()
    }

    /// Its session's plan changed now: the watcher is not idle.
    pub(super) fn active(&self) {
        self.last_change
            .store(self.budget.now_ms(), Ordering::Relaxed);
    }

    /// The status a shed watcher ends with.
    pub(super) fn shed_status() -> Status {
        Status::resource_exhausted(
            "the server's memory is short and this session has not stepped for a while: its \
             watcher was ended; watch again later",
        )
    }
}

impl Drop for WatcherTicket {
    fn drop(&mut self) {
        if self.budget.lock_watchers().remove(&self.id).is_none() {
            let bytes = costs::WATCHER;
            self.budget.shedding.fetch_sub(bytes, Ordering::Relaxed);
        }
    }
}

/// The status a reset never-started call ends with.
pub(super) fn call_reset_status() -> Status {
    Status::resource_exhausted(
        "the server's memory is short and this call had sent no message: it was reset to make \
         room; retry",
    )
}
