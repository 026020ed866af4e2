"""Generate cell/v1/*_pb2.py from proto/ with the pinned protoc (grpcio-tools).

The generated code is committed so that a plain install needs no compiler;
tests/bus/test_proto.py regenerates it into a temporary folder and fails when the
committed copy is stale.  Run `make proto` after editing a .proto file.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROTO_DIR = ROOT / "proto"


def proto_files() -> list[Path]:
    return sorted(PROTO_DIR.glob("cell/v1/*.proto"))


def generate(out_dir: Path) -> list[Path]:
    """Write the generated modules for every .proto under proto/ into out_dir; return their paths."""
    from grpc_tools import protoc  # test extra: only needed to regenerate

    out_dir.mkdir(parents=True, exist_ok=True)
    files = [str(p.relative_to(PROTO_DIR)) for p in proto_files()]
    args = ["protoc", f"-I{PROTO_DIR}", f"--python_out={out_dir}", f"--pyi_out={out_dir}", *files]
    if protoc.main(args) != 0:
        raise RuntimeError(f"protoc failed on {files}")
    return sorted((out_dir / "cell" / "v1").glob("*_pb2.py*"))


def main() -> int:
    written = generate(ROOT)
    for path in written:
        print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
