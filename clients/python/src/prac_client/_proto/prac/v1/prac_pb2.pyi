from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ListPoliciesRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListPoliciesResponse(_message.Message):
    __slots__ = ("policies",)
    POLICIES_FIELD_NUMBER: _ClassVar[int]
    policies: _containers.RepeatedCompositeFieldContainer[PolicyInfo]
    def __init__(self, policies: _Optional[_Iterable[_Union[PolicyInfo, _Mapping]]] = ...) -> None: ...

class PolicyInfo(_message.Message):
    __slots__ = ("name", "domain", "obs_dim", "act_dim", "action_low", "action_high", "gamma", "value_scale", "content_hash", "q_aggregation", "format_version", "default_guard", "control_period", "observation_features", "action_features")
    NAME_FIELD_NUMBER: _ClassVar[int]
    DOMAIN_FIELD_NUMBER: _ClassVar[int]
    OBS_DIM_FIELD_NUMBER: _ClassVar[int]
    ACT_DIM_FIELD_NUMBER: _ClassVar[int]
    ACTION_LOW_FIELD_NUMBER: _ClassVar[int]
    ACTION_HIGH_FIELD_NUMBER: _ClassVar[int]
    GAMMA_FIELD_NUMBER: _ClassVar[int]
    VALUE_SCALE_FIELD_NUMBER: _ClassVar[int]
    CONTENT_HASH_FIELD_NUMBER: _ClassVar[int]
    Q_AGGREGATION_FIELD_NUMBER: _ClassVar[int]
    FORMAT_VERSION_FIELD_NUMBER: _ClassVar[int]
    DEFAULT_GUARD_FIELD_NUMBER: _ClassVar[int]
    CONTROL_PERIOD_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_FEATURES_FIELD_NUMBER: _ClassVar[int]
    ACTION_FEATURES_FIELD_NUMBER: _ClassVar[int]
    name: str
    domain: str
    obs_dim: int
    act_dim: int
    action_low: _containers.RepeatedScalarFieldContainer[float]
    action_high: _containers.RepeatedScalarFieldContainer[float]
    gamma: float
    value_scale: ValueScale
    content_hash: str
    q_aggregation: str
    format_version: int
    default_guard: PlanGuard
    control_period: float
    observation_features: _containers.RepeatedCompositeFieldContainer[Feature]
    action_features: _containers.RepeatedCompositeFieldContainer[Feature]
    def __init__(self, name: _Optional[str] = ..., domain: _Optional[str] = ..., obs_dim: _Optional[int] = ..., act_dim: _Optional[int] = ..., action_low: _Optional[_Iterable[float]] = ..., action_high: _Optional[_Iterable[float]] = ..., gamma: _Optional[float] = ..., value_scale: _Optional[_Union[ValueScale, _Mapping]] = ..., content_hash: _Optional[str] = ..., q_aggregation: _Optional[str] = ..., format_version: _Optional[int] = ..., default_guard: _Optional[_Union[PlanGuard, _Mapping]] = ..., control_period: _Optional[float] = ..., observation_features: _Optional[_Iterable[_Union[Feature, _Mapping]]] = ..., action_features: _Optional[_Iterable[_Union[Feature, _Mapping]]] = ...) -> None: ...

class Feature(_message.Message):
    __slots__ = ("name", "unit")
    NAME_FIELD_NUMBER: _ClassVar[int]
    UNIT_FIELD_NUMBER: _ClassVar[int]
    name: str
    unit: str
    def __init__(self, name: _Optional[str] = ..., unit: _Optional[str] = ...) -> None: ...

class ValueScale(_message.Message):
    __slots__ = ("v_pi", "v_rand")
    V_PI_FIELD_NUMBER: _ClassVar[int]
    V_RAND_FIELD_NUMBER: _ClassVar[int]
    v_pi: float
    v_rand: float
    def __init__(self, v_pi: _Optional[float] = ..., v_rand: _Optional[float] = ...) -> None: ...

class SessionOptions(_message.Message):
    __slots__ = ("epsilon", "epsilon_coef", "grow", "fixed", "max_horizon", "sampled", "seed", "guard")
    EPSILON_FIELD_NUMBER: _ClassVar[int]
    EPSILON_COEF_FIELD_NUMBER: _ClassVar[int]
    GROW_FIELD_NUMBER: _ClassVar[int]
    FIXED_FIELD_NUMBER: _ClassVar[int]
    MAX_HORIZON_FIELD_NUMBER: _ClassVar[int]
    SAMPLED_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    GUARD_FIELD_NUMBER: _ClassVar[int]
    epsilon: float
    epsilon_coef: float
    grow: int
    fixed: int
    max_horizon: int
    sampled: bool
    seed: int
    guard: PlanGuard
    def __init__(self, epsilon: _Optional[float] = ..., epsilon_coef: _Optional[float] = ..., grow: _Optional[int] = ..., fixed: _Optional[int] = ..., max_horizon: _Optional[int] = ..., sampled: _Optional[bool] = ..., seed: _Optional[int] = ..., guard: _Optional[_Union[PlanGuard, _Mapping]] = ...) -> None: ...

class PlanGuard(_message.Message):
    __slots__ = ("every_critic", "support_limit", "max_epsilon_coef")
    EVERY_CRITIC_FIELD_NUMBER: _ClassVar[int]
    SUPPORT_LIMIT_FIELD_NUMBER: _ClassVar[int]
    MAX_EPSILON_COEF_FIELD_NUMBER: _ClassVar[int]
    every_critic: bool
    support_limit: float
    max_epsilon_coef: float
    def __init__(self, every_critic: _Optional[bool] = ..., support_limit: _Optional[float] = ..., max_epsilon_coef: _Optional[float] = ...) -> None: ...

