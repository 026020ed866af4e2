"""The controller's bus methods pass the data plane's refusals on as they came (cell/controller/rpc.py)."""

from __future__ import annotations

from cell.bus import RemoteError
from cell.controller.rpc import _refused


def test_a_data_plane_refusal_is_passed_on_with_its_code_and_reason() -> None:
    why = "robot(s) [1] taken over by another controller"
    fault = _refused(RemoteError("dataplane", "update", "taken", why))
    assert fault.code == "taken" and fault.message == f"the data plane refused: {why}"
    # (a code this side does not know is a failure, its reason kept: not "the data plane is not answering")
    fault = _refused(RemoteError("dataplane", "update", "newer_code", "why"))
    assert fault.code == "failed" and fault.message.endswith("why")
