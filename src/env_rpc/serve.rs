//! `prac env-serve`: a built-in domain served over dm_env_rpc, with the same offer
//! `prac_client.env_server` makes for gymnasium's envs (docs/environments.md):
//!
//! - worlds: each CreateWorld makes one environment of the domain (setting `seed`, INT64: its
//!   first episode's seed, the server's `--seed` otherwise); one agent per world; the worlds a
//!   connection created are destroyed when it ends;
//! - vector worlds: with the setting `num_envs` (INT64, 1..=1024) a world holds that many
//!   environments, stepped together on the machine's cores: every tensor gains a leading
//!   dimension of that size, observations `terminated` and `truncated` (BOOL) say which ended,
//!   the state stays RUNNING, and an environment that ended starts its next episode at the
//!   following step, ignoring its action (gymnasium's next-step autoreset). Environment i plays
//!   seeds `seed + i`, `seed + i + num_envs`, ...;
//! - specs: the action `action` (FLOAT, the domain's bounds); observations `observation` (FLOAT,
//!   the domain's documented ranges), `reward` and `discount` (DOUBLE), `env_id` (STRING) and
//!   `max_episode_steps` (INT64);
//! - episodes: the first step after joining, a reset or an episode's end ignores its actions and
//!   starts an episode seeded as the world's settings or the last ResetRequest say (each later
//!   episode with the next seed); a fall answers TERMINATED (discount 0), the step limit
//!   INTERRUPTED (discount 1);
//! - bad requests (unknown uids or settings, a wrong dtype or shape, a non-finite or
//!   out-of-bounds action, a step before joining) are answered with an error status and change
//!   nothing.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use tokio_stream::{Stream, StreamExt};
use tonic::{Request as GrpcRequest, Response as GrpcResponse, Status, Streaming};

use super::tensor;
use super::wire::dm_env_rpc::v1 as pb;
use super::wire::google::rpc::Status as ErrorStatus;
use crate::domains::{self, Env, EnvSpec};
use pb::environment_request::Payload as Request;
use pb::environment_response::Payload as Response;
use pb::environment_server::{Environment, EnvironmentServer};

const ACTION: u64 = 1;
const OBSERVATION: u64 = 1;
const REWARD: u64 = 2;
const DISCOUNT: u64 = 3;
const ENV_ID: u64 = 4;
const MAX_EPISODE_STEPS: u64 = 5;
const TERMINATED: u64 = 6;
const TRUNCATED: u64 = 7;
/// An action this far past a bound (relative to the bound's range) is still taken, clipped:
/// float32 rounding of a rescaled tanh lands just outside.
const BOUND_TOLERANCE: f32 = 1e-6;
// google.rpc.Code's values are gRPC's status codes.
const INVALID_ARGUMENT: i32 = tonic::Code::InvalidArgument as i32;
const NOT_FOUND: i32 = tonic::Code::NotFound as i32;
const FAILED_PRECONDITION: i32 = tonic::Code::FailedPrecondition as i32;
const UNIMPLEMENTED: i32 = tonic::Code::Unimplemented as i32;
const INTERNAL: i32 = tonic::Code::Internal as i32;

/// A request the server refuses; nothing changed.
struct Refusal(i32, String);

fn refuse<T>(code: i32, message: impl Into<String>) -> Result<T, Refusal> {
    Err(Refusal(code, message.into()))
}

/// The world a connection joined; step, reset and leave_world need one.
fn joined_world(joined: &Option<Arc<Mutex<World>>>) -> Result<&Mutex<World>, Refusal> {
    joined.as_deref().ok_or_else(|| {
        Refusal(
            FAILED_PRECONDITION,
            "step, reset and leave_world need a joined world: create and join one first".into(),
        )
    })
}

fn lock(world: &Mutex<World>) -> Result<MutexGuard<'_, World>, Refusal> {
    world
        .lock()
        .map_err(|_| Refusal(INTERNAL, "the world failed earlier".into()))
}

/// One environment of a world and the state of its episode.
struct Slot {
    env: Box<dyn Env>,
    /// The seed of this slot's next episode; each episode after it adds the world's size, so
    /// the slots of a world play distinct seeds.
    next_seed: u64,
    running: bool,
    obs: Vec<f32>,
    reward: f64,
    terminated: bool,
    truncated: bool,
}

