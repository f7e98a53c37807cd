"""What sessions keep to survive losing their server (a restart, a failover to another replica):
the plan committed by the last answer, the options in force, and how to tell from the server's
plan whether a step whose answer was lost was applied. Shared by the sync and asyncio clients."""

from __future__ import annotations

from prac_client import errors
from prac_client._proto.prac.v1 import prac_pb2 as pb

# The server no longer knows the session (restarted, another replica, evicted) or no server
# answered: the session is re-opened with the plan it holds.
RESUMABLE: tuple[type[errors.PracError], ...] = (
    errors.SessionNotFound,
    errors.SessionExpired,
    errors.ServerUnavailable,
)

# Metadata key a proxy hashes on to keep a client's calls on one replica (deploy/haproxy, deploy/nginx).
AFFINITY_HEADER = "x-prac-affinity"

# Seconds between tries while no server answers.
RETRY_PAUSE = 0.1

# While a session goes on on board: seconds between tries to resume it on a server, and how long
# each try waits.
PROBE_EVERY = 1.0
PROBE_TIMEOUT = 0.2


def held_plan(response: pb.StepResponse) -> pb.Plan:
    """The commitment an answer holds, as OpenSession's `resume` takes it."""
    return pb.Plan(episode=response.episode, start_step=response.step, actions=response.forecast)


def options_in_force(resolved: pb.ResolvedOptions) -> pb.SessionOptions:
    """The options a session was opened with, as resolved by its first server (epsilon absolute),
    so that a resumed session keeps exactly its tolerance, growth, horizon, seed and guard."""
    options = pb.SessionOptions(
        epsilon=resolved.epsilon,
        max_horizon=resolved.max_horizon,
        sampled=resolved.sampled,
        seed=resolved.seed,
    )
    if resolved.growth_mode == "fixed":
        options.fixed = resolved.growth
    else:
        options.grow = resolved.growth
    # The guard in force, which may have been the bundle's default: explicit, so another server's
    # default cannot change it.
    if resolved.HasField("guard"):
        options.guard.CopyFrom(resolved.guard)
    return options


def applied(held: pb.Plan | None, now: pb.Plan) -> bool:
    """Whether the server applied a step after the one that committed `held`: every applied step
    moves the step counter or the episode (and the first gives the session a plan)."""
    if held is None:
        return len(now.actions) > 0
    return (now.episode, now.start_step) != (held.episode, held.start_step)


def answer_from_plan(held: pb.Plan | None, now: pb.Plan) -> pb.StepResponse:
    """The answer of an applied step, rebuilt from the plan it committed: its kept actions are
    the ones decided before this step, and the old plan broke where they stop."""
    fresh = held is None or now.episode != held.episode
    remaining = 0 if held is None or fresh else max(len(held.actions) - 1, 0)
    kept = sum(1 for a in now.actions if a.decided_at < now.start_step)
    response = pb.StepResponse(
        action=now.actions[0].action,
        forecast=now.actions,
        kept=kept,
        f_t=now.start_step + 1 - now.actions[0].decided_at,
        step=now.start_step,
        episode=now.episode,
    )
    if kept < remaining:
        response.broke_at = kept
    return response


def following(held: pb.Plan | None) -> pb.StepResponse | None:
    """The held plan one step on, as an answer: its action for the next step, unchecked; None
    when the plan holds no action past the one executed."""
    if held is None or len(held.actions) < 2:
        return None
    rest = held.actions[1:]
    step = held.start_step + 1
    return pb.StepResponse(
        action=rest[0].action,
        forecast=rest,
        kept=len(rest),
        f_t=step + 1 - rest[0].decided_at,
        step=step,
        episode=held.episode,
    )
