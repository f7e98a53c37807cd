//! An environment played over dm_env_rpc: one world of a server, joined over one stream.

use std::collections::HashMap;
use std::sync::OnceLock;
use std::time::Duration;

use anyhow::{Context, bail};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Streaming;

use super::tensor;
use super::wire::dm_env_rpc::v1 as pb;
use crate::domains::{Env, EnvError, EnvSpec, Scene, Transition, clip_action};
use pb::environment_client::EnvironmentClient;
use pb::environment_request::Payload as Request;
use pb::environment_response::Payload as Response;

/// How long a request may wait for its answer before the server counts as gone.
const ANSWER_PATIENCE: Duration = Duration::from_secs(60);
/// Observations larger than gRPC's default 4 MB are fine; prac's networks set the real limit.
const MAX_MESSAGE_BYTES: usize = 64 << 20;

/// The uids (with names and sizes) prac uses from a world's specs.
#[derive(Clone, Debug)]
pub(crate) struct RemoteSpecs {
    observation: (u64, String, usize),
    reward: u64,
    action: (u64, String, usize),
    action_is_double: bool,
    env_id: Option<u64>,
    max_episode_steps: Option<u64>,
}

/// The observation and action bounds of a world's specs, as the [`EnvSpec`] takes them.
#[derive(Clone, Debug)]
pub(crate) struct Bounds {
    obs_low: Vec<f32>,
    obs_high: Vec<f32>,
    action_low: Vec<f32>,
    action_high: Vec<f32>,
}

impl RemoteSpecs {
    /// Reads the specs a world answered JoinWorld with, refusing what prac cannot train on.
    pub(crate) fn read(
        specs: &pb::ActionObservationSpecs,
    ) -> Result<(RemoteSpecs, Bounds), String> {
        let names = |m: &HashMap<u64, pb::TensorSpec>| {
            let mut n: Vec<String> = m.values().map(|s| s.name.clone()).collect();
            n.sort();
            n.join(", ")
        };
        if specs.actions.len() != 1 {
            return Err(format!(
                "prac trains on one action tensor; the environment has {} ({})",
                specs.actions.len(),
                names(&specs.actions)
            ));
        }
        let (&action_uid, action) = specs.actions.iter().next().expect("one action");
        let action_is_double = match action.dtype() {
            pb::DataType::Float => false,
            pb::DataType::Double => true,
            other => {
                return Err(format!(
                    "the action '{}' is {}: prac trains on bounded continuous (FLOAT or DOUBLE) \
                     actions, not discrete ones",
                    action.name,
                    other.as_str_name()
                ));
            }
        };
        let act_dim = tensor::element_count(&action.name, &action.shape)?;
        let (Some(low), Some(high)) = (
            tensor::bound(&action.name, action.min.as_ref(), act_dim)?,
            tensor::bound(&action.name, action.max.as_ref(), act_dim)?,
        ) else {
            return Err(format!(
                "the action '{}' has no min/max bounds: prac trains on bounded actions only",
                action.name
            ));
        };
        if let Some(i) =
            (0..act_dim).find(|&i| !low[i].is_finite() || !high[i].is_finite() || low[i] >= high[i])
        {
            return Err(format!(
                "the action '{}'[{i}] is bounded by [{}, {}]: prac trains on finite bounds with \
                 min < max",
                action.name, low[i], high[i]
            ));
        }

        let find = |name: &str| {
            specs
                .observations
                .iter()
                .find(|(_, s)| s.name == name)
                .map(|(&uid, s)| (uid, s))
        };
        let numeric = |s: &pb::TensorSpec| {
            !matches!(
                s.dtype(),
                pb::DataType::String | pb::DataType::Proto | pb::DataType::InvalidDataType
            )
        };
        const NOT_OBSERVATIONS: [&str; 4] = ["reward", "discount", "env_id", "max_episode_steps"];
        let observation = match find("observation") {
            Some(found) => found,
            None => {
                let candidates: Vec<(u64, &pb::TensorSpec)> = specs
                    .observations
                    .iter()
                    .filter(|(_, s)| numeric(s) && !NOT_OBSERVATIONS.contains(&s.name.as_str()))
                    .map(|(&uid, s)| (uid, s))
                    .collect();
                match candidates.as_slice() {
                    [one] => *one,
                    _ => {
                        return Err(format!(
                            "no observation named 'observation' and not exactly one other \
                             numeric observation to take instead (the environment has: {})",
                            names(&specs.observations)
                        ));
                    }
                }
            }
        };
        if !numeric(observation.1) {
            return Err(format!(
                "the observation '{}' is not numeric",
                observation.1.name
            ));
        }
        let obs_dim = tensor::element_count(&observation.1.name, &observation.1.shape)?;
        let obs_bound = |value, fill: f32| -> Result<Vec<f32>, String> {
            Ok(tensor::bound(&observation.1.name, value, obs_dim)?
                .map(|v| v.iter().map(|&x| x as f32).collect())
                .unwrap_or_else(|| vec![fill; obs_dim]))
        };
        let Some((reward, _)) = find("reward") else {
            return Err(format!(
                "the environment observes no scalar 'reward' (it has: {})",
                names(&specs.observations)
            ));
        };
        let bounds = Bounds {
            obs_low: obs_bound(observation.1.min.as_ref(), f32::NEG_INFINITY)?,
            obs_high: obs_bound(observation.1.max.as_ref(), f32::INFINITY)?,
            action_low: low.iter().map(|&x| x as f32).collect(),
            action_high: high.iter().map(|&x| x as f32).collect(),
        };
        let specs = RemoteSpecs {
            observation: (observation.0, observation.1.name.clone(), obs_dim),
            reward,
            action: (action_uid, action.name.clone(), act_dim),
            action_is_double,
            env_id: find("env_id").map(|(uid, _)| uid),
            max_episode_steps: find("max_episode_steps").map(|(uid, _)| uid),
        };
        Ok((specs, bounds))
    }
}

