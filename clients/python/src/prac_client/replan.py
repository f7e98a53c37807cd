"""Algorithm 2 (Replan) in numpy, over any networks that give the policy's action, the critics'
values and the model's next state. The on-board fallback (`prac_client.onboard`) runs it on
`prac export-onnx`'s files; the Python baseline server (clients/python/baseline) runs it on a
bundle's weights. Python has this one Replan.

Plans are batched across sessions of one policy: the old plans are checked CHUNK actions at a
time (the model rolled over the chunk, then one actor and one critic pass over every state of
every chunk), and the new actions are added in lockstep.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from prac_client._proto.prac.v1 import prac_pb2 as pb

F32 = np.float32
FloatArray = npt.NDArray[np.float32]
# Old actions checked per round: one batched actor and critic pass for all of them.
CHUNK = 8
# Longest plan when a session sets none (the server's default).
DEFAULT_MAX_HORIZON = 32


class Networks(Protocol):
    """A policy's networks, batched over rows. Actions are in the networks' own units (squashed to
    [-1, 1] for a bundle's weights, the environment's for exported files); `to_environment` and
    `from_environment` convert."""

    obs_dim: int
    act_dim: int

    def act(self, s: FloatArray) -> FloatArray:
        """The deterministic action at each state."""
        ...

    def q_each(self, s: FloatArray, a: FloatArray) -> list[FloatArray]:
        """Each critic's value of (s, a), one array per critic."""
        ...

    def aggregate(self, qs: list[FloatArray]) -> FloatArray:
        """The critics' values combined as the bundle says (min or mean)."""
        ...

    def distance(self, s: FloatArray, a: FloatArray) -> FloatArray:
        """How many of the policy's standard deviations a lies from its Gaussian's mean before
        tanh, the largest over the action's entries (the guard's support_limit test)."""
        ...

    def predict(self, s: FloatArray, a: FloatArray) -> FloatArray:
        """The model's next observation, kept inside the observation bounds."""
        ...

    def to_environment(self, a: FloatArray) -> FloatArray:
        """Actions in the environment's units."""
        ...

    def from_environment(self, a: FloatArray) -> FloatArray:
        """Actions in the environment's units (within the bounds) in the networks' units."""
        ...


@dataclass(kw_only=True)
class PlanState:
    """One session's settings and committed plan."""

    epsilon: float
    grow: int | None
    fixed: int | None
    max_horizon: int
    # The guard (all off: the paper's test).
    every_critic: bool = False
    support_limit: float = 0.0
    # The committed plan, in the networks' units: actions [n, act], predicted observations
    # [n, obs], and the step each action was decided at.
    actions: FloatArray = field(default_factory=lambda: np.zeros((0, 0), F32))
    predicted: FloatArray = field(default_factory=lambda: np.zeros((0, 0), F32))
    decided: list[int] = field(default_factory=list)
    step: int | None = None
    episode: int = 0
    served: int = 0


def settings_from(options: pb.ResolvedOptions) -> PlanState:
    """A session's state with the options a server resolved (epsilon absolute, guard explicit)."""
    fixed = options.growth_mode == "fixed"
    return PlanState(
        epsilon=float(F32(options.epsilon)),
        grow=None if fixed else int(options.growth),
        fixed=int(options.growth) if fixed else None,
        max_horizon=int(options.max_horizon),
        every_critic=bool(options.guard.every_critic),
        support_limit=float(F32(options.guard.support_limit)),
    )


def resume(state: PlanState, networks: Networks, plan: pb.Plan, low: FloatArray, high: FloatArray) -> None:
    """Takes over a plan committed elsewhere, as the server's OpenSession with `resume` does:
    `plan.actions[0]` was executed at step `plan.start_step`, the rest is the commitment, each
    kept only while it passes Replan's test. Raises ValueError for a plan a server would refuse."""
    if not plan.actions:
        raise ValueError("the resumed plan has no actions")
    if len(plan.actions) > state.max_horizon:
        raise ValueError(f"the resumed plan has {len(plan.actions)} actions; the session's max_horizon is {state.max_horizon}")
    actions = np.array([list(entry.action) for entry in plan.actions], dtype=F32)
    if actions.shape[1] != networks.act_dim:
        raise ValueError(f"the resumed plan's actions have {actions.shape[1]} values; the policy expects {networks.act_dim}")
    if not (np.isfinite(actions).all() and (actions >= low).all() and (actions <= high).all()):
        raise ValueError("the resumed plan has an action that is not finite or outside the action bounds")
    decided = [int(entry.decided_at) for entry in plan.actions]
    if max(decided) > plan.start_step:
        raise ValueError("the resumed plan has an action decided after its start_step")
    state.actions = networks.from_environment(actions)
    # Not trusted, as the server does not: the next step rolls the model again.
    state.predicted = np.full((len(decided), networks.obs_dim), np.nan, F32)
    state.decided = decided
    state.step = int(plan.start_step)
    state.episode = int(plan.episode)


