"""Writing prac weight bundles (docs/bundle-format.md) from numpy arrays named as
Stable-Baselines3 names them."""

from __future__ import annotations

import datetime
import json
import os
import re
from typing import Any, Mapping

import numpy as np
import numpy.typing as npt

FORMAT_VERSION = 1
# Version 2 adds the actor's kind (gaussian_sde, deterministic), mean_clip and obs_normalization; a
# bundle that uses none of them stays version 1, so any prac reads it.
FORMAT_VERSION_ACTOR_KINDS = 2
# Version 4 adds obs_bounds, the observation space the server keeps the model's forecasts inside
# (older servers refuse such a bundle rather than serve unbounded forecasts).
FORMAT_VERSION_OBS_BOUNDS = 4
ACTOR_KINDS = ("gaussian", "gaussian_sde", "deterministic")
Array = npt.NDArray[np.float32]


def _linear_chain(state: Mapping[str, npt.ArrayLike], prefix: str) -> list[tuple[str, Array, Array]]:
    """The linear layers prefix.{0,2,4,..} in index order, as (name, weight, bias)."""
    indices = sorted(
        int(m.group(1)) for k in state if (m := re.fullmatch(re.escape(prefix) + r"\.(\d+)\.weight", k))
    )
    layers = []
    for i in indices:
        weight = np.asarray(state[f"{prefix}.{i}.weight"], dtype=np.float32)
        bias = np.asarray(state[f"{prefix}.{i}.bias"], dtype=np.float32)
        layers.append((f"{prefix}.{i}", weight, bias))
    expected = [f"{prefix}.{2 * j}" for j in range(len(layers))]
    if [name for name, _, _ in layers] != expected:
        raise ValueError(f"{prefix}: linear layers {[n for n, _, _ in layers]}, expected {expected}")
    return layers


def _actor_tensors(
    state: Mapping[str, npt.ArrayLike], kind: str, mean_clip: float | None
) -> tuple[list[tuple[str, Array, Array]], dict[str, Array]]:
    """The actor as a bundle holds it: trunk layers (named actor.latent_pi.*) and heads.

    SAC: actor.latent_pi.* then the linear heads actor.mu and actor.log_std. SAC with gSDE: the
    mean head is actor.mu.0 when SB3 clipped it (Sequential(Linear, Hardtanh)), actor.mu
    otherwise; actor.log_std is the gSDE noise parameter, not a head, and is left out. TD3 and
    DDPG: actor.mu is Sequential(Linear, act, ..., Linear, Tanh): all but its last layer are
    the trunk."""
    heads: dict[str, Array] = {}
    if kind == "deterministic":
        chain = _linear_chain(state, "actor.mu")
        if not chain:
            raise ValueError("no actor.mu.0.weight: not an SB3 TD3/DDPG actor")
        trunk = [(f"actor.latent_pi.{2 * i}", w, b) for i, (_, w, b) in enumerate(chain[:-1])]
        heads["actor.mu.weight"], heads["actor.mu.bias"] = chain[-1][1], chain[-1][2]
        return trunk, heads
    trunk = _linear_chain(state, "actor.latent_pi")
    if kind == "gaussian" and "actor.log_std.weight" not in state:
        raise ValueError("no actor.log_std.weight: not a plain SAC actor (a gSDE one has actor.log_std alone)")
    mu = "actor.mu.0" if kind == "gaussian_sde" and mean_clip is not None else "actor.mu"
    if f"{mu}.weight" not in state:
        raise ValueError(f"no {mu}.weight: not an SB3 SAC actor of kind {kind}")
    for part in ("weight", "bias"):
        heads[f"actor.mu.{part}"] = np.asarray(state[f"{mu}.{part}"], dtype=np.float32)
        if kind == "gaussian":
            heads[f"actor.log_std.{part}"] = np.asarray(state[f"actor.log_std.{part}"], dtype=np.float32)
    return trunk, heads


