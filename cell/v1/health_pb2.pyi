from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ServiceState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SERVICE_STATE_UNSPECIFIED: _ClassVar[ServiceState]
    SERVICE_STATE_STARTING: _ClassVar[ServiceState]
    SERVICE_STATE_RUNNING: _ClassVar[ServiceState]
    SERVICE_STATE_BACKOFF: _ClassVar[ServiceState]
    SERVICE_STATE_FAILED: _ClassVar[ServiceState]
    SERVICE_STATE_STOPPED: _ClassVar[ServiceState]

class Health(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    HEALTH_UNSPECIFIED: _ClassVar[Health]
    HEALTH_OK: _ClassVar[Health]
    HEALTH_STARTING: _ClassVar[Health]
    HEALTH_BACKOFF: _ClassVar[Health]
    HEALTH_FAILED: _ClassVar[Health]
    HEALTH_STOPPED: _ClassVar[Health]
    HEALTH_STALE: _ClassVar[Health]
    HEALTH_MISSING: _ClassVar[Health]
    HEALTH_UNKNOWN: _ClassVar[Health]
SERVICE_STATE_UNSPECIFIED: ServiceState
SERVICE_STATE_STARTING: ServiceState
SERVICE_STATE_RUNNING: ServiceState
SERVICE_STATE_BACKOFF: ServiceState
SERVICE_STATE_FAILED: ServiceState
SERVICE_STATE_STOPPED: ServiceState
HEALTH_UNSPECIFIED: Health
HEALTH_OK: Health
HEALTH_STARTING: Health
HEALTH_BACKOFF: Health
HEALTH_FAILED: Health
HEALTH_STOPPED: Health
HEALTH_STALE: Health
HEALTH_MISSING: Health
HEALTH_UNKNOWN: Health

class Heartbeat(_message.Message):
    __slots__ = ("service", "host", "pid", "state", "uptime_s", "restarts", "last_error", "counters", "interval_s", "process", "sched")
    class CountersEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    HOST_FIELD_NUMBER: _ClassVar[int]
    PID_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    UPTIME_S_FIELD_NUMBER: _ClassVar[int]
    RESTARTS_FIELD_NUMBER: _ClassVar[int]
    LAST_ERROR_FIELD_NUMBER: _ClassVar[int]
    COUNTERS_FIELD_NUMBER: _ClassVar[int]
    INTERVAL_S_FIELD_NUMBER: _ClassVar[int]
    PROCESS_FIELD_NUMBER: _ClassVar[int]
    SCHED_FIELD_NUMBER: _ClassVar[int]
    service: str
    host: str
    pid: int
    state: ServiceState
    uptime_s: float
    restarts: int
    last_error: str
    counters: _containers.ScalarMap[str, float]
    interval_s: float
    process: str
    sched: str
    def __init__(self, service: _Optional[str] = ..., host: _Optional[str] = ..., pid: _Optional[int] = ..., state: _Optional[_Union[ServiceState, str]] = ..., uptime_s: _Optional[float] = ..., restarts: _Optional[int] = ..., last_error: _Optional[str] = ..., counters: _Optional[_Mapping[str, float]] = ..., interval_s: _Optional[float] = ..., process: _Optional[str] = ..., sched: _Optional[str] = ...) -> None: ...

class ServiceEvent(_message.Message):
    __slots__ = ("service", "kind", "text", "restarts")
    class Kind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        KIND_UNSPECIFIED: _ClassVar[ServiceEvent.Kind]
        KIND_STARTED: _ClassVar[ServiceEvent.Kind]
        KIND_FAILED: _ClassVar[ServiceEvent.Kind]
        KIND_RESTARTING: _ClassVar[ServiceEvent.Kind]
        KIND_STOPPED: _ClassVar[ServiceEvent.Kind]
    KIND_UNSPECIFIED: ServiceEvent.Kind
    KIND_STARTED: ServiceEvent.Kind
    KIND_FAILED: ServiceEvent.Kind
    KIND_RESTARTING: ServiceEvent.Kind
    KIND_STOPPED: ServiceEvent.Kind
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    TEXT_FIELD_NUMBER: _ClassVar[int]
    RESTARTS_FIELD_NUMBER: _ClassVar[int]
    service: str
    kind: ServiceEvent.Kind
    text: str
    restarts: int
    def __init__(self, service: _Optional[str] = ..., kind: _Optional[_Union[ServiceEvent.Kind, str]] = ..., text: _Optional[str] = ..., restarts: _Optional[int] = ...) -> None: ...

class StatusRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ServiceStatus(_message.Message):
    __slots__ = ("name", "health", "heartbeat_age_s", "last")
    NAME_FIELD_NUMBER: _ClassVar[int]
    HEALTH_FIELD_NUMBER: _ClassVar[int]
    HEARTBEAT_AGE_S_FIELD_NUMBER: _ClassVar[int]
    LAST_FIELD_NUMBER: _ClassVar[int]
    name: str
    health: str
    heartbeat_age_s: float
    last: Heartbeat
    def __init__(self, name: _Optional[str] = ..., health: _Optional[str] = ..., heartbeat_age_s: _Optional[float] = ..., last: _Optional[_Union[Heartbeat, _Mapping]] = ...) -> None: ...

class CellStatus(_message.Message):
    __slots__ = ("cell", "mode", "uptime_s", "services", "config", "launcher_pid", "member", "dataplane")
    CELL_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    UPTIME_S_FIELD_NUMBER: _ClassVar[int]
    SERVICES_FIELD_NUMBER: _ClassVar[int]
    CONFIG_FIELD_NUMBER: _ClassVar[int]
    LAUNCHER_PID_FIELD_NUMBER: _ClassVar[int]
    MEMBER_FIELD_NUMBER: _ClassVar[int]
    DATAPLANE_FIELD_NUMBER: _ClassVar[int]
    cell: str
    mode: str
    uptime_s: float
    services: _containers.RepeatedCompositeFieldContainer[ServiceStatus]
    config: str
    launcher_pid: int
    member: str
    dataplane: str
    def __init__(self, cell: _Optional[str] = ..., mode: _Optional[str] = ..., uptime_s: _Optional[float] = ..., services: _Optional[_Iterable[_Union[ServiceStatus, _Mapping]]] = ..., config: _Optional[str] = ..., launcher_pid: _Optional[int] = ..., member: _Optional[str] = ..., dataplane: _Optional[str] = ...) -> None: ...
