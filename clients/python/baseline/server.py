"""A prac.v1 server in Python, written as a Python engineer would write it well: grpc.aio,
float32 numpy, and Replan batched across sessions, the plan checked in chunks. It is the
yardstick docs/performance.md compares `prac serve` with, not part of the client package.

    python clients/python/baseline/server.py --bundles bundles --listen 127.0.0.1:50061

Serves ListPolicies, OpenSession (deterministic sessions: no `sampled`, no `resume`),
CloseSession, Step, StepStream and GetPlan. Answers equal prac serve's (actions to float32
rounding; kept, broke_at, f_t exactly) for the same bundle, options and observations.
"""

from __future__ import annotations

import os

# One BLAS thread: a latency server gets nothing from BLAS threads spinning on small matrices
# (measured: 2.1x the CPU per step at 1 session with OpenBLAS's default threads, same throughput).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse
import asyncio
import json
import pathlib
import secrets
from dataclasses import dataclass
from typing import Any, AsyncIterator

import grpc
import grpc.aio
import numpy as np
from safetensors.numpy import load_file

from prac_client._proto.prac.v1 import prac_pb2 as pb
from prac_client._proto.prac.v1 import prac_pb2_grpc as pb_grpc
from prac_client.replan import DEFAULT_MAX_HORIZON, PlanState, replan_batch, response

F32 = np.float32
LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0
# Actions and means are clamped here before atanh, so actions at the bounds compare finitely.
SQUASHED_LIMIT = F32(1.0) - np.finfo(F32).eps


def _activation(name: str) -> Any:
    return {"relu": lambda x: np.maximum(x, 0, out=x), "tanh": lambda x: np.tanh(x, out=x)}[name.lower()]


LAYER_NORM_EPS = 1e-5  # PyTorch's nn.LayerNorm default


class Mlp:
    """Linear layers [out, in] (PyTorch layout, kept transposed for x @ W), activation between
    them, and after the last one too when `last_activation`. With `layer_norm` the network is
    nn.Sequential(Linear, LayerNorm, act, ..., Linear): linear layer i at index 3i, its norm at
    3i + 1, normalising each hidden layer's output before the activation."""

    def __init__(
        self,
        tensors: dict[str, np.ndarray],
        prefix: str,
        layers: int,
        activation: str,
        last_activation: bool,
        layer_norm: bool = False,
    ):
        stride = 3 if layer_norm else 2
        self.weights = [np.ascontiguousarray(tensors[f"{prefix}.{stride * i}.weight"].T, dtype=F32) for i in range(layers)]
        self.biases = [tensors[f"{prefix}.{stride * i}.bias"].astype(F32) for i in range(layers)]
        self.norms = [
            (tensors[f"{prefix}.{3 * i + 1}.weight"].astype(F32), tensors[f"{prefix}.{3 * i + 1}.bias"].astype(F32))
            for i in range(layers - 1 if layer_norm else 0)
        ]
        self.act = _activation(activation)
        self.last_activation = last_activation

    def __call__(self, x: np.ndarray) -> np.ndarray:
        n = len(self.weights)
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = x @ w
            x += b
            if i < len(self.norms):
                scale, shift = self.norms[i]
                mean = x.mean(axis=-1, keepdims=True)
                var = ((x - mean) ** 2).mean(axis=-1, keepdims=True)
                x = (x - mean) / np.sqrt(var + LAYER_NORM_EPS) * scale + shift
            if i < n - 1 or self.last_activation:
                x = self.act(x)
        return x


