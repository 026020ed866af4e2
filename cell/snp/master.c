/* The master's side of the 1 kHz cycle in C: the hot path of cell.snp.modular.Master.
 *
 * cell/snp/native.py builds this (with cycle.c, into one library) and runs it on the master's
 * UDP socket between the Python master's timers.  It takes the A and C queries of the included
 * modules (Master._cycle_query: parsed by their shape, admitted or denied as Handler.admit
 * decides, their inputs taken into the arm model), answers them earliest deadline first with B
 * (ArmModel.command) or D (ArmModel.torque), and keeps FDIR's per-cycle watch (Master._fdir: a
 * missing A guessed, a module silent for suspect_cycles reported, one silent for lost_ns
 * excluded).  Every other datagram (node info, configuration, SnP-TSP, RMAP, queries of other
 * shapes, junk) goes back to Python untouched; so does the call at `until` (beacons,
 * exploration) and at every FDIR event.
 *
 * Why C: through the Python master a query costs about 20 us on this machine kind, so twelve a
 * period take a quarter of the cycle's budget and any late start of the modules turns into
 * denials; here a query costs its two syscalls.  The arithmetic mirrors the Python master's
 * line for line (tests/snp/test_snp_native.py checks the answers' bytes against it). */

#include "wire.h"

#define MAX_JOINTS 16 /* ArmModel's default size */
#define VDC_JOINTS 6  /* the modular arm's (cell.modular.cycle) */
#define QUEUE 64      /* admitted queries waiting for their turn */
#define EVENTS 32

enum { NODE_OFF = 0, NODE_INCLUDED = 1, NODE_SUSPECT = 2, NODE_LOST = 3 };
enum { EVENT_SILENT = 1, EVENT_BACK = 2, EVENT_LOST = 3 };

/* A joint's module and its part of the arm model; cell/snp/native.py's JointEntry mirrors it. */
typedef struct {
    int64_t state, ip, port, phase_ns; /* state: NODE_*; ip, port in host order */
    int64_t ids[5];                    /* item ids: position, velocity, commanded velocity, force, torque */
    double pos, vel, force;            /* ArmModel.pos, vel, force */
    int64_t at, a_cycle, heard_ns, silent_cycles, checked; /* a_cycle -1: no A yet */
} joint_t;

typedef struct {
    int64_t deadline, seq, joint, is_a, qid, dest, pid, src, dst, t, ip, port, local;
} pending_t;

/* VDC's master (cell.modular.cycle.VdcModel): the modular arm's bodies, its reference, each body's
 * last F*_r and the forward recursion's steps; cell/snp/native.py's VdcState mirrors it. */
typedef struct {
    int64_t n_ref, ref_dt_ns, start_ns, settle_ns; /* the reference: n_ref points ref_dt_ns apart */
    double lam;
    const double *q_ref, *qd_ref, *qdd_ref; /* (n_ref, VDC_JOINTS), row-major */
    int64_t b_ids[VDC_JOINTS][20], f_ids[VDC_JOINTS][6];
    double body_pos[VDC_JOINTS][3], body_rot[VDC_JOINTS][9]; /* Body.pos, Body.rot (row-major) */
    double f_star[VDC_JOINTS][6];
    int64_t seq[VDC_JOINTS]; /* A's taken per joint */
    /* the recursion's step per body: made in cycle key_cycle from the A's key_seq (VdcModel._chain) */
    int64_t key_cycle[VDC_JOINTS], key_seq[VDC_JOINTS][VDC_JOINTS];
    double b[VDC_JOINTS][20], rot[VDC_JOINTS][9], carry[VDC_JOINTS][18]; /* its B, R, (v, v_r, a_r) */
    int64_t g_ids[VDC_JOINTS][6]; /* G's, for a module that computes its own [C, D] */
} vdc_t;

