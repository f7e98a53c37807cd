//! `prac env-serve`: a built-in domain served over dm_env_rpc, with the same offer
//! `prac_client.env_server` makes for gymnasium's envs (docs/environments.md):
//!
//! - worlds: each CreateWorld makes one environment of the domain (setting `seed`, INT64: its
//!   first episode's seed, the server's `--seed` otherwise); one agent per world; the worlds a
//!   connection created are destroyed when it ends;
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
use crate::domains::{self, Env};
use pb::environment_request::Payload as Request;
use pb::environment_response::Payload as Response;
use pb::environment_server::{Environment, EnvironmentServer};

const ACTION: u64 = 1;
const OBSERVATION: u64 = 1;
const REWARD: u64 = 2;
const DISCOUNT: u64 = 3;
const ENV_ID: u64 = 4;
const MAX_EPISODE_STEPS: u64 = 5;
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

/// One environment and the state of its episode.
struct World {
    env: Box<dyn Env>,
    next_seed: u64,
    joined: bool,
    running: bool,
    obs: Vec<f32>,
    action: Vec<f32>,
    reward: f64,
    discount: f64,
}

impl World {
    fn new(domain: &str, seed: u64) -> World {
        let env = domains::make(domain).expect("the domain was checked at start");
        let spec = env.spec();
        World {
            obs: vec![0.0; spec.obs_dim],
            action: vec![0.0; spec.act_dim],
            env,
            next_seed: seed,
            joined: false,
            running: false,
            reward: 0.0,
            discount: 1.0,
        }
    }

    /// Ends the episode: the next step starts one (seeded with `seed` where given).
    fn restart(&mut self, seed: Option<u64>) {
        if let Some(seed) = seed {
            self.next_seed = seed;
        }
        self.running = false;
    }

