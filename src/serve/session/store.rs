//! The concurrent store of sessions: caps, looks up, closes and evicts them.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, SystemTime};

// tokio's clock, so that tests can pause and advance it.
use tokio::time::Instant;

use super::Session;
use crate::policy::Policy;

#[derive(Debug, thiserror::Error)]
pub(crate) enum SessionError {
    #[error("unknown session '{0}'; open one with OpenSession")]
    NotFound(String),
    #[error("session '{id}' was closed at {at}; open a new one with OpenSession")]
    Closed { id: String, at: String },
    #[error(
        "session '{id}' expired at {at} after {idle_secs:.1} s idle (the server's session TTL is \
         {ttl}); open a new one with OpenSession"
    )]
    Expired {
        id: String,
        at: String,
        idle_secs: f64,
        ttl: String,
    },
    #[error("the server holds its maximum of {0} sessions; close one or retry later")]
    CapReached(usize),
    #[error("session '{0}' belongs to another client")]
    NotOwner(String),
}

pub(crate) struct SessionSlot {
    /// The session's policy (also in the session), readable without the lock.
    pub(crate) policy: Arc<Policy>,
    pub(crate) owner: Option<String>,
    /// Its policy's step counter in the metrics.
    pub(crate) steps_served: prometheus_client::metrics::counter::Counter,
    session: Mutex<Session>,
    /// When the session was last used (ms since the store's epoch); idle time starts here.
    last_used_ms: AtomicU64,
    /// Requests using the session now: a session with one in flight never expires.
    in_use: AtomicU64,
    /// Its charge against the server's memory budget, given back when the last user lets go.
    _memory: Option<crate::serve::memory::Charge>,
}

/// Marks a session in use from [`Sessions::get`] until dropped; then its idle time starts.
pub(crate) struct InUse {
    slot: Arc<SessionSlot>,
    epoch: Instant,
}

impl std::ops::Deref for InUse {
    type Target = Arc<SessionSlot>;
    fn deref(&self) -> &Arc<SessionSlot> {
        &self.slot
    }
}

impl Drop for InUse {
    fn drop(&mut self) {
        // Stamp before releasing, so the evictor never sees it free with an old stamp.
        self.slot
            .last_used_ms
            .store(self.epoch.elapsed().as_millis() as u64, Ordering::SeqCst);
        self.slot.in_use.fetch_sub(1, Ordering::SeqCst);
    }
}

impl SessionSlot {
    /// Locks the session (a panic elsewhere cannot wedge it: poisoning is ignored).
    pub(crate) fn lock(&self) -> MutexGuard<'_, Session> {
        self.session.lock().unwrap_or_else(|p| p.into_inner())
    }
}

#[derive(Clone, Debug)]
enum Ended {
    Closed { at: SystemTime },
    Expired { at: SystemTime, idle: Duration },
}

/// Ids of ended sessions, remembered (up to a bound) so that a late request learns why.
struct Tombstones {
    order: VecDeque<String>,
    ended: HashMap<String, Ended>,
}

/// Ended sessions remembered (about 200 bytes each). Beyond, the oldest is forgotten and a late
/// request for it gets a plain NOT_FOUND. With 65,536, prac-soak's churn (20 sessions/s) grew the
/// server by about 0.5 MB a minute towards a 13 MB plateau; 4,096 reaches its plateau in minutes.
const MAX_TOMBSTONES: usize = 4_096;

/// Stops the evictor of [`Sessions::start`] when dropped, with its store.
struct Evictor(tokio::task::JoinHandle<()>);

impl Drop for Evictor {
    fn drop(&mut self) {
        self.0.abort();
    }
}

pub(crate) struct Sessions {
    slots: Mutex<HashMap<String, Arc<SessionSlot>>>,
    tombstones: Mutex<Tombstones>,
    max_sessions: usize,
    ttl: Duration,
    epoch: Instant,
    /// Set by [`Sessions::start`]: the store's own evictor, which ends when the store does.
    evictor: std::sync::OnceLock<Evictor>,
}

fn rfc3339(t: SystemTime) -> String {
    humantime::format_rfc3339_millis(t).to_string()
}

/// Shortens a client-supplied id for error messages.
fn shown(id: &str) -> String {
    id.chars().take(64).collect()
}

impl Sessions {
    pub(crate) fn new(max_sessions: usize, ttl: Duration) -> Sessions {
        Sessions {
            slots: Mutex::new(HashMap::new()),
            tombstones: Mutex::new(Tombstones {
                order: VecDeque::new(),
                ended: HashMap::new(),
            }),
            max_sessions,
            ttl,
            epoch: Instant::now(),
            evictor: std::sync::OnceLock::new(),
        }
    }

    /// A store that evicts its idle sessions every quarter of the TTL (10 ms to 1 s) for as long
    /// as it lives, telling `on_evicted` how many went each time. Needs a tokio runtime.
    pub(crate) fn start(
        max_sessions: usize,
        ttl: Duration,
        on_evicted: impl Fn(usize) + Send + 'static,
    ) -> Arc<Sessions> {
        let sessions = Arc::new(Sessions::new(max_sessions, ttl));
        let store = Arc::downgrade(&sessions);
        let period = (ttl / 4).clamp(Duration::from_millis(10), Duration::from_secs(1));
        let evictor = Evictor(tokio::spawn(async move {
            let mut tick = tokio::time::interval(period);
            loop {
                tick.tick().await;
                let Some(sessions) = store.upgrade() else {
                    return;
                };
                on_evicted(sessions.evict_idle());
            }
        }));
        let _ = sessions.evictor.set(evictor);
        sessions
    }

