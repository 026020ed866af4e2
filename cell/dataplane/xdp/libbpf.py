"""The few libbpf calls the XDP backend needs, through ctypes (libbpf.so.1, Debian's libbpf1).

No compiler at run time: the BPF object is built by `make` (clang); this only opens, sizes,
loads and attaches it, and reads what the verifier said when it refuses.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import struct
from functools import cache
from typing import NoReturn


class BpfError(RuntimeError):
    """A libbpf call failed; the message says which, why, and what the loader logged."""


class _TestRunOpts(ctypes.Structure):
    _fields_ = [
        ("sz", ctypes.c_size_t),
        ("data_in", ctypes.c_void_p),
        ("data_out", ctypes.c_void_p),
        ("data_size_in", ctypes.c_uint32),
        ("data_size_out", ctypes.c_uint32),
        ("ctx_in", ctypes.c_void_p),
        ("ctx_out", ctypes.c_void_p),
        ("ctx_size_in", ctypes.c_uint32),
        ("ctx_size_out", ctypes.c_uint32),
        ("retval", ctypes.c_uint32),
        ("repeat", ctypes.c_int),
        ("duration", ctypes.c_uint32),
        ("flags", ctypes.c_uint32),
        ("cpu", ctypes.c_uint32),
        ("batch_size", ctypes.c_uint32),
    ]


_PRINT = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_int, ctypes.c_char_p, ctypes.c_void_p)
_log: list[str] = []  # what libbpf printed (the verifier's log among it), for error messages


def _printer(level: int, fmt: bytes, args: int) -> int:
    buf = ctypes.create_string_buffer(4096)
    _libc().vsnprintf(buf, len(buf), fmt, ctypes.c_void_p(args))
    _log.append(buf.value.decode(errors="replace"))
    del _log[:-400]
    return 0


_printer_ref = _PRINT(_printer)


@cache
def _libc() -> ctypes.CDLL:
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    libc.vsnprintf.argtypes = [ctypes.c_char_p, ctypes.c_size_t, ctypes.c_char_p, ctypes.c_void_p]
    return libc


@cache
def lib() -> ctypes.CDLL:
    """libbpf, its prototypes declared; BpfError if it is not installed."""
    try:
        bpf = ctypes.CDLL("libbpf.so.1", use_errno=True)
    except OSError as exc:
        raise BpfError(f"libbpf.so.1 not found ({exc}): install Debian's libbpf1") from None
    p, i, u32, s = ctypes.c_void_p, ctypes.c_int, ctypes.c_uint32, ctypes.c_char_p
    for name, res, args in (
        ("bpf_object__open_file", p, [s, p]),
        ("bpf_object__load", i, [p]),
        ("bpf_object__close", None, [p]),
        ("bpf_object__find_map_by_name", p, [p, s]),
        ("bpf_object__find_program_by_name", p, [p, s]),
        ("bpf_map__set_max_entries", i, [p, u32]),
        ("bpf_map__value_size", u32, [p]),
        ("bpf_map__max_entries", u32, [p]),
        ("bpf_map__fd", i, [p]),
        ("bpf_program__fd", i, [p]),
        ("bpf_obj_get_info_by_fd", i, [i, p, ctypes.POINTER(u32)]),
        ("bpf_map_lookup_elem", i, [i, p, p]),
        ("bpf_prog_test_run_opts", i, [i, p]),
        ("bpf_xdp_attach", i, [i, i, u32, p]),
        ("bpf_xdp_detach", i, [i, u32, p]),
        ("bpf_xdp_query_id", i, [i, i, ctypes.POINTER(u32)]),
        ("libbpf_num_possible_cpus", i, []),
        ("libbpf_set_print", p, [_PRINT]),
    ):
        f = getattr(bpf, name)
        f.restype, f.argtypes = res, args
    bpf.libbpf_set_print(_printer_ref)
    return bpf


def check(ret: int, what: str) -> int:
    """ret when it is >= 0; else BpfError naming the call, the error and libbpf's last words."""
    if ret >= 0:
        return ret
    _fail(-ret if ret < -1 else ctypes.get_errno(), what)


def pointer(ret: int | None, what: str) -> int:
    if not ret:
        _fail(ctypes.get_errno(), what)
    return int(ret)


def _fail(err: int, what: str) -> NoReturn:
    tail = "".join(_log[-12:]).strip()
    del _log[:]
    raise BpfError(f"{what}: {os.strerror(err)}" + (f"\n{tail}" if tail else ""))


def test_run(prog_fd: int, data: bytes, out_size: int = 4096) -> tuple[int, bytes]:
    """Run a program once on a packet in the kernel (BPF_PROG_TEST_RUN): its verdict and the packet."""
    src = ctypes.create_string_buffer(data, len(data))
    dst = ctypes.create_string_buffer(out_size)
    opts = _TestRunOpts(
        sz=ctypes.sizeof(_TestRunOpts),
        data_in=ctypes.addressof(src),
        data_out=ctypes.addressof(dst),
        data_size_in=len(data),
        data_size_out=out_size,
        repeat=1,
    )
    check(lib().bpf_prog_test_run_opts(prog_fd, ctypes.byref(opts)), "BPF_PROG_TEST_RUN")
    return int(opts.retval), dst.raw[: opts.data_size_out]


def prog_sizes(prog_fd: int) -> tuple[int, int]:
    """(translated, JIT-compiled) bytes of a loaded program: struct bpf_prog_info's jited_prog_len
    and xlated_prog_len (offsets 16 and 20, stable since they were added)."""
    info = ctypes.create_string_buffer(256)
    size = ctypes.c_uint32(len(info))
    check(lib().bpf_obj_get_info_by_fd(prog_fd, info, ctypes.byref(size)), "reading a program's info")
    jited, xlated = struct.unpack_from("<II", info.raw, 16)
    return xlated, jited


def fdinfo(fd: int) -> dict[str, str]:
    """The kernel's fdinfo of a BPF map or program (memlock, verified_insns, ...)."""
    with open(f"/proc/self/fdinfo/{fd}") as f:
        return {k.strip(): v.strip() for k, _, v in (line.partition(":") for line in f) if v}