    fn specs(&self) -> pb::ActionObservationSpecs {
        let spec = self.env.spec();
        let bounded = |name: &str, low: &[f32], high: &[f32]| pb::TensorSpec {
            name: name.to_string(),
            shape: vec![low.len() as i32],
            dtype: pb::DataType::Float as i32,
            min: Some(float_bound(low)),
            max: Some(float_bound(high)),
        };
        let scalar = |name: &str, dtype: pb::DataType| pb::TensorSpec {
            name: name.to_string(),
            shape: Vec::new(),
            dtype: dtype as i32,
            min: None,
            max: None,
        };
        pb::ActionObservationSpecs {
            actions: HashMap::from([(
                ACTION,
                bounded("action", &spec.action_low, &spec.action_high),
            )]),
            observations: HashMap::from([
                (
                    OBSERVATION,
                    bounded("observation", &spec.obs_low, &spec.obs_high),
                ),
                (REWARD, scalar("reward", pb::DataType::Double)),
                (DISCOUNT, scalar("discount", pb::DataType::Double)),
                (ENV_ID, scalar("env_id", pb::DataType::String)),
                (
                    MAX_EPISODE_STEPS,
                    scalar("max_episode_steps", pb::DataType::Int64),
                ),
            ]),
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
        let n = self.action.len();
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
        if tensor.shape != [n as i32] || values.len() != n {
            return refuse(
                INVALID_ARGUMENT,
                format!(
                    "the action has shape {:?} and {} values; the spec's shape is [{n}]",
                    tensor.shape,
                    values.len()
                ),
            );
        }
        let spec = self.env.spec();
        for (i, &v) in values.iter().enumerate() {
            let (low, high) = (spec.action_low[i], spec.action_high[i]);
            let slack = BOUND_TOLERANCE * (high - low);
            if !v.is_finite() {
                return refuse(
                    INVALID_ARGUMENT,
                    format!("action[{i}] is {v}; every value must be finite"),
                );
            }
            if v < low - slack || v > high + slack {
                return refuse(
                    INVALID_ARGUMENT,
                    format!("action[{i}] is {v}, outside [{low}, {high}]"),
                );
            }
        }
        self.action.copy_from_slice(&values);
        Ok(())
    }

    fn step(&mut self, request: &pb::StepRequest) -> Result<pb::StepResponse, Refusal> {
        if let Some(uid) = request
            .requested_observations
            .iter()
            .find(|&&u| !(OBSERVATION..=MAX_EPISODE_STEPS).contains(&u))
        {
            return refuse(
                INVALID_ARGUMENT,
                format!(
                    "unknown observation uid {uid}; known: {:?}",
                    (OBSERVATION..=MAX_EPISODE_STEPS).collect::<Vec<_>>()
                ),
            );
        }
        let state = if !self.running {
            // Actions are ignored: the step starts an episode.
            let seed = self.next_seed;
            self.env
                .reset(seed, &mut self.obs)
                .map_err(|e| Refusal(INTERNAL, e.to_string()))?;
            self.next_seed = seed.wrapping_add(1);
            (self.running, self.reward, self.discount) = (true, 0.0, 1.0);
            pb::EnvironmentStateType::Running
        } else {
            self.read_action(&request.actions)?;
            let t = self
                .env
                .step(&self.action, &mut self.obs)
                .map_err(|e| Refusal(INVALID_ARGUMENT, e.to_string()))?;
            self.reward = t.reward;
            self.discount = if t.terminated { 0.0 } else { 1.0 };
            self.running = !(t.terminated || t.truncated);
            if t.terminated {
                pb::EnvironmentStateType::Terminated
            } else if t.truncated {
                pb::EnvironmentStateType::Interrupted
            } else {
                pb::EnvironmentStateType::Running
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

    fn observe(&self, uid: u64) -> pb::Tensor {
        let spec = self.env.spec();
        match uid {
            OBSERVATION => tensor::floats(&self.obs),
            REWARD => tensor::doubles(&[self.reward], Vec::new()),
            DISCOUNT => tensor::doubles(&[self.discount], Vec::new()),
            ENV_ID => tensor::string(spec.name),
            _ => tensor::scalar_i64(i64::from(spec.episode_len)),
        }
    }
}

fn float_bound(values: &[f32]) -> pb::tensor_spec::Value {
    pb::tensor_spec::Value {
        payload: Some(pb::tensor_spec::value::Payload::Floats(
            pb::tensor::FloatArray {
                array: values.to_vec(),
            },
        )),
    }
}

/// The `seed` setting, the only one there is; None where it is not given.
fn seed_setting(settings: &HashMap<String, pb::Tensor>) -> Result<Option<u64>, Refusal> {
    let mut unknown: Vec<&String> = settings.keys().filter(|k| *k != "seed").collect();
    if !unknown.is_empty() {
        unknown.sort();
        return refuse(
            INVALID_ARGUMENT,
            format!("unknown settings {unknown:?}; known: [\"seed\"]"),
        );
    }
    let Some(tensor) = settings.get("seed") else {
        return Ok(None);
    };
    match tensor::read_integer(tensor) {
        Some(seed) if seed >= 0 => Ok(Some(seed as u64)),
        Some(seed) => refuse(
            INVALID_ARGUMENT,
            format!("setting 'seed' is {seed}; it must be >= 0"),
        ),
        None => refuse(INVALID_ARGUMENT, "setting 'seed' is not an integer"),
    }
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
                let seed = seed_setting(&create.settings)?.unwrap_or(self.seed);
                let n = self.created.fetch_add(1, Ordering::Relaxed);
                let name = format!("{}-{n}", self.domain);
                let world = Arc::new(Mutex::new(World::new(&self.domain, seed)));
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
                let seed = seed_setting(&join.settings)?;
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
                let seed = seed_setting(&reset.settings)?;
                let world = self.world(&reset.world_name)?;
                lock(&world)?.restart(seed);
                Ok(Response::ResetWorld(pb::ResetWorldResponse {}))
            }
            Request::Extension(_) => refuse(UNIMPLEMENTED, "this server has no extensions"),
            Request::Step(step) => lock(joined_world(joined)?)?.step(&step).map(Response::Step),
            Request::Reset(reset) => {
                let seed = seed_setting(&reset.settings)?;
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
