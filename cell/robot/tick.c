/* The robots' tick in C: cell/robot/emulator.py's RobotGroup.tick for a group of emulated arms
 * (kinematic or MuJoCo), with no Python and no numpy on six-element arrays per tick.
 *
 * Everything lives in the group's own numpy arrays (the Drives', the backend's q and qd, the status
 * records, the counters): Python built them, this file steps them in place, and whatever Python
 * reads of the group (truth, RTDE, `cell status`, the Responsive Link's holds) is what C wrote.
 * The semantics are cell/robot/drive.py's and emulator.py's, operation for operation (no fused
 * multiply-add: built with -ffp-contract=off), so that a group ticked here and one ticked by the
 * Python model send the same datagrams; tests/robot/test_native_tick.py holds them to that.
 *
 * A tick is two calls, as the Python tick is two halves around the UR interfaces' hook:
 *   rg_send   the status packed at the end of the last tick goes out (a GSO send a socket);
 *   rg_after  the commands that came in (recvmmsg, GRO bursts, kernel stamps), the command windows
 *             that ended, the physics stepped to the next deadline, the next status packed.
 * rg_start (below) loops both on absolute deadlines in a thread of its own: the tick with no Python
 * at all.  Each tick's state goes into a ring Python reads at its own pace (every tick, or only the
 * ticks it asks to be woken for: wake_every, and any tick a robot stopped or resumed in), and what
 * Python changes of the drives (holds, programs' targets) it changes under the group's lock, a
 * priority-inheriting mutex the tick holds while it runs.
 */
#define _GNU_SOURCE
#include <endian.h>
#include <errno.h>
#include <math.h>
#include <netinet/in.h>
#include <pthread.h>
#include "../rt_thread.h"
#include <stdlib.h>
#include <unistd.h>
#include <netinet/udp.h>
#include <stdint.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <time.h>

#ifndef UDP_SEGMENT
#define UDP_SEGMENT 103
#endif
#ifndef UDP_GRO
#define UDP_GRO 104
#endif

#define SIZE 24            /* the robot datagram (cell/robot/datagram.py) */
#define KIND_COMMAND 1
#define MAX_READS 256      /* recvmsg calls per socket per tick (emulator.MAX_READS) */
#define VLEN 8             /* messages per recvmmsg */
#define RX_BYTES 65536     /* one message: a GRO burst */
#define GSO_MAX_SEGMENTS 64
#define CATCH_UP_WINDOWED_S 0.25
#define BIN_US 10.0
#define BINS 2000

typedef void (*mj_step_t)(const void *m, void *d);
typedef void (*mj_mulM_t)(const void *m, const void *d, double *res, const double *vec);

/* GroupCounters' fields, in order (cell/robot/native.py COUNTERS) */
enum { C_STATUS_SENT, C_STATUS_UNSENT, C_LATE_SENDS, C_COMMANDS, C_REJ_LENGTH, C_REJ_KIND, C_REJ_ROBOT,
       C_REJ_JOINT, C_PROTECTIVE_STOPS, C_RESUMES, C_TICKS, C_MISSED_TICKS, C_N };
/* Drives' counts (drive.Drives.counts) */
enum { D_IGNORED, D_STOPS, D_WINDOWS };
/* a Lateness' stats (emulator.Lateness.stats) */
enum { H_N, H_MAX, H_WN, H_WSUM, H_WMAX };