def replan_batch(networks: Networks, jobs: list[tuple[PlanState, FloatArray, bool]]) -> list[tuple[int, int | None]]:
    """Algorithm 2 for several sessions of one policy at once. Each job is (session, observed
    state, fresh); returns (kept, broke_at) per job and leaves each new plan on its session."""
    b = len(jobs)
    od, ad = networks.obs_dim, networks.act_dim
    state = np.stack([s for _, s, _ in jobs]).astype(F32)
    olds: list[tuple[FloatArray, list[int]]] = []
    for session, _, fresh in jobs:
        if fresh or len(session.decided) == 0:
            olds.append((np.zeros((0, ad), F32), []))
        else:
            olds.append((session.actions[1:], session.decided[1:]))
    limit = [min(len(o[1]), jobs[k][0].max_horizon) for k, o in enumerate(olds)]
    kept = [0] * b
    broke: list[int | None] = [None] * b
    new_actions: list[list[FloatArray]] = [[] for _ in range(b)]
    new_states: list[list[FloatArray]] = [[] for _ in range(b)]
    new_decided: list[list[int]] = [[] for _ in range(b)]
    pi_at_break: list[FloatArray | None] = [None] * b
    checking = [k for k in range(b) if limit[k] > 0]
    while checking:
        rows, owner, depth = [], [], []
        starts = {k: state[k].copy() for k in checking}
        s = np.stack([state[k] for k in checking])
        cur = {k: i for i, k in enumerate(checking)}
        rolled: dict[int, list[FloatArray]] = {k: [] for k in checking}
        for c in range(CHUNK):
            alive = [k for k in checking if kept[k] + c < limit[k]]
            if not alive:
                break
            idx = [cur[k] for k in alive]
            a = np.stack([olds[k][0][kept[k] + c] for k in alive])
            for k, i in zip(alive, idx):
                rows.append(s[i].copy())
                owner.append(k)
                depth.append(c)
            nxt = networks.predict(s[idx], a)
            s[idx] = nxt
            for k, r in zip(alive, nxt):
                rolled[k].append(r)
        states = np.stack(rows)
        old_a = np.stack([olds[k][0][kept[k] + c] for k, c in zip(owner, depth)])
        pi = networks.act(states)
        each = networks.q_each(np.concatenate([states, states]), np.concatenate([pi, old_a]))
        both = networks.aggregate(each)
        q_pi, q_a = both[: len(rows)], both[len(rows) :]
        # The guard: the largest one-critic gap, and the distance from the policy's Gaussian.
        gap = np.maximum.reduce([q[: len(rows)] - q[len(rows) :] for q in each])
        support = any(jobs[k][0].support_limit > 0 for k in checking)
        distance = networks.distance(states, old_a) if support else None
        first_fail: dict[int, int] = {}
        for r, (k, c) in enumerate(zip(owner, depth)):
            session = jobs[k][0]
            eps = F32(session.epsilon)
            breaks = bool(q_a[r] + eps < q_pi[r]) or (session.every_critic and bool(gap[r] > eps))
            if distance is not None and session.support_limit > 0:
                breaks = breaks or bool(distance[r] > F32(session.support_limit))
            if k not in first_fail and breaks:
                first_fail[k] = c
                pi_at_break[k] = pi[r]
        still = []
        for k in checking:
            n_checked = len(rolled[k])
            good = first_fail.get(k, n_checked)
            for c in range(good):
                new_actions[k].append(olds[k][0][kept[k] + c])
                new_states[k].append(rolled[k][c])
                new_decided[k].append(olds[k][1][kept[k] + c])
            state[k] = rolled[k][good - 1] if good > 0 else starts[k]
            kept[k] += good
            if k in first_fail:
                broke[k] = kept[k]
            elif kept[k] < limit[k]:
                still.append(k)
        checking = still
    # Extend each plan with the policy, all sessions in lockstep.
    wanted = []
    for k, (session, _, _) in enumerate(jobs):
        w = session.grow if session.grow is not None else max((session.fixed or 0) - kept[k], 0)
        wanted.append(min(w, session.max_horizon - kept[k]))
    s = state.copy()
    for m in range(max(wanted, default=0)):
        alive = [k for k in range(b) if m < wanted[k]]
        need = [k for k in alive if not (m == 0 and pi_at_break[k] is not None)]
        a = np.zeros((len(alive), ad), F32)
        if need:
            computed = networks.act(s[need])
            for k, row in zip(need, computed):
                a[alive.index(k)] = row
        for k in alive:
            at_break = pi_at_break[k]
            if m == 0 and at_break is not None:
                a[alive.index(k)] = at_break
        nxt = networks.predict(s[alive], a)
        s[alive] = nxt
        for i, k in enumerate(alive):
            new_actions[k].append(a[i])
            new_states[k].append(nxt[i])
            new_decided[k].append(-1)  # decided now: the step, filled in below
    out = []
    for k, (session, _, fresh) in enumerate(jobs):
        t = 0 if fresh or session.step is None else session.step + 1
        if fresh and session.step is not None:
            session.episode += 1
        session.step = t
        session.actions = np.stack(new_actions[k]).astype(F32) if new_actions[k] else np.zeros((0, ad), F32)
        session.predicted = np.stack(new_states[k]).astype(F32) if new_states[k] else np.zeros((0, od), F32)
        session.decided = [t if d < 0 else d for d in new_decided[k]]
        session.served += 1
        out.append((kept[k], broke[k]))
    return out


def response(session: PlanState, networks: Networks, kept: int, broke_at: int | None) -> pb.StepResponse:
    """The step's answer, as the server gives it: the action now and the committed forecast."""
    assert session.step is not None, "answered before any step"
    actions = networks.to_environment(session.actions)
    forecast = [
        pb.PlannedAction(
            action=actions[j].tolist(), predicted_observation=session.predicted[j].tolist(), decided_at=session.decided[j]
        )
        for j in range(len(session.decided))
    ]
    r = pb.StepResponse(
        action=actions[0].tolist(),
        forecast=forecast,
        kept=kept,
        f_t=session.step + 1 - session.decided[0],
        step=session.step,
        episode=session.episode,
    )
    if broke_at is not None:
        r.broke_at = broke_at
    return r