impl Slot {
    /// Starts the next episode: its observation, reward 0, no end.
    fn start(&mut self, stride: u64) -> Result<(), Refusal> {
        self.env
            .reset(self.next_seed, &mut self.obs)
            .map_err(|e| Refusal(INTERNAL, e.to_string()))?;
        self.next_seed = self.next_seed.wrapping_add(stride);
        (self.running, self.reward) = (true, 0.0);
        (self.terminated, self.truncated) = (false, false);
        Ok(())
    }

    fn step(&mut self, action: &[f32]) -> Result<(), Refusal> {
        let t = self
            .env
            .step(action, &mut self.obs)
            .map_err(|e| Refusal(INTERNAL, e.to_string()))?;
        (self.reward, self.terminated, self.truncated) = (t.reward, t.terminated, t.truncated);
        self.running = !(t.terminated || t.truncated);
        Ok(())
    }

    /// A vector world's step of this slot: one that ended last step starts its next episode
    /// instead, ignoring its action (gymnasium's next-step autoreset).
    fn advance(&mut self, action: &[f32], stride: u64) -> Result<(), Refusal> {
        if self.running {
            self.step(action)
        } else {
            self.start(stride)
        }
    }
}

/// The environments of a world: one, or with the `num_envs` setting a vector of them whose
/// tensors gain a leading dimension of that size.
struct World {
    slots: Vec<Slot>,
    vector: bool,
    joined: bool,
    /// A vector world's slots have started their episodes since joining or the last reset.
    started: bool,
    action: Vec<f32>,
}

impl World {
    fn new(domain: &str, seed: u64, num_envs: Option<usize>) -> World {
        let size = num_envs.unwrap_or(1);
        let slots: Vec<Slot> = (0..size)
            .map(|i| {
                let env = domains::make(domain).expect("the domain was checked at start");
                let obs = vec![0.0; env.spec().obs_dim];
                Slot {
                    env,
                    next_seed: seed.wrapping_add(i as u64),
                    running: false,
                    obs,
                    reward: 0.0,
                    terminated: false,
                    truncated: false,
                }
            })
            .collect();
        let act_dim = slots[0].env.spec().act_dim;
        World {
            slots,
            vector: num_envs.is_some(),
            joined: false,
            started: false,
            action: vec![0.0; size * act_dim],
        }
    }

    fn spec(&self) -> &EnvSpec {
        self.slots[0].env.spec()
    }

    fn size(&self) -> usize {
        self.slots.len()
    }

    /// Ends the episodes: the next step starts new ones (slot i seeded with `seed + i` where
    /// given).
    fn restart(&mut self, seed: Option<u64>) {
        for (i, slot) in self.slots.iter_mut().enumerate() {
            if let Some(seed) = seed {
                slot.next_seed = seed.wrapping_add(i as u64);
            }
            slot.running = false;
        }
        self.started = false;
    }

    /// A tensor's shape in this world: a vector world's tensors lead with its size.
    fn shape(&self, dims: &[usize]) -> Vec<i32> {
        let lead = self.vector.then_some(self.size());
        lead.iter().chain(dims).map(|&d| d as i32).collect()
    }

    fn observation_uids(&self) -> std::ops::RangeInclusive<u64> {
        OBSERVATION..=if self.vector {
            TRUNCATED
        } else {
            MAX_EPISODE_STEPS
        }
    }

    fn specs(&self) -> pb::ActionObservationSpecs {
        let spec = self.spec();
        let repeat = |values: &[f32]| values.repeat(self.size());
        let bounded = |name: &str, low: &[f32], high: &[f32]| pb::TensorSpec {
            name: name.to_string(),
            shape: self.shape(&[low.len()]),
            dtype: pb::DataType::Float as i32,
            min: Some(float_bound(repeat(low))),
            max: Some(float_bound(repeat(high))),
        };
        let per_env = |name: &str, dtype: pb::DataType| pb::TensorSpec {
            name: name.to_string(),
            shape: self.shape(&[]),
            dtype: dtype as i32,
            min: None,
            max: None,
        };
        let scalar = |name: &str, dtype: pb::DataType| pb::TensorSpec {
            name: name.to_string(),
            shape: Vec::new(),
            dtype: dtype as i32,
            min: None,
            max: None,
        };
        let mut observations = HashMap::from([
            (
                OBSERVATION,
                bounded("observation", &spec.obs_low, &spec.obs_high),
            ),
            (REWARD, per_env("reward", pb::DataType::Double)),
            (DISCOUNT, per_env("discount", pb::DataType::Double)),
            (ENV_ID, scalar("env_id", pb::DataType::String)),
            (
                MAX_EPISODE_STEPS,
                scalar("max_episode_steps", pb::DataType::Int64),
            ),
        ]);
        if self.vector {
            observations.insert(TERMINATED, per_env("terminated", pb::DataType::Bool));
            observations.insert(TRUNCATED, per_env("truncated", pb::DataType::Bool));
        }
        pb::ActionObservationSpecs {
            actions: HashMap::from([(
                ACTION,
                bounded("action", &spec.action_low, &spec.action_high),
            )]),
            observations,
        }
    }

