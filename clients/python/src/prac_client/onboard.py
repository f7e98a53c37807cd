"""Replan on board: `prac export-onnx`'s files run with ONNX Runtime, so that a session whose
servers all fail goes on locally from the plan it holds (`client.session(..., fallback=DIR)`).

    from prac_client.onboard import Fallback
    fallback = Fallback("hopper-onnx")   # prac export-onnx bundles/hopper.safetensors --out hopper-onnx
    with client.session("hopper", epsilon_coef=0.005, fallback=fallback) as session:
        result = session.step(observation)   # result.local: answered on board

The Replan is `prac_client.replan`'s, the one the Python baseline server runs; the networks are
the exported graphs, in the environment's units. Needs `onnxruntime` (the `onboard` extra).
"""

from __future__ import annotations

import hashlib
import json
import os
import pathlib
from typing import Any

import numpy as np

from prac_client import errors, replan
from prac_client._proto.prac.v1 import prac_pb2 as pb
from prac_client.replan import F32, FloatArray

PathLike = str | os.PathLike[str]
# prac.json's layout this client reads.
CONTRACT_VERSION = 1
# Actions at the bounds are clamped here before atanh, as the server does.
SQUASHED_LIMIT = F32(1.0) - np.finfo(F32).eps


def _runtime() -> Any:
    try:
        import onnxruntime
    except ImportError as e:
        raise errors.FallbackFailed("the on-board fallback needs onnxruntime: pip install 'prac-client[onboard]'") from e
    return onnxruntime


def _bounds(values: list[float | None], missing: float) -> FloatArray:
    return np.array([missing if v is None else v for v in values], dtype=F32)


class OnnxNetworks:
    """The exported actor, critics and model, run with ONNX Runtime on `threads` threads. Every
    file's sha256 is checked against prac.json, and each graph's inputs against its sizes."""

    def __init__(self, folder: PathLike, *, threads: int = 1) -> None:
        self.folder = pathlib.Path(folder)
        try:
            contract = json.loads((self.folder / "prac.json").read_text())
        except (OSError, ValueError) as e:
            raise errors.FallbackFailed(f"cannot read {self.folder / 'prac.json'}: {e}") from e
        if contract.get("contract_version") != CONTRACT_VERSION:
            raise errors.FallbackFailed(
                f"{self.folder / 'prac.json'} has contract_version {contract.get('contract_version')}; "
                f"this client reads {CONTRACT_VERSION}"
            )
        self.contract: dict[str, Any] = contract
        self.obs_dim = int(contract["observation"]["size"])
        self.act_dim = int(contract["action"]["size"])
        self.low = _bounds(contract["action"]["low"], -np.inf)
        self.high = _bounds(contract["action"]["high"], np.inf)
        if not (np.isfinite(self.low).all() and np.isfinite(self.high).all()):
            raise errors.FallbackFailed("the exported action bounds are not finite")
        self.mean_q = contract["q_aggregation"] == "mean"
        ort = _runtime()
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1

        def load(entry: dict[str, Any]) -> Any:
            path = self.folder / entry["path"]
            try:
                data = path.read_bytes()
            except OSError as e:
                raise errors.FallbackFailed(f"cannot read {path}: {e}") from e
            digest = "sha256:" + hashlib.sha256(data).hexdigest()
            if digest != entry["sha256"]:
                raise errors.FallbackFailed(f"{path} is not the file prac.json names ({digest}, expected {entry['sha256']})")
            try:
                graph = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])
            except Exception as e:  # onnxruntime raises its own exception types
                raise errors.FallbackFailed(f"ONNX Runtime cannot load {path}: {e}") from e
            for given in graph.get_inputs():
                want = {"observation": self.obs_dim, "action": self.act_dim}.get(given.name)
                if want is None or given.shape[-1] != want:
                    raise errors.FallbackFailed(f"{path}'s input {given.name} {given.shape} does not fit prac.json's sizes")
            return graph

        self.actor = load(contract["actor"])
        self.critics = [load(c) for c in contract["critics"]]
        self.model = load(contract["model"])
        self.gaussian = "log_std" in contract["actor"]["outputs"]

    def _run(self, graph: Any, outputs: list[str], feeds: dict[str, FloatArray]) -> list[FloatArray]:
        try:
            return [np.asarray(o, dtype=F32) for o in graph.run(outputs, feeds)]
        except Exception as e:
            raise errors.FallbackFailed(f"ONNX Runtime failed: {e}") from e

    def act(self, s: FloatArray) -> FloatArray:
        (action,) = self._run(self.actor, ["action"], {"observation": s})
        return action

    def q_each(self, s: FloatArray, a: FloatArray) -> list[FloatArray]:
        return [self._run(c, ["q"], {"observation": s, "action": a})[0][:, 0] for c in self.critics]

    def aggregate(self, qs: list[FloatArray]) -> FloatArray:
        result: FloatArray = np.mean(qs, axis=0, dtype=F32) if self.mean_q else np.minimum.reduce(qs)
        return result

    def distance(self, s: FloatArray, a: FloatArray) -> FloatArray:
        if not self.gaussian:
            raise errors.FallbackFailed("guard.support_limit needs a Gaussian actor")
        mean, log_std = self._run(self.actor, ["mean", "log_std"], {"observation": s})
        squashed = 2.0 * (a - self.low) / (self.high - self.low) - 1.0
        pre = np.arctanh(np.clip(squashed, -SQUASHED_LIMIT, SQUASHED_LIMIT))
        limit = np.arctanh(SQUASHED_LIMIT)
        result: FloatArray = (np.abs(pre - np.clip(mean, -limit, limit)) / np.exp(log_std)).max(axis=1)
        return result

    def predict(self, s: FloatArray, a: FloatArray) -> FloatArray:
        (next_observation,) = self._run(self.model, ["next_observation"], {"observation": s, "action": a})
        return next_observation

    def to_environment(self, a: FloatArray) -> FloatArray:
        return a

    def from_environment(self, a: FloatArray) -> FloatArray:
        return np.asarray(a, dtype=F32)