def from_sb3_state_dict(
    state: Mapping[str, npt.ArrayLike],
    *,
    name: str,
    domain: str,
    action_low: npt.ArrayLike,
    action_high: npt.ArrayLike,
    gamma: float,
    activation: str = "relu",
    q_aggregation: str = "min",
    value_scale: tuple[float, float] | None = None,
    provenance: Mapping[str, Any] | None = None,
    model: Mapping[str, Any] | None = None,
    actor_kind: str = "gaussian",
    mean_clip: float | None = None,
    obs_normalization: Mapping[str, Any] | None = None,
    obs_bounds: tuple[npt.ArrayLike, npt.ArrayLike] | None = None,
) -> tuple[dict[str, Array], dict[str, Any]]:
    """Maps an SB3 SAC, TD3 or DDPG policy state dict (actor.*, critic.qf{k}.*; the target
    networks are dropped) to bundle tensors and manifest. `actor_kind` is "gaussian" (SAC),
    "gaussian_sde" (SAC with gSDE; `mean_clip` its clip_mean, None where it did not clip) or
    "deterministic" (TD3, DDPG). Layer sizes come from the shapes. `model`, if given, holds the
    dynamics model: {"tensors": {model.net.*}, "hidden", "activation", "normalization"}.
    `obs_normalization` ({"mean", "var", "clip_obs", "epsilon"}, as SB3's VecNormalize applies
    them) is what the actor and critics were trained behind. `obs_bounds` (low, high), the
    observation space (e.g. a gymnasium Box's), keeps the model's forecasts inside it; infinite
    entries are unbounded, and a space unbounded everywhere adds nothing."""
    if actor_kind not in ACTOR_KINDS:
        raise ValueError(f"actor kind {actor_kind!r}; expected one of {', '.join(ACTOR_KINDS)}")
    if mean_clip is not None and actor_kind != "gaussian_sde":
        raise ValueError(f"mean_clip is for gaussian_sde actors, not {actor_kind}")
    trunk, heads = _actor_tensors(state, actor_kind, mean_clip)
    mu_w = heads["actor.mu.weight"]
    act_dim = mu_w.shape[0]
    obs_dim = trunk[0][1].shape[1] if trunk else mu_w.shape[1]
    tensors: dict[str, Array] = {}
    for layer, w, b in trunk:
        tensors[f"{layer}.weight"], tensors[f"{layer}.bias"] = w, b
    tensors.update(heads)
    n_critics = 0
    critic_hidden: list[int] | None = None
    while f"critic.qf{n_critics}.0.weight" in state:
        chain = _linear_chain(state, f"critic.qf{n_critics}")
        if chain[0][1].shape[1] != obs_dim + act_dim or chain[-1][1].shape[0] != 1:
            raise ValueError(f"critic.qf{n_critics}: expected input {obs_dim + act_dim} and output 1")
        hidden = [w.shape[0] for _, w, _ in chain[:-1]]
        if critic_hidden is not None and hidden != critic_hidden:
            raise ValueError(f"critic.qf{n_critics}: hidden {hidden} differs from critic.qf0's {critic_hidden}")
        critic_hidden = hidden
        for layer, w, b in chain:
            tensors[f"{layer}.weight"], tensors[f"{layer}.bias"] = w, b
        n_critics += 1
    if n_critics == 0:
        raise ValueError("no critic.qf0.* tensors: not an SB3 SAC, TD3 or DDPG policy")
    low = np.broadcast_to(np.asarray(action_low, dtype=np.float32), (act_dim,))
    high = np.broadcast_to(np.asarray(action_high, dtype=np.float32), (act_dim,))
    actor: dict[str, Any] = {"hidden": [int(w.shape[0]) for _, w, _ in trunk], "activation": activation}
    if actor_kind != "gaussian":
        actor["kind"] = actor_kind
        if mean_clip is not None:
            actor["mean_clip"] = float(mean_clip)
    manifest: dict[str, Any] = {
        "format_version": (
            FORMAT_VERSION if actor_kind == "gaussian" and obs_normalization is None else FORMAT_VERSION_ACTOR_KINDS
        ),
        "name": name,
        "domain": domain,
        "obs_dim": int(obs_dim),
        "act_dim": int(act_dim),
        "action_low": [float(v) for v in low],
        "action_high": [float(v) for v in high],
        "gamma": float(gamma),
        "actor": actor,
        "critic": {"n_critics": n_critics, "hidden": critic_hidden, "activation": activation},
        "model": None,
        "q_aggregation": q_aggregation,
        "value_scale": None if value_scale is None else {"v_pi": value_scale[0], "v_rand": value_scale[1]},
        "provenance": {
            "trainer": "stable-baselines3 (exported by prac_client)",
            "steps": 0,
            "seed": 0,
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            **(provenance or {}),
        },
    }
    if obs_normalization is not None:
        manifest["obs_normalization"] = {
            "mean": [float(v) for v in obs_normalization["mean"]],
            "var": [float(v) for v in obs_normalization["var"]],
            "clip_obs": float(obs_normalization["clip_obs"]),
            "epsilon": float(obs_normalization["epsilon"]),
        }
    if obs_bounds is not None:
        field = obs_bounds_field(obs_bounds[0], obs_bounds[1], int(obs_dim))
        if field is not None:
            manifest["obs_bounds"] = field
            manifest["format_version"] = FORMAT_VERSION_OBS_BOUNDS
    if model is not None:
        for key, value in model["tensors"].items():
            tensors[key] = np.asarray(value, dtype=np.float32)
        manifest["model"] = {
            "hidden": list(model["hidden"]),
            "activation": model.get("activation", "relu"),
            "normalization": {k: [float(x) for x in v] for k, v in model["normalization"].items()},
        }
    return tensors, manifest


