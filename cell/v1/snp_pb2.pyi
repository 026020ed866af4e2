from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from typing import ClassVar as _ClassVar, Optional as _Optional

DESCRIPTOR: _descriptor.FileDescriptor

class SnpDenial(_message.Message):
    __slots__ = ("query_id", "explanation", "peer", "t_ns")
    QUERY_ID_FIELD_NUMBER: _ClassVar[int]
    EXPLANATION_FIELD_NUMBER: _ClassVar[int]
    PEER_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    query_id: int
    explanation: int
    peer: str
    t_ns: int
    def __init__(self, query_id: _Optional[int] = ..., explanation: _Optional[int] = ..., peer: _Optional[str] = ..., t_ns: _Optional[int] = ...) -> None: ...
