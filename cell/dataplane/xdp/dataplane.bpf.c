// SPDX-License-Identifier: MIT
/* The in-network velocity controller (NSDI'22, Algorithms 1 and 2) as an XDP program.
 *
 * It is the numpy pipeline (cell/dataplane/pipeline.py) in the kernel's receive path, to the bit:
 * the same integer fixed point, the same Transform tables (flat arrays indexed the way a
 * longest-prefix match lands), LimitVelocity as prefix entries, TPStepper / TrajectorySwitcher /
 * TargetData rows and the registers per entity, all in BPF array maps that the Python control plane
 * maps into its own memory (BPF_F_MMAPABLE) and writes as numpy arrays.
 *
 * A UDP datagram to the listen address carries one 24-byte record (robot datagram); a GSO batch
 * carries several back to back, and is handled as the numpy service handles one receive batch:
 * Algorithm 1 steps each entity once per record of it (every step beyond its first is a
 * resubmission, counted), then Algorithm 2 turns every record into a command, and the packet goes
 * back where it came from (XDP_TX).  Everything else passes untouched.
 *
 * The control plane's batch stays atomic: while it flips (globals.closed), each status is answered
 * with the last command its joint was sent, nothing read from the tables being changed.
 *
 * Loops run through bpf_loop, so the verifier checks each body once, whatever the batch size.
 *
 * The same source is the user-space data plane's (backend "native", cell/dataplane/native.c): built
 * there with CELL_USERSPACE, its maps are memory the control plane allocated and bpf_loop a loop,
 * and handle() below is all of the packet path but the frame around the records.
 */
#ifndef CELL_USERSPACE
#include <linux/bpf.h>
#include <linux/if_ether.h>
#include <linux/in.h>
#include <linux/ip.h>
#include <linux/udp.h>
#include <bpf/bpf_endian.h>
#include <bpf/bpf_helpers.h>
#endif

#define MAX_JOINTS 12    /* values per TP (an entity's joints); [dataplane] max_joints must not exceed it */
#define MAX_RECS 64      /* records in one datagram (a GSO batch); more: dropped, counted */
#define MAX_ENTITIES 4096
#define NO_ROW (-1)
#define REC_SIZE 24
#define WORD 64
#define INPUT_LIMIT (1LL << 60)
#define QUIET_PIN_NS 500000000LL   /* a robot quiet this long may be pinned to a new sender */
#define STALL_DROP_NS 50000000LL
#define KIND_STATUS 0
#define KIND_COMMAND 1
#define DROP_WATCHDOG 1
#define DROP_UNDERRUN 2
#define DROP_QUIET 4

/* counters (a per-CPU array: the Python side sums the CPUs) */
enum {
	C_PACKETS, C_HOLDS, C_STEPS, C_RESUBMITS, C_STALLS, C_LIMITED, C_STOP_COMMANDS, C_DROPPED,
	C_REJ_LENGTH, C_REJ_KIND, C_REJ_JOINT, C_REJ_SPOOFED, C_REJ_BATCH, C_HELD, C_COMMANDS_OUT,
	C_DATAGRAMS, C_COUNT
};

struct robot {              /* per robot id */
	__s32 entity;           /* NO_ROW: not known */
	__s32 joint0;           /* its first joint within the entity */
	__s64 joints;           /* its joint count (0: not configured, joint ids unchecked) */
	__s64 stale_periods;    /* a jump in status numbers beyond this: it lived without us (0: never judged) */
	__s64 quiet_ns;         /* no status this long: it, or we, hung (0: never judged) */
	__s64 status_ns;        /* when its last status came */
	__s64 status_seq;       /* that status's sequence number */
	__u32 pin_addr;         /* the sender it is pinned to (network order) */
	__u16 pin_port;
	__u8 pinned;
	__u8 stop;              /* REG_stop: commands come from the StopRamp */
};

struct status {             /* per robot id: its joints' last status and command (wire units) */
	__s64 pos[MAX_JOINTS];
	__s64 vel[MAX_JOINTS];
	__s64 cmd[MAX_JOINTS];
};

