/* The user-space data plane (backend "native"): the XDP program's own C (xdp/dataplane.bpf.c, built
 * here with CELL_USERSPACE) run over recvmmsg/sendmmsg in a thread of its own, no Python per packet.
 *
 * Its maps are memory the Python control plane allocated (cell/dataplane/native.py) and writes as
 * numpy arrays through the same Tables and Pipeline code as the XDP backend's; the gate protocol
 * (globals.closed, globals.inflight) is the kernel program's, so a batch of table updates appears
 * to the packet path all at once here too.  Each burst a sender's statuses came in (UDP GRO) is
 * handled as one datagram of the XDP program is, 64 records at most at a time, and answered to
 * its sender with one GSO send.
 */
#define _GNU_SOURCE
#include <endian.h>
#include <errno.h>
#include <linux/types.h>
#include <netinet/in.h>
#include <poll.h>
#include <pthread.h>
#include "../rt_thread.h"
#include <sched.h>
#include <stdint.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#ifndef UDP_SEGMENT
#define UDP_SEGMENT 103
#endif
#ifndef UDP_GRO
#define UDP_GRO 104
#endif
#ifndef SOL_UDP
#define SOL_UDP 17
#endif

/* --- what the BPF program needs of the kernel, in user space -------------------------------------- */

#define CELL_USERSPACE 1
#define SEC(name)
#define barrier_var(x) __asm__ volatile("" : "+r"(x))
#define bpf_be64_to_cpu(x) be64toh(x)
#define bpf_cpu_to_be64(x) htobe64(x)
#define bpf_htons(x) htons(x)
#define bpf_ntohs(x) ntohs(x)
#ifndef __always_inline
#define __always_inline inline __attribute__((always_inline))
#endif

struct umap { /* an array map: `max` values of `size` bytes at `base` */
    char *base;
    __u64 max;
    __u64 size;
};

struct maps { /* one data plane's (the Python side's NativeMaps, in this order) */
    struct umap robots, status, entities, rows, transform, limits, globals, counters, scratches, marks;
};

/* the maps of the data plane this thread is running, by the names the BPF program uses (use()) */
static __thread struct umap robots, status, entities, rows, transform, limits, globals, counters, scratches,
    marks;

static void use(const struct maps *m)
{
    robots = m->robots, status = m->status, entities = m->entities, rows = m->rows;
    transform = m->transform, limits = m->limits, globals = m->globals, counters = m->counters;
    scratches = m->scratches, marks = m->marks;
}

static inline void *bpf_map_lookup_elem(struct umap *m, const void *key)
{
    __u32 k = *(const __u32 *)key;
    return k < m->max ? m->base + (__u64)k * m->size : (void *)0;
}

static inline long bpf_loop(__u32 n, long (*fn)(__u32, void *), void *ctx, __u64 flags)
{
    (void)flags;
    for (__u32 i = 0; i < n; i++)
        if (fn(i, ctx))
            return i + 1;
    return n;
}

#include "xdp/dataplane.bpf.c"

/* --- one payload (tests, and statuses the Python side hands in) ----------------------------------- */

static __s64 mono_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (__s64)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* `n` whole records at `data` (rewritten in place into commands) from saddr:sport (network order):
 * HANDLED, HELD or BAD (drop them), as the XDP program does with one datagram */
static int run_records(struct maps *m, __u8 *data, __u32 n, __u32 saddr, __u16 sport)
{
    use(m);
    __u32 zero = 0;
    struct globals *g = bpf_map_lookup_elem(&m->globals, &zero);
    struct scratch *s = bpf_map_lookup_elem(&m->scratches, &zero);
    if (!g || !s)
        return BAD;
    memcpy(s->wire, data, (size_t)n * REC_SIZE);
    int done = handle(g, s, n, saddr, sport, mono_ns());
    if (done != BAD) {
        memcpy(data, s->wire, (size_t)n * REC_SIZE);
        count(C_COMMANDS_OUT, n);
    }
    return done;
}

