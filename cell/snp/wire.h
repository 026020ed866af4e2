/* What the C fast paths of the modular robot share (cycle.c: the joint modules; master.c: the
 * master): the SnP packets' fields and CRC as cell.snp.packet writes them, the host clock, a
 * seeded lossy link, and reading a datagram with the kernel's receive stamp.  Static inline: each
 * file is its own translation unit in the one library cell/snp/native.py builds. */
#ifndef CELL_SNP_WIRE_H
#define CELL_SNP_WIRE_H

#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <netinet/in.h>
#include <poll.h>
#include <sched.h>
#include <stdint.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>

/* The cycle's packets (cell.snp.packet.QueryShape / ReplyShape with no return address): A asks
 * for one item from two inputs, C from one; the answer carries one item; a denial its reason. */
enum { A_SIZE = 80, C_SIZE = 64, ANSWER_SIZE = 40, DENIAL_SIZE = 22 };
/* VDC's (cell.modular.wire): A (2 in, B's 20 wanted) and B; C (F*'s 6 in, tau_r wanted); a local
 * [C, D]'s A (q, qd and its last F*, B's 20 and G's 6 wanted) and its B */
enum { VDC_A_SIZE = 308, VDC_B_SIZE = 344, VDC_C_SIZE = 144, VDC_AL_SIZE = 476, VDC_BL_SIZE = 440 };
enum { VDC_G_SIZE = 120 }; /* a "neighbour" [C, D]'s force passed inwards (wire.G_PASS): 6 items */
enum { PID_MRT = 0xF0, QUERY = 1, REPLY = 2, DENIAL = 3 };
enum { DEADLINE_CANNOT_BE_MET = 1 };
enum { RUN_UNTIL = 0, RUN_HANDED = 1, RUN_RECORDS_FULL = 2, RUN_EVENT = 3 };

/* A datagram handed back to Python (cell.snp.native.Handed). */
typedef struct {
    int64_t index, len, at, ip, port;
} handed_t;

/* --- polling without sleeping, at a real-time priority only within a budget (cell.sched.Spin) -----
 * A SCHED_FIFO thread that polls through its cycles runs into the kernel's RT throttling (95% of
 * each second of a CPU at most: the rest of that second none of the CPU's real-time threads run,
 * 20-50 ms of silence for every module at once).  Polling at the normal policy instead lets any
 * busy normal process take the CPU from a cycle in flight (a CPU hog: 6% of exchanges missed where
 * 0.7% were).  So the loops sleep at their real-time priority, so that a wake-up comes at once,
 * and poll at it too while their polling stays within SPIN_BUDGET_NS of each SPIN_WINDOW_NS (90 ms
 * of each 100: the kernel's 95% is never reached, and the CPU's normal threads get 10 ms of every
 * 100; a six-module cycle polls 60-65% of the time, and missed 1.9% at 6 ms of 10, 0.04-7.9% at
 * 80 of 100, 0.2-1.1% at 90), past that at the normal policy until the next window.  At most two
 * system calls a cycle (~1-2 us), and a clock read a poll. */
#define SPIN_WINDOW_NS 100000000LL
#define SPIN_BUDGET_NS 90000000LL
typedef struct {
    int prio; /* the real-time priority the thread came with (0: none, nothing to do) */
    int policy;
    int low;        /* polling at the normal policy now */
    int64_t window; /* the budget's window began (CLOCK_MONOTONIC ns) */
    int64_t polled; /* ns polled in it */
    int64_t last;   /* the last poll's time, while polling (0: asleep) */
} spin_t;