struct entity {             /* the registers of Algorithm 1 */
	__s32 tp;               /* REG_tp: the row it heads for (NO_ROW: none) */
	__u8 stalled;
	__s8 dropped_why;
	__u16 pad;
	__s64 next_time;        /* REG_nextTime (ns) */
	__s64 stall_ns;
	__s64 dropped_ns;
};

struct row {                /* TPStepper + TrajectorySwitcher + TargetData */
	__s32 next_row;
	__s32 switch_row;
	__s64 duration;         /* ns */
	__s64 trg_pos[MAX_JOINTS];
	__s64 trg_vel[MAX_JOINTS];
};

struct limit {              /* LimitVelocity of one joint: the entry ending at each bit, per side */
	__s64 limit;
	__s64 neg;
	__s64 hi_v[WORD];
	__s64 hi_m[WORD];
	__s64 lo_v[WORD];
	__s64 lo_m[WORD];
};

struct globals {
	__u32 listen_addr;      /* network order; 0: any */
	__u16 listen_port;      /* network order */
	__u16 pad0;
	__s64 clock_ns;         /* 0: the kernel's CLOCK_MONOTONIC; else this (tests) */
	__u32 n_bits;
	__u32 joints;           /* joints the constants cover (Transform / LimitVelocity / StopRamp) */
	__u32 max_joints;       /* TP width the control plane uses (<= MAX_JOINTS) */
	__u32 stopping;         /* robots with REG_stop set */
	__u64 entries_per_sign;
	__u64 bank_size;        /* entries of one Transform bank: joints * 2 * entries_per_sign */
	__u32 closed;           /* the control plane is flipping a batch in */
	__u32 inflight;         /* packets being handled now */
	__s64 stop_ramp[MAX_JOINTS];
};

struct rec {                /* one record, host order */
	__s64 vel;
	__s64 pos;
	__s64 seq;
	__s32 robot;
	__s32 joint;
	__s32 kind;
	__s32 ent;
	__s64 out;
};

struct scratch {            /* per CPU: one datagram's records while they are handled */
	__u8 wire[MAX_RECS * REC_SIZE];
	struct rec r[MAX_RECS];
	__u64 serial;
	__s64 now;
	__u32 n;
	__u32 saddr;
	__u16 sport;
	__u16 pad;
	__u32 bad;
};

struct mark {               /* per CPU and entity: its records in the datagram being handled */
	__u64 serial;           /* which datagram (scratch.serial) the count is of */
	__u32 count;
	__u32 pad;
};

struct loop {               /* what each bpf_loop body gets (its context must live on the stack) */
	struct scratch *s;
};

#ifndef CELL_USERSPACE
struct {
	__uint(type, BPF_MAP_TYPE_ARRAY);
	__uint(map_flags, BPF_F_MMAPABLE);
	__uint(max_entries, 65536);
	__type(key, __u32);
	__type(value, struct robot);
} robots SEC(".maps");

struct {
	__uint(type, BPF_MAP_TYPE_ARRAY);
	__uint(map_flags, BPF_F_MMAPABLE);
	__uint(max_entries, 65536);
	__type(key, __u32);
	__type(value, struct status);
} status SEC(".maps");

struct {
	__uint(type, BPF_MAP_TYPE_ARRAY);
	__uint(map_flags, BPF_F_MMAPABLE);
	__uint(max_entries, MAX_ENTITIES);
	__type(key, __u32);
	__type(value, struct entity);
} entities SEC(".maps");

struct {
	__uint(type, BPF_MAP_TYPE_ARRAY);
	__uint(map_flags, BPF_F_MMAPABLE);
	__uint(max_entries, 1);   /* the capacity: set by the loader */
	__type(key, __u32);
	__type(value, struct row);
} rows SEC(".maps");

struct {
	__uint(type, BPF_MAP_TYPE_ARRAY);
	__uint(map_flags, BPF_F_MMAPABLE);
	__uint(max_entries, 1);   /* 3 banks * joints * 2 signs * entries_per_sign: set by the loader */
	__type(key, __u32);
	__type(value, __s64);
} transform SEC(".maps");

struct {
	__uint(type, BPF_MAP_TYPE_ARRAY);
	__uint(map_flags, BPF_F_MMAPABLE);
	__uint(max_entries, MAX_JOINTS);
	__type(key, __u32);
	__type(value, struct limit);
} limits SEC(".maps");

