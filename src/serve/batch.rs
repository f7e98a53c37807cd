//! Cross-session dynamic batching: steps go through bounded queues to worker threads, which take
//! what is queued (waiting up to the batch window for more) and replan each policy's sessions
//! together with [`replan_batch`], so that every network evaluation is a matrix product over the
//! batch. A session always goes to the same worker, so its steps are replanned in the order they
//! came. A full queue is answered at once with RESOURCE_EXHAUSTED. A step of the only session
//! that stepped lately, finding no other step waiting, is replanned in its request handler
//! instead ([`Batcher::claim_alone`]): alone it has nothing to batch with, and the hand-off to a
//! worker thread would cost more than it saves. A batch window (steps wait for company) turns
//! this off.
//!
//! Without a window, a worker expects company from the sessions that stepped lately
//! ([`Activity`]): with several of them (each sends its next step once answered, closed loop, or
//! on its control clock), it waits for their steps, up to [`COMPANY_WAIT`], before replanning, so
//! that a core whose steps arrive one by one still replans them together instead of one at a
//! time. While it waits it sleeps until the last expected step is queued ([`Doorbell`]), not
//! woken by each step on the way. Steps too cheap to be worth a hand-off ([`CHEAP_STEP_FLOPS`]) stay in
//! their handlers.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering, fence};
use std::sync::{Arc, OnceLock};
use std::thread::Thread;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, TryRecvError, TrySendError};
use tokio::sync::oneshot;
use tonic::Status;

use super::arrival::Arrival;
use super::session::{Session, SessionSlot, StepInput, apply_steps};
use super::workspace::{Workspace, Workspaces};
use crate::policy::Policy;
use crate::proto;

/// How long a worker waits for the steps of the sessions that stepped lately, when no batch window
/// is set: a closed-loop client answered in one batch sends its next steps within about this.
const COMPANY_WAIT: Duration = Duration::from_micros(1_000);

/// How often an idle worker looks whether the server has stopped (its queue disconnected).
const IDLE_RECHECK: Duration = Duration::from_millis(100);

/// A step whose replan evaluates fewer network FLOPs than this (a moving average over the steps
/// replanned in handlers and in batches) costs less than the hand-off to a worker thread and the
/// wait for company (about 10 us at a lone row's rate): such steps are replanned in their
/// handlers whatever the company (one-step serving: one actor row). Counted in FLOPs, not time,
/// since a step batched with others takes a fraction of its time alone, and the choice must not
/// flip with the choice it made.
const CHEAP_STEP_FLOPS: u64 = 500_000;

/// How recently a session must have stepped to count as active ([`Activity`]).
const ACTIVITY_EPOCH_MS: u64 = 20;

/// Bits of the active-session sketch per worker.
const ACTIVITY_BITS: usize = 256;

/// Sessions of one worker that stepped in the current or last epoch ([`ACTIVITY_EPOCH_MS`]),
/// estimated lock-free: each step sets its session's bit in a 256-bit sketch, and the count is
/// the bits set. Sessions whose bits collide count once, so it errs low (64 sessions at random
/// bits set about 57), which only ends a worker's wait for company sooner.
struct Activity {
    start: Instant,
    epoch: AtomicU64,
    current: [AtomicU64; ACTIVITY_BITS / 64],
    previous: [AtomicU64; ACTIVITY_BITS / 64],
}

impl Activity {
    fn new() -> Activity {
        Activity {
            start: Instant::now(),
            epoch: AtomicU64::new(0),
            current: Default::default(),
            previous: Default::default(),
        }
    }

    /// Starts a new epoch when the current one is over (the last one's bits are kept a while).
    fn rotate(&self) {
        let now = self.start.elapsed().as_millis() as u64 / ACTIVITY_EPOCH_MS;
        let seen = self.epoch.load(Ordering::Acquire);
        if now != seen
            && self
                .epoch
                .compare_exchange(seen, now, Ordering::AcqRel, Ordering::Acquire)
                .is_ok()
        {
            // Two epochs or more apart: the last one saw nothing either.
            let stale = now > seen + 1;
            for (current, previous) in self.current.iter().zip(&self.previous) {
                let bits = current.swap(0, Ordering::AcqRel);
                previous.store(if stale { 0 } else { bits }, Ordering::Release);
            }
        }
    }