/// The runtime of every link: one worker thread keeps each connection polled (answering the
/// server's HTTP/2 pings) while the synchronous trainer is busy elsewhere, e.g. while the
/// evaluation world sits idle between evaluations.
fn runtime() -> anyhow::Result<&'static tokio::runtime::Runtime> {
    static RUNTIME: OnceLock<tokio::runtime::Runtime> = OnceLock::new();
    if let Some(runtime) = RUNTIME.get() {
        return Ok(runtime);
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("prac-env-rpc")
        .enable_all()
        .build()?;
    Ok(RUNTIME.get_or_init(|| runtime))
}

/// One bidirectional `Process` stream (the trainer is synchronous: calls block on it).
struct Link {
    runtime: &'static tokio::runtime::Runtime,
    requests: mpsc::Sender<pb::EnvironmentRequest>,
    responses: Streaming<pb::EnvironmentResponse>,
    addr: String,
}

impl Link {
    /// Opens the stream with its first request already queued: a server may send nothing, not
    /// even the response headers the call waits for, before it has a request to answer.
    fn open(addr: &str, first: Request) -> anyhow::Result<(Link, Response)> {
        let runtime = runtime()?;
        let (requests, responses) = runtime.block_on(async {
            let channel = crate::client::channel(addr).await?;
            let mut client = EnvironmentClient::new(channel)
                .max_decoding_message_size(MAX_MESSAGE_BYTES)
                .max_encoding_message_size(MAX_MESSAGE_BYTES);
            let (tx, rx) = mpsc::channel(4);
            tx.send(pb::EnvironmentRequest {
                payload: Some(first),
            })
            .await
            .expect("the receiver is alive");
            let responses = client
                .process(ReceiverStream::new(rx))
                .await
                .with_context(|| format!("{addr} does not serve dm_env_rpc.v1.Environment"))?
                .into_inner();
            anyhow::Ok((tx, responses))
        })?;
        let mut link = Link {
            runtime,
            requests,
            responses,
            addr: addr.to_string(),
        };
        let answer = link.answer().map_err(anyhow::Error::msg)?;
        Ok((link, answer))
    }