struct {
	__uint(type, BPF_MAP_TYPE_ARRAY);
	__uint(map_flags, BPF_F_MMAPABLE);
	__uint(max_entries, 1);
	__type(key, __u32);
	__type(value, struct globals);
} globals SEC(".maps");

struct {
	__uint(type, BPF_MAP_TYPE_PERCPU_ARRAY);
	__uint(max_entries, C_COUNT);
	__type(key, __u32);
	__type(value, __u64);
} counters SEC(".maps");

struct {
	__uint(type, BPF_MAP_TYPE_PERCPU_ARRAY);
	__uint(max_entries, 1);
	__type(key, __u32);
	__type(value, struct scratch);
} scratches SEC(".maps");

struct {
	__uint(type, BPF_MAP_TYPE_PERCPU_ARRAY);
	__uint(max_entries, MAX_ENTITIES);
	__type(key, __u32);
	__type(value, struct mark);
} marks SEC(".maps");
#endif

static __always_inline void count(__u32 which, __u64 n)
{
	__u64 *c = bpf_map_lookup_elem(&counters, &which);
	if (c)
		*c += n;  /* per CPU: no atomics needed */
}

static __always_inline struct globals *globals_get(void)
{
	__u32 zero = 0;
	return bpf_map_lookup_elem(&globals, &zero);
}

static __always_inline struct scratch *scratch_get(void)
{
	__u32 zero = 0;
	return bpf_map_lookup_elem(&scratches, &zero);
}

static __always_inline __s64 clamp(__s64 x, __s64 limit)
{
	return x > limit ? limit : (x < -limit ? -limit : x);
}

/* bit length of a non-negative value: where a TCAM's leading-one match lands */
static __always_inline __s64 bit_length(__u64 y)
{
	__s64 b = 0;
	if (y >> 32) { y >>= 32; b += 32; }
	if (y >> 16) { y >>= 16; b += 16; }
	if (y >> 8) { y >>= 8; b += 8; }
	if (y >> 4) { y >>= 4; b += 4; }
	if (y >> 2) { y >>= 2; b += 2; }
	if (y >> 1) { y >>= 1; b += 1; }
	return b + (__s64)y;
}

/* the Transform entry x matches (approx.table_index): sign, bit length and n leading bits */
static __always_inline __u64 table_index(__s64 x, __u32 n, __u64 eps)
{
	__u64 y = (__u64)(x ^ (x >> 63));
	__s64 shift = bit_length(y) - (__s64)n;
	if (shift < 0)
		shift = 0;
	__u64 idx = (y >> (shift & 63)) + (__u64)shift * (1ULL << ((n - 1) & 63));
	if (x < 0)
		idx += eps;
	return idx;
}

static __always_inline __s64 transform_lookup(struct globals *g, __u32 bank, __u32 joint, __s64 x)
{
	__u64 i = (__u64)bank * g->bank_size + (__u64)joint * 2 * g->entries_per_sign
		+ table_index(x, g->n_bits, g->entries_per_sign);
	__u32 key = (__u32)i;
	__s64 *v = bpf_map_lookup_elem(&transform, &key);
	return v ? *v : 0;
}

static __always_inline __u32 first_bit_differing(__s64 z)
{
	if (z < 0)
		return WORD - 1;
	__s64 b = bit_length((__u64)z) - 1;
	return b < 0 ? 0 : (__u32)b;
}

static __always_inline __s64 limit_velocity(__u32 joint, __s64 x, int *limited)
{
	struct limit *l = bpf_map_lookup_elem(&limits, &joint);
	if (!l)
		return 0;
	__u32 hi = first_bit_differing(x ^ l->limit) & (WORD - 1);
	__u32 lo = first_bit_differing(x ^ l->neg) & (WORD - 1);
	__s64 out = x;
	if ((x & l->hi_m[hi]) == l->hi_v[hi])
		out = l->limit;
	else if ((x & l->lo_m[lo]) == l->lo_v[lo])
		out = l->neg;
	*limited = out != x;
	return out;
}