    fn mark(&self, session: usize) {
        self.rotate();
        // Fibonacci hashing: the top 8 bits of the product spread the slots' addresses over
        // the 256 bits.
        let hashed = (session as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let bit = (hashed >> (64 - ACTIVITY_BITS.trailing_zeros())) as usize;
        self.current[bit / 64].fetch_or(1 << (bit % 64), Ordering::AcqRel);
    }

    /// Sessions that stepped in this epoch or the last.
    fn sessions(&self) -> usize {
        self.rotate();
        let set: u32 = self
            .current
            .iter()
            .zip(&self.previous)
            .map(|(c, p)| (c.load(Ordering::Acquire) | p.load(Ordering::Acquire)).count_ones())
            .sum();
        set as usize
    }
}

/// How a worker waiting for company is woken: once the steps it still expects are all queued (or
/// at its deadline), instead of by every step on the way. On a busy core each wake-up is a thread
/// switch away from the request handlers that are reading the very steps it waits for.
#[derive(Default)]
struct Doorbell {
    /// Steps the worker still expects while it sleeps for company; 0 when it is not sleeping so.
    wanted: AtomicUsize,
    worker: OnceLock<Thread>,
}

impl Doorbell {
    /// After a step was queued: wakes the worker if the queue now holds all it waits for.
    fn queued(&self, queue_len: impl FnOnce() -> usize) {
        // Pairs with the fence in `sleep`: either this sees the worker's wish or the worker
        // sees this step in the queue.
        fence(Ordering::SeqCst);
        let wanted = self.wanted.load(Ordering::Relaxed);
        if wanted > 0
            && queue_len() >= wanted
            && let Some(worker) = self.worker.get()
        {
            worker.unpark();
        }
    }

    /// Sleeps until `wanted` more steps are queued (as `queue_len` counts them) or `deadline`.
    /// May return sooner (a stale wake-up); the caller takes what is queued and decides.
    fn sleep(&self, wanted: usize, queue_len: impl FnOnce() -> usize, deadline: Instant) {
        self.wanted.store(wanted, Ordering::Relaxed);
        fence(Ordering::SeqCst);
        if queue_len() < wanted {
            let now = Instant::now();
            if now < deadline {
                std::thread::park_timeout(deadline - now);
            }
        }
        self.wanted.store(0, Ordering::Relaxed);
    }
}

/// Settings of the batch workers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct BatchConfig {
    /// Most steps replanned together.
    pub(crate) max_batch: usize,
    /// How long a worker waits for more steps after the first (0: take only what is queued).
    pub(crate) window: Duration,
    /// Steps waiting at most; beyond, requests are refused (RESOURCE_EXHAUSTED).
    pub(crate) queue: usize,
    pub(crate) workers: usize,
}

/// A step's answer: the response and the session's steps served with it (to take it back).
pub(super) type Answer = Result<(proto::StepResponse, u64), Status>;

struct Work {
    slot: Arc<SessionSlot>,
    request: proto::StepRequest,
    /// The caller's deadline; a step not replanned by then is answered DEADLINE_EXCEEDED and
    /// not applied.
    deadline: Option<Instant>,
    arrival: Arrival,
    reply: oneshot::Sender<Answer>,
}

/// The submitting side of the batch queues.
#[derive(Clone)]
pub(super) struct Batcher {
    queues: Vec<Sender<Work>>,
    capacity: usize,
    /// Steps submitted whose callers still wait for their answers.
    waiting: Arc<AtomicUsize>,
    /// A batch window asks steps to wait for company: then no step is replanned alone.
    inline_when_alone: bool,
    /// Per worker, its sessions that stepped lately.
    activity: Vec<Arc<Activity>>,
    /// Per worker, how a step wakes it when it waits for company.
    doorbells: Vec<Arc<Doorbell>>,
    /// Moving average of a step's replan, in FLOPs ([`CHEAP_STEP_FLOPS`]).
    step_cost: Arc<StepCost>,
}

/// A moving average of the FLOPs of a step's replan, over about the last 16 steps or batches.
#[derive(Default)]
pub(super) struct StepCost(AtomicU64);

impl StepCost {
    fn note(&self, flops_per_step: u64) {
        let average = self.0.load(Ordering::Relaxed);
        self.0.store(
            average - average / 16 + flops_per_step / 16,
            Ordering::Relaxed,
        );
    }

    fn cheap(&self) -> bool {
        self.0.load(Ordering::Relaxed) < CHEAP_STEP_FLOPS
    }
}

/// Counts one waiting caller while it lives (a dropped, cancelled call included).
pub(super) struct Waiting<'a>(&'a AtomicUsize);

