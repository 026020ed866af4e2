"""The data plane as an XDP program in the kernel's receive path (issue 18): see dataplane.bpf.c."""
