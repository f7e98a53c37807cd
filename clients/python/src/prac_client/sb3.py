"""Stable-Baselines3 checkpoints: their facts and weights read from the zip without unpickling,
and their policies played (needs torch; playing also stable-baselines3).

Nothing is unpickled to read a checkpoint but the weights (torch.load(weights_only=True)): the
spaces and the algorithm are read from the readable fields SB3 writes next to its pickles, so
zips from the rl-zoo (saved with gym, not gymnasium) read as they are.
"""

from __future__ import annotations

import io
import json
import pathlib
import re
import sys
import zipfile
from typing import Any, Callable, Mapping

import numpy as np
import numpy.typing as npt

from prac_client.vecnormalize import for_checkpoint


def _array(text: Any) -> npt.NDArray[np.float32]:
    """Parses numpy's str() of an array, e.g. '[-1. -1. -2.]', as SB3 stores it in 'data'."""
    if isinstance(text, list):
        return np.asarray(text, dtype=np.float32)
    cleaned = str(text).replace("[", " ").replace("]", " ").replace("\n", " ")
    if "..." in cleaned:
        raise ValueError(f"cannot read a summarised array from SB3 data: {text!r}")
    return np.asarray([float(v) for v in cleaned.split()], dtype=np.float32)


def spaces_from_sb3_data(data: Mapping[str, Any]) -> dict[str, Any]:
    """obs_dim, observation and action bounds, gamma and activation from SB3's `data` JSON
    (observation bounds None where the checkpoint does not record them)."""
    obs = data["observation_space"]
    act = data["action_space"]
    shape = obs.get("_shape") or obs.get("shape")
    if shape is None or len(shape) != 1:
        raise ValueError(f"observation space shape {shape}: only flat Box observations are supported")
    obs_low = np.broadcast_to(_array(obs["low"]), tuple(shape)).astype(np.float32) if "low" in obs else None
    obs_high = np.broadcast_to(_array(obs["high"]), tuple(shape)).astype(np.float32) if "high" in obs else None
    low, high = _array(act["low"]), _array(act["high"])
    act_shape = act.get("_shape") or act.get("shape") or [low.size]
    low = np.broadcast_to(low, tuple(act_shape)).astype(np.float32)
    high = np.broadcast_to(high, tuple(act_shape)).astype(np.float32)
    activation = "relu"
    kwargs = data.get("policy_kwargs") or {}
    fn = str(kwargs.get("activation_fn", "ReLU")) if isinstance(kwargs, dict) else "ReLU"
    if "Tanh" in fn:
        activation = "tanh"
    elif "ReLU" not in fn:
        raise ValueError(f"activation {fn}: prac bundles support ReLU and Tanh")
    return {
        "obs_dim": int(shape[0]),
        "obs_low": obs_low,
        "obs_high": obs_high,
        "action_low": low,
        "action_high": high,
        "gamma": float(data.get("gamma", 0.99)),
        "activation": activation,
        "steps": int(data.get("num_timesteps", 0)),
        "seed": int(data.get("seed") or 0),
    }


def zip_path(path: str | pathlib.Path) -> pathlib.Path:
    """The checkpoint's file: PATH, or PATH.zip as SB3's load accepts it (also where PATH is the
    rl-zoo's folder of the same name beside the zip)."""
    path = pathlib.Path(path)
    if not path.is_file() and path.suffix != ".zip" and path.with_name(path.name + ".zip").is_file():
        return path.with_name(path.name + ".zip")
    return path


def algorithm_of(data: Mapping[str, Any], state: Mapping[str, Any]) -> tuple[str, str, float | None]:
    """(algorithm, actor kind, mean clip) of an SB3 checkpoint, from its policy class's module
    and the weights; anything but SAC, TD3 and DDPG is a ValueError with one line."""
    policy_class = data.get("policy_class")
    module = str(policy_class.get("__module__", "")) if isinstance(policy_class, dict) else ""
    family = module.split(".")[1] if module.startswith("stable_baselines3.") else ""
    if not family:
        family = "sac" if any(k.startswith("actor.latent_pi.") for k in state) else "td3" if "actor.mu.0.weight" in state else ""
    if family == "sac":
        if "actor.log_std" not in state:
            return "SAC", "gaussian", None
        kwargs = data.get("policy_kwargs") or {}
        clip = float(kwargs.get("clip_mean", 2.0)) if isinstance(kwargs, dict) else 2.0
        clipped = "actor.mu.0.weight" in state
        return "SAC (gSDE)", "gaussian_sde", (clip if clipped else None)
    if family == "td3":
        # SB3's DDPG is TD3 with one update per step and no target smoothing noise clip.
        ddpg = data.get("policy_delay") == 1 and data.get("target_noise_clip") == 0.0
        return ("DDPG" if ddpg else "TD3"), "deterministic", None
    what = module or "an unknown policy"
    raise ValueError(
        f"the checkpoint holds {what}: prac serves off-policy actor-critics with Q critics "
        "(SB3's SAC, TD3 and DDPG)"
    )