    /// Reads the step's action into `self.action`, refusing anything but the spec's.
    fn read_action(&mut self, actions: &HashMap<u64, pb::Tensor>) -> Result<(), Refusal> {
        let mut unknown: Vec<u64> = actions.keys().copied().filter(|&u| u != ACTION).collect();
        if !unknown.is_empty() {
            unknown.sort_unstable();
            return refuse(
                INVALID_ARGUMENT,
                format!("unknown action uids {unknown:?}; the action is uid {ACTION}"),
            );
        }
        let Some(tensor) = actions.get(&ACTION) else {
            return refuse(
                INVALID_ARGUMENT,
                format!("the step has no action (uid {ACTION})"),
            );
        };
        let act_dim = self.spec().act_dim;
        let shape = self.shape(&[act_dim]);
        let values: Vec<f32> = match &tensor.payload {
            Some(pb::tensor::Payload::Floats(a)) => a.array.clone(),
            Some(pb::tensor::Payload::Doubles(a)) => a.array.iter().map(|&v| v as f32).collect(),
            _ => {
                return refuse(
                    INVALID_ARGUMENT,
                    "the action must be FLOAT (floats) or DOUBLE (doubles)",
                );
            }
        };
        if tensor.shape != shape || values.len() != self.action.len() {
            return refuse(
                INVALID_ARGUMENT,
                format!(
                    "the action has shape {:?} and {} values; the spec's shape is {shape:?}",
                    tensor.shape,
                    values.len()
                ),
            );
        }
        let spec = self.spec();
        for (k, &v) in values.iter().enumerate() {
            let i = k % act_dim;
            let at = if self.vector {
                format!("action[{}][{i}]", k / act_dim)
            } else {
                format!("action[{i}]")
            };
            let (low, high) = (spec.action_low[i], spec.action_high[i]);
            let slack = BOUND_TOLERANCE * (high - low);
            if !v.is_finite() {
                return refuse(
                    INVALID_ARGUMENT,
                    format!("{at} is {v}; every value must be finite"),
                );
            }
            if v < low - slack || v > high + slack {
                return refuse(
                    INVALID_ARGUMENT,
                    format!("{at} is {v}, outside [{low}, {high}]"),
                );
            }
        }
        self.action.copy_from_slice(&values);
        Ok(())
    }

    fn step(&mut self, request: &pb::StepRequest) -> Result<pb::StepResponse, Refusal> {
        let known = self.observation_uids();
        if let Some(uid) = request
            .requested_observations
            .iter()
            .find(|&u| !known.contains(u))
        {
            return refuse(
                INVALID_ARGUMENT,
                format!(
                    "unknown observation uid {uid}; known: {:?}",
                    known.collect::<Vec<_>>()
                ),
            );
        }
        let state = if self.vector {
            self.step_vector(&request.actions)?;
            pb::EnvironmentStateType::Running
        } else {
            let slot = &mut self.slots[0];
            if !slot.running {
                // Actions are ignored: the step starts an episode.
                slot.start(1)?;
                pb::EnvironmentStateType::Running
            } else {
                self.read_action(&request.actions)?;
                let slot = &mut self.slots[0];
                slot.step(&self.action)?;
                if slot.terminated {
                    pb::EnvironmentStateType::Terminated
                } else if slot.truncated {
                    pb::EnvironmentStateType::Interrupted
                } else {
                    pb::EnvironmentStateType::Running
                }
            }
        };
        let observations = request
            .requested_observations
            .iter()
            .map(|&uid| (uid, self.observe(uid)))
            .collect();
        Ok(pb::StepResponse {
            state: state as i32,
            observations,
        })
    }