static __always_inline void drop(struct entity *e, __s64 now, __s8 why)
{
	if (e->tp == NO_ROW)
		return;
	e->tp = NO_ROW;
	e->stalled = 0;
	e->dropped_ns = now;
	e->dropped_why = why;
	count(C_DROPPED, 1);
}

/* a bpf_loop index, its bound check kept on the register used to index (the verifier must see it) */
static __always_inline __u64 bounded(__u32 i)
{
	__u64 k = i;
	barrier_var(k);
	return k;
}

/* a record's status number (bytes 4-7, network order): the packet path's and the gate's reading */
static __always_inline __u32 wire_seq(const __u8 *w)
{
	return ((__u32)w[4] << 24) | ((__u32)w[5] << 16) | ((__u32)w[6] << 8) | w[7];
}

/* --- parsing: host order, validity, senders -------------------------------------------------- */

static long parse_one(__u32 i, void *ctx)
{
	struct scratch *s = ((struct loop *)ctx)->s;
	__u64 k = bounded(i);
	if (k >= MAX_RECS)
		return 1;
	__u8 *w = &s->wire[k * REC_SIZE];
	struct rec *r = &s->r[k];
	r->robot = ((__u32)w[0] << 8) | w[1];
	r->joint = w[2];
	r->kind = w[3];
	r->seq = wire_seq(w);
	r->vel = (__s64)bpf_be64_to_cpu(*(__u64 *)&w[8]);
	r->pos = (__s64)bpf_be64_to_cpu(*(__u64 *)&w[16]);
	__u32 key = r->robot;
	struct robot *rb = bpf_map_lookup_elem(&robots, &key);
	if (!rb)
		return 1;
	if (r->kind != KIND_STATUS) {
		count(C_REJ_KIND, 1);
		s->bad = 1;
		return 0;
	}
	if (rb->joints > 0 && r->joint >= rb->joints) {
		count(C_REJ_JOINT, 1);
		s->bad = 1;
		return 0;
	}
	/* pinned to its first sender until it has been quiet (a restart on a new port) */
	if (!rb->pinned || rb->pin_addr != s->saddr || rb->pin_port != s->sport) {
		if (!rb->pinned || s->now - rb->status_ns > QUIET_PIN_NS) {
			rb->pin_addr = s->saddr;
			rb->pin_port = s->sport;
			rb->pinned = 1;
		} else {
			count(C_REJ_SPOOFED, 1);
			s->bad = 1;
			return 0;
		}
	}
	r->ent = rb->entity;
	return 0;
}

/* --- Algorithm 1: drops, then one step per record of each entity ----------------------------- */

static long judge_one(__u32 i, void *ctx)
{
	/* a robot whose status numbers jumped past its watchdog, or that was quiet too long: its plan
	 * is stale (i < n: the watchdog rule over every record, then i >= n: the quiet rule) */
	struct scratch *s = ((struct loop *)ctx)->s;
	int quiet_pass = i >= s->n;
	__u64 k = bounded(quiet_pass ? i - s->n : i);
	if (k >= MAX_RECS)
		return 1;
	struct rec *r = &s->r[k];
	if (r->ent == NO_ROW)
		return 0;
	__u32 key = r->robot;
	struct robot *rb = bpf_map_lookup_elem(&robots, &key);
	if (!rb || rb->status_ns <= 0 || rb->quiet_ns <= 0)
		return 0;
	__u32 ek = r->ent;
	struct entity *e = bpf_map_lookup_elem(&entities, &ek);
	if (!e)
		return 0;
	__s64 jump = (r->seq - rb->status_seq) & 0xFFFFFFFFLL;
	int jumped = jump > rb->stale_periods;
	if (!quiet_pass && jumped)
		drop(e, s->now, DROP_WATCHDOG);
	else if (quiet_pass && !jumped && s->now - rb->status_ns > rb->quiet_ns)
		drop(e, s->now, DROP_QUIET);
	return 0;
}

struct stepping {
	struct scratch *s;
	struct entity *e;
	__u32 budget;
	__u32 done;
};