def load_sb3_zip(path: str | pathlib.Path) -> tuple[dict[str, npt.NDArray[np.float32]], dict[str, Any]]:
    """The policy state dict (numpy) and the facts (spaces, gamma, algorithm, actor kind) of an
    SB3 checkpoint."""
    try:
        import torch
    except ImportError:
        raise SystemExit("export_sb3 needs torch: pip install 'prac-client[sb3]'") from None
    try:
        with zipfile.ZipFile(zip_path(path)) as archive:
            data = json.loads(archive.read("data"))
            weights = torch.load(io.BytesIO(archive.read("policy.pth")), map_location="cpu", weights_only=True)
    except (OSError, zipfile.BadZipFile, KeyError, ValueError) as e:
        raise SystemExit(f"{path}: not a readable SB3 checkpoint ({e})") from None
    state = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in weights.items()}
    facts = spaces_from_sb3_data(data)
    try:
        facts["algorithm"], facts["actor_kind"], facts["mean_clip"] = algorithm_of(data, state)
    except ValueError as e:
        raise SystemExit(f"{path}: {e}") from None
    return state, facts


_GYM_MUJOCO = re.compile(
    r"(Ant|HalfCheetah|Hopper|Humanoid|HumanoidStandup|InvertedDoublePendulum|InvertedPendulum|"
    r"Pusher|Reacher|Swimmer|Walker2d)-v[23]"
)


def gymnasium_id(env_id: str) -> str:
    """gymnasium's id for `env_id`: gym's MuJoCo v2/v3 ids (the rl-zoo's) map to v4, with a
    warning on stderr; any other id is unchanged."""
    match = _GYM_MUJOCO.fullmatch(env_id)
    if match is None:
        return env_id
    ported = f"{match.group(1)}-v4"
    print(
        f"warning: {env_id} is gym's MuJoCo task, which gymnasium no longer has; playing {ported}, "
        "gymnasium's port of it (same observation and action spaces)",
        file=sys.stderr,
    )
    return ported


def load_sb3(path: str, env: Any) -> Any:
    """An SB3 SAC, TD3 or DDPG model from its checkpoint, loaded as rl-zoo's enjoy.py does."""
    try:
        from stable_baselines3 import DDPG, SAC, TD3
    except ImportError:
        raise SystemExit("--sb3 needs stable-baselines3: pip install 'prac-client[sb3]'") from None
    checkpoint = zip_path(path)
    with zipfile.ZipFile(checkpoint) as archive:
        data = json.loads(archive.read("data"))
    try:
        algorithm = algorithm_of(data, {})[0]
    except ValueError as e:
        raise SystemExit(f"{path}: {e}") from None
    # SB3 types `load` on each class; the table would otherwise widen them to ABCMeta.
    classes: dict[str, Any] = {"SAC": SAC, "TD3": TD3, "DDPG": DDPG}
    cls = classes.get(algorithm, SAC)
    custom_objects = {
        "learning_rate": 0.0,
        "lr_schedule": lambda _: 0.0,
        "exploration_schedule": lambda _: 0.0,
        "observation_space": env.observation_space,
        "action_space": env.action_space,
    }
    return cls.load(checkpoint, device="cpu", custom_objects=custom_objects)


def sb3_policy(
    path: str, env: Any, vecnormalize: str | None = None
) -> Callable[[npt.NDArray[np.float32]], npt.NDArray[np.float32]]:
    """SB3's deterministic action for a raw observation: the checkpoint loaded by `load_sb3`,
    behind its VecNormalize statistics where it has them (`vecnormalize`, or the file found beside
    the checkpoint as the rl-zoo keeps it)."""
    model = load_sb3(path, env)
    stats_file, stats = for_checkpoint(zip_path(path), vecnormalize)
    if stats_file:
        print(f"observations normalised as {stats_file} says", file=sys.stderr)

    def act(obs: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        seen = stats.normalize(obs) if stats else obs
        return np.asarray(model.predict(seen, deterministic=True)[0], dtype=np.float32)

    return act