/* The master; cell/snp/native.py's MasterState mirrors it field for field (all 64-bit). */
typedef struct {
    /* set by Python */
    int64_t fd, period_ns, phase_ns, budget_ns, t0, suspect_cycles, lost_ns, floor_ns;
    double gain, margin, loss;
    int64_t service_ns; /* the running estimate of a query's service time (make and send) */
    vdc_t *vdc;         /* NULL: the toy arm model's A and C; else VDC's (cell.modular.wire's shapes) */
    joint_t joints[MAX_JOINTS];
    /* counted since Python last took them */
    int64_t queries, replies, denied, late, guessed, sent, lost, errors, n_events;
    int64_t events[EVENTS][3]; /* t, EVENT_*, joint */
    int64_t n_pending, seq;
    pending_t pending[QUEUE]; /* by deadline, then arrival */
    route_t route; /* over the two routers (route.on): a module's address is (0, its return address) */
} master_t;

static uint64_t rng_state = 0xD1B54A32D192ED03ull; /* the link's losses */

static int64_t floor_div(int64_t a, int64_t b) { return a / b - (a % b != 0 && (a < 0) != (b < 0)); }

static int live(const joint_t *j) { return j->state == NODE_INCLUDED || j->state == NODE_SUSPECT; }

static void event(master_t *m, int64_t t, int64_t what, int64_t joint) {
    int64_t *e = m->events[m->n_events < EVENTS ? m->n_events++ : EVENTS - 1];
    e[0] = t, e[1] = what, e[2] = joint;
}

/* --- the arm model (ArmModel.reference, guess, command, torque) ------------------------------- */

static double guess(const joint_t *j, int64_t t) { return j->pos + j->vel * (double)(t - j->at) / 1e9; }

static double command(const master_t *m, int joint, int64_t t_ns) {
    double t = (double)(t_ns - m->t0) / 1e9;
    double w = 2 * M_PI * 0.5, a = 0.2 * (1 + (double)joint / 10);
    double p_ref = a * sin(w * t), v_ref = a * w * cos(w * t);
    return v_ref + m->gain * (p_ref - guess(&m->joints[joint], t_ns));
}

static double torque(const master_t *m, int joint, int64_t t_ns) {
    double angle = 0.0, load = 0.0;
    for (int j = 0; j < MAX_JOINTS; j++) {
        if (!live(&m->joints[j])) continue;
        angle += guess(&m->joints[j], t_ns);
        if (j >= joint) load += cos(angle);
    }
    return 0.8 * m->joints[joint].force + 2.0 * load;
}

/* --- VDC (cell.modular.vdc.forward_step, cell.modular.cycle.VdcModel.b, tau_r) ------------------ */


static void mat_t_vec(const double *r, const double *v, double *out) { /* R^T v */
    for (int i = 0; i < 3; i++) out[i] = r[i] * v[0] + r[3 + i] * v[1] + r[6 + i] * v[2];
}

/* ^iX_{i-1} m, X of a child at p turned R: [R^T w; R^T (v - p x w)] */
static void motion_x(const double *r, const double *p, const double *m, double *out) {
    double pw[3], d[3];
    cross(p, m, pw);
    for (int i = 0; i < 3; i++) d[i] = m[3 + i] - pw[i];
    mat_t_vec(r, m, out);
    mat_t_vec(r, d, out + 3);
}

static void desired(vdc_t *v, const master_t *m, int j, int64_t t, double *qd3) {
    if (v->start_ns == 0) { /* the reference starts once every joint is in the cycle */
        int all = 1;
        for (int i = 0; i < VDC_JOINTS; i++) all &= live(&m->joints[i]);
        if (all) v->start_ns = t + v->settle_ns;
    }
    int64_t k = v->start_ns == 0 ? 0 : floor_div(t - v->start_ns, v->ref_dt_ns);
    k = k < 0 ? 0 : (k > v->n_ref - 1 ? v->n_ref - 1 : k);
    qd3[0] = v->q_ref[k * VDC_JOINTS + j], qd3[1] = v->qd_ref[k * VDC_JOINTS + j];
    qd3[2] = v->qdd_ref[k * VDC_JOINTS + j];
}