class OpenSessionRequest(_message.Message):
    __slots__ = ("policy", "options", "resume", "local_steps")
    POLICY_FIELD_NUMBER: _ClassVar[int]
    OPTIONS_FIELD_NUMBER: _ClassVar[int]
    RESUME_FIELD_NUMBER: _ClassVar[int]
    LOCAL_STEPS_FIELD_NUMBER: _ClassVar[int]
    policy: str
    options: SessionOptions
    resume: Plan
    local_steps: int
    def __init__(self, policy: _Optional[str] = ..., options: _Optional[_Union[SessionOptions, _Mapping]] = ..., resume: _Optional[_Union[Plan, _Mapping]] = ..., local_steps: _Optional[int] = ...) -> None: ...

class OpenSessionResponse(_message.Message):
    __slots__ = ("session_id", "policy", "options", "resumed_actions")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    POLICY_FIELD_NUMBER: _ClassVar[int]
    OPTIONS_FIELD_NUMBER: _ClassVar[int]
    RESUMED_ACTIONS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    policy: PolicyInfo
    options: ResolvedOptions
    resumed_actions: int
    def __init__(self, session_id: _Optional[str] = ..., policy: _Optional[_Union[PolicyInfo, _Mapping]] = ..., options: _Optional[_Union[ResolvedOptions, _Mapping]] = ..., resumed_actions: _Optional[int] = ...) -> None: ...

class ResolvedOptions(_message.Message):
    __slots__ = ("epsilon", "growth_mode", "growth", "max_horizon", "sampled", "seed", "guard")
    EPSILON_FIELD_NUMBER: _ClassVar[int]
    GROWTH_MODE_FIELD_NUMBER: _ClassVar[int]
    GROWTH_FIELD_NUMBER: _ClassVar[int]
    MAX_HORIZON_FIELD_NUMBER: _ClassVar[int]
    SAMPLED_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    GUARD_FIELD_NUMBER: _ClassVar[int]
    epsilon: float
    growth_mode: str
    growth: int
    max_horizon: int
    sampled: bool
    seed: int
    guard: PlanGuard
    def __init__(self, epsilon: _Optional[float] = ..., growth_mode: _Optional[str] = ..., growth: _Optional[int] = ..., max_horizon: _Optional[int] = ..., sampled: _Optional[bool] = ..., seed: _Optional[int] = ..., guard: _Optional[_Union[PlanGuard, _Mapping]] = ...) -> None: ...

class CloseSessionRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class CloseSessionResponse(_message.Message):
    __slots__ = ("steps",)
    STEPS_FIELD_NUMBER: _ClassVar[int]
    steps: int
    def __init__(self, steps: _Optional[int] = ...) -> None: ...

class StepRequest(_message.Message):
    __slots__ = ("session_id", "observation", "new_episode")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    OBSERVATION_FIELD_NUMBER: _ClassVar[int]
    NEW_EPISODE_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    observation: _containers.RepeatedScalarFieldContainer[float]
    new_episode: bool
    def __init__(self, session_id: _Optional[str] = ..., observation: _Optional[_Iterable[float]] = ..., new_episode: _Optional[bool] = ...) -> None: ...

class PlannedAction(_message.Message):
    __slots__ = ("action", "predicted_observation", "decided_at")
    ACTION_FIELD_NUMBER: _ClassVar[int]
    PREDICTED_OBSERVATION_FIELD_NUMBER: _ClassVar[int]
    DECIDED_AT_FIELD_NUMBER: _ClassVar[int]
    action: _containers.RepeatedScalarFieldContainer[float]
    predicted_observation: _containers.RepeatedScalarFieldContainer[float]
    decided_at: int
    def __init__(self, action: _Optional[_Iterable[float]] = ..., predicted_observation: _Optional[_Iterable[float]] = ..., decided_at: _Optional[int] = ...) -> None: ...

class StepResponse(_message.Message):
    __slots__ = ("action", "forecast", "kept", "broke_at", "f_t", "step", "episode")
    ACTION_FIELD_NUMBER: _ClassVar[int]
    FORECAST_FIELD_NUMBER: _ClassVar[int]
    KEPT_FIELD_NUMBER: _ClassVar[int]
    BROKE_AT_FIELD_NUMBER: _ClassVar[int]
    F_T_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    EPISODE_FIELD_NUMBER: _ClassVar[int]
    action: _containers.RepeatedScalarFieldContainer[float]
    forecast: _containers.RepeatedCompositeFieldContainer[PlannedAction]
    kept: int
    broke_at: int
    f_t: int
    step: int
    episode: int
    def __init__(self, action: _Optional[_Iterable[float]] = ..., forecast: _Optional[_Iterable[_Union[PlannedAction, _Mapping]]] = ..., kept: _Optional[int] = ..., broke_at: _Optional[int] = ..., f_t: _Optional[int] = ..., step: _Optional[int] = ..., episode: _Optional[int] = ...) -> None: ...

class GetPlanRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class WatchPlanRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class Plan(_message.Message):
    __slots__ = ("session_id", "episode", "start_step", "actions")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    EPISODE_FIELD_NUMBER: _ClassVar[int]
    START_STEP_FIELD_NUMBER: _ClassVar[int]
    ACTIONS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    episode: int
    start_step: int
    actions: _containers.RepeatedCompositeFieldContainer[PlannedAction]
    def __init__(self, session_id: _Optional[str] = ..., episode: _Optional[int] = ..., start_step: _Optional[int] = ..., actions: _Optional[_Iterable[_Union[PlannedAction, _Mapping]]] = ...) -> None: ...
