"""Makes a prac bundle from a Stable-Baselines3 SAC, TD3 or DDPG checkpoint (needs torch).

    python -m prac_client.export_sb3 MODEL[.zip] --out P.safetensors [--name P] [--domain D]
        [--env ENV_ID [--episodes N] | --value-scale V_PI V_RAND] [--vecnormalize FILE]

The bundle holds the actor and critics and a manifest from the checkpoint's spaces and gamma; it
has no dynamics model (record transitions with `python -m prac_client.record` and add one with
`prac fit-model`). Nothing is unpickled but the weights (torch.load(weights_only=True)): the
spaces and the algorithm are read from the readable fields SB3 writes next to its pickles, so
zips from the rl-zoo (saved with gym, not gymnasium) export as they are.

Actor kinds: SAC's squashed Gaussian; SAC with gSDE (use_sde), whose deterministic action is
tanh of the mean clipped to +-clip_mean and which has no sampling distribution in the bundle;
TD3 and DDPG, deterministic. Any other algorithm is refused.

An agent trained behind VecNormalize (vecnormalize.pkl beside the zip, or in ENV_ID/ beside
ENV_ID.zip as the rl-zoo keeps it, or --vecnormalize FILE) gets its observation normalisation in
the bundle, which the server applies in front of the actor and critics. Where rewards were
normalised too, its critics' Q is in scaled reward units that drift over training: the bundle gets
no value scale (give absolute epsilons), and --env and --value-scale are refused.
"""

from __future__ import annotations

import argparse
import io
import json
import pathlib
import sys
import zipfile
from typing import Any, Mapping

import numpy as np
import numpy.typing as npt

from prac_client import vecnormalize
from prac_client.bundle import from_sb3_state_dict, write_bundle


def _array(text: Any) -> npt.NDArray[np.float32]:
    """Parses numpy's str() of an array, e.g. '[-1. -1. -2.]', as SB3 stores it in 'data'."""
    if isinstance(text, list):
        return np.asarray(text, dtype=np.float32)
    cleaned = str(text).replace("[", " ").replace("]", " ").replace("\n", " ")
    if "..." in cleaned:
        raise ValueError(f"cannot read a summarised array from SB3 data: {text!r}")
    return np.asarray([float(v) for v in cleaned.split()], dtype=np.float32)


def spaces_from_sb3_data(data: Mapping[str, Any]) -> dict[str, Any]:
    """obs_dim, action bounds, gamma and activation from SB3's `data` JSON."""
    obs = data["observation_space"]
    act = data["action_space"]
    shape = obs.get("_shape") or obs.get("shape")
    if shape is None or len(shape) != 1:
        raise ValueError(f"observation space shape {shape}: only flat Box observations are supported")
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m prac_client.export_sb3", description=__doc__.split("\n")[0])
    parser.add_argument("model", help="SB3 SAC, TD3 or DDPG checkpoint (.zip; the suffix may be left out)")
    parser.add_argument("--out", required=True, help="bundle to write (NAME.safetensors)")
    parser.add_argument("--name", help="policy name [default: the output file's stem]")
    parser.add_argument("--domain", default="unknown", help="domain the policy controls")
    scale = parser.add_mutually_exclusive_group()
    scale.add_argument("--value-scale", nargs=2, type=float, metavar=("V_PI", "V_RAND"))
    scale.add_argument(
        "--env", help="measure the value scale on this gymnasium env (needs stable-baselines3), as prac evaluate does"
    )
    parser.add_argument("--episodes", type=int, default=50, help="episodes per value with --env [default: 50]")
    parser.add_argument(
        "--vecnormalize", help="the agent's VecNormalize file [default: vecnormalize.pkl found beside the zip]"
    )
    args = parser.parse_args(argv)
    state, facts = load_sb3_zip(args.model)
    stats_file, stats = vecnormalize.for_checkpoint(zip_path(args.model), args.vecnormalize)
    if stats is not None:
        if stats.mean.size != facts["obs_dim"]:
            raise SystemExit(f"{stats_file}: normalises {stats.mean.size} features, the agent takes {facts['obs_dim']}")
        print(f"read {stats_file}: observations {'normalised' if stats.norm_obs else 'raw'}, rewards {'normalised' if stats.norm_reward else 'raw'}")
        if stats.norm_reward:
            if args.env or args.value_scale:
                raise SystemExit(f"{stats_file}: {vecnormalize.NORMALISED_REWARDS} (export without --env/--value-scale)")
            print("note: rewards were normalised, so the bundle has no value scale; give absolute epsilons")
    if args.env:
        import gymnasium

        from prac_client.record import gymnasium_id, sb3_policy
        from prac_client.value_scale import measure

        env = gymnasium.make(gymnasium_id(args.env))
        policy = sb3_policy(args.model, env, args.vecnormalize)
        v_pi, v_rand = measure(env, policy, facts["gamma"], args.episodes, 0)
        print(f"measured on {args.env} over {args.episodes} episodes: V_pi = {v_pi:.4f}, V_rand = {v_rand:.4f}")
        if v_pi > v_rand:
            args.value_scale = (v_pi, v_rand)
        else:
            print("warning: V_pi is not above V_rand, so the bundle gets no value scale", file=sys.stderr)
    out = pathlib.Path(args.out)
    tensors, manifest = from_sb3_state_dict(
        state,
        name=args.name or out.stem,
        domain=args.domain,
        action_low=facts["action_low"],
        action_high=facts["action_high"],
        gamma=facts["gamma"],
        activation=facts["activation"],
        value_scale=tuple(args.value_scale) if args.value_scale else None,
        provenance={
            "trainer": f"stable-baselines3 {facts['algorithm']} (exported by prac_client)",
            "steps": facts["steps"],
            "seed": facts["seed"],
        },
        actor_kind=facts["actor_kind"],
        mean_clip=facts["mean_clip"],
        obs_normalization=stats.bundle_field() if stats else None,
    )
    if manifest["obs_dim"] != facts["obs_dim"]:
        raise SystemExit(f"actor takes {manifest['obs_dim']} inputs, observation space has {facts['obs_dim']}")
    write_bundle(out, tensors, manifest)
    print(
        f"wrote {out}: {facts['algorithm']}, {manifest['obs_dim']} obs, {manifest['act_dim']} actions, "
        f"{facts['actor_kind']} actor{', normalised observations' if stats and stats.norm_obs else ''}, no dynamics model"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