typedef struct {
    /* shape and schedule */
    int64_t n, dof, window_ticks, watchdog, shared, nsock, gso, mujoco, epfd;
    int64_t tick_no, n_stopping, n_resuming;
    double period, scale, h;
    /* the Drives' arrays (n x dof, or n) and counts */
    double *v_max, *a_max, *velocity, *target, *pending;
    uint8_t *has_pending;
    int64_t *missed;
    uint8_t *stopped, *armed, *holds, *scripted;
    int64_t *drive_counts;
    /* the backend: q, qd (n x dof), the joint limits (dof), limit hits (kinematic) */
    double *q, *qd, *q_min, *q_max;
    int64_t *limit_hits;
    /* MuJoCo: the model, each robot's MjData and its arrays; q_ref (n x dof), the feed-forward
     * gains (dof), scratch */
    void *model;
    void **data;
    mj_step_t step;
    mj_mulM_t mulM;
    double **qpos, **qvel, **ctrl, **applied, **bias, **gravcomp;
    double *q_ref, *feedforward, *damping, *before, *mean, *accel, *tau;
    /* sockets: each robot's (or the group's one), the data plane's address, robot ids and rows */
    int32_t *fds, *row_of_fd;
    int64_t max_fd;
    uint8_t *addr;
    int64_t addrlen;
    uint16_t *ids;
    int64_t *row_of_id; /* 65536 of them with a shared socket (-1: not of this group) */
    double *silent_until;
    /* the status records (n x dof x 24 bytes, robot and joint ids filled) and their seqs */
    uint8_t *status;
    uint32_t *seq;
    int64_t *counters;
    int64_t *answers;        /* the answers' histogram (BINS), emulator.Lateness.counts */
    double *answer_stats;    /* and its stats */
    int64_t *stopping, *resuming; /* (n each) rows that stopped / resumed in the last rg_after */
    /* commands stamped after the cutoff: the next window's (latest a joint), and how many a robot */
    double *later_v;
    uint8_t *later_has;
    int64_t *later_n;
    uint8_t *flags;          /* (n) scratch: bit 0 stopped, bit 1 resumed in this rg_after */
    uint8_t *rx;             /* VLEN x RX_BYTES */
    uint8_t *tx;             /* n x dof x 24: the statuses of robots that are not silent */
    /* the thread (rg_start): its tick grid, its wake-ups of Python (an eventfd) and the ring */
    int64_t origin_ns, stop, running, tid, wake_every, wake_fd, wakes;
    int64_t ring_cap, ring_head; /* ticks written so far; tick i is in slot i % ring_cap */
    int64_t *ring_tick;          /* (cap) each slot's tick_no */
    double *ring_q, *ring_qd, *ring_target, *ring_velocity; /* (cap x n x dof) */
    uint8_t *ring_stopped, *ring_flags;                     /* (cap x n): stopped; bit 0 stopped, 1 resumed now */
    int64_t *lateness;           /* the ticks' lateness histogram (emulator.Lateness.counts) */
    double *lateness_stats;
    void *rt;                    /* (C's own: the mutex and the thread) */
    /* servoj's references (Drives.servo_*): n x dof, then n each */
    double *servo_q, *servo_ff, *servo_t, *servo_since, *servo_tau;
    uint8_t *servo_extrapolate;
    /* (2 x n) CLOCK_REALTIME each robot's status left in this tick's send, then in the last (0: it
     * did not): an answer is timed from its own robot's send, not the group's first */
    int64_t *sent;
} group_t;

static double now_mono(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec / 1e9;
}

/* numpy's minimum and maximum: NaN wins */
static inline double np_max(double a, double b) { return (a != a || a >= b) ? a : b; }
static inline double np_min(double a, double b) { return (a != a || a <= b) ? a : b; }

/* --- the drives (cell/robot/drive.py) ----------------------------------------------------------- */

static void command(group_t *g, int64_t row, int64_t joint, double v) {
    if (g->scripted[row]) { /* a URScript program drives it: not the data plane's */
        g->drive_counts[D_IGNORED]++;
        return;
    }
    int64_t i = row * g->dof + joint;
    g->pending[i] = v;
    g->has_pending[i] = 1;
}

/* Drives.end_window: the kept commands execute; flags bit 0 for robots that stopped, bit 1 (with
 * `resumes`) for robots that resumed */