static inline int64_t spin_clock(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static inline void spin_init(spin_t *s) {
    struct sched_param sp;
    int policy = sched_getscheduler(0) & 0xff; /* (without SCHED_RESET_ON_FORK) */
    s->prio = 0, s->low = 0, s->policy = policy, s->window = 0, s->polled = 0, s->last = 0;
    if ((policy == SCHED_FIFO || policy == SCHED_RR) && sched_getparam(0, &sp) == 0) s->prio = sp.sched_priority;
}

static inline void spin_set(spin_t *s, int low) {
    struct sched_param sp = {.sched_priority = low ? 0 : s->prio};
    if (sched_setscheduler(0, low ? SCHED_OTHER : s->policy, &sp) == 0) s->low = low;
}

static inline void spin_poll(spin_t *s) { /* about to poll without sleeping */
    if (!s->prio) return;
    int64_t now = spin_clock();
    if (s->last) s->polled += now - s->last; /* (polling since the last call) */
    s->last = now;
    if (now - s->window >= SPIN_WINDOW_NS) s->window = now, s->polled = 0;
    int over = s->polled >= SPIN_BUDGET_NS;
    if (over != s->low) spin_set(s, over);
}

static inline void spin_sleep(spin_t *s) { /* about to sleep, or return: real-time again */
    if (s->last) s->polled += spin_clock() - s->last, s->last = 0;
    if (s->low) spin_set(s, 0);
}

/* --- the RMAP CRC-8 (x^8 + x^2 + x + 1, reflected, init 0): cell.snp.packet.crc8 ------------ */

static uint8_t crc_table[256];

static inline void crc_init(void) {
    for (int i = 0; i < 256; i++) {
        uint8_t c = (uint8_t)i;
        for (int k = 0; k < 8; k++) c = (c & 1) ? (uint8_t)((c >> 1) ^ 0xE0) : (uint8_t)(c >> 1);
        crc_table[i] = c;
    }
}

static inline uint8_t crc8(const uint8_t *p, size_t n) {
    uint8_t c = 0;
    while (n--) c = crc_table[c ^ *p++];
    return c;
}

/* Both CRCs of a packet with no return address right: the header's (bytes 0-10) and the data's. */
static inline int crcs_ok(const uint8_t *p, size_t n) {
    return n > 13 && crc8(p, 11) == p[11] && crc8(p + 12, n - 13) == p[n - 1];
}

static inline void seal(uint8_t *p, size_t n) { p[11] = crc8(p, 11), p[n - 1] = crc8(p + 12, n - 13); }

/* --- big-endian fields ----------------------------------------------------------------------- */

static inline void put16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)(v >> 8), p[1] = (uint8_t)v; }
static inline void put32(uint8_t *p, uint32_t v) {
    p[0] = (uint8_t)(v >> 24), p[1] = (uint8_t)(v >> 16), p[2] = (uint8_t)(v >> 8), p[3] = (uint8_t)v;
}
static inline void put64(uint8_t *p, uint64_t v) { put32(p, (uint32_t)(v >> 32)), put32(p + 4, (uint32_t)v); }
static inline void putf(uint8_t *p, double v) {
    float f = (float)v;
    uint32_t u;
    memcpy(&u, &f, 4);
    put32(p, u);
}
static inline uint32_t get32(const uint8_t *p) {
    return (uint32_t)p[0] << 24 | (uint32_t)p[1] << 16 | (uint32_t)p[2] << 8 | p[3];
}
static inline uint64_t get64(const uint8_t *p) { return (uint64_t)get32(p) << 32 | get32(p + 4); }
static inline float getf(const uint8_t *p) {
    uint32_t u = get32(p);
    float f;
    memcpy(&f, &u, 4);
    return f;
}

/* The 15 bytes before the cargo: destination, protocol id, no return address, source and
 * destination process, header CRC (sealed later), a zero byte, the packet type. */
static inline void head(uint8_t *p, int64_t dest, int64_t pid, int64_t src, int64_t dst, int type) {
    p[0] = (uint8_t)dest, p[1] = (uint8_t)pid, p[2] = 0;
    put32(p + 3, (uint32_t)src), put32(p + 7, (uint32_t)dst);
    p[11] = 0, p[12] = 0, put16(p + 13, (uint16_t)type);
}

/* --- the host clock and a seeded lossy link ----------------------------------------------------- */