static long step_one(__u32 i, void *ctx)
{
	struct stepping *st = ctx;
	struct entity *e = st->e;
	if (i >= st->budget || e->tp == NO_ROW || st->s->now < e->next_time)
		return 1;
	__u32 cur = (__u32)e->tp;
	struct row *rc = bpf_map_lookup_elem(&rows, &cur);
	if (!rc)
		return 1;
	__s32 nxt = rc->switch_row != NO_ROW ? rc->switch_row : rc->next_row;
	if (nxt == NO_ROW) {  /* underrun: hold the TP; a long one ends the trajectory */
		count(C_STALLS, 1);
		if (!e->stalled) {
			e->stalled = 1;
			e->stall_ns = st->s->now;
		}
		if (st->s->now - e->stall_ns > STALL_DROP_NS)
			drop(e, st->s->now, DROP_UNDERRUN);
		return 1;
	}
	__u32 nk = (__u32)nxt;
	struct row *rn = bpf_map_lookup_elem(&rows, &nk);
	if (!rn)
		return 1;
	e->stalled = 0;
	e->tp = nxt;
	e->next_time += rn->duration;
	count(C_STEPS, 1);
	if (i > 0)
		count(C_RESUBMITS, 1);
	return 0;
}

/* record i's entity and its mark (the shared start of count_one and ingress_one): 1 found,
 * 0 none (no entity, or the lookup failed), -1 past the records (the loop ends) */
static __always_inline int mark_at(void *ctx, __u32 i, __u32 *ent, struct mark **m)
{
	struct scratch *s = ((struct loop *)ctx)->s;
	__u64 k = bounded(i);
	if (k >= MAX_RECS)
		return -1;
	struct rec *r = &s->r[k];
	if (r->ent < 0)
		return 0;
	*ent = r->ent;
	*m = bpf_map_lookup_elem(&marks, ent);
	return *m ? 1 : 0;
}

static long count_one(__u32 i, void *ctx)
{
	struct scratch *s = ((struct loop *)ctx)->s;
	__u32 e;
	struct mark *m;
	int got = mark_at(ctx, i, &e, &m);
	if (got <= 0)
		return got < 0;
	if (m->serial != s->serial) {
		m->serial = s->serial;
		m->count = 0;
	}
	m->count += 1;
	return 0;
}

static long ingress_one(__u32 i, void *ctx)
{
	struct scratch *s = ((struct loop *)ctx)->s;
	__u32 ek;
	struct mark *m;
	int got = mark_at(ctx, i, &ek, &m);
	if (got <= 0)
		return got < 0;
	if (m->serial != s->serial || !m->count)  /* stepped at the entity's first record */
		return 0;
	__u32 budget = m->count;
	m->count = 0;
	struct entity *e = bpf_map_lookup_elem(&entities, &ek);
	if (!e)
		return 0;
	struct stepping st = {.s = s, .e = e, .budget = budget};
	bpf_loop(MAX_RECS, step_one, &st, 0);
	return 0;
}

/* record i of the datagram being handled, with its robot's registers (the shared start of the
 * Algorithm 2 bodies); 0: none (past the records, or a lookup failed) */
struct at {
	struct scratch *s;
	struct globals *g;
	struct rec *r;
	struct robot *rb;
	struct status *st;
};

static __always_inline int record_at(void *ctx, __u32 i, struct at *a)
{
	struct scratch *s = ((struct loop *)ctx)->s;
	__u64 k = bounded(i);
	if (k >= MAX_RECS)
		return 0;
	struct rec *r = &s->r[k];
	__u32 rk = r->robot;
	struct globals *g = globals_get();
	struct robot *rb = bpf_map_lookup_elem(&robots, &rk);
	struct status *st = bpf_map_lookup_elem(&status, &rk);
	if (!g || !rb || !st)
		return 0;
	*a = (struct at){.s = s, .g = g, .r = r, .rb = rb, .st = st};
	return 1;
}

/* --- Algorithm 2: every record a command -------------------------------------------------------- */