static void end_window(group_t *g, int resumes) {
    int64_t n = g->n, dof = g->dof;
    g->drive_counts[D_WINDOWS]++;
    for (int64_t r = 0; r < n; r++) {
        uint8_t *has = g->has_pending + r * dof;
        int halted = g->holds[r] != 0, any = 0, all = 1, starved = 0;
        for (int64_t j = 0; j < dof; j++) {
            int64_t i = r * dof + j;
            if (halted) has[j] = 0;
            if (has[j]) {
                g->target[i] = g->pending[i];
                g->missed[i] = 0;
                any = 1;
            } else {
                g->missed[i] += 1;
                all = 0;
            }
            if (g->missed[i] >= g->watchdog) starved = 1;
        }
        if (any) g->armed[r] = 1;
        starved = starved && g->armed[r] && !halted;
        int stopping = starved && !g->stopped[r];
        int resuming = g->stopped[r] && all;
        g->stopped[r] = (g->stopped[r] || stopping) && !resuming;
        if (stopping) {
            g->drive_counts[D_STOPS]++;
            g->flags[r] |= 1;
        }
        if (resuming && resumes) g->flags[r] |= 2;
        if (g->stopped[r] || halted)
            for (int64_t j = 0; j < dof; j++) g->target[r * dof + j] = 0.0;
        memset(has, 0, (size_t)dof);
    }
}

/* Drives.servo: the servoing robots' targets for the next dt, closed on q now (a URScript program's
 * servoj, whenever the program that set the reference last ran) */
static void servo(group_t *g, double dt) {
    int64_t dof = g->dof;
    for (int64_t r = 0; r < g->n; r++) {
        if (!(g->servo_tau[r] > 0.0) || g->holds[r]) continue;
        double since = g->servo_since[r] + dt, tau = g->servo_tau[r];
        g->servo_since[r] = since;
        int ff_on = 1;
        if (since > g->servo_t[r] + 1e-9) {
            if (g->servo_extrapolate[r])
                for (int64_t j = 0; j < dof; j++) g->servo_q[r * dof + j] += g->servo_ff[r * dof + j] * dt;
            else
                ff_on = 0;
        }
        for (int64_t j = 0; j < dof; j++) {
            int64_t i = r * dof + j;
            double ff = ff_on ? g->servo_ff[i] : 0.0;
            g->target[i] = ff + (g->servo_q[i] - g->q[i]) / tau;
        }
    }
}

/* Drives.step: toward the targets within the limits; the mean velocity over dt into g->mean */
static void drives_step(group_t *g, double dt) {
    int64_t size = g->n * g->dof;
    for (int64_t i = 0; i < size; i++) {
        double vmax = g->v_max[i];
        double goal = np_min(np_max(g->target[i], -vmax), vmax);
        double step = g->a_max[i] * dt;
        double dv = np_min(np_max(goal - g->velocity[i], -step), step);
        double before = g->velocity[i];
        g->velocity[i] += dv;
        g->mean[i] = before + 0.5 * dv;
    }
}

/* --- the backends (cell/robot/backends.py) ------------------------------------------------------ */

static void kinematic_step(group_t *g, double dt) {
    int64_t n = g->n, dof = g->dof;
    drives_step(g, dt);
    for (int64_t r = 0; r < n; r++)
        for (int64_t j = 0; j < dof; j++) {
            int64_t i = r * dof + j;
            g->q[i] += g->mean[i] * dt;
            if (g->q[i] < g->q_min[j] || g->q[i] > g->q_max[j]) { /* at its end stop: halts there */
                g->limit_hits[0]++;
                g->q[i] = g->q[i] < g->q_min[j] ? g->q_min[j] : g->q_max[j];
                g->velocity[i] = 0.0;
                g->target[i] = 0.0;
            }
        }
}