static inline int64_t host_now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static inline double uniform(uint64_t *s) { /* xorshift64* */
    *s ^= *s >> 12, *s ^= *s << 25, *s ^= *s >> 27;
    return (double)((*s * 0x2545F4914F6CDD1Dull) >> 11) / 9007199254740992.0;
}

/* Send a datagram, or drop it with probability `loss` (a lossy SpaceWire link); counts each. */
static inline void send_lossy(int fd, const uint8_t *p, size_t n, int64_t ip, int64_t port, double loss,
                              uint64_t *rng, int64_t *sent, int64_t *lost, int64_t *errors) {
    if (loss > 0 && uniform(rng) < loss) {
        (*lost)++;
        return;
    }
    struct sockaddr_in to = {.sin_family = AF_INET};
    to.sin_addr.s_addr = htonl((uint32_t)ip);
    to.sin_port = htons((uint16_t)port);
    if (sendto(fd, p, n, 0, (struct sockaddr *)&to, sizeof to) == (ssize_t)n)
        (*sent)++;
    else
        (*errors)++; /* a full buffer, or the peer's port gone: the link loses it */
}

/* One waiting datagram into p: its length (-1: none waiting), its sender and its arrival on
 * CLOCK_MONOTONIC (the kernel's SO_TIMESTAMPNS stamp less mono_of_real, else when read). */
static inline ssize_t receive(int fd, uint8_t *p, size_t cap, int64_t mono_of_real, int64_t *ip, int64_t *port,
                              int64_t *at) {
    char control[CMSG_SPACE(sizeof(struct timespec))];
    for (;;) {
        struct sockaddr_in from;
        struct iovec iov = {p, cap};
        struct msghdr msg = {.msg_name = &from, .msg_namelen = sizeof from, .msg_iov = &iov,
                             .msg_iovlen = 1, .msg_control = control, .msg_controllen = sizeof control};
        ssize_t got = recvmsg(fd, &msg, MSG_DONTWAIT);
        if (got < 0) {
            if (errno == EAGAIN || errno == EWOULDBLOCK) return -1;
            continue; /* (an ICMP error queued on the socket: read it away) */
        }
        *at = host_now();
        for (struct cmsghdr *c = CMSG_FIRSTHDR(&msg); c; c = CMSG_NXTHDR(&msg, c))
            if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SO_TIMESTAMPNS) {
                struct timespec k;
                memcpy(&k, CMSG_DATA(c), sizeof k);
                *at = (int64_t)k.tv_sec * 1000000000 + k.tv_nsec - mono_of_real;
            }
        *ip = ntohl(from.sin_addr.s_addr), *port = ntohs(from.sin_port);
        return got;
    }
}

/* Hand a datagram back to Python. */
static inline int hand(handed_t *h, int64_t index, const uint8_t *p, ssize_t got, int64_t at, int64_t ip,
                       int64_t port, uint8_t *buf, int64_t cap) {
    h->index = index, h->len = got, h->at = at, h->ip = ip, h->port = port;
    memcpy(buf, p, (size_t)(got < cap ? got : cap));
    return RUN_HANDED;
}

/* --- a node's link over the two routers (cell.snp.routed.RoutedLink) ------------------------- */

/* native.py's RouteState mirrors it.  A node sends `path + packet` with its own return address in
 * the packet's header, to the router port its socket is joined to; it takes the return address out
 * of what comes in (the sender's name from then on).  A module moves to the other router after
 * failover_after sends unheard; the master answers each return address through the router it
 * last heard it on. */
typedef struct {
    int64_t on, own;                        /* on 0: direct links; own: its return address (1 byte) */
    int64_t ip[2], port[2];                 /* the router ports its socket is joined to (R1, R2) */
    int64_t active, unheard, failover_after, failovers, refused;
    int64_t via[256];                       /* per return address: the router last heard it on */
} route_t;