    /// Steps every slot of a vector world, on as many threads as there are cores: the first
    /// step after joining or a reset starts them all, ignoring the actions.
    fn step_vector(&mut self, actions: &HashMap<u64, pb::Tensor>) -> Result<(), Refusal> {
        let stride = self.size() as u64;
        if !self.started {
            for slot in &mut self.slots {
                slot.start(stride)?;
            }
            self.started = true;
            return Ok(());
        }
        self.read_action(actions)?;
        let act_dim = self.spec().act_dim;
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        let per_thread = self.size().div_ceil(threads);
        if per_thread == self.size() {
            for (slot, action) in self.slots.iter_mut().zip(self.action.chunks(act_dim)) {
                slot.advance(action, stride)?;
            }
            return Ok(());
        }
        std::thread::scope(|scope| {
            let work: Vec<_> = self
                .slots
                .chunks_mut(per_thread)
                .zip(self.action.chunks(per_thread * act_dim))
                .map(|(slots, actions)| {
                    scope.spawn(move || {
                        slots
                            .iter_mut()
                            .zip(actions.chunks(act_dim))
                            .try_for_each(|(slot, action)| slot.advance(action, stride))
                    })
                })
                .collect();
            work.into_iter()
                .try_for_each(|w| w.join().expect("a domain's step panicked"))
        })
    }

    fn observe(&self, uid: u64) -> pb::Tensor {
        let spec = self.spec();
        let per_env = |value: fn(&Slot) -> f64| {
            let values: Vec<f64> = self.slots.iter().map(value).collect();
            tensor::doubles(&values, self.shape(&[]))
        };
        let flags = |flag: fn(&Slot) -> bool| pb::Tensor {
            shape: self.shape(&[]),
            payload: Some(pb::tensor::Payload::Bools(pb::tensor::BoolArray {
                array: self.slots.iter().map(flag).collect(),
            })),
        };
        match uid {
            OBSERVATION if self.vector => {
                let values: Vec<f32> = self.slots.iter().flat_map(|s| s.obs.clone()).collect();
                pb::Tensor {
                    shape: self.shape(&[spec.obs_dim]),
                    ..tensor::floats(&values)
                }
            }
            OBSERVATION => tensor::floats(&self.slots[0].obs),
            REWARD => per_env(|s| s.reward),
            DISCOUNT => per_env(|s| if s.terminated { 0.0 } else { 1.0 }),
            ENV_ID => tensor::string(spec.name),
            TERMINATED => flags(|s| s.terminated),
            TRUNCATED => flags(|s| s.truncated),
            _ => tensor::scalar_i64(i64::from(spec.episode_len)),
        }
    }
}

fn float_bound(values: Vec<f32>) -> pb::tensor_spec::Value {
    pb::tensor_spec::Value {
        payload: Some(pb::tensor_spec::value::Payload::Floats(
            pb::tensor::FloatArray { array: values },
        )),
    }
}

/// The largest `num_envs` a world may have.
const MAX_NUM_ENVS: usize = 1024;

/// A request's settings: `seed` everywhere, `num_envs` where a world is created.
#[derive(Default)]
struct Settings {
    seed: Option<u64>,
    num_envs: Option<usize>,
}

fn read_settings(
    settings: &HashMap<String, pb::Tensor>,
    known: &[&str],
) -> Result<Settings, Refusal> {
    let mut unknown: Vec<&String> = settings
        .keys()
        .filter(|k| !known.contains(&k.as_str()))
        .collect();
    if !unknown.is_empty() {
        unknown.sort();
        return refuse(
            INVALID_ARGUMENT,
            format!("unknown settings {unknown:?}; known here: {known:?}"),
        );
    }
    let integer = |name: &str, min: i64, max: i64| -> Result<Option<i64>, Refusal> {
        let Some(tensor) = settings.get(name) else {
            return Ok(None);
        };
        match tensor::read_integer(tensor) {
            Some(v) if (min..=max).contains(&v) => Ok(Some(v)),
            Some(v) if max == i64::MAX => refuse(
                INVALID_ARGUMENT,
                format!("setting '{name}' is {v}; it must be >= {min}"),
            ),
            Some(v) => refuse(
                INVALID_ARGUMENT,
                format!("setting '{name}' is {v}; it must be in {min}..={max}"),
            ),
            None => refuse(
                INVALID_ARGUMENT,
                format!("setting '{name}' is not an integer"),
            ),
        }
    };
    Ok(Settings {
        seed: integer("seed", 0, i64::MAX)?.map(|v| v as u64),
        num_envs: integer("num_envs", 1, MAX_NUM_ENVS as i64)?.map(|v| v as usize),
    })
}