    /// Sends one request and waits for its answer; an error answer, a closed stream or a silent
    /// server is an error naming the server.
    fn call(&mut self, request: Request) -> Result<Response, String> {
        let request = pb::EnvironmentRequest {
            payload: Some(request),
        };
        if self.runtime.block_on(self.requests.send(request)).is_err() {
            return Err(self.gone());
        }
        self.answer()
    }

    fn gone(&self) -> String {
        format!(
            "the environment server at {} closed the connection",
            self.addr
        )
    }

    /// Waits for the answer to the oldest unanswered request.
    fn answer(&mut self) -> Result<Response, String> {
        let gone = self.gone();
        let Link {
            runtime,
            responses,
            addr,
            ..
        } = self;
        runtime.block_on(async {
            match tokio::time::timeout(ANSWER_PATIENCE, responses.message()).await {
                Err(_) => Err(format!(
                    "the environment server at {addr} did not answer within {} s",
                    ANSWER_PATIENCE.as_secs()
                )),
                Ok(Err(status)) => Err(format!(
                    "the environment server at {addr} failed: {} ({:?})",
                    status.message(),
                    status.code()
                )),
                Ok(Ok(None)) => Err(gone),
                Ok(Ok(Some(answer))) => match answer.payload {
                    Some(Response::Error(status)) => Err(format!(
                        "the environment server at {addr} refused the request: {} (code {})",
                        status.message, status.code
                    )),
                    Some(payload) => Ok(payload),
                    None => Err(format!(
                        "the environment server at {addr} sent an empty answer"
                    )),
                },
            }
        })
    }

    fn step(
        &mut self,
        actions: HashMap<u64, pb::Tensor>,
        requested: Vec<u64>,
    ) -> Result<pb::StepResponse, String> {
        match self.call(Request::Step(pb::StepRequest {
            actions,
            requested_observations: requested,
        }))? {
            Response::Step(step) => Ok(step),
            _ => Err(format!(
                "the environment server at {} answered a step with something else",
                self.addr
            )),
        }
    }
}

/// An [`Env`] in a world of a dm_env_rpc server. Each instance creates its own world (seeded
/// with the `seed` world setting) and leaves and destroys it when dropped.
pub struct RemoteEnv {
    link: Link,
    world: String,
    specs: RemoteSpecs,
    spec: EnvSpec,
    clipped: Vec<f32>,
    running: bool,
}

fn seed_setting(seed: u64) -> HashMap<String, pb::Tensor> {
    // Seeds travel as INT64; gymnasium takes any non-negative int.
    HashMap::from([(
        "seed".to_string(),
        tensor::scalar_i64((seed & (i64::MAX as u64)) as i64),
    )])
}

impl RemoteEnv {
    /// Connects to `addr`, creates and joins a world, and reads its specs. The environment's
    /// name (its `env_id` observation, else the world's name) becomes the spec's name.
    pub fn connect(addr: &str, seed: u64) -> anyhow::Result<RemoteEnv> {
        let (mut link, created) = Link::open(
            addr,
            Request::CreateWorld(pb::CreateWorldRequest {
                settings: seed_setting(seed),
            }),
        )?;
        let world = match created {
            Response::CreateWorld(created) => created.world_name,
            _ => bail!("{addr} answered CreateWorld with something else"),
        };
        let specs = match link
            .call(Request::JoinWorld(pb::JoinWorldRequest {
                world_name: world.clone(),
                settings: HashMap::new(),
            }))
            .map_err(anyhow::Error::msg)?
        {
            Response::JoinWorld(joined) => joined.specs.unwrap_or_default(),
            _ => bail!("{addr} answered JoinWorld with something else"),
        };
        let (specs, bounds) = RemoteSpecs::read(&specs)
            .map_err(|e| anyhow::anyhow!("the environment at {addr} (world {world}): {e}"))?;
        // The first step starts an episode; it also carries the environment's name and limit.
        let requested: Vec<u64> = specs
            .env_id
            .iter()
            .chain(&specs.max_episode_steps)
            .copied()
            .collect();
        let first = link
            .step(HashMap::new(), requested)
            .map_err(anyhow::Error::msg)?;
        let env_id = specs
            .env_id
            .and_then(|uid| first.observations.get(&uid))
            .and_then(tensor::read_string)
            .unwrap_or_else(|| world.clone());
        let episode_len = specs
            .max_episode_steps
            .and_then(|uid| first.observations.get(&uid))
            .and_then(tensor::read_integer)
            .and_then(|n| u32::try_from(n).ok())
            .unwrap_or(u32::MAX);
        let spec = EnvSpec {
            // One name per connection for the life of the process, as the built-in domains'
            // names are static.
            name: Box::leak(env_id.into_boxed_str()),
            obs_dim: specs.observation.2,
            act_dim: specs.action.2,
            obs_low: bounds.obs_low,
            obs_high: bounds.obs_high,
            action_low: bounds.action_low,
            action_high: bounds.action_high,
            episode_len,
            control_period: 0.0,
            engine: "dm_env_rpc",
        };
        Ok(RemoteEnv {
            link,
            world,
            clipped: vec![0.0; spec.act_dim],
            running: first.state() == pb::EnvironmentStateType::Running,
            specs,
            spec,
        })
    }

