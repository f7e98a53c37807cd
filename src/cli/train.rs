//! `prac train`: SAC with a dynamics model (Algorithm 1), with or without PrAC while training.

use std::path::PathBuf;

use clap::Args;

use prac::domains::Env;
use prac::env_rpc::RemoteEnv;
use prac::train::options::TrainOptions;
use prac::train::run::Trainer;
use prac::train::sac::SacConfig;

#[derive(Args, Debug)]
pub struct TrainArgs {
    /// Domain to train on (see `prac domains`).
    #[arg(
        long,
        required_unless_present = "env_server",
        conflicts_with = "env_server"
    )]
    pub domain: Option<String>,
    /// Train on the environment a dm_env_rpc server offers at ADDR (`HOST:PORT`), e.g.
    /// `python -m prac_client.env_server --env Pendulum-v1`; the bundle's domain is its name.
    #[arg(long, value_name = "ADDR")]
    pub env_server: Option<String>,
    /// Environment steps in all (a resumed run counts its earlier steps).
    #[arg(long, default_value_t = TrainOptions::DEFAULT_STEPS)]
    pub steps: u64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Training-with-PrAC: act from the plan with eps = C * (V_pi - V_rand); 0 = plain SAC.
    #[arg(long, default_value_t = 0.0)]
    pub epsilon_coef: f64,
    /// Fixed V_pi,V_rand for eps while training [default: V_rand measured before training,
    /// V_pi the critic's value of the policy at each episode's first state].
    #[arg(long, value_name = "V_PI,V_RAND", allow_hyphen_values = true)]
    pub value_scale: Option<String>,
    /// Longest plan while training with PrAC.
    #[arg(long, default_value_t = prac::plan::DEFAULT_MAX_HORIZON)]
    pub max_horizon: usize,
    /// The bundle to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Training curve CSV [default: OUT without extension + .train.csv].
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// Checkpoint directory [default: OUT without extension + .ckpt].
    #[arg(long)]
    pub checkpoint_dir: Option<PathBuf>,
    /// Time between checkpoints.
    #[arg(long, default_value_t = TrainOptions::DEFAULT_CHECKPOINT_EVERY.into())]
    pub checkpoint_every: humantime::Duration,
    /// Leave the replay buffer out of checkpoints (smaller files; a resumed run then refills the
    /// buffer with its current policy before it learns again).
    #[arg(long)]
    pub no_checkpoint_replay: bool,
    /// Continue from the checkpoint (networks, optimiser state, counters, curve).
    #[arg(long)]
    pub resume: bool,
    /// Steps between deterministic evaluations.
    #[arg(long, default_value_t = TrainOptions::DEFAULT_EVAL_EVERY)]
    pub eval_every: u64,
    #[arg(long, default_value_t = TrainOptions::DEFAULT_EVAL_EPISODES)]
    pub eval_episodes: usize,
    /// Episodes for V_pi and V_rand at the end.
    #[arg(long, default_value_t = TrainOptions::DEFAULT_VALUE_EPISODES)]
    pub value_episodes: usize,
    /// Hide the progress bar.
    #[arg(long)]
    pub quiet: bool,
    // SAC overrides [default: SB3 with gamma 0.98 and the paper's per-domain settings].
    #[arg(long)]
    pub gamma: Option<f64>,
    #[arg(long)]
    pub learning_rate: Option<f64>,
    #[arg(long)]
    pub buffer_size: Option<usize>,
    #[arg(long)]
    pub batch_size: Option<usize>,
    #[arg(long)]
    pub tau: Option<f64>,
    #[arg(long)]
    pub learning_starts: Option<u64>,
    #[arg(long)]
    pub train_freq: Option<u64>,
    #[arg(long)]
    pub gradient_steps: Option<usize>,
    /// Hidden layers of actor and critics, e.g. 256,256.
    #[arg(long, value_delimiter = ',')]
    pub hidden: Option<Vec<usize>>,
    /// Normalise the actor's and critics' observations by the running mean and variance of
    /// those seen (the SB3 zoo's `normalize: true`); the bundle carries them. A run resumes
    /// the way it started.
    #[arg(long)]
    pub norm_obs: bool,
    /// A layer norm after each of the critics' hidden layers (for several gradient steps per
    /// environment step, `--gradient-steps`); the bundle carries them. A run resumes the way
    /// it started.
    #[arg(long)]
    pub critic_layer_norm: bool,
}

fn apply_overrides(config: &mut SacConfig, a: &TrainArgs) {
    macro_rules! set {
        ($field:ident) => {
            if let Some(v) = a.$field.clone() {
                config.$field = v;
            }
        };
    }
    set!(gamma);
    set!(learning_rate);
    set!(buffer_size);
    set!(batch_size);
    set!(tau);
    set!(learning_starts);
    set!(train_freq);
    set!(gradient_steps);
    set!(hidden);
    config.norm_obs |= a.norm_obs;
    config.critic_layer_norm |= a.critic_layer_norm;
}

impl TrainArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let args = self;
        let served = match &args.env_server {
            // Two worlds: one to train in, one to evaluate in.
            Some(addr) => Some((
                RemoteEnv::connect(addr, args.seed)?,
                RemoteEnv::connect(addr, args.seed.wrapping_add(1))?,
            )),
            None => None,
        };
        let domain = match (&served, &args.domain) {
            (Some((env, _)), _) => env.spec().name.to_string(),
            (None, Some(domain)) => domain.clone(),
            (None, None) => anyhow::bail!("give --domain or --env-server"),
        };
        let mut options = TrainOptions::new(&domain, &args.out);
        options.steps = args.steps;
        options.seed = args.seed;
        options.epsilon_coef = args.epsilon_coef;
        options.max_horizon = args.max_horizon;
        options.value_scale = args
            .value_scale
            .as_deref()
            .map(|text| prac::client::parse_number_pair(text, "--value-scale V_PI,V_RAND"))
            .transpose()?;
        if let Some(csv) = &args.csv {
            options.csv = csv.clone();
            options.eval_csv = csv.with_extension("eval.csv");
        }
        if let Some(dir) = &args.checkpoint_dir {
            options.checkpoint_dir = dir.clone();
        }
        options.checkpoint_every = args.checkpoint_every.into();
        options.checkpoint_replay = !args.no_checkpoint_replay;
        options.eval_every = args.eval_every;
        options.eval_episodes = args.eval_episodes;
        options.value_episodes = args.value_episodes;
        options.progress = !args.quiet;
        apply_overrides(&mut options.sac, &args);
        let mut trainer = match served {
            Some((env, eval_env)) => {
                Trainer::with_envs(options, args.resume, Box::new(env), Box::new(eval_env))?
            }
            None => Trainer::new(options, args.resume)?,
        };
        if args.resume {
            eprintln!(
                "resuming at step {} (episode {})",
                trainer.progress.step, trainer.progress.episode
            );
            match trainer.restored_transitions {
                Some(n) => {
                    eprintln!("restored {n} transitions from the checkpoint's replay buffer")
                }
                None => eprintln!(
                    "the checkpoint has no replay buffer: refilling it before learning goes on"
                ),
            }
        }
        let report = trainer.run()?;
        println!("{}", serde_json::to_string_pretty(&report)?);
        Ok(())
    }
}