type Worlds = Arc<Mutex<HashMap<String, Arc<Mutex<World>>>>>;

/// dm_env_rpc's Environment service over one built-in domain.
#[derive(Clone)]
pub struct DomainServer {
    domain: String,
    seed: u64,
    worlds: Worlds,
    created: Arc<AtomicU64>,
}

impl DomainServer {
    /// A server of `domain` (one of [`domains::DOMAINS`]); worlds created without a `seed`
    /// setting start from `seed`.
    pub fn new(domain: &str, seed: u64) -> anyhow::Result<DomainServer> {
        anyhow::ensure!(
            domains::make(domain).is_some(),
            "unknown domain '{domain}'; known: {}",
            domains::DOMAINS.join(", ")
        );
        Ok(DomainServer {
            domain: domain.to_string(),
            seed,
            worlds: Arc::default(),
            created: Arc::default(),
        })
    }

    fn world(&self, name: &str) -> Result<Arc<Mutex<World>>, Refusal> {
        let worlds = self.worlds.lock().expect("world map lock");
        match worlds.get(name) {
            Some(world) => Ok(world.clone()),
            None => {
                let mut known: Vec<&String> = worlds.keys().collect();
                known.sort();
                refuse(NOT_FOUND, format!("no world '{name}'; known: {known:?}"))
            }
        }
    }

    /// Answers one request of a connection that has joined `joined` (if any) and created
    /// `created`.
    fn handle(
        &self,
        request: Request,
        joined: &mut Option<Arc<Mutex<World>>>,
        created: &mut Vec<String>,
    ) -> Result<Response, Refusal> {
        match request {
            Request::CreateWorld(create) => {
                let settings = read_settings(&create.settings, &["seed", "num_envs"])?;
                let seed = settings.seed.unwrap_or(self.seed);
                let n = self.created.fetch_add(1, Ordering::Relaxed);
                let name = format!("{}-{n}", self.domain);
                let world = Arc::new(Mutex::new(World::new(
                    &self.domain,
                    seed,
                    settings.num_envs,
                )));
                self.worlds
                    .lock()
                    .expect("world map lock")
                    .insert(name.clone(), world);
                created.push(name.clone());
                Ok(Response::CreateWorld(pb::CreateWorldResponse {
                    world_name: name,
                }))
            }
            Request::JoinWorld(join) => {
                if joined.is_some() {
                    return refuse(
                        FAILED_PRECONDITION,
                        "this connection has joined a world already; leave it first",
                    );
                }
                let seed = read_settings(&join.settings, &["seed"])?.seed;
                let world = self.world(&join.world_name)?;
                let specs = {
                    let mut w = lock(&world)?;
                    if w.joined {
                        return refuse(
                            FAILED_PRECONDITION,
                            format!(
                                "world '{}' has an agent already (one per world)",
                                join.world_name
                            ),
                        );
                    }
                    w.joined = true;
                    w.restart(seed);
                    w.specs()
                };
                *joined = Some(world);
                Ok(Response::JoinWorld(pb::JoinWorldResponse {
                    specs: Some(specs),
                }))
            }
            Request::DestroyWorld(destroy) => {
                let mut worlds = self.worlds.lock().expect("world map lock");
                match worlds.get(&destroy.world_name) {
                    None => refuse(NOT_FOUND, format!("no world '{}'", destroy.world_name)),
                    Some(w) if lock(w)?.joined => refuse(
                        FAILED_PRECONDITION,
                        "an agent is in the world; it must leave first",
                    ),
                    Some(_) => {
                        worlds.remove(&destroy.world_name);
                        Ok(Response::DestroyWorld(pb::DestroyWorldResponse {}))
                    }
                }
            }
            Request::ResetWorld(reset) => {
                let seed = read_settings(&reset.settings, &["seed"])?.seed;
                let world = self.world(&reset.world_name)?;
                lock(&world)?.restart(seed);
                Ok(Response::ResetWorld(pb::ResetWorldResponse {}))
            }
            Request::Extension(_) => refuse(UNIMPLEMENTED, "this server has no extensions"),
            Request::Step(step) => lock(joined_world(joined)?)?.step(&step).map(Response::Step),
            Request::Reset(reset) => {
                let seed = read_settings(&reset.settings, &["seed"])?.seed;
                let mut world = lock(joined_world(joined)?)?;
                world.restart(seed);
                Ok(Response::Reset(pb::ResetResponse {
                    specs: Some(world.specs()),
                }))
            }
            Request::LeaveWorld(_) => {
                lock(joined_world(joined)?)?.joined = false;
                *joined = None;
                Ok(Response::LeaveWorld(pb::LeaveWorldResponse {}))
            }
        }
    }