static void mujoco_step(group_t *g, double dt) {
    int64_t n = g->n, dof = g->dof, size = n * dof;
    double h = g->h;
    int64_t steps = (int64_t)nearbyint(dt / h); /* Python's round(): half to even */
    if (steps < 1) steps = 1;
    for (int64_t s = 0; s < steps; s++) {
        memcpy(g->before, g->velocity, (size_t)size * sizeof(double));
        drives_step(g, h);
        for (int64_t i = 0; i < size; i++) {
            int64_t j = i % dof;
            g->accel[i] = (g->velocity[i] - g->before[i]) / h;
            double ctrl = g->q_ref[i] + g->feedforward[j] * g->before[i];
            ctrl += g->feedforward[j] * (g->velocity[i] - g->before[i]);
            g->accel[i + size] = ctrl; /* (the second half of accel: this step's ctrl) */
            g->q_ref[i] += g->mean[i] * h;
            g->q_ref[i] = np_min(np_max(g->q_ref[i], g->q_min[j]), g->q_max[j]);
        }
        for (int64_t r = 0; r < n; r++) {
            double *tau = g->tau;
            for (int64_t j = 0; j < dof; j++) g->ctrl[r][j] = g->accel[size + r * dof + j];
            g->mulM(g->model, g->data[r], tau, g->accel + r * dof);
            for (int64_t j = 0; j < dof; j++) {
                tau[j] += g->bias[r][j];
                tau[j] -= g->gravcomp[r][j];
                g->applied[r][j] = tau[j] + g->damping[j] * g->velocity[r * dof + j];
            }
            g->step(g->model, g->data[r]);
        }
    }
    for (int64_t r = 0; r < n; r++)
        for (int64_t j = 0; j < dof; j++) {
            g->q[r * dof + j] = g->qpos[r][j];
            g->qd[r * dof + j] = g->qvel[r][j];
        }
}

void rg_step(group_t *g, double dt) {
    if (g->mujoco)
        mujoco_step(g, dt);
    else
        kinematic_step(g, dt);
}

/* --- datagrams ---------------------------------------------------------------------------------- */

static void pack(group_t *g) {
    int64_t size = g->n * g->dof;
    for (int64_t i = 0; i < size; i++) {
        uint8_t *rec = g->status + i * SIZE;
        g->seq[i] += 1;
        uint32_t seq = htobe32(g->seq[i]);
        int64_t v = (int64_t)rint(g->qd[i] * g->scale), p = (int64_t)rint(g->q[i] * g->scale);
        uint64_t vb = htobe64((uint64_t)v), pb = htobe64((uint64_t)p);
        memcpy(rec + 4, &seq, 4);
        memcpy(rec + 8, &vb, 8);
        memcpy(rec + 16, &pb, 8);
    }
}

void rg_pack(group_t *g) { pack(g); }

static void hist_add(int64_t *counts, double *st, double us, int64_t times) {
    int64_t bin = us > 0 ? (int64_t)(us / BIN_US) : 0;
    if (bin < 0) bin = 0;
    if (bin > BINS - 1) bin = BINS - 1;
    counts[bin] += times;
    st[H_N] += (double)times;
    if (us > st[H_MAX]) st[H_MAX] = us;
    st[H_WN] += (double)times;
    st[H_WSUM] += us * (double)times;
    if (us > st[H_WMAX]) st[H_WMAX] = us;
}

/* One message's whole datagrams: checked, counted, taken (or kept for the next window if late) */
static void take_records(group_t *g, int64_t owner, const uint8_t *data, int64_t count, int late,
                         double *now) {
    for (int64_t k = 0; k < count; k++) {
        const uint8_t *rec = data + k * SIZE;
        uint16_t rid = (uint16_t)(rec[0] << 8 | rec[1]);
        uint8_t joint = rec[2], kind = rec[3];
        int64_t row = owner;
        if (kind != KIND_COMMAND) {
            g->counters[C_REJ_KIND]++;
            continue;
        }
        if (g->shared) {
            row = g->row_of_id[rid];
            if (row < 0) {
                g->counters[C_REJ_ROBOT]++;
                continue;
            }
        } else if (rid != g->ids[row]) {
            g->counters[C_REJ_ROBOT]++;
            continue;
        }
        if (joint >= g->dof) {
            g->counters[C_REJ_JOINT]++;
            continue;
        }
        if (g->silent_until[row] > 0) { /* (a silent robot hears nothing) */
            if (*now < 0) *now = now_mono();
            if (g->silent_until[row] > *now) continue;
        }
        g->counters[C_COMMANDS]++;
        uint64_t raw;
        memcpy(&raw, rec + 8, 8);
        double v = (double)(int64_t)be64toh(raw) / g->scale;
        if (late) {
            int64_t i = row * g->dof + joint;
            g->later_v[i] = v;
            g->later_has[i] = 1;
            g->later_n[row]++;
        } else {
            command(g, row, joint, v);
        }
    }
}