static long egress_one(__u32 i, void *ctx)
{
	struct at a;
	if (!record_at(ctx, i, &a))
		return 1;
	struct scratch *s = a.s;
	struct globals *g = a.g;
	struct rec *r = a.r;
	struct robot *rb = a.rb;
	struct status *st = a.st;
	__s32 row = NO_ROW;
	int stalled = 0;
	if (r->ent != NO_ROW) {
		__u32 ek = r->ent;
		struct entity *e = bpf_map_lookup_elem(&entities, &ek);
		if (e) {
			row = e->tp;
			stalled = e->stalled;
		}
	}
	__s64 v_trg = 0, p_trg = 0;
	if (row != NO_ROW) {
		__u64 j = (__u32)(rb->joint0 + r->joint);
		__u32 rw = (__u32)row;
		barrier_var(j);
		struct row *t = bpf_map_lookup_elem(&rows, &rw);
		if (t && j < MAX_JOINTS) {
			v_trg = stalled ? 0 : t->trg_vel[j];  /* stalled: hold the TP's position */
			p_trg = t->trg_pos[j];
		}
	}
	__s64 v = clamp(r->vel, INPUT_LIMIT), p = clamp(r->pos, INPUT_LIMIT);
	__u64 jid = (__u32)r->joint;
	barrier_var(jid);
	if (jid < g->max_joints && jid < MAX_JOINTS) {
		st->pos[jid] = p;
		st->vel[jid] = v;
	}
	rb->status_ns = s->now;
	rb->status_seq = r->seq;
	__s64 diff = clamp(p_trg - p, INPUT_LIMIT);
	__u32 local = (__u32)r->joint < g->joints ? (__u32)r->joint : g->joints - 1;
	__s64 v_new = transform_lookup(g, 0, local, v) + transform_lookup(g, 1, local, v_trg)
		+ transform_lookup(g, 2, local, diff) + diff;
	int limited = 0;
	__s64 out = limit_velocity(local, v_new, &limited);
	if (row == NO_ROW) {
		out = 0;
		count(C_HOLDS, 1);
	} else if (limited) {
		count(C_LIMITED, 1);
	}
	r->out = out;
	return 0;
}

static long stop_one(__u32 i, void *ctx)
{
	/* robots under REG_stop: each velocity StopRamp closer to 0, from its joint's last status */
	struct at a;
	if (!record_at(ctx, i, &a) || !a.rb->stop)
		return 0;
	struct globals *g = a.g;
	struct rec *r = a.r;
	struct status *st = a.st;
	/* (indexes are u64 and pass barrier_var: the verifier must see the bound on the register used) */
	__u64 j = (__u32)r->joint < g->max_joints ? (__u32)r->joint : g->max_joints - 1;
	__u64 local = (__u32)r->joint < g->joints ? (__u32)r->joint : g->joints - 1;
	barrier_var(j);
	barrier_var(local);
	if (j >= MAX_JOINTS || local >= MAX_JOINTS)
		return 0;
	__s64 v = st->vel[j];
	__s64 dv = g->stop_ramp[local];
	__s64 mag = (v < 0 ? -v : v) - dv;
	if (mag < 0)
		mag = 0;
	r->out = v > 0 ? mag : (v < 0 ? -mag : 0);
	count(C_STOP_COMMANDS, 1);
	return 0;
}

static long write_one(__u32 i, void *ctx)
{
	/* the command into the datagram (kind and velocity), and remembered for held answers */
	struct scratch *s = ((struct loop *)ctx)->s;
	__u64 k = bounded(i);
	if (k >= MAX_RECS)
		return 1;
	struct rec *r = &s->r[k];
	__u8 *w = &s->wire[k * REC_SIZE];
	__u32 rk = r->robot;
	struct status *st = bpf_map_lookup_elem(&status, &rk);
	__u64 jid = (__u32)r->joint;
	barrier_var(jid);
	if (st && jid < MAX_JOINTS)
		st->cmd[jid] = r->out;
	w[3] = KIND_COMMAND;
	*(__u64 *)&w[8] = bpf_cpu_to_be64((__u64)r->out);
	return 0;
}