    /// Frees what a finished connection held: its world is left, the worlds it made destroyed.
    fn release(&self, joined: Option<Arc<Mutex<World>>>, created: Vec<String>) {
        if let Some(world) = joined
            && let Ok(mut w) = world.lock()
        {
            w.joined = false;
        }
        let mut worlds = self.worlds.lock().expect("world map lock");
        for name in created {
            worlds.remove(&name);
        }
    }
}

type ResponseStream = Pin<Box<dyn Stream<Item = Result<pb::EnvironmentResponse, Status>> + Send>>;

#[tonic::async_trait]
impl Environment for DomainServer {
    type ProcessStream = ResponseStream;

    async fn process(
        &self,
        request: GrpcRequest<Streaming<pb::EnvironmentRequest>>,
    ) -> Result<GrpcResponse<ResponseStream>, Status> {
        let mut connection = Connection {
            server: self.clone(),
            joined: None,
            created: Vec::new(),
        };
        // Answered as the response stream is polled, on the connection's own task: no hand-off
        // between tasks per step (the domains' steps take microseconds to a millisecond).
        let answers = request
            .into_inner()
            .map_while(move |request| request.ok().map(|r| Ok(connection.answer(r))));
        Ok(GrpcResponse::new(Box::pin(answers)))
    }
}

/// One client's stream: the world it joined and the worlds it created, freed when it ends.
struct Connection {
    server: DomainServer,
    joined: Option<Arc<Mutex<World>>>,
    created: Vec<String>,
}

impl Connection {
    fn answer(&mut self, request: pb::EnvironmentRequest) -> pb::EnvironmentResponse {
        let payload = match request.payload {
            None => Err(Refusal(INVALID_ARGUMENT, "an empty request".into())),
            Some(request) => self
                .server
                .handle(request, &mut self.joined, &mut self.created),
        };
        let payload = payload.unwrap_or_else(|Refusal(code, message)| {
            Response::Error(ErrorStatus {
                code,
                message,
                details: Vec::new(),
            })
        });
        pb::EnvironmentResponse {
            payload: Some(payload),
        }
    }
}

impl Drop for Connection {
    fn drop(&mut self) {
        self.server
            .release(self.joined.take(), std::mem::take(&mut self.created));
    }
}

/// Serves `domain` on `listen` until the process ends, printing `listening on ADDR` once bound.
pub async fn run(domain: &str, listen: SocketAddr, seed: u64) -> anyhow::Result<()> {
    let server = DomainServer::new(domain, seed)?;
    let listener = tokio::net::TcpListener::bind(listen)
        .await
        .map_err(|e| anyhow::anyhow!("cannot listen on {listen}: {e}"))?;
    println!("listening on {}", listener.local_addr()?);
    serve_on(server, listener).await
}

/// Serves on a bound listener until the process ends.
pub(crate) async fn serve_on(
    server: DomainServer,
    listener: tokio::net::TcpListener,
) -> anyhow::Result<()> {
    tonic::transport::Server::builder()
        .add_service(EnvironmentServer::new(server))
        .serve_with_incoming(
            // Answers go out at once: an env step is one small message each way.
            tokio_stream::wrappers::TcpListenerStream::new(listener).map(|stream| {
                if let Ok(stream) = &stream {
                    let _ = stream.set_nodelay(true);
                }
                stream
            }),
        )
        .await?;
    Ok(())
}

#[cfg(test)]
mod tests;