    fn observe(&self, step: &pb::StepResponse, obs: &mut [f32]) -> Result<(), EnvError> {
        let (uid, name, _) = &self.specs.observation;
        let tensor = step.observations.get(uid).ok_or_else(|| {
            EnvError::Remote(format!(
                "the environment server at {} sent no '{name}'",
                self.link.addr
            ))
        })?;
        tensor::read_into(name, tensor, obs).map_err(EnvError::Remote)
    }
}

impl Env for RemoteEnv {
    fn spec(&self) -> &EnvSpec {
        &self.spec
    }

    fn reset(&mut self, seed: u64, obs: &mut [f32]) -> Result<(), EnvError> {
        crate::domains::check_obs_len(&self.spec, obs)?;
        match self.link.call(Request::Reset(pb::ResetRequest {
            settings: seed_setting(seed),
        })) {
            Ok(Response::Reset(_)) => {}
            Ok(_) => {
                return Err(EnvError::Remote(format!(
                    "the environment server at {} answered a reset with something else",
                    self.link.addr
                )));
            }
            Err(e) => return Err(EnvError::Remote(e)),
        }
        let step = self
            .link
            .step(HashMap::new(), vec![self.specs.observation.0])
            .map_err(EnvError::Remote)?;
        if step.state() != pb::EnvironmentStateType::Running {
            return Err(EnvError::Remote(format!(
                "the environment server at {} started an episode in state {}",
                self.link.addr,
                step.state().as_str_name()
            )));
        }
        self.observe(&step, obs)?;
        self.running = true;
        Ok(())
    }

    fn step(&mut self, action: &[f32], obs: &mut [f32]) -> Result<Transition, EnvError> {
        crate::domains::check_obs_len(&self.spec, obs)?;
        if !self.running {
            return Err(EnvError::EpisodeOver);
        }
        clip_action(&self.spec, action, &mut self.clipped)?;
        let (uid, _, _) = self.specs.action;
        let value = if self.specs.action_is_double {
            let values: Vec<f64> = self.clipped.iter().map(|&v| v as f64).collect();
            tensor::doubles(&values, vec![values.len() as i32])
        } else {
            tensor::floats(&self.clipped)
        };
        let step = self
            .link
            .step(
                HashMap::from([(uid, value)]),
                vec![self.specs.observation.0, self.specs.reward],
            )
            .map_err(EnvError::Remote)?;
        self.observe(&step, obs)?;
        let reward = step
            .observations
            .get(&self.specs.reward)
            .ok_or_else(|| {
                EnvError::Remote(format!(
                    "the environment server at {} sent no reward",
                    self.link.addr
                ))
            })
            .and_then(|t| tensor::read_scalar("reward", t).map_err(EnvError::Remote))?;
        let state = step.state();
        self.running = state == pb::EnvironmentStateType::Running;
        Ok(Transition {
            reward,
            terminated: state == pb::EnvironmentStateType::Terminated,
            truncated: state == pb::EnvironmentStateType::Interrupted,
        })
    }