static long held_one(__u32 i, void *ctx)
{
	/* the tables are being flipped: answer with the joint's last command, touching no table.  The
	 * robot heard us, so its liveness registers move on (when and which status came last): else a
	 * robot answered at the gate through a run of flips (a fleet's table updates back to back) was
	 * judged, at its next status, to have lived past its watchdog without us, and its plan dropped */
	struct scratch *s = ((struct loop *)ctx)->s;
	__u64 k = bounded(i);
	if (k >= MAX_RECS)
		return 1;
	__u8 *w = &s->wire[k * REC_SIZE];
	__u32 rk = ((__u32)w[0] << 8) | w[1];
	__u64 j = w[2];
	barrier_var(j);
	struct status *st = bpf_map_lookup_elem(&status, &rk);
	__s64 out = 0;
	if (st && j < MAX_JOINTS)
		out = st->cmd[j];
	struct robot *rb = bpf_map_lookup_elem(&robots, &rk);
	if (rb && w[3] == KIND_STATUS && rb->pinned && rb->pin_addr == s->saddr && rb->pin_port == s->sport
	    && rb->status_ns > 0) {  /* (its own sender's, and heard before: the judge's rule, not a pin) */
		rb->status_ns = s->now;
		rb->status_seq = wire_seq(w);
	}
	w[3] = KIND_COMMAND;
	*(__u64 *)&w[8] = bpf_cpu_to_be64((__u64)out);
	return 0;
}

/* --- the packet path: n records in s->wire, from saddr:sport (network order), now on the
 * data plane's clock; each turned into its command in place, or the whole datagram dropped ------- */

#define HANDLED 0
#define HELD 1   /* the gate was closed: each joint's last command, the tables untouched */
#define BAD 2    /* a bad record in it (each counted): dropped whole */

static __always_inline int handle(struct globals *g, struct scratch *s, __u32 n, __u32 saddr, __u16 sport,
				  __s64 now)
{
	struct loop lp = {.s = s};
	__sync_fetch_and_add(&g->inflight, 1);
	s->now = g->clock_ns ? g->clock_ns : now;
	s->saddr = saddr;
	s->sport = sport;
	if (g->closed) {  /* the control plane is flipping a batch in */
		count(C_HELD, n);
		bpf_loop(n, held_one, &lp, 0);
		__sync_fetch_and_add(&g->inflight, -1);
		return HELD;
	}
	s->n = n;
	s->bad = 0;
	s->serial += 1;
	bpf_loop(n, parse_one, &lp, 0);
	if (s->bad) {  /* a datagram with a bad record is dropped whole (each bad one counted) */
		__sync_fetch_and_add(&g->inflight, -1);
		return BAD;
	}
	count(C_PACKETS, n);
	bpf_loop(2 * n, judge_one, &lp, 0);
	bpf_loop(n, count_one, &lp, 0);
	bpf_loop(n, ingress_one, &lp, 0);
	bpf_loop(n, egress_one, &lp, 0);
	if (g->stopping)
		bpf_loop(n, stop_one, &lp, 0);
	bpf_loop(n, write_one, &lp, 0);
	__sync_fetch_and_add(&g->inflight, -1);
	return HANDLED;
}

#ifndef CELL_USERSPACE
static __always_inline int answer(struct xdp_md *ctx)
{
	/* back where it came from: swap the addresses and ports; no UDP checksum (IPv4 allows it) */
	void *data = (void *)(long)ctx->data, *end = (void *)(long)ctx->data_end;
	struct ethhdr *eth = data;
	if ((void *)(eth + 1) > end)
		return XDP_DROP;
	struct iphdr *ip = (void *)(eth + 1);
	if ((void *)(ip + 1) > end)
		return XDP_DROP;
	struct udphdr *udp = (void *)ip + ip->ihl * 4;
	if ((void *)(udp + 1) > end)
		return XDP_DROP;
	unsigned char mac[ETH_ALEN];
	__builtin_memcpy(mac, eth->h_source, ETH_ALEN);
	__builtin_memcpy(eth->h_source, eth->h_dest, ETH_ALEN);
	__builtin_memcpy(eth->h_dest, mac, ETH_ALEN);
	__u32 a = ip->saddr;
	ip->saddr = ip->daddr;
	ip->daddr = a;  /* (the header checksum is a sum: swapping its words leaves it right) */
	__u16 p = udp->source;
	udp->source = udp->dest;
	udp->dest = p;
	udp->check = 0;
	return XDP_TX;
}