/* RobotGroup.receive: drain every readable socket (MAX_READS messages each at most) */
static void receive(group_t *g, int64_t cutoff_ns) {
    struct epoll_event ready[64];
    struct mmsghdr msgs[VLEN];
    struct iovec iov[VLEN];
    char cmsg[VLEN][CMSG_SPACE(sizeof(int)) + CMSG_SPACE(sizeof(struct timespec))];
    double now = -1.0;
    for (;;) {
        int nready = epoll_wait((int)g->epfd, ready, 64, 0);
        if (nready <= 0) return;
        for (int e = 0; e < nready; e++) {
            int fd = ready[e].data.fd;
            if (fd < 0 || fd > g->max_fd || g->row_of_fd[fd] < 0) continue;
            int64_t owner = g->row_of_fd[fd];
            for (int reads = 0; reads < MAX_READS;) {
                for (int m = 0; m < VLEN; m++) {
                    iov[m].iov_base = g->rx + (size_t)m * RX_BYTES;
                    iov[m].iov_len = RX_BYTES;
                    memset(&msgs[m], 0, sizeof msgs[m]);
                    msgs[m].msg_hdr.msg_iov = &iov[m];
                    msgs[m].msg_hdr.msg_iovlen = 1;
                    msgs[m].msg_hdr.msg_control = cmsg[m];
                    msgs[m].msg_hdr.msg_controllen = sizeof cmsg[m];
                }
                int want = MAX_READS - reads < VLEN ? MAX_READS - reads : VLEN;
                int got = recvmmsg(fd, msgs, (unsigned)want, MSG_DONTWAIT, NULL);
                if (got <= 0) break;
                reads += got;
                for (int m = 0; m < got; m++) {
                    int64_t len = msgs[m].msg_len, seg = len, stamp = 0;
                    for (struct cmsghdr *c = CMSG_FIRSTHDR(&msgs[m].msg_hdr); c;
                         c = CMSG_NXTHDR(&msgs[m].msg_hdr, c)) {
                        if (c->cmsg_level == SOL_UDP && c->cmsg_type == UDP_GRO) {
                            int s;
                            memcpy(&s, CMSG_DATA(c), sizeof s);
                            seg = s;
                        } else if (c->cmsg_level == SOL_SOCKET && c->cmsg_type == SCM_TIMESTAMPNS) {
                            struct timespec ts;
                            memcpy(&ts, CMSG_DATA(c), sizeof ts);
                            stamp = (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
                        }
                    }
                    if (seg != SIZE) { /* a burst of the wrong size: every datagram of it malformed */
                        int64_t s = seg > 1 ? seg : 1, bad = (len + s - 1) / s;
                        g->counters[C_REJ_LENGTH] += bad > 1 ? bad : 1;
                        continue;
                    }
                    int64_t whole = len - len % SIZE, count = whole / SIZE;
                    if (whole != len) g->counters[C_REJ_LENGTH]++;
                    if (!count) continue;
                    if (cutoff_ns && stamp > 0) { /* the loop as the robot sees it: from its status */
                        int64_t now_sent = g->sent[owner], since = g->sent[g->n + owner];
                        if (now_sent > 0 && stamp >= now_sent) since = now_sent; /* this tick's */
                        if (since > 0)
                            hist_add(g->answers, g->answer_stats, (double)(stamp - since) / 1e3, count);
                    }
                    int late = cutoff_ns && stamp > cutoff_ns;
                    take_records(g, owner, (const uint8_t *)iov[m].iov_base, count, late, &now);
                }
                if (got < want) break;
            }
        }
        if (nready < 64) return;
    }
}

/* The last rg_after's stopped and resumed rows out of the flags, in order */
static void rows_of_flags(group_t *g) {
    g->n_stopping = g->n_resuming = 0;
    for (int64_t r = 0; r < g->n; r++) {
        if (g->flags[r] & 1) g->stopping[g->n_stopping++] = r;
        if (g->flags[r] & 2) g->resuming[g->n_resuming++] = r;
        g->flags[r] = 0;
    }
}

static int64_t floordiv(int64_t a, int64_t b) { return a / b - ((a % b != 0) && ((a < 0) != (b < 0))); }

/* RobotGroup.take: the commands, the windows that ended over `periods`; the periods left to step */
static int64_t take(group_t *g, int64_t cutoff_ns, int64_t periods) {
    receive(g, cutoff_ns);
    int64_t last = g->tick_no, w = g->window_ticks;
    g->tick_no += periods;
    int64_t ends = floordiv(g->tick_no, w) - floordiv(last > 0 ? last : 0, w);
    if (ends) end_window(g, 1);
    int64_t left = periods;
    int windowed = (double)periods * g->period > CATCH_UP_WINDOWED_S;
    for (int64_t k = 0; windowed && k < ends - 1; k++) { /* a long catch-up: window by window */
        int64_t chunk = w < left - 1 ? w : left - 1;
        if (chunk) rg_step(g, g->period * (double)chunk);
        left -= chunk;
        end_window(g, 0);
    }
    int64_t size = g->n * g->dof;
    for (int64_t r = 0; r < g->n; r++) { /* the answers to this tick's status: the next window's */
        if (!g->later_n[r]) continue;
        if (g->scripted[r]) {
            g->drive_counts[D_IGNORED] += g->later_n[r];
        } else {
            for (int64_t j = 0; j < g->dof; j++) {
                int64_t i = r * g->dof + j;
                if (g->later_has[i]) command(g, r, j, g->later_v[i]);
            }
        }
        g->later_n[r] = 0;
    }
    memset(g->later_has, 0, (size_t)size);
    rows_of_flags(g);
    g->counters[C_PROTECTIVE_STOPS] += g->n_stopping;
    g->counters[C_RESUMES] += g->n_resuming;
    return left;
}

/* After the status went out: take, step to the next deadline, pack the next status */
void rg_after(group_t *g, int64_t cutoff_ns, int64_t periods) {
    int64_t left = take(g, cutoff_ns, periods);
    servo(g, g->period * (double)periods);
    rg_step(g, g->period * (double)left);
    pack(g);
    g->counters[C_TICKS]++;
    g->counters[C_MISSED_TICKS] += periods - 1;
}

static int64_t send_gso(group_t *g, int fd, const uint8_t *buf, int64_t len) {
    /* UDP_SEGMENT is set on the socket (udp.Sender): one send carries up to 64 datagrams */
    int64_t sent = 0;
    for (int64_t off = 0; off < len; off += SIZE * GSO_MAX_SEGMENTS) {
        int64_t chunk = len - off < SIZE * GSO_MAX_SEGMENTS ? len - off : SIZE * GSO_MAX_SEGMENTS;
        if (g->gso) {
            ssize_t rc = sendto(fd, buf + off, (size_t)chunk, MSG_DONTWAIT,
                                (const struct sockaddr *)g->addr, (socklen_t)g->addrlen);
            if (rc >= 0) {
                sent += chunk / SIZE;
                continue;
            }
            if (errno == EAGAIN || errno == EWOULDBLOCK) return sent;
        }
        for (int64_t k = 0; k < chunk; k += SIZE) { /* no GSO: one datagram a call */
            if (sendto(fd, buf + off + k, SIZE, MSG_DONTWAIT, (const struct sockaddr *)g->addr,
                       (socklen_t)g->addrlen) < 0)
                return sent;
            sent++;
        }
    }
    return sent;
}

static int64_t real_ns(void);

/* RobotGroup._send: each robot's status (robots made silent by `cell chaos` send none) */
void rg_send(group_t *g, double deadline) {
    int64_t per = g->dof * SIZE;
    memcpy(g->sent + g->n, g->sent, (size_t)g->n * sizeof *g->sent); /* (this tick's is the last's) */
    memset(g->sent, 0, (size_t)g->n * sizeof *g->sent);
    double late_after = deadline + g->period, now = -1.0;
    int silent_any = 0;
    for (int64_t r = 0; r < g->n; r++)
        if (g->silent_until[r] > 0) {
            if (now < 0) now = now_mono();
            if (g->silent_until[r] > now) silent_any = 1;
        }
    if (g->nsock == 0) return;
    if (g->shared) {
        const uint8_t *buf = g->status;
        int64_t len = g->n * per;
        if (silent_any) { /* (rare) the others' statuses only */
            len = 0;
            for (int64_t r = 0; r < g->n; r++)
                if (!(g->silent_until[r] > now)) {
                    memcpy(g->tx + len, g->status + r * per, (size_t)per);
                    len += per;
                }
            buf = g->tx;
        }
        int64_t at = real_ns();
        for (int64_t r = 0; r < g->n; r++) g->sent[r] = at;
        int64_t sent = send_gso(g, g->fds[0], buf, len);
        g->counters[C_STATUS_SENT] += sent;
        g->counters[C_STATUS_UNSENT] += len / SIZE - sent;
        if (now_mono() >= late_after) g->counters[C_LATE_SENDS] += sent;
        return;
    }
    for (int64_t r = 0; r < g->n; r++) {
        if (silent_any && g->silent_until[r] > now) continue;
        g->sent[r] = real_ns();
        int64_t sent = send_gso(g, g->fds[r], g->status + r * per, per);
        g->counters[C_STATUS_SENT] += sent;
        g->counters[C_STATUS_UNSENT] += g->dof - sent;
        if (now_mono() >= late_after) g->counters[C_LATE_SENDS] += sent;
    }
}

/* --- the tick in a thread of its own ------------------------------------------------------------- */

typedef struct {
    pthread_mutex_t mutex;
    pthread_t thread;
} rt_t;

static int64_t mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static int64_t real_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* The tick's state into the ring, then published (Python reads ring_head, then the slots below it) */
static int ring_write(group_t *g) {
    int64_t slot = g->ring_head % g->ring_cap, size = g->n * g->dof, n = g->n;
    g->ring_tick[slot] = g->tick_no;
    memcpy(g->ring_q + slot * size, g->q, (size_t)size * sizeof(double));
    memcpy(g->ring_qd + slot * size, g->qd, (size_t)size * sizeof(double));
    memcpy(g->ring_target + slot * size, g->target, (size_t)size * sizeof(double));
    memcpy(g->ring_velocity + slot * size, g->velocity, (size_t)size * sizeof(double));
    memcpy(g->ring_stopped + slot * n, g->stopped, (size_t)n);
    uint8_t *flags = g->ring_flags + slot * n;
    memset(flags, 0, (size_t)n);
    for (int64_t k = 0; k < g->n_stopping; k++) flags[g->stopping[k]] |= 1;
    for (int64_t k = 0; k < g->n_resuming; k++) flags[g->resuming[k]] |= 2;
    __atomic_store_n(&g->ring_head, g->ring_head + 1, __ATOMIC_RELEASE);
    return g->n_stopping || g->n_resuming;
}

static void *run(void *arg) {
    group_t *g = arg;
    rt_t *rt = g->rt;
    __atomic_store_n(&g->tid, (int64_t)gettid(), __ATOMIC_RELEASE);
    int64_t period_ns = (int64_t)llround(g->period * 1e9), last = -1;
    int64_t next = g->origin_ns;
    while (!__atomic_load_n(&g->stop, __ATOMIC_ACQUIRE)) {
        struct timespec at = {.tv_sec = next / 1000000000, .tv_nsec = next % 1000000000};
        if (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &at, NULL)) continue; /* (a signal) */
        int64_t now = mono_ns();
        if (now < next) continue;
        int64_t due = (now - g->origin_ns) / period_ns; /* the latest deadline passed */
        int64_t periods = due - last, deadline_ns = g->origin_ns + due * period_ns;
        /* (late against the deadline slept for: a wake past the next one too shows as late as it was) */
        hist_add(g->lateness, g->lateness_stats, (double)(now - next) / 1e3, 1);
        pthread_mutex_lock(&rt->mutex);
        int64_t cutoff = real_ns(); /* (the kernel stamps datagrams in CLOCK_REALTIME) */
        rg_send(g, (double)deadline_ns / 1e9);
        rg_after(g, cutoff, periods);
        int events = ring_write(g);
        pthread_mutex_unlock(&rt->mutex);
        int64_t every = __atomic_load_n(&g->wake_every, __ATOMIC_RELAXED);
        if (g->wake_fd >= 0 && (events || (every > 0 && g->tick_no % every == 0))) {
            uint64_t one = 1;
            if (write((int)g->wake_fd, &one, sizeof one) == sizeof one) g->wakes++;
        }
        last = due;
        next = g->origin_ns + (due + 1) * period_ns;
    }
    return NULL;
}