def obs_bounds_field(low: npt.ArrayLike, high: npt.ArrayLike, obs_dim: int) -> dict[str, list[float | None]] | None:
    """The manifest's obs_bounds for an observation space: null where a side is infinite; None
    where every side is."""
    lo = np.broadcast_to(np.asarray(low, dtype=np.float32), (obs_dim,))
    hi = np.broadcast_to(np.asarray(high, dtype=np.float32), (obs_dim,))
    if not (np.isfinite(lo).any() or np.isfinite(hi).any()):
        return None

    def side(values: Array) -> list[float | None]:
        return [float(v) if np.isfinite(v) else None for v in values]

    return {"low": side(lo), "high": side(hi)}


def write_bundle(path: str | os.PathLike[str], tensors: Mapping[str, Array], manifest: Mapping[str, Any]) -> None:
    """Writes a bundle atomically (a temporary file renamed into place)."""
    from safetensors.numpy import save_file

    path = os.fspath(path)
    tmp = path + ".tmp"
    contiguous = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in tensors.items()}
    save_file(contiguous, tmp, metadata={"format": "prac-bundle", "manifest": json.dumps(manifest)})
    os.replace(tmp, path)


def random_sb3_state_dict(
    obs_dim: int,
    act_dim: int,
    hidden: list[int],
    *,
    seed: int = 0,
    n_critics: int = 2,
) -> dict[str, Array]:
    """An SB3-named SAC state dict with PyTorch-default random weights, including the
    critic_target.* copies SB3 saves (for tests and benchmarks)."""
    rng = np.random.default_rng(seed)

    def linear(out: int, inp: int) -> tuple[Array, Array]:
        bound = 1.0 / np.sqrt(inp)
        return (
            rng.uniform(-bound, bound, (out, inp)).astype(np.float32),
            rng.uniform(-bound, bound, (out,)).astype(np.float32),
        )

    state: dict[str, Array] = {}
    width = obs_dim
    for i, h in enumerate(hidden):
        state[f"actor.latent_pi.{2 * i}.weight"], state[f"actor.latent_pi.{2 * i}.bias"] = linear(h, width)
        width = h
    state["actor.mu.weight"], state["actor.mu.bias"] = linear(act_dim, width)
    state["actor.log_std.weight"], state["actor.log_std.bias"] = linear(act_dim, width)
    for k in range(n_critics):
        width = obs_dim + act_dim
        for i, h in enumerate([*hidden, 1]):
            w, b = linear(h, width)
            for root in ("critic", "critic_target"):
                state[f"{root}.qf{k}.{2 * i}.weight"], state[f"{root}.qf{k}.{2 * i}.bias"] = w, b
            width = h
    return state


def random_model(obs_dim: int, act_dim: int, hidden: list[int], *, seed: int = 0) -> dict[str, Any]:
    """A randomly initialised dynamics model in the shape `from_sb3_state_dict(model=...)` takes."""
    rng = np.random.default_rng(seed)
    tensors: dict[str, Array] = {}
    width = obs_dim + act_dim
    for i, h in enumerate([*hidden, obs_dim]):
        bound = 1.0 / np.sqrt(width)
        tensors[f"model.net.{2 * i}.weight"] = rng.uniform(-bound, bound, (h, width)).astype(np.float32)
        tensors[f"model.net.{2 * i}.bias"] = rng.uniform(-bound, bound, (h,)).astype(np.float32)
        width = h
    normalization = {
        "obs_mean": [0.0] * obs_dim,
        "obs_std": [1.0] * obs_dim,
        "action_mean": [0.0] * act_dim,
        "action_std": [1.0] * act_dim,
        "delta_mean": [0.0] * obs_dim,
        "delta_std": [0.1] * obs_dim,
    }
    return {"tensors": tensors, "hidden": hidden, "activation": "relu", "normalization": normalization}
