"""Makes a prac bundle from a Stable-Baselines3 SAC checkpoint (needs torch).

    python -m prac_client.export_sb3 MODEL.zip --out P.safetensors [--name P] [--domain D]

The bundle holds the actor and critics and a manifest from the checkpoint's spaces and gamma; it
has no dynamics model (record transitions with `python -m prac_client.record` and add one with
`prac fit-model`). Nothing is unpickled but the weights (torch.load(weights_only=True)): the
spaces are read from the readable fields SB3 writes next to its pickles.
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


def load_sb3_zip(path: str | pathlib.Path) -> tuple[dict[str, npt.NDArray[np.float32]], dict[str, Any]]:
    """The policy state dict (numpy) and the space facts of an SB3 checkpoint."""
    try:
        import torch
    except ImportError:
        raise SystemExit("export_sb3 needs torch: pip install 'prac-client[sb3]'") from None
    with zipfile.ZipFile(path) as archive:
        data = json.loads(archive.read("data"))
        weights = torch.load(io.BytesIO(archive.read("policy.pth")), map_location="cpu", weights_only=True)
    state = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in weights.items()}
    return state, spaces_from_sb3_data(data)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m prac_client.export_sb3", description=__doc__.split("\n")[0])
    parser.add_argument("model", help="SB3 checkpoint (.zip)")
    parser.add_argument("--out", required=True, help="bundle to write (NAME.safetensors)")
    parser.add_argument("--name", help="policy name [default: the output file's stem]")
    parser.add_argument("--domain", default="unknown", help="domain the policy controls")
    parser.add_argument("--value-scale", nargs=2, type=float, metavar=("V_PI", "V_RAND"))
    args = parser.parse_args(argv)
    state, facts = load_sb3_zip(args.model)
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
        provenance={"steps": facts["steps"], "seed": facts["seed"]},
    )
    if manifest["obs_dim"] != facts["obs_dim"]:
        raise SystemExit(f"actor takes {manifest['obs_dim']} inputs, observation space has {facts['obs_dim']}")
    write_bundle(out, tensors, manifest)
    print(f"wrote {out}: {manifest['obs_dim']} obs, {manifest['act_dim']} actions, no dynamics model")
    return 0


if __name__ == "__main__":
    sys.exit(main())