impl<'a> Waiting<'a> {
    fn enter(count: &'a AtomicUsize) -> Waiting<'a> {
        count.fetch_add(1, Ordering::AcqRel);
        Waiting(count)
    }
}

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

impl Batcher {
    /// Starts the worker threads, each with its share of the queue; they stop when every
    /// `Batcher` clone is dropped.
    pub(super) fn start(config: BatchConfig) -> Batcher {
        let workers = config.workers.max(1);
        let per_worker = config.queue.div_ceil(workers).max(1);
        let mut queues = Vec::with_capacity(workers);
        let mut activity = Vec::with_capacity(workers);
        let mut doorbells = Vec::with_capacity(workers);
        let step_cost = Arc::new(StepCost::default());
        for i in 0..workers {
            let (queue, receiver) = crossbeam_channel::bounded(per_worker);
            queues.push(queue);
            let sessions = Arc::new(Activity::new());
            activity.push(sessions.clone());
            let cost = step_cost.clone();
            let doorbell = Arc::new(Doorbell::default());
            doorbells.push(doorbell.clone());
            let worker = std::thread::Builder::new()
                .name(format!("prac-batch-{i}"))
                .spawn(move || Worker::new(config, sessions, cost, doorbell).run(&receiver))
                .expect("spawning a batch worker thread");
            let _ = doorbells[i].worker.set(worker.thread().clone());
        }
        Batcher {
            queues,
            capacity: per_worker,
            waiting: Arc::default(),
            inline_when_alone: config.window.is_zero(),
            activity,
            doorbells,
            step_cost,
        }
    }

    /// Records the FLOPs of a step replanned in its handler (see [`CHEAP_STEP_FLOPS`]).
    pub(super) fn note_alone_cost(&self, flops: u64) {
        self.step_cost.note(flops);
    }

    /// The worker of a session: one per session keeps its steps in order.
    fn worker_of(&self, slot: &Arc<SessionSlot>) -> usize {
        (Arc::as_ptr(slot) as usize / std::mem::align_of::<SessionSlot>()) % self.queues.len()
    }

    /// When no step is queued or being replanned (and no batch window is set), a step has
    /// nothing to be batched with: this claims the right to replan it in its handler, until the
    /// guard drops. Steps that come meanwhile are batched. A session's steps keep their order,
    /// since its next step cannot claim while an earlier one waits.
    pub(super) fn claim_alone(&self, slot: &Arc<SessionSlot>) -> Option<Waiting<'_>> {
        let activity = &self.activity[self.worker_of(slot)];
        activity.mark(Arc::as_ptr(slot) as usize);
        // Other sessions of its worker stepped lately: their steps will keep it company, unless
        // a step is too cheap to be worth the hand-off.
        let cheap = self.step_cost.cheap();
        if !self.inline_when_alone || (activity.sessions() > 1 && !cheap) {
            return None;
        }
        self.waiting
            .compare_exchange(0, 1, Ordering::AcqRel, Ordering::Acquire)
            .ok()
            .map(|_| Waiting(&self.waiting))
    }

    /// Queues a step and waits for its answer, until `deadline`. A step is applied only if its
    /// answer is taken here: one the worker answers after the caller gave up (this future was
    /// dropped, or the deadline passed) is taken back.
    pub(super) async fn submit(
        &self,
        slot: Arc<SessionSlot>,
        request: proto::StepRequest,
        deadline: Option<Instant>,
        arrival: Arrival,
    ) -> Answer {
        let _waiting = Waiting::enter(&self.waiting);
        let (reply, mut answer) = oneshot::channel();
        let worker = self.worker_of(&slot);
        let work = Work {
            slot,
            request,
            deadline,
            arrival,
            reply,
        };
        let queue = &self.queues[worker];
        match queue.try_send(work) {
            Ok(()) => self.doorbells[worker].queued(|| queue.len()),
            Err(TrySendError::Full(_)) => {
                return Err(Status::resource_exhausted(format!(
                    "overloaded: {} steps are already queued for this session's batch worker; \
                     retry later or use fewer sessions",
                    self.capacity
                )));
            }
            Err(TrySendError::Disconnected(_)) => {
                return Err(Status::unavailable("the batch workers have stopped"));
            }
        }
        let dropped = |_| Err(Status::internal("the batch worker dropped the step"));
        let Some(deadline) = deadline else {
            return answer.await.unwrap_or_else(dropped);
        };
        tokio::select! {
            biased;
            answered = &mut answer => answered.unwrap_or_else(dropped),
            _ = tokio::time::sleep_until(deadline.into()) => {
                // Closed first: the worker either answered already (taken here, so applied) or
                // finds the channel closed and takes its step back.
                answer.close();
                match answer.try_recv() {
                    Ok(answered) => answered,
                    Err(_) => Err(super::deadline::exceeded()),
                }
            }
        }
    }
}