class Fallback:
    """A policy on board: the exported networks, shareable by any number of sessions; each
    session that goes local starts its own `OnBoard` session from them."""

    def __init__(self, folder: PathLike, *, threads: int = 1) -> None:
        self.networks = OnnxNetworks(folder, threads=threads)
        self.content_hash: str = self.networks.contract["content_hash"]

    def start(self, options: pb.ResolvedOptions, held: pb.Plan | None) -> OnBoard:
        """A local session with the options in force, resumed from `held` (the plan the last
        answer committed) as a server would resume it."""
        if options.sampled:
            raise errors.FallbackFailed("the on-board fallback replans deterministic sessions only")
        state = replan.settings_from(options)
        if held is not None and len(held.actions) > 0:
            try:
                replan.resume(state, self.networks, held, self.networks.low, self.networks.high)
            except ValueError as e:
                raise errors.FallbackFailed(f"cannot resume the held plan on board: {e}") from e
        return OnBoard(self.networks, state)


class OnBoard:
    """One session's Replan on board, from the moment no server answered until one takes it back."""

    def __init__(self, networks: OnnxNetworks, state: replan.PlanState) -> None:
        self.networks = networks
        self._state = state

    def step(self, observation: list[float], new_episode: bool) -> pb.StepResponse:
        """One Replan on board; the answer is what a server would give."""
        state = self._state
        s = np.asarray(observation, dtype=F32)
        if s.shape != (self.networks.obs_dim,):
            raise errors.InvalidObservation(f"observation has {s.size} values; the policy expects {self.networks.obs_dim}")
        if not np.isfinite(s).all():
            raise errors.InvalidObservation("observation has a value that is not finite")
        ((kept, broke_at),) = replan.replan_batch(self.networks, [(state, s, new_episode or state.step is None)])
        return replan.response(state, self.networks, kept, broke_at)