class Policy:
    def __init__(self, path: pathlib.Path):
        tensors = load_file(str(path))
        with open(path, "rb") as f:
            header_len = int.from_bytes(f.read(8), "little")
            header = json.loads(f.read(header_len))
        m = json.loads(header["__metadata__"]["manifest"])
        self.manifest = m
        self.obs_dim, self.act_dim = m["obs_dim"], m["act_dim"]
        self.low = np.array(m["action_low"], dtype=F32)
        self.high = np.array(m["action_high"], dtype=F32)
        actor_layers = len(m["actor"]["hidden"])
        self.trunk = Mlp(tensors, "actor.latent_pi", actor_layers, m["actor"]["activation"], True)
        self.mu_w = np.ascontiguousarray(tensors["actor.mu.weight"].T, dtype=F32)
        self.mu_b = tensors["actor.mu.bias"].astype(F32)
        self.log_std_w = np.ascontiguousarray(tensors["actor.log_std.weight"].T, dtype=F32) if "actor.log_std.weight" in tensors else None
        self.log_std_b = tensors["actor.log_std.bias"].astype(F32) if "actor.log_std.bias" in tensors else None
        critic_layers = len(m["critic"]["hidden"]) + 1
        critic_norm = bool(m["critic"].get("layer_norm", False))
        self.critics = [
            Mlp(tensors, f"critic.qf{k}", critic_layers, m["critic"]["activation"], False, critic_norm)
            for k in range(m["critic"]["n_critics"])
        ]
        self.mean_q = m.get("q_aggregation", "min") == "mean"
        spec = m["model"]
        self.model = Mlp(tensors, "model.net", len(spec["hidden"]) + 1, spec["activation"], False)
        n = spec["normalization"]
        self.norm = {k: np.array(v, dtype=F32) for k, v in n.items()}
        self.value_scale = m.get("value_scale")
        bounds = m.get("obs_bounds")
        # The observation space the forecasts are kept inside (infinite where unbounded).
        self.obs_limits = None if bounds is None else (
            np.array([-np.inf if v is None else v for v in bounds["low"]], dtype=F32),
            np.array([np.inf if v is None else v for v in bounds["high"]], dtype=F32),
        )

    def act(self, s: np.ndarray) -> np.ndarray:
        """Deterministic actions tanh(mu) in [-1, 1], one row per state."""
        return np.tanh(self.trunk(s.copy()) @ self.mu_w + self.mu_b)

    def q(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        return self.aggregate(self.q_each(s, a))

    def q_each(self, s: np.ndarray, a: np.ndarray) -> list[np.ndarray]:
        x = np.concatenate([s, a], axis=1)
        return [c(x.copy())[:, 0] for c in self.critics]

    def aggregate(self, qs: list[np.ndarray]) -> np.ndarray:
        return np.mean(qs, axis=0, dtype=F32) if self.mean_q else np.minimum.reduce(qs)

    def distance(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Per row, how many of the policy's standard deviations a lies from its Gaussian's mean
        before tanh (the guard's support_limit test), the largest over the action's entries."""
        assert self.log_std_w is not None and self.log_std_b is not None
        latent = self.trunk(s.copy())
        mu = latent @ self.mu_w + self.mu_b
        std = np.exp(np.clip(latent @ self.log_std_w + self.log_std_b, F32(LOG_STD_MIN), F32(LOG_STD_MAX)))
        pre = np.arctanh(np.clip(a, -SQUASHED_LIMIT, SQUASHED_LIMIT))
        limit = np.arctanh(SQUASHED_LIMIT)
        return (np.abs(pre - np.clip(mu, -limit, limit)) / std).max(axis=1)

    def predict(self, s: np.ndarray, a: np.ndarray) -> np.ndarray:
        n = self.norm
        x = np.concatenate([(s - n["obs_mean"]) / n["obs_std"], (a - n["action_mean"]) / n["action_std"]], axis=1)
        predicted = s + (self.model(x) * n["delta_std"] + n["delta_mean"])
        if self.obs_limits is not None:
            # np.clip keeps NaN, as the server does (a non-finite prediction is refused).
            predicted = np.clip(predicted, self.obs_limits[0], self.obs_limits[1])
        return predicted

    def to_environment(self, a: np.ndarray) -> np.ndarray:
        return self.low + 0.5 * (a + 1.0) * (self.high - self.low)

    def from_environment(self, a: np.ndarray) -> np.ndarray:
        return np.clip(2.0 * (a - self.low) / (self.high - self.low) - 1.0, -1.0, 1.0).astype(F32)


@dataclass(kw_only=True)
class Session(PlanState):
    policy_name: str
    policy: Policy


class Batcher:
    """Steps wait here; one task replans everything waiting, policy by policy, in one batch."""

    def __init__(self) -> None:
        self.queue: asyncio.Queue[tuple[Session, np.ndarray, bool, asyncio.Future[pb.StepResponse]]] = asyncio.Queue()

    async def step(self, session: Session, observation: np.ndarray, new_episode: bool) -> pb.StepResponse:
        done: asyncio.Future[pb.StepResponse] = asyncio.get_running_loop().create_future()
        await self.queue.put((session, observation, new_episode, done))
        return await done

    async def run(self) -> None:
        while True:
            batch = [await self.queue.get()]
            while not self.queue.empty() and len(batch) < 256:
                batch.append(self.queue.get_nowait())
            groups: dict[int, list[Any]] = {}
            seen: set[int] = set()
            later = []
            for item in batch:
                if id(item[0]) in seen:
                    later.append(item)  # a session's steps stay in order
                    continue
                seen.add(id(item[0]))
                groups.setdefault(id(item[0].policy), []).append(item)
            for items in groups.values():
                jobs = [(sess, obs, new_episode or sess.step is None) for sess, obs, new_episode, _ in items]
                try:
                    outcomes = replan_batch(items[0][0].policy, jobs)
                except Exception as e:  # a bug must not stop the batcher
                    for *_, done in items:
                        if not done.done():
                            done.set_exception(e)
                    continue
                for (sess, _, _, done), (kept, broke_at) in zip(items, outcomes):
                    if not done.done():
                        done.set_result(response(sess, sess.policy, kept, broke_at))
            for item in later:
                self.queue.put_nowait(item)


class Service(pb_grpc.PracServicer):  # type: ignore[misc]
    def __init__(self, policies: dict[str, Policy]) -> None:
        self.policies = policies
        self.sessions: dict[str, Session] = {}
        self.batcher = Batcher()

    def info(self, name: str) -> pb.PolicyInfo:
        p = self.policies[name]
        info = pb.PolicyInfo(
            name=name,
            domain=p.manifest["domain"],
            obs_dim=p.obs_dim,
            act_dim=p.act_dim,
            action_low=p.low.tolist(),
            action_high=p.high.tolist(),
            gamma=p.manifest["gamma"],
        )
        default_guard = p.manifest.get("default_guard") or {}
        info.default_guard.every_critic = default_guard.get("every_critic", False)
        info.default_guard.support_limit = float(F32(default_guard.get("support_limit", 0.0)))
        info.default_guard.max_epsilon_coef = default_guard.get("max_epsilon_coef", 0.0)
        if p.value_scale:
            info.value_scale.v_pi = p.value_scale["v_pi"]
            info.value_scale.v_rand = p.value_scale["v_rand"]
        return info

    async def ListPolicies(self, request: Any, context: Any) -> pb.ListPoliciesResponse:
        return pb.ListPoliciesResponse(policies=[self.info(name) for name in self.policies])

    async def OpenSession(self, request: Any, context: Any) -> pb.OpenSessionResponse:
        p = self.policies.get(request.policy)
        if p is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"unknown policy '{request.policy}'")
        o = request.options
        if o.sampled or request.HasField("resume"):
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "the baseline serves deterministic sessions without resume")
        which = o.WhichOneof("tolerance")
        eps = 0.0
        if which == "epsilon":
            eps = o.epsilon
        elif which == "epsilon_coef":
            vs = p.value_scale
            eps = o.epsilon_coef * (vs["v_pi"] - vs["v_rand"])
        growth = o.WhichOneof("growth")
        grow = o.grow if growth == "grow" else (None if growth == "fixed" else 2)
        fixed = o.fixed if growth == "fixed" else None
        horizon = o.max_horizon or (max(fixed, DEFAULT_MAX_HORIZON) if fixed else DEFAULT_MAX_HORIZON)
        # Unset: the bundle's default_guard (absent: the paper's test).
        guard = o.guard if o.HasField("guard") else p.manifest.get("default_guard") or {}
        every_critic = bool(guard.every_critic if o.HasField("guard") else guard.get("every_critic", False))
        support_limit = guard.support_limit if o.HasField("guard") else guard.get("support_limit", 0.0)
        if support_limit > 0 and p.log_std_w is None:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "guard.support_limit needs a Gaussian actor")
        # Not a break: eps is held to max_epsilon_coef x (V_pi - V_rand), in f64 before it becomes an f32.
        max_coef = guard.max_epsilon_coef if o.HasField("guard") else guard.get("max_epsilon_coef", 0.0)
        if max_coef > 0:
            if not p.value_scale or p.value_scale["v_pi"] <= p.value_scale["v_rand"]:
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "guard.max_epsilon_coef needs a value scale")
            eps = min(eps, max_coef * (p.value_scale["v_pi"] - p.value_scale["v_rand"]))
        session = Session(
            policy_name=request.policy,
            policy=p,
            epsilon=float(F32(eps)),
            grow=grow,
            fixed=fixed,
            max_horizon=horizon,
            every_critic=every_critic,
            support_limit=float(F32(support_limit)),
        )
        sid = secrets.token_hex(16)
        self.sessions[sid] = session
        resolved = pb.ResolvedOptions(
            epsilon=session.epsilon,
            growth_mode="fixed" if fixed else "grow",
            growth=fixed or grow or 2,
            max_horizon=horizon,
            guard=pb.PlanGuard(
                every_critic=every_critic, support_limit=session.support_limit, max_epsilon_coef=max_coef
            ),
        )
        return pb.OpenSessionResponse(session_id=sid, policy=self.info(request.policy), options=resolved)

    async def CloseSession(self, request: Any, context: Any) -> pb.CloseSessionResponse:
        session = self.sessions.pop(request.session_id, None)
        if session is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"unknown session '{request.session_id}'")
        return pb.CloseSessionResponse(steps=session.served)

    async def _step(self, request: Any, context: Any) -> pb.StepResponse:
        session = self.sessions.get(request.session_id)
        if session is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"unknown session '{request.session_id}'")
        obs = np.asarray(request.observation, dtype=F32)
        if obs.shape != (session.policy.obs_dim,) or not np.isfinite(obs).all():
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "bad observation")
        return await self.batcher.step(session, obs, request.new_episode)

    async def Step(self, request: Any, context: Any) -> pb.StepResponse:
        return await self._step(request, context)

    async def StepStream(self, requests: AsyncIterator[Any], context: Any) -> AsyncIterator[pb.StepResponse]:
        async for request in requests:
            yield await self._step(request, context)

    async def GetPlan(self, request: Any, context: Any) -> pb.Plan:
        session = self.sessions.get(request.session_id)
        if session is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"unknown session '{request.session_id}'")
        actions = session.policy.to_environment(session.actions)
        return pb.Plan(
            session_id=request.session_id,
            episode=session.episode,
            start_step=session.step or 0,
            actions=[
                pb.PlannedAction(action=actions[j].tolist(), predicted_observation=session.predicted[j].tolist(), decided_at=d)
                for j, d in enumerate(session.decided)
            ],
        )


async def serve(bundles: pathlib.Path, listen: str) -> None:
    policies = {}
    for path in sorted(bundles.glob("*.safetensors")):
        try:
            policies[path.stem] = Policy(path)
        except (KeyError, TypeError) as e:
            print(f"skipping {path}: {e}", flush=True)
    service = Service(policies)
    server = grpc.aio.server(options=[("grpc.so_reuseport", 0)])
    pb_grpc.add_PracServicer_to_server(service, server)
    port = server.add_insecure_port(listen)
    await server.start()
    host = listen.rsplit(":", 1)[0]
    print(f"listening on {host}:{port}", flush=True)
    batcher = asyncio.create_task(service.batcher.run())
    try:
        await server.wait_for_termination()
    finally:
        batcher.cancel()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bundles", type=pathlib.Path, required=True)
    parser.add_argument("--listen", default="127.0.0.1:50061")
    args = parser.parse_args()
    asyncio.run(serve(args.bundles, args.listen))


if __name__ == "__main__":
    main()