/* One body of the forward recursion from the carry of the body below (v, v_r, a_r: 18 values). */
static void forward_step(vdc_t *v, const master_t *m, int i, int64_t t, const double *parent) {
    const joint_t *jt = &m->joints[i];
    double q = live(jt) ? guess(jt, t) : jt->pos, qd = live(jt) ? jt->vel : 0.0, ref[3]; /* (one gone: braked) */
    desired(v, m, i, t, ref);
    double qd_r = ref[1] + v->lam * (ref[0] - q), qdd_r = ref[2] + v->lam * (ref[1] - qd);
    double *r = v->rot[i];
    const double *p = v->body_pos[i];
    turned(v->body_rot[i], q, r); /* R = rot rz(q) */
    double *out = v->carry[i], *vv = out, *vr = out + 6, *ar = out + 12, carried[6], mw[3] = {0, 0, qd};
    motion_x(r, p, parent, vv);
    vv[2] += qd;
    motion_x(r, p, parent + 6, carried);
    memcpy(vr, carried, sizeof carried);
    vr[2] += qd_r;
    motion_x(r, p, parent + 12, ar);
    ar[2] += qdd_r;
    double cw[3], cv[3]; /* crm(carried) (z qd) = [w x m_w; v x m_w] */
    cross(carried, mw, cw);
    cross(carried + 3, mw, cv);
    for (int k = 0; k < 3; k++) ar[k] += cw[k], ar[3 + k] += cv[k];
    double *b = v->b[i];
    b[0] = qd_r, b[1] = qdd_r;
    memcpy(b + 2, vr, 6 * sizeof(double)), memcpy(b + 8, ar, 6 * sizeof(double));
    memcpy(b + 14, vv, 6 * sizeof(double));
}

static int step_current(const vdc_t *v, int i, int64_t cycle) {
    if (v->key_cycle[i] != cycle) return 0;
    for (int k = 0; k <= i; k++)
        if (v->key_seq[i][k] != v->seq[k]) return 0;
    return 1;
}

/* Joint j's B at t: the steps below j made this cycle from the same A's kept, the rest made anew. */
static const double *vdc_b(vdc_t *v, const master_t *m, int j, int64_t t) {
    int64_t cycle = floor_div(t + m->period_ns / 2, m->period_ns);
    int start = j;
    while (start > 0 && !step_current(v, start - 1, cycle)) start--;
    static const double base[18] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 9.81};
    for (int i = start; i <= j; i++) {
        forward_step(v, m, i, t, i == 0 ? base : v->carry[i - 1]);
        v->key_cycle[i] = cycle;
        for (int k = 0; k <= i; k++) v->key_seq[i][k] = v->seq[k];
    }
    return v->b[j];
}

/* G (VdcModel.outboard): what the bodies out from j to the tip need of body j, in j's frame. */
static void vdc_outboard(const vdc_t *v, int j, double *g) {
    double f[6];
    memset(g, 0, 6 * sizeof *g);
    if (j == VDC_JOINTS - 1) return;
    memcpy(f, v->f_star[VDC_JOINTS - 1], sizeof f);
    for (int i = VDC_JOINTS - 2; i > j; i--) {
        force_xt(v->rot[i + 1], v->body_pos[i + 1], f, g);
        for (int k = 0; k < 6; k++) f[k] = v->f_star[i][k] + g[k];
    }
    force_xt(v->rot[j + 1], v->body_pos[j + 1], f, g);
}

/* Joint j's D: its body's F*_r plus what the bodies out to the tip need of it, projected on z. */
static double vdc_tau_r(const vdc_t *v, int j) {
    double g[6];
    vdc_outboard(v, j, g);
    return v->f_star[j][2] + g[2];
}

/* --- admitting, queueing and serving (Handler.admit, enqueue, serve) -------------------------- */

static void send_to(master_t *m, const uint8_t *p, size_t n, int64_t ip, int64_t port) {
    send_via(&m->route, (int)m->fd, p, n, ip, port, m->loss, &rng_state, &m->sent, &m->lost, &m->errors);
}

static void deny(master_t *m, const pending_t *q) {
    uint8_t p[DENIAL_SIZE];
    head(p, q->dest, q->pid, q->src, q->dst, DENIAL);
    put32(p + 15, (uint32_t)q->qid), put16(p + 19, DEADLINE_CANNOT_BE_MET);
    seal(p, sizeof p);
    m->denied++;
    send_to(m, p, sizeof p, q->ip, q->port);
}