/* The tick in a thread of its own from origin_ns (CLOCK_MONOTONIC: period 0's deadline), at
 * SCHED_FIFO `priority` from its first instruction (0, or refused: the caller's scheduling,
 * inherited); 0, or the errno of what failed */
int rg_start(group_t *g, int priority) {
    g->stop = 0;
    g->tid = 0;
    int rc = rt_thread_start(&((rt_t *)g->rt)->thread, priority, run, g);
    g->running = rc == 0;
    return rc;
}

void rg_stop(group_t *g) {
    if (!g->running) return;
    rt_t *rt = g->rt;
    __atomic_store_n(&g->stop, 1, __ATOMIC_RELEASE);
    pthread_join(rt->thread, NULL);
    g->running = 0;
}

/* The group's lock: what Python changes of the drives, it changes between two ticks */
void rg_lock(group_t *g) { pthread_mutex_lock(&((rt_t *)g->rt)->mutex); }
void rg_unlock(group_t *g) { pthread_mutex_unlock(&((rt_t *)g->rt)->mutex); }

/* C's own part of a group (the mutex priority-inheriting: a Python thread holding it runs at the
 * tick's priority until it lets go); 0 or an errno */
int rg_init(group_t *g) {
    rt_t *rt = calloc(1, sizeof *rt);
    if (!rt) return ENOMEM;
    pthread_mutexattr_t attr;
    pthread_mutexattr_init(&attr);
    pthread_mutexattr_setprotocol(&attr, PTHREAD_PRIO_INHERIT);
    int rc = pthread_mutex_init(&rt->mutex, &attr);
    pthread_mutexattr_destroy(&attr);
    if (rc) {
        free(rt);
        return rc;
    }
    g->rt = rt;
    return 0;
}

void rg_free(group_t *g) {
    if (!g->rt) return;
    rg_stop(g);
    pthread_mutex_destroy(&((rt_t *)g->rt)->mutex);
    free(g->rt);
    g->rt = NULL;
}

/* One tick as the thread runs it (send, take, step, pack), its work timed here (ns): the bench's
 * figure of what a tick costs, without the caller's own */
int64_t rg_tick_timed(group_t *g, double deadline, int64_t periods) {
    int64_t t0 = mono_ns(), cutoff = real_ns();
    rg_send(g, deadline);
    rg_after(g, cutoff, periods);
    return mono_ns() - t0;
}