    fn now_ms(&self) -> u64 {
        self.epoch.elapsed().as_millis() as u64
    }

    fn slots(&self) -> MutexGuard<'_, HashMap<String, Arc<SessionSlot>>> {
        self.slots.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub(crate) fn len(&self) -> usize {
        self.slots().len()
    }

    pub(crate) fn insert(
        &self,
        session: Session,
        steps_served: prometheus_client::metrics::counter::Counter,
        memory: Option<crate::serve::memory::Charge>,
    ) -> Result<(), SessionError> {
        let mut slots = self.slots();
        if slots.len() >= self.max_sessions {
            return Err(SessionError::CapReached(self.max_sessions));
        }
        let id = session.id.clone();
        slots.insert(
            id,
            Arc::new(SessionSlot {
                policy: session.policy.clone(),
                owner: session.owner.clone(),
                steps_served,
                session: Mutex::new(session),
                last_used_ms: AtomicU64::new(self.now_ms()),
                in_use: AtomicU64::new(0),
                _memory: memory,
            }),
        );
        Ok(())
    }

    /// The live session with this id, in use until the guard drops, if `caller` owns it.
    pub(crate) fn get(&self, id: &str, caller: Option<&str>) -> Result<InUse, SessionError> {
        // Marked in use under the map's lock, so the evictor cannot take it in between.
        let slots = self.slots();
        match slots.get(id) {
            Some(slot) if slot.owner.as_deref() != caller => Err(SessionError::NotOwner(shown(id))),
            Some(slot) => {
                slot.in_use.fetch_add(1, Ordering::SeqCst);
                slot.last_used_ms.store(self.now_ms(), Ordering::SeqCst);
                Ok(InUse {
                    slot: slot.clone(),
                    epoch: self.epoch,
                })
            }
            None => {
                drop(slots);
                Err(self.why_missing(id))
            }
        }
    }

    fn why_missing(&self, id: &str) -> SessionError {
        let tombstones = self.tombstones.lock().unwrap_or_else(|p| p.into_inner());
        match tombstones.ended.get(id) {
            Some(Ended::Closed { at }) => SessionError::Closed {
                id: shown(id),
                at: rfc3339(*at),
            },
            Some(Ended::Expired { at, idle }) => SessionError::Expired {
                id: shown(id),
                at: rfc3339(*at),
                idle_secs: idle.as_secs_f64(),
                ttl: humantime::format_duration(self.ttl).to_string(),
            },
            None => SessionError::NotFound(shown(id)),
        }
    }

    fn bury(&self, id: String, ended: Ended) {
        let mut t = self.tombstones.lock().unwrap_or_else(|p| p.into_inner());
        if t.order.len() >= MAX_TOMBSTONES
            && let Some(old) = t.order.pop_front()
        {
            t.ended.remove(&old);
        }
        t.order.push_back(id.clone());
        t.ended.insert(id, ended);
    }

    pub(crate) fn close(
        &self,
        id: &str,
        caller: Option<&str>,
    ) -> Result<Arc<SessionSlot>, SessionError> {
        let removed = {
            let mut slots = self.slots();
            match slots.get(id) {
                Some(slot) if slot.owner.as_deref() != caller => {
                    return Err(SessionError::NotOwner(shown(id)));
                }
                Some(_) => slots.remove(id),
                None => None,
            }
        };
        match removed {
            Some(slot) => {
                self.bury(
                    id.to_string(),
                    Ended::Closed {
                        at: SystemTime::now(),
                    },
                );
                Ok(slot)
            }
            None => Err(self.why_missing(id)),
        }
    }

    /// Removes every session idle for longer than the TTL; returns how many. Idle time starts
    /// when a request ends: a session with a request in flight is never idle.
    pub(crate) fn evict_idle(&self) -> usize {
        let ttl_ms = self.ttl.as_millis() as u64;
        let expired: Vec<(String, u64)> = {
            let mut slots = self.slots();
            let now = self.now_ms();
            let ids: Vec<(String, u64)> = slots
                .iter()
                .filter_map(|(id, slot)| {
                    if slot.in_use.load(Ordering::SeqCst) > 0 {
                        return None;
                    }
                    let idle = now.saturating_sub(slot.last_used_ms.load(Ordering::SeqCst));
                    (idle > ttl_ms).then(|| (id.clone(), idle))
                })
                .collect();
            for (id, _) in &ids {
                slots.remove(id);
            }
            ids
        };
        let at = SystemTime::now();
        for (id, idle_ms) in &expired {
            tracing::info!(session = %id, idle_ms, "session expired");
            self.bury(
                id.clone(),
                Ended::Expired {
                    at,
                    idle: Duration::from_millis(*idle_ms),
                },
            );
        }
        expired.len()
    }
}