SEC("xdp")
int velocity_control(struct xdp_md *ctx)
{
	void *data = (void *)(long)ctx->data, *end = (void *)(long)ctx->data_end;
	struct globals *g = globals_get();
	struct scratch *s = scratch_get();
	if (!g || !s)
		return XDP_PASS;
	struct ethhdr *eth = data;
	if ((void *)(eth + 1) > end || eth->h_proto != bpf_htons(ETH_P_IP))
		return XDP_PASS;
	struct iphdr *ip = (void *)(eth + 1);
	if ((void *)(ip + 1) > end || ip->protocol != IPPROTO_UDP || ip->ihl < 5)
		return XDP_PASS;
	if (ip->frag_off & bpf_htons(0x3FFF))  /* fragments: not ours to judge */
		return XDP_PASS;
	__u32 ihl = ip->ihl * 4;
	struct udphdr *udp = (void *)ip + ihl;
	if ((void *)(udp + 1) > end)
		return XDP_PASS;
	if (udp->dest != g->listen_port || (g->listen_addr && ip->daddr != g->listen_addr))
		return XDP_PASS;
	count(C_DATAGRAMS, 1);
	__u32 off = sizeof(*eth) + ihl + sizeof(*udp);
	__u32 total = bpf_ntohs(ip->tot_len);
	__u32 len = total > ihl + sizeof(*udp) ? total - ihl - sizeof(*udp) : 0;
	if (len == 0 || len % REC_SIZE || (void *)udp + sizeof(*udp) + len > end) {
		count(C_REJ_LENGTH, 1);
		return XDP_DROP;
	}
	__u32 n = len / REC_SIZE;
	if (n > MAX_RECS) {
		count(C_REJ_BATCH, n);
		return XDP_DROP;
	}
	__u64 bytes = n * REC_SIZE;
	asm volatile("" : "+r"(bytes));  /* (keep the bound check on the very register the helper gets) */
	if (bytes > sizeof(s->wire) || bytes == 0)
		return XDP_DROP;
	if (bpf_xdp_load_bytes(ctx, off, s->wire, bytes))
		return XDP_DROP;
	if (handle(g, s, n, ip->saddr, udp->source, bpf_ktime_get_ns()) == BAD)
		return XDP_DROP;
	if (bpf_xdp_store_bytes(ctx, off, s->wire, bytes))
		return XDP_DROP;
	count(C_COMMANDS_OUT, n);
	return answer(ctx);
}


/* The control plane's gate, run by it through BPF_PROG_TEST_RUN: the packet's first byte 1 closes
 * (globals.closed + 1), 0 opens.  A locked add on each side (here, and the packet path's inflight)
 * is the fence that makes "closed, then no packet in flight" mean no packet reads the tables. */
SEC("xdp")
int gate(struct xdp_md *ctx)
{
	void *data = (void *)(long)ctx->data, *end = (void *)(long)ctx->data_end;
	struct globals *g = globals_get();
	__u8 *op = data;
	if (!g || (void *)(op + 1) > end)
		return XDP_ABORTED;
	if (*op == 1)
		__sync_fetch_and_add(&g->closed, 1);
	else
		__sync_fetch_and_add(&g->closed, -1);
	return XDP_PASS;
}

/* The baseline the benchmark puts next to velocity_control: every datagram to the listen port sent
 * straight back, untouched but for the addresses (this machine's XDP_TX limit). */
SEC("xdp")
int reflect(struct xdp_md *ctx)
{
	void *data = (void *)(long)ctx->data, *end = (void *)(long)ctx->data_end;
	struct globals *g = globals_get();
	struct ethhdr *eth = data;
	if (!g || (void *)(eth + 1) > end || eth->h_proto != bpf_htons(ETH_P_IP))
		return XDP_PASS;
	struct iphdr *ip = (void *)(eth + 1);
	if ((void *)(ip + 1) > end || ip->protocol != IPPROTO_UDP || ip->ihl != 5)
		return XDP_PASS;
	struct udphdr *udp = (void *)(ip + 1);
	if ((void *)(udp + 1) > end || udp->dest != g->listen_port)
		return XDP_PASS;
	return answer(ctx);
}

char LICENSE[] SEC("license") = "Dual MIT/GPL";
#endif /* CELL_USERSPACE */
