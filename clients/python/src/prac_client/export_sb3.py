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
import pathlib
import sys

from prac_client import vecnormalize
from prac_client.bundle import from_sb3_state_dict, write_bundle
from prac_client.sb3 import algorithm_of, gymnasium_id, load_sb3_zip, sb3_policy, spaces_from_sb3_data, zip_path
from prac_client.value_scale import measure

# The checkpoint readers are prac_client.sb3's, also importable from here.
__all__ = ["algorithm_of", "load_sb3_zip", "main", "spaces_from_sb3_data", "zip_path"]


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
        obs_bounds=(facts["obs_low"], facts["obs_high"]) if facts["obs_low"] is not None and facts["obs_high"] is not None else None,
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