/* A payload as the XDP program takes one datagram: its verdict (-1: malformed, counted; BAD) */
int dp_payload(struct maps *m, __u8 *data, __u32 len, __u32 saddr, __u16 sport)
{
    use(m);
    count(C_DATAGRAMS, 1);
    if (len == 0 || len % REC_SIZE) {
        count(C_REJ_LENGTH, 1);
        return -1;
    }
    __u32 n = len / REC_SIZE;
    if (n > MAX_RECS) {
        count(C_REJ_BATCH, n);
        return -1;
    }
    return run_records(m, data, n, saddr, sport);
}

/* The gate, as the kernel program's `gate`: 1 closes (closed + 1), 0 opens */
void dp_gate(struct maps *m, int op)
{
    __u32 zero = 0;
    struct globals *g = bpf_map_lookup_elem(&m->globals, &zero);
    if (g)
        __sync_fetch_and_add(&g->closed, op ? 1 : (__u32)-1);
}

/* --- the packet path: a socket served until told to stop ----------------------------------------- */

#define VLEN 16
#define RX_BYTES 65536
#define BATCH_BINS 1024

struct server {
    struct maps *maps;
    __s64 fd;
    __s64 stop;       /* set by dp_stop */
    __s64 running;
    __s64 wakeups, bursts, answered, unsent, batch_ns_max;
    __s64 tid;        /* the serving thread's (0 until it runs) */
    __s64 batch_us[BATCH_BINS]; /* each wake-up's handling time, 1 us bins (the last: longer) */
    pthread_t thread;
    __u8 rx[VLEN][RX_BYTES];
    char cmsg[VLEN][CMSG_SPACE(sizeof(int)) + CMSG_SPACE(sizeof(struct timespec))];
    struct sockaddr_storage from[VLEN];
};

/* Every burst waiting (VLEN a call), each sender's records answered to it; how many bursts */
static int serve_once(struct server *sv)
{
    struct mmsghdr in[VLEN], out[VLEN];
    struct iovec iov[VLEN], oiov[VLEN * 2];
    char ocmsg[VLEN][CMSG_SPACE(sizeof(__u16))];
    for (int i = 0; i < VLEN; i++) {
        iov[i].iov_base = sv->rx[i];
        iov[i].iov_len = RX_BYTES;
        memset(&in[i], 0, sizeof in[i]);
        in[i].msg_hdr.msg_iov = &iov[i];
        in[i].msg_hdr.msg_iovlen = 1;
        in[i].msg_hdr.msg_name = &sv->from[i];
        in[i].msg_hdr.msg_namelen = sizeof sv->from[i];
        in[i].msg_hdr.msg_control = sv->cmsg[i];
        in[i].msg_hdr.msg_controllen = sizeof sv->cmsg[i];
    }
    int got = recvmmsg((int)sv->fd, in, VLEN, MSG_DONTWAIT, NULL);
    if (got <= 0)
        return 0;
    use(sv->maps);
    __s64 t0 = mono_ns();
    int nout = 0;
    for (int i = 0; i < got; i++) {
        __u32 len = in[i].msg_len, seg = len;
        for (struct cmsghdr *c = CMSG_FIRSTHDR(&in[i].msg_hdr); c; c = CMSG_NXTHDR(&in[i].msg_hdr, c))
            if (c->cmsg_level == SOL_UDP && c->cmsg_type == UDP_GRO) {
                int s;
                memcpy(&s, CMSG_DATA(c), sizeof s);
                seg = (__u32)s;
            }
        count(C_DATAGRAMS, 1);
        if (seg != REC_SIZE || len % REC_SIZE || len == 0) { /* a burst of the wrong size: malformed */
            __u32 per = seg ? seg : 1;
            count(C_REJ_LENGTH, (len + per - 1) / per ? (len + per - 1) / per : 1);
            continue;
        }
        struct sockaddr_in *from = (struct sockaddr_in *)&sv->from[i];
        if (from->sin_family != AF_INET)
            continue;
        __u32 n = len / REC_SIZE, kept = 0;
        for (__u32 k = 0; k < n; k += MAX_RECS) { /* 64 records a datagram of the XDP program */
            __u32 part = n - k < MAX_RECS ? n - k : MAX_RECS;
            __u8 *at = sv->rx[i] + (size_t)k * REC_SIZE;
            if (run_records(sv->maps, at, part, from->sin_addr.s_addr, from->sin_port) == BAD)
                continue;
            if (kept != k) /* (a dropped part before it: close the gap) */
                memmove(sv->rx[i] + (size_t)kept * REC_SIZE, at, (size_t)part * REC_SIZE);
            kept += part;
        }
        if (!kept)
            continue;
        struct msghdr *h = &out[nout].msg_hdr;
        memset(&out[nout], 0, sizeof out[nout]);
        oiov[nout].iov_base = sv->rx[i];
        oiov[nout].iov_len = (size_t)kept * REC_SIZE;
        h->msg_iov = &oiov[nout];
        h->msg_iovlen = 1;
        h->msg_name = &sv->from[i];
        h->msg_namelen = in[i].msg_hdr.msg_namelen;
        if (kept > 1) { /* GSO: the records leave as the datagrams they came as */
            h->msg_control = ocmsg[nout];
            h->msg_controllen = sizeof ocmsg[nout];
            struct cmsghdr *c = CMSG_FIRSTHDR(h);
            c->cmsg_level = SOL_UDP;
            c->cmsg_type = UDP_SEGMENT;
            c->cmsg_len = CMSG_LEN(sizeof(__u16));
            __u16 size = REC_SIZE;
            memcpy(CMSG_DATA(c), &size, sizeof size);
        }
        nout++;
    }
    for (int done = 0; done < nout;) {
        int sent = sendmmsg((int)sv->fd, out + done, (unsigned)(nout - done), MSG_DONTWAIT);
        if (sent <= 0) { /* a full buffer: what is left is lost, counted */
            for (int k = done; k < nout; k++)
                sv->unsent += (__s64)(out[k].msg_hdr.msg_iov->iov_len / REC_SIZE);
            break;
        }
        for (int k = done; k < done + sent; k++)
            sv->answered += (__s64)(out[k].msg_hdr.msg_iov->iov_len / REC_SIZE);
        done += sent;
    }
    sv->bursts += got;
    __s64 took = mono_ns() - t0, bin = took / 1000;
    if (took > sv->batch_ns_max)
        sv->batch_ns_max = took;
    sv->batch_us[bin < BATCH_BINS ? bin : BATCH_BINS - 1]++;
    return got;
}