static void enqueue(master_t *m, const pending_t *q) {
    int64_t i = m->n_pending++;
    while (i > 0 && m->pending[i - 1].deadline > q->deadline) m->pending[i] = m->pending[i - 1], i--;
    m->pending[i] = *q;
}

/* Answer every pending query, earliest deadline first: B or D, or a denial if its deadline can no
 * longer be met. */
static void serve(master_t *m) {
    for (int64_t k = 0; k < m->n_pending; k++) {
        const pending_t *q = &m->pending[k];
        int64_t t0 = host_now();
        if (t0 + m->service_ns > q->deadline) {
            deny(m, q);
            continue;
        }
        uint8_t p[VDC_BL_SIZE];
        size_t size = ANSWER_SIZE;
        head(p, q->dest, q->pid, q->src, q->dst, REPLY);
        put32(p + 15, (uint32_t)q->qid);
        if (m->vdc != NULL && q->is_a) { /* B: the forward recursion's 20 values (local: and G's 6) */
            const vdc_t *v = m->vdc;
            double values[26];
            memcpy(values, vdc_b(m->vdc, m, (int)q->joint, q->t), 20 * sizeof(double));
            if (q->local) vdc_outboard(v, (int)q->joint, values + 20);
            int n = q->local ? 26 : 20;
            put32(p + 19, (uint32_t)n);
            for (int k = 0; k < n; k++) {
                uint8_t *at = p + 23 + 16 * k;
                int64_t id = k < 20 ? v->b_ids[q->joint][k] : v->g_ids[q->joint][k - 20];
                put32(at, (uint32_t)id), putf(at + 4, values[k]), put64(at + 8, (uint64_t)q->t);
            }
            size = q->local ? VDC_BL_SIZE : VDC_B_SIZE;
        } else {
            double value = m->vdc != NULL ? vdc_tau_r(m->vdc, (int)q->joint)
                           : q->is_a     ? command(m, (int)q->joint, q->t)
                                         : torque(m, (int)q->joint, q->t);
            put32(p + 19, 1);
            put32(p + 23, (uint32_t)m->joints[q->joint].ids[q->is_a ? 2 : 4]), putf(p + 27, value);
            put64(p + 31, (uint64_t)q->t);
        }
        seal(p, size);
        send_to(m, p, size, q->ip, q->port);
        int64_t t1 = host_now();
        int64_t est = (int64_t)(0.9 * (double)m->service_ns + 0.1 * (double)(t1 - t0) * m->margin);
        m->service_ns = est > m->floor_ns ? est : m->floor_ns;
        if (t1 > q->deadline) m->late++; /* the estimate was too low */
        m->replies++;
    }
    m->n_pending = 0;
}

/* An included module's A or C (Master._cycle_query): 1 if it was one (taken), else 0. */
/* The A or C of the toy arm model (Master._cycle_query's checks): 1 if its items are joint j's */
static int toy_items(const master_t *m, const uint8_t *p, int j, int is_a) {
    const joint_t *jt = &m->joints[j];
    if (is_a)
        return get32(p + 27) == 2 && get32(p + 63) == 1 && get32(p + 31) == (uint32_t)jt->ids[0] &&
               get32(p + 47) == (uint32_t)jt->ids[1] && get32(p + 67) == (uint32_t)jt->ids[2];
    return get32(p + 27) == 1 && get32(p + 47) == 1 && get32(p + 31) == (uint32_t)jt->ids[3] &&
           get32(p + 51) == (uint32_t)jt->ids[4];
}

/* VDC's A (is_a 1; 2: a local [C, D]'s, with F*) or C (cell.modular.cycle.VdcMaster._cycle_query's
 * checks): 1 if its items are joint j's */