/* path + p with own as its return address (p has none): its size (n + 2), and the router to send to */
static inline size_t route_out(route_t *r, const uint8_t *p, size_t n, int64_t path, uint8_t *out, int *link) {
    if (r->failover_after) {
        if (++r->unheard > r->failover_after) r->active = 1 - r->active, r->unheard = 0, r->failovers++;
        *link = (int)r->active;
    } else {
        *link = (int)r->via[path & 0xFF];
    }
    out[0] = (uint8_t)path, out[1] = p[0], out[2] = p[1], out[3] = 1, out[4] = (uint8_t)r->own;
    memcpy(out + 5, p + 3, 8);
    out[13] = crc8(out + 1, 12);
    memcpy(out + 14, p + 12, n - 12);
    return n + 2;
}

/* p (n bytes from ip:port) into q without its return address (one byte, *ret), the header CRC
 * made anew: its size, or -1 if it is not from one of the links or its header does not hold */
static inline ssize_t route_in(route_t *r, const uint8_t *p, ssize_t n, int64_t ip, int64_t port, uint8_t *q,
                               int64_t *ret) {
    int link = r->ip[0] == ip && r->port[0] == port ? 0 : r->ip[1] == ip && r->port[1] == port ? 1 : -1;
    if (link < 0 || n < 16 || p[2] != 1 || crc8(p, 12) != p[12]) {
        r->refused++;
        return -1;
    }
    *ret = p[3];
    memcpy(q, p, 2), q[2] = 0;
    memcpy(q + 3, p + 4, 8);
    q[11] = crc8(q, 11);
    memcpy(q + 12, p + 13, (size_t)n - 13);
    r->via[*ret] = link, r->unheard = 0;
    return n - 1;
}

static inline void route_send(route_t *r, int fd, const uint8_t *p, size_t n, int64_t path, double loss,
                              uint64_t *rng, int64_t *sent, int64_t *lost, int64_t *errors) {
    uint8_t out[2048];
    int link;
    if (n + 2 > sizeof out) return;
    size_t size = route_out(r, p, n, path, out, &link);
    send_lossy(fd, out, size, r->ip[link], r->port[link], loss, rng, sent, lost, errors);
}

/* p to a node: at ip:port, or over the routers (r->on) to the one whose address is (0, its return
 * address: native._c_addr) */
static inline void send_via(route_t *r, int fd, const uint8_t *p, size_t n, int64_t ip, int64_t port, double loss,
                            uint64_t *rng, int64_t *sent, int64_t *lost, int64_t *errors) {
    if (r->on && ip == 0)
        route_send(r, fd, p, n, port, loss, rng, sent, lost, errors);
    else
        send_lossy(fd, p, n, ip, port, loss, rng, sent, lost, errors);
}

/* --- VDC's spatial algebra (cell.modular.arm), shared by master.c and cycle.c --------------- */

static inline void cross(const double *a, const double *b, double *out) {
    double o0 = a[1] * b[2] - a[2] * b[1], o1 = a[2] * b[0] - a[0] * b[2], o2 = a[0] * b[1] - a[1] * b[0];
    out[0] = o0, out[1] = o1, out[2] = o2;
}

static inline void mat_vec(const double *r, const double *v, double *out) { /* R v */
    for (int i = 0; i < 3; i++) out[i] = r[3 * i] * v[0] + r[3 * i + 1] * v[1] + r[3 * i + 2] * v[2];
}

/* ^{i+1}X_i^T f: [R n + p x (R f); R f] */
static inline void force_xt(const double *r, const double *p, const double *f, double *out) {
    double rf[3], pr[3];
    mat_vec(r, f + 3, rf);
    cross(p, rf, pr);
    mat_vec(r, f, out);
    for (int i = 0; i < 3; i++) out[i] += pr[i], out[3 + i] = rf[i];
}

/* A body's R = rot rz(q) (Body.transform's), row-major, from its fixed rot */
static inline void turned(const double *r0, double q, double *r) {
    double c = cos(q), s = sin(q);
    for (int k = 0; k < 3; k++) {
        r[3 * k] = r0[3 * k] * c + r0[3 * k + 1] * s;
        r[3 * k + 1] = -r0[3 * k] * s + r0[3 * k + 1] * c;
        r[3 * k + 2] = r0[3 * k + 2];
    }
}

#endif