/* Serve what waits now, without blocking (tests, and a caller that polls): bursts handled */
__s64 dp_serve(struct server *sv)
{
    __s64 total = 0;
    int got;
    while ((got = serve_once(sv)) > 0)
        total += got;
    return total;
}

static void *serve_thread(void *arg)
{
    struct server *sv = arg;
    struct pollfd p = {.fd = (int)sv->fd, .events = POLLIN};
    __atomic_store_n(&sv->tid, (__s64)gettid(), __ATOMIC_RELEASE);
    while (!__atomic_load_n(&sv->stop, __ATOMIC_ACQUIRE)) {
        int r = poll(&p, 1, 100); /* (a stop is seen within 100 ms) */
        if (r <= 0)
            continue;
        sv->wakeups++;
        while (serve_once(sv) == VLEN) /* a full read: more may wait */
            ;
    }
    return NULL;
}

/* Start serving in a thread of its own at SCHED_FIFO `priority` (0: the caller's policy, inherited);
 * 0, or the errno of what failed */
int dp_start(struct server *sv, int priority)
{
    sv->stop = 0;
    int rc = rt_thread_start(&sv->thread, priority, serve_thread, sv);
    sv->running = rc == 0;
    return rc;
}

void dp_stop(struct server *sv)
{
    if (!sv->running)
        return;
    __atomic_store_n(&sv->stop, 1, __ATOMIC_RELEASE);
    pthread_join(sv->thread, NULL);
    sv->running = 0;
}

__u64 dp_server_size(void) { return sizeof(struct server); }

/* The sizes of the maps' values, for the Python side to check its dtypes against (robot, status,
 * entity, row, limit, globals, scratch, mark, the counters' count) */
void dp_sizes(__u64 *out)
{
    out[0] = sizeof(struct robot), out[1] = sizeof(struct status), out[2] = sizeof(struct entity);
    out[3] = sizeof(struct row), out[4] = sizeof(struct limit), out[5] = sizeof(struct globals);
    out[6] = sizeof(struct scratch), out[7] = sizeof(struct mark), out[8] = C_COUNT;
}