static int vdc_items(const master_t *m, const uint8_t *p, int j, int is_a) {
    const joint_t *jt = &m->joints[j];
    const vdc_t *v = m->vdc;
    if (j >= VDC_JOINTS) return 0;
    if (is_a == 2) {
        if (get32(p + 27) != 8 || get32(p + 159) != 26 || get32(p + 31) != (uint32_t)jt->ids[0] ||
            get32(p + 47) != (uint32_t)jt->ids[1] || get32(p + 163) != (uint32_t)v->b_ids[j][0] ||
            get32(p + 403) != (uint32_t)v->g_ids[j][0])
            return 0;
        for (int k = 0; k < 6; k++)
            if (get32(p + 63 + 16 * k) != (uint32_t)v->f_ids[j][k]) return 0;
        return 1;
    }
    if (is_a)
        return get32(p + 27) == 2 && get32(p + 63) == 20 && get32(p + 31) == (uint32_t)jt->ids[0] &&
               get32(p + 47) == (uint32_t)jt->ids[1] && get32(p + 67) == (uint32_t)v->b_ids[j][0];
    if (get32(p + 27) != 6 || get32(p + 127) != 1 || get32(p + 131) != (uint32_t)jt->ids[4]) return 0;
    for (int k = 0; k < 6; k++)
        if (get32(p + 31 + 16 * k) != (uint32_t)v->f_ids[j][k]) return 0;
    return 1;
}

static int fast_path(master_t *m, const uint8_t *p, ssize_t n, int64_t ip, int64_t port, int64_t at) {
    int64_t a_size = m->vdc != NULL ? VDC_A_SIZE : A_SIZE, c_size = m->vdc != NULL ? VDC_C_SIZE : C_SIZE;
    int local = m->vdc != NULL && n == VDC_AL_SIZE; /* a module computing its own [C, D] */
    if (n != a_size && n != c_size && !local) return 0;
    int j = 0;
    while (j < MAX_JOINTS && !(live(&m->joints[j]) && m->joints[j].ip == ip && m->joints[j].port == port)) j++;
    if (j == MAX_JOINTS) return 0;
    joint_t *jt = &m->joints[j];
    int is_a = n == a_size || local;
    /* QueryShape.parse: no return address, the query type, both CRCs, the counts; then its items */
    if (p[2] || p[13] || p[14] != QUERY || !crcs_ok(p, (size_t)n) || p[1] != PID_MRT) return 0;
    if (!(m->vdc != NULL ? vdc_items : toy_items)(m, p, j, is_a + local)) return 0;
    jt->heard_ns = at, jt->silent_cycles = 0; /* (Master.receive: heard from) */
    if (jt->state == NODE_SUSPECT) {
        jt->state = NODE_INCLUDED;
        event(m, at, EVENT_BACK, j);
    }
    pending_t q = {.deadline = (int64_t)get64(p + 19), .seq = m->seq++, .joint = j, .is_a = is_a,
                   .qid = get32(p + 15), .dest = p[0], .pid = p[1], .src = get32(p + 7), .dst = get32(p + 3),
                   .t = (int64_t)get64(p + (m->vdc != NULL ? 39 : is_a ? 71 : 55)), .ip = ip, .port = port,
                   .local = local};
    if (is_a) jt->a_cycle = floor_div(at - jt->phase_ns + m->period_ns / 4, m->period_ns);
    m->queries++;
    if (at + m->service_ns * (1 + m->n_pending) > q.deadline || m->n_pending == QUEUE) {
        deny(m, &q);
        return 1;
    }
    if (is_a)
        jt->pos = getf(p + 35), jt->at = (int64_t)get64(p + 39), jt->vel = getf(p + 51);
    else if (m->vdc == NULL)
        jt->force = getf(p + 35);
    else
        for (int k = 0; k < 6; k++) m->vdc->f_star[j][k] = getf(p + 35 + 16 * k);
    if (is_a && m->vdc != NULL) m->vdc->seq[j]++;
    for (int k = 0; k < 6 && local; k++) m->vdc->f_star[j][k] = getf(p + 67 + 16 * k);
    enqueue(m, &q);
    return 1;
}

/* --- FDIR (Master._fdir) ----------------------------------------------------------------------- */

/* Each live module's last cycle past its deadline: guessed if its A did not come, reported when
 * silent for suspect_cycles, excluded when silent for lost_ns.  The earliest time it has
 * something to do again. */
