from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class FaultCode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    FAULT_CODE_UNSPECIFIED: _ClassVar[FaultCode]
    FAULT_CODE_BAD_REQUEST: _ClassVar[FaultCode]
    FAULT_CODE_BUS_LOST: _ClassVar[FaultCode]
    FAULT_CODE_BUSY: _ClassVar[FaultCode]
    FAULT_CODE_FAILED: _ClassVar[FaultCode]
    FAULT_CODE_IN_USE: _ClassVar[FaultCode]
    FAULT_CODE_INTERNAL: _ClassVar[FaultCode]
    FAULT_CODE_NO_FRAME: _ClassVar[FaultCode]
    FAULT_CODE_PLAN: _ClassVar[FaultCode]
    FAULT_CODE_REFUSED: _ClassVar[FaultCode]
    FAULT_CODE_STOPPED: _ClassVar[FaultCode]
    FAULT_CODE_UNKNOWN_METHOD: _ClassVar[FaultCode]
    FAULT_CODE_UNKNOWN_MODULE: _ClassVar[FaultCode]
    FAULT_CODE_UNKNOWN_ROBOT: _ClassVar[FaultCode]
    FAULT_CODE_UNREACHABLE: _ClassVar[FaultCode]
    FAULT_CODE_TABLE_FULL: _ClassVar[FaultCode]
    FAULT_CODE_TOO_MANY_JOINTS: _ClassVar[FaultCode]
    FAULT_CODE_UNKNOWN_TP: _ClassVar[FaultCode]
    FAULT_CODE_TAKEN: _ClassVar[FaultCode]
FAULT_CODE_UNSPECIFIED: FaultCode
FAULT_CODE_BAD_REQUEST: FaultCode
FAULT_CODE_BUS_LOST: FaultCode
FAULT_CODE_BUSY: FaultCode
FAULT_CODE_FAILED: FaultCode
FAULT_CODE_IN_USE: FaultCode
FAULT_CODE_INTERNAL: FaultCode
FAULT_CODE_NO_FRAME: FaultCode
FAULT_CODE_PLAN: FaultCode
FAULT_CODE_REFUSED: FaultCode
FAULT_CODE_STOPPED: FaultCode
FAULT_CODE_UNKNOWN_METHOD: FaultCode
FAULT_CODE_UNKNOWN_MODULE: FaultCode
FAULT_CODE_UNKNOWN_ROBOT: FaultCode
FAULT_CODE_UNREACHABLE: FaultCode
FAULT_CODE_TABLE_FULL: FaultCode
FAULT_CODE_TOO_MANY_JOINTS: FaultCode
FAULT_CODE_UNKNOWN_TP: FaultCode
FAULT_CODE_TAKEN: FaultCode

class RpcError(_message.Message):
    __slots__ = ("code", "message")
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    code: str
    message: str
    def __init__(self, code: _Optional[str] = ..., message: _Optional[str] = ...) -> None: ...

class Empty(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class BenchPayload(_message.Message):
    __slots__ = ("data",)
    DATA_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    def __init__(self, data: _Optional[bytes] = ...) -> None: ...