/// One worker's networks and buffers, reused across batches.
struct Worker {
    config: BatchConfig,
    workspaces: Workspaces,
    activity: Arc<Activity>,
    step_cost: Arc<StepCost>,
    doorbell: Arc<Doorbell>,
}

impl Worker {
    fn new(
        config: BatchConfig,
        activity: Arc<Activity>,
        step_cost: Arc<StepCost>,
        doorbell: Arc<Doorbell>,
    ) -> Worker {
        Worker {
            config,
            workspaces: Workspaces::new(config.max_batch, 0),
            activity,
            step_cost,
            doorbell,
        }
    }

    fn run(mut self, receiver: &Receiver<Work>) {
        let mut batch = Vec::with_capacity(self.config.max_batch);
        let mut deferred = Vec::new();
        loop {
            // Idle, it sleeps on its doorbell too: a channel's blocking receive spins and yields
            // to the very handlers that are queueing steps, a thread switch each time.
            let first = match receiver.try_recv() {
                Ok(work) => work,
                Err(TryRecvError::Empty) => {
                    self.doorbell
                        .sleep(1, || receiver.len(), Instant::now() + IDLE_RECHECK);
                    continue;
                }
                // Every Batcher is gone: the server stopped.
                Err(TryRecvError::Disconnected) => return,
            };
            batch.push(first);
            // Without a window, the steps to expect: one from each session that stepped lately,
            // for at most COMPANY_WAIT. A window is waited out whatever the company.
            let window = self.config.window;
            let company = if window.is_zero() {
                self.activity.sessions().clamp(1, self.config.max_batch)
            } else {
                self.config.max_batch
            };
            let deadline = Instant::now()
                + if window.is_zero() {
                    COMPANY_WAIT
                } else {
                    window
                };
            loop {
                while batch.len() < self.config.max_batch {
                    match receiver.try_recv() {
                        Ok(work) => batch.push(work),
                        Err(_) => break,
                    }
                }
                if batch.len() >= company || Instant::now() >= deadline {
                    break;
                }
                let wanted = company - batch.len();
                self.doorbell.sleep(wanted, || receiver.len(), deadline);
            }
            // A session twice in one batch (two streams on one session) goes in order: its
            // later steps wait for the next round.
            while !batch.is_empty() {
                // A bug must not take the worker down: the batch's callers get INTERNAL (their
                // reply channels drop) and the worker goes on.
                let processed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    self.process(&mut batch, &mut deferred)
                }));
                if processed.is_err() {
                    tracing::error!("a batch worker panicked; its batch was dropped");
                    batch.clear();
                    deferred.clear();
                    self.workspaces.clear();
                }
                std::mem::swap(&mut batch, &mut deferred);
            }
        }
    }

    fn process(&mut self, batch: &mut Vec<Work>, deferred: &mut Vec<Work>) {
        // Group by policy: one replan_batch per policy.
        let mut groups: HashMap<*const Policy, Vec<Work>> = HashMap::new();
        for work in batch.drain(..) {
            // The caller gave up (deadline, cancel): applying its step would move the session
            // on behind its back.
            if work.reply.is_closed() {
                continue;
            }
            if super::deadline::passed(work.deadline) {
                let _ = work.reply.send(Err(super::deadline::exceeded()));
                continue;
            }
            let policy = Arc::as_ptr(&work.slot.policy);
            groups.entry(policy).or_default().push(work);
        }
        for works in groups.into_values() {
            let mut seen: Vec<*const SessionSlot> = Vec::with_capacity(works.len());
            let mut mine = Vec::with_capacity(works.len());
            for work in works {
                let ptr = Arc::as_ptr(&work.slot);
                if seen.contains(&ptr) {
                    deferred.push(work);
                } else {
                    seen.push(ptr);
                    mine.push(work);
                }
            }
            let steps = mine.len() as u64;
            let flops = self.replan_group(mine);
            self.step_cost.note(flops / steps.max(1));
        }
    }

    /// Replans the sessions of `works` (all of one policy, each session once) together; returns
    /// the FLOPs it took.
    fn replan_group(&mut self, mut works: Vec<Work>) -> u64 {
        // Sessions are locked in one global order, so workers never wait on each other in a cycle.
        works.sort_by_key(|work| Arc::as_ptr(&work.slot));
        let mut slots = Vec::with_capacity(works.len());
        let mut requests = Vec::with_capacity(works.len());
        let mut replies = Vec::with_capacity(works.len());
        for work in works {
            slots.push(work.slot);
            requests.push((work.request, work.arrival));
            replies.push(work.reply);
        }
        let mut guards: Vec<_> = slots.iter().map(|slot| slot.lock()).collect();
        let inputs: Vec<StepInput<'_>> = requests
            .iter()
            .map(|(request, arrival)| StepInput {
                observation: &request.observation,
                new_episode: request.new_episode,
                arrival: *arrival,
            })
            .collect();
        let Workspace { evaluator, scratch } = self.workspaces.get(&guards[0].policy);
        let mut sessions: Vec<&mut Session> = guards.iter_mut().map(|guard| &mut **guard).collect();
        let mut answers: Vec<Answer> = Vec::with_capacity(replies.len());
        apply_steps(
            &mut sessions,
            &inputs,
            evaluator,
            scratch,
            |_, session, report| {
                answers.push(
                    report
                        .map(|report| (session.response(&report), report.served))
                        .map_err(Status::from),
                );
            },
        );
        // Answered together once the whole batch is built, so that the handlers the answers wake
        // find them all ready (`handlers_do_not_preempt` lets the worker finish first).
        debug_assert_eq!(answers.len(), replies.len());
        for ((reply, answer), session) in replies.into_iter().zip(answers).zip(&mut sessions) {
            let served = answer.as_ref().ok().map(|(_, served)| *served);
            // A caller that gave up meanwhile takes nothing: the step is taken back, still
            // under its session's lock, so nobody ever sees it applied.
            if let (Err(_), Some(served)) = (reply.send(answer), served) {
                session.take_back(served);
            }
        }
        evaluator.take_flops()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_activity_sketch_counts_the_sessions_that_stepped_lately() {
        let activity = Activity::new();
        assert_eq!(activity.sessions(), 0);
        // Slots are heap addresses, aligned: stand-ins 64 bytes apart.
        let slot = |k: usize| 0x7f00_0000_0000 + 64 * k;
        activity.mark(slot(1));
        activity.mark(slot(1));
        assert_eq!(activity.sessions(), 1);
        for k in 0..64 {
            activity.mark(slot(k));
        }
        let estimate = activity.sessions();
        assert!((52..=64).contains(&estimate), "{estimate} for 64 sessions");
        // Two epochs without a step: nobody is active.
        std::thread::sleep(Duration::from_millis(3 * ACTIVITY_EPOCH_MS));
        assert_eq!(activity.sessions(), 0);
    }

    /// A worker sleeping for `wanted` steps, on its own thread: how long it slept.
    fn sleeper(
        doorbell: &Arc<Doorbell>,
        receiver: &Receiver<u32>,
        wanted: usize,
        deadline: Duration,
    ) -> std::thread::JoinHandle<Duration> {
        let (bell, queue) = (doorbell.clone(), receiver.clone());
        let (ready, started) = crossbeam_channel::bounded(1);
        let worker = std::thread::spawn(move || {
            ready.send(()).unwrap();
            let start = Instant::now();
            bell.sleep(wanted, || queue.len(), start + deadline);
            start.elapsed()
        });
        let _ = doorbell.worker.set(worker.thread().clone());
        started.recv().unwrap();
        worker
    }

    #[test]
    fn the_doorbell_wakes_its_worker_once_all_it_waits_for_is_queued() {
        let (queue, receiver) = crossbeam_channel::bounded(8);
        let doorbell = Arc::new(Doorbell::default());
        // Three steps awaited, a minute allowed: the third step rings.
        let worker = sleeper(&doorbell, &receiver, 3, Duration::from_secs(60));
        for step in 0..3 {
            std::thread::sleep(Duration::from_millis(20));
            queue.send(step).unwrap();
            doorbell.queued(|| queue.len());
        }
        assert!(worker.join().unwrap() < Duration::from_secs(30));
        assert_eq!(doorbell.wanted.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn the_doorbell_lets_its_worker_sleep_to_the_deadline_while_steps_are_missing() {
        let (queue, receiver) = crossbeam_channel::bounded(8);
        let doorbell = Arc::new(Doorbell::default());
        let deadline = Duration::from_millis(200);
        let worker = sleeper(&doorbell, &receiver, 3, deadline);
        for step in 0..2 {
            queue.send(step).unwrap();
            doorbell.queued(|| queue.len());
        }
        assert!(worker.join().unwrap() >= deadline);
    }
}