static int64_t fdir(master_t *m, int64_t now) {
    int64_t next = INT64_MAX;
    for (int j = 0; j < MAX_JOINTS; j++) {
        joint_t *jt = &m->joints[j];
        if (!live(jt)) continue;
        int64_t cycle = floor_div(now - m->budget_ns - jt->phase_ns, m->period_ns);
        if (cycle > jt->checked && jt->a_cycle >= 0 && jt->a_cycle < cycle) {
            m->guessed++;
            if (++jt->silent_cycles == m->suspect_cycles) {
                jt->state = NODE_SUSPECT;
                event(m, now, EVENT_SILENT, j);
            }
        }
        if (cycle > jt->checked) jt->checked = cycle;
        if (now - jt->heard_ns > m->lost_ns) {
            jt->state = NODE_LOST;
            event(m, now, EVENT_LOST, j);
            continue;
        }
        int64_t due = (jt->checked + 2) * m->period_ns + jt->phase_ns + m->budget_ns;
        int64_t silent = jt->heard_ns + m->lost_ns + 1;
        due = due < silent ? due : silent;
        next = due < next ? due : next;
    }
    return next;
}

/* --- the loop ------------------------------------------------------------------------------------ */

int snp_master_init(uint64_t seed) {
    crc_init();
    rng_state = seed ? seed : rng_state;
    return (int)sizeof(master_t);
}

/* Serve the cycle until host time `until` (CLOCK_MONOTONIC ns, the master's clock) or an FDIR
 * event (RUN_EVENT); a datagram this path does not take is copied to buf and described in *h
 * (RUN_HANDED), after the queries read before it are answered.  Sleeps until lead_ns before the
 * next period starts (or until what is due), then polls without sleeping spin_ns + lead_ns, and
 * spin_ns after each datagram: serve_master's schedule. */
int snp_master_run(master_t *m, int64_t until, int64_t mono_of_real, int64_t spin_ns, int64_t lead_ns,
                   uint8_t *buf, int64_t cap, handed_t *h) {
    struct pollfd pfd = {.fd = (int)m->fd, .events = POLLIN};
    int64_t spin_until = 0;
    uint8_t p[2048];
    uint8_t q[2048];
    spin_t spin;
    spin_init(&spin);
    int ret = RUN_UNTIL;
    int64_t ip, port, at;
    ssize_t got;
    for (;;) {
        /* what came in first, then FDIR: after a stall of this process (not the modules' silence)
         * FDIR would otherwise find every module silent and exclude them all */
        int any = 0;
        while ((got = receive((int)m->fd, p, sizeof p, mono_of_real, &ip, &port, &at)) >= 0) {
            any = 1;
            if (m->route.on) { /* a module is (0, its return address); the datagram as it came to Python */
                int64_t from;
                ssize_t len = route_in(&m->route, p, got, ip, port, q, &from);
                if (len < 0 || fast_path(m, q, len, 0, from, at)) continue;
            } else if (fast_path(m, p, got, ip, port, at)) {
                continue;
            }
            serve(m);
            spin_sleep(&spin);
            return hand(h, 0, p, got, at, ip, port, buf, cap);
        }
        serve(m);
        int64_t now = host_now();
        if (any) spin_until = now + spin_ns;
        int64_t wake = fdir(m, now);
        if (m->n_events) {
            ret = RUN_EVENT;
            break;
        }
        if (now >= until) break;
        int64_t start = (floor_div(now - m->phase_ns, m->period_ns) + 1) * m->period_ns + m->phase_ns;
        wake = wake < until ? wake : until;
        wake = wake < start - lead_ns ? wake : start - lead_ns;
        int64_t wait = 0; /* ns; 0: poll without sleeping */
        if (now >= spin_until && wake > now) wait = wake - now;
        if (wait) spin_sleep(&spin); else spin_poll(&spin);
        struct timespec ts = {wait / 1000000000, wait % 1000000000};
        int ready = ppoll(&pfd, 1, &ts, NULL);
        if (ready < 0 && errno != EINTR) {
            ret = -errno;
            break;
        }
        if (ready == 0 && wait) spin_until = host_now() + spin_ns + lead_ns; /* woken on time: spin through */
    }
    spin_sleep(&spin);
    return ret;
}
