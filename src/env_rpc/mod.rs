//! Environments over DeepMind's dm_env_rpc protocol (`proto/dm_env_rpc`): [`RemoteEnv`] is an
//! [`Env`](crate::domains::Env) played over the protocol, so `prac train --env-server ADDR` trains
//! on any environment a dm_env_rpc server offers (`prac_client.env_server` serves gymnasium's);
//! [`DomainServer`] serves the built-in domains over it (`prac env-serve`), so Python reaches them
//! (`prac_client.envs`).
//!
//! Conventions prac relies on, beyond the protocol itself (docs/environments.md):
//! - one action tensor, bounded (`min`/`max`), FLOAT or DOUBLE;
//! - the observation is the tensor named `observation` (or the only numeric one besides
//!   `reward` and `discount`); the reward is the scalar named `reward`;
//! - TERMINATED ends an episode by the task (a fall), INTERRUPTED by its step limit;
//! - world and reset settings take an INT64 `seed`; optional observations `env_id` (STRING) and
//!   `max_episode_steps` (INT64) name the environment and its step limit.

mod remote;
mod serve;
mod tensor;

pub use remote::RemoteEnv;
pub use serve::{DomainServer, run as serve};

/// Generated from proto/dm_env_rpc/v1/dm_env_rpc.proto and the google.rpc.Status it imports.
#[allow(unreachable_pub, clippy::all)]
pub(crate) mod wire {
    pub(crate) mod dm_env_rpc {
        pub(crate) mod v1 {
            tonic::include_proto!("dm_env_rpc.v1");
        }
    }
    pub(crate) mod google {
        pub(crate) mod rpc {
            tonic::include_proto!("google.rpc");
        }
    }
}