    fn scene(&self) -> Scene {
        Scene {
            shapes: Vec::new(),
            center: (0.0, 0.0),
            width: 1.0,
            height: 1.0,
        }
    }

    fn trace(&self, _predicted: &[f32]) -> Vec<(f64, f64)> {
        Vec::new()
    }
}

impl Drop for RemoteEnv {
    fn drop(&mut self) {
        // Best effort: a server that is already gone has nothing left to free.
        if self
            .link
            .call(Request::LeaveWorld(pb::LeaveWorldRequest {}))
            .is_ok()
        {
            let _ = self
                .link
                .call(Request::DestroyWorld(pb::DestroyWorldRequest {
                    world_name: self.world.clone(),
                }));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pb::tensor::FloatArray;
    use pb::tensor_spec::Value;
    use pb::tensor_spec::value::Payload as Bound;

    fn spec(
        name: &str,
        dtype: pb::DataType,
        shape: Vec<i32>,
        bounds: Option<(f32, f32)>,
    ) -> pb::TensorSpec {
        let value = |v: f32| Value {
            payload: Some(Bound::Floats(FloatArray { array: vec![v] })),
        };
        pb::TensorSpec {
            name: name.to_string(),
            shape,
            dtype: dtype as i32,
            min: bounds.map(|b| value(b.0)),
            max: bounds.map(|b| value(b.1)),
        }
    }

    fn pendulum_like(action: pb::TensorSpec) -> pb::ActionObservationSpecs {
        pb::ActionObservationSpecs {
            actions: HashMap::from([(1, action)]),
            observations: HashMap::from([
                (1, spec("observation", pb::DataType::Float, vec![3], None)),
                (2, spec("reward", pb::DataType::Double, vec![], None)),
                (4, spec("env_id", pb::DataType::String, vec![], None)),
            ]),
        }
    }

    #[test]
    fn a_bounded_continuous_action_and_a_reward_are_read() {
        let action = spec("action", pb::DataType::Float, vec![1], Some((-2.0, 2.0)));
        let (read, bounds) = RemoteSpecs::read(&pendulum_like(action)).unwrap();
        assert_eq!(read.observation.2, 3);
        assert_eq!((read.action.2, read.reward, read.env_id), (1, 2, Some(4)));
        assert_eq!(
            (bounds.action_low, bounds.action_high),
            (vec![-2.0], vec![2.0])
        );
        assert!(bounds.obs_low.iter().all(|v| *v == f32::NEG_INFINITY));
    }

    #[test]
    fn unbounded_discrete_and_rewardless_environments_are_refused_by_name() {
        let unbounded = spec("action", pb::DataType::Float, vec![2], None);
        let e = RemoteSpecs::read(&pendulum_like(unbounded)).unwrap_err();
        assert!(e.contains("no min/max bounds"), "{e}");
        let infinite = spec(
            "action",
            pb::DataType::Float,
            vec![2],
            Some((f32::NEG_INFINITY, 1.0)),
        );
        let e = RemoteSpecs::read(&pendulum_like(infinite)).unwrap_err();
        assert!(e.contains("finite bounds"), "{e}");
        let discrete = spec("move", pb::DataType::Int64, vec![], Some((0.0, 3.0)));
        let e = RemoteSpecs::read(&pendulum_like(discrete)).unwrap_err();
        assert!(
            e.contains("'move' is INT64") && e.contains("not discrete ones"),
            "{e}"
        );
        let variable = spec("action", pb::DataType::Float, vec![-1], Some((-1.0, 1.0)));
        let e = RemoteSpecs::read(&pendulum_like(variable)).unwrap_err();
        assert!(e.contains("variable dimension"), "{e}");
        let mut rewardless = pendulum_like(spec(
            "action",
            pb::DataType::Float,
            vec![1],
            Some((-1.0, 1.0)),
        ));
        rewardless.observations.remove(&2);
        let e = RemoteSpecs::read(&rewardless).unwrap_err();
        assert!(e.contains("no scalar 'reward'"), "{e}");
    }
}
