/* The joint modules' 1 kHz cycle in C: the hot path of cell.snp.modular.JointModule.
 *
 * cell/snp/native.py builds this with the system's C compiler and runs, for all the modules of
 * one process, their [A, B] and [C, D] exchanges (time-bounded queries, transport "snp") on
 * their own UDP sockets: cycle starts on the master's time grid through each module's servoed
 * clock, the A and C queries packed as cell.snp.packet.QueryShape packs them, B, D and denials
 * parsed as ReplyShape and the full decoder would, deadlines passed guessed.  Any other
 * datagram (configuration, SnP-TSP, node info, a packet this fast path does not know) goes back
 * to Python, which runs the rest of the module; so does the call every `until`.
 *
 * Why C: in Python a module's cycle costs 25-35 us and each answer 40-45 us on this machine
 * kind, so six modules need most of a core per 1 ms period; here the syscalls are the cost.
 * The arithmetic mirrors JointModule's, line for line (tests/snp/test_snp_native.py checks the
 * bytes against the Python module's). */

#include "wire.h"

#define RECORDS 256 /* cycle records a module holds until Python takes them */
#define MAX_MODULES 64

enum { STAGE_DONE = 0, STAGE_AB = 1, STAGE_CD = 2 };

/* The modular arm in MuJoCo (cell.modular.cycle.Plant), stepped here in real time: the arrays are
 * the Python Plant's (numpy) and MuJoCo's own, mj_step MuJoCo's; cell/snp/native.py's PlantState
 * mirrors it. */
typedef void (*mj_step_t)(const void *model, void *data);
typedef struct {
    int64_t dof, dt_ns, period_ns, cap;
    const void *model;
    void *data;
    mj_step_t step;
    double *qpos, *qvel, *ctrl;     /* mjData's */
    const double *tool;             /* the tool site's position in mjData */
    int64_t *clock;                 /* t (host ns the arm is at), the next record's time, records made */
    double *tau, *hold, *limit;     /* per joint: the torque set, where its brake holds it, its limit */
    int64_t *driven;                /* per joint: 1 if its module sets its torque (else: its brake) */
    int64_t *rec_t;                 /* records: host ns, */
    double *rec_tool;               /* and the tool's position */
    double kp, kd;                  /* the brake */
} plant_t;

/* A module's VDC (cell.modular.cycle.VdcModule, cell.modular.vdc.Module); native.py's VdcModuleState. */
typedef struct {
    int64_t joint, b_ids[20], f_ids[6];
    double inertia[36], k[6];       /* its body's spatial inertia; velocity feedback gains */
    double joint_gain, armature, damping, torque_max;
    double b[20], tau_r, qd;        /* its last B (qd_r, qdd_r, V_r, dV_r, V), last tau_r, qd at T1 */
    int64_t have_b, fresh;
    int64_t safe_after, missed_run, braked; /* VdcModule._drive's fail safe */
    int64_t local, g_ids[6];        /* local: it computes its own [C, D] (VdcModule.local) from */
    double g[6], f_star[6];         /* the last G it took; its last F*_r, sent with its next A */
    double adapt, theta[10], bound[10], mass0; /* the inertial parameters' adaptation (vdc.Module) */
    /* neighbour: G from its outboard neighbour, its own force passed to its inboard one at nb (its
     * G ids: g_in_ids), carried by its body's ^iX_{i-1}(q) (body_rot, body_pos; q at T1) */
    int64_t neighbour, tip, nb_ip, nb_port, g_in_ids[6];
    double body_pos[3], body_rot[9], q;
    /* neighbour: a G of this cycle come before B (its neighbour ahead of it), kept until it waits:
     * its cycle's number + 1 (0: none), its values */
    int64_t g_early_at;
    double g_early[6];
    plant_t *plant;
} vdc_module_t;

/* One module; cell/snp/native.py's ModuleState mirrors it field for field (all 64-bit). */
typedef struct {
    /* set by Python */
    int64_t fd, active, source_process, master_ip, master_port; /* ip, port: host order */
    int64_t ids[5]; /* item ids: position, velocity, commanded velocity, force, torque */
    int64_t period_ns, phase_ns, budget_ns;
    int64_t osc_origin, osc_offset; /* the module's oscillator: host -> raw */
    double osc_drift;
    int64_t servo_anchor, servo_base; /* its servo: raw -> master */
    double servo_rate;
    double loss; /* the share of sent datagrams the link drops */
    vdc_module_t *vdc; /* NULL: the toy joint's A and C; else VDC's on the plant */
    /* the cycle (Python seeds pos, vel, next_start, qid when it sets active) */
    double pos, vel, v_des, torque;
    int64_t next_start, scheduled, start, deadline, qid, stage, missed_now;
    /* counted since Python last took them */
    int64_t missed_ab, missed_cd, overruns, sent, lost, errors, late, n_records;
    int64_t records[RECORDS][4]; /* scheduled, T1, end (master ns), exchanges guessed */
    route_t route; /* over the two routers (route.on), its link's state */
} module_t;

/* --- clocks: host CLOCK_MONOTONIC -> the module's raw oscillator -> the master's time --------- */

static int64_t master_of(const module_t *m, int64_t host) {
    int64_t raw = m->osc_origin + m->osc_offset + llround((double)(host - m->osc_origin) * (1.0 + m->osc_drift));
    return m->servo_base + llround((double)(raw - m->servo_anchor) * (1.0 + m->servo_rate));
}

static int64_t host_of(const module_t *m, int64_t master) {
    int64_t raw = m->servo_anchor + llround((double)(master - m->servo_base) / (1.0 + m->servo_rate));
    return m->osc_origin + llround((double)(raw - m->osc_origin - m->osc_offset) / (1.0 + m->osc_drift));
}

static uint64_t rng_state = 0x9E3779B97F4A7C15ull; /* the links' losses */

static void send_master(module_t *m, const uint8_t *p, size_t n) {
    send_via(&m->route, (int)m->fd, p, n, m->master_ip, m->master_port, m->loss, &rng_state, &m->sent, &m->lost,
             &m->errors);
}

/* --- the cycle (JointModule._start, _second, _answered, _expired, _finish) -------------------- */

/* A or C: QueryShape.pack with no return address; n_out wanted items, all stamped wanted_at. */
static void query(module_t *m, int n_in, const int64_t *ids_in, const double *values, int64_t stamp,
                  int n_out, const int64_t *wanted, int64_t wanted_at) {
    uint8_t p[VDC_AL_SIZE];
    size_t size = 31 + 16 * (size_t)n_in + 4 + 12 * (size_t)n_out + 1;
    m->qid = (m->qid + 1) & 0xFFFFFFFF;
    head(p, 0, PID_MRT, m->source_process, 0, QUERY);
    put32(p + 15, (uint32_t)m->qid), put64(p + 19, (uint64_t)m->deadline), put32(p + 27, (uint32_t)n_in);
    uint8_t *q = p + 31;
    for (int i = 0; i < n_in; i++, q += 16)
        put32(q, (uint32_t)ids_in[i]), putf(q + 4, values[i]), put64(q + 8, (uint64_t)stamp);
    put32(q, (uint32_t)n_out), q += 4;
    for (int i = 0; i < n_out; i++, q += 12) put32(q, (uint32_t)wanted[i]), put64(q + 4, (uint64_t)wanted_at);
    seal(p, size);
    send_master(m, p, size);
}

/* --- the plant and VDC's module (Plant.advance, VdcModule, vdc.Module.net_force and torque) ---- */

/* Step the arm up to host time now (Plant.advance); exported for the tests' twin of Python's. */
void snp_plant_advance(plant_t *pl, int64_t now) {
    while (pl->clock[0] + pl->dt_ns <= now) {
        for (int j = 0; j < pl->dof; j++) {
            double tau = pl->tau[j];
            if (!pl->driven[j]) {
                tau = pl->kp * (pl->hold[j] - pl->qpos[j]) - pl->kd * pl->qvel[j];
                tau = tau > pl->limit[j] ? pl->limit[j] : (tau < -pl->limit[j] ? -pl->limit[j] : tau);
            }
            pl->ctrl[j] = tau;
        }
        pl->step(pl->model, pl->data);
        pl->clock[0] += pl->dt_ns;
        if (pl->clock[0] >= pl->clock[1]) {
            int64_t n = pl->clock[2], i = n % pl->cap; /* (a ring: the last cap records) */
            pl->rec_t[i] = pl->clock[0];
            memcpy(pl->rec_tool + 3 * i, pl->tool, 3 * sizeof(double));
            pl->clock[2] = n + 1;
            pl->clock[1] += pl->period_ns;
        }
    }
}

static void inertia_times(const double *in, const double *v, double *out) {
    for (int i = 0; i < 6; i++) {
        out[i] = 0;
        for (int k = 0; k < 6; k++) out[i] += in[6 * i + k] * v[k];
    }
}

/* I dV_r + V x* I V_r, V x* f = [w x n + v x f; w x f]: a body's dynamics of inertia I */
static void dynamics(const double *inertia, const double *b, double *f) {
    const double *vr = b + 2, *ar = b + 8, *vv = b + 14;
    double ia[6], iv[6], c1[3], c2[3], c3[3];
    inertia_times(inertia, ar, ia);
    inertia_times(inertia, vr, iv);
    cross(vv, iv, c1);
    cross(vv + 3, iv + 3, c2);
    cross(vv, iv + 3, c3);
    for (int k = 0; k < 3; k++) f[k] = ia[k] + c1[k] + c2[k], f[3 + k] = ia[3 + k] + c3[k];
}

/* The 6x6 spatial inertia of ten inertial parameters (vdc.inertia_of): [m, m c, xx yy zz xy xz yz] */
static void inertia_of(const double *th, double *out) {
    const double rot[9] = {th[4], th[7], th[8], th[7], th[5], th[9], th[8], th[9], th[6]};
    const double *mc = th + 1;
    const double sk[9] = {0, -mc[2], mc[1], mc[2], 0, -mc[0], -mc[1], mc[0], 0}; /* skew(mc) */
    memset(out, 0, 36 * sizeof *out);
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) {
            out[6 * r + c] = rot[3 * r + c];
            out[6 * r + 3 + c] = sk[3 * r + c];
            out[6 * (3 + r) + c] = sk[3 * c + r];
        }
    for (int k = 3; k < 6; k++) out[7 * k] = th[0];
}

/* F*_r = I dV_r + V x* I V_r + K (V_r - V); with adaptation, I from theta, then theta moved on by
 * dt of theta' = adapt Y^T (V_r - V) within its bounds (vdc.Module.net_force).  Exported for the
 * tests' twin of Python's. */
void snp_vdc_net_force(vdc_module_t *v, double dt, double *f) {
    const double *vr = v->b + 2, *vv = v->b + 14;
    double inertia[36], e[6];
    if (v->adapt > 0) inertia_of(v->theta, inertia);
    dynamics(v->adapt > 0 ? inertia : v->inertia, v->b, f);
    for (int k = 0; k < 6; k++) e[k] = vr[k] - vv[k], f[k] += v->k[k] * e[k];
    if (!(v->adapt > 0 && dt > 0)) return;
    double step[10];
    for (int p = 0; p < 10; p++) { /* Y's column p: the dynamics of the unit parameter p */
        double unit[10] = {0}, y[6];
        unit[p] = 1.0;
        inertia_of(unit, inertia);
        dynamics(inertia, v->b, y);
        step[p] = 0;
        for (int k = 0; k < 6; k++) step[p] += y[k] * e[k];
    }
    for (int p = 0; p < 10; p++) {
        double t = v->theta[p] + v->adapt * dt * step[p];
        v->theta[p] = t > v->bound[p] ? v->bound[p] : (t < -v->bound[p] ? -v->bound[p] : t);
    }
    if (v->theta[0] < 0.25 * v->mass0) v->theta[0] = 0.25 * v->mass0;
}

static double motor_torque(const vdc_module_t *v) {
    double tau = v->tau_r + v->armature * v->b[1] + v->damping * v->b[0] + v->joint_gain * (v->b[0] - v->qd);
    return tau > v->torque_max ? v->torque_max : (tau < -v->torque_max ? -v->torque_max : tau);
}

static void start(module_t *m, int64_t scheduled, int64_t now) {
    m->scheduled = scheduled, m->start = now, m->stage = STAGE_AB, m->missed_now = 0;
    m->deadline = scheduled + m->budget_ns / 2;
    vdc_module_t *v = m->vdc;
    if (v != NULL) { /* A: its joint on the plant now (local: and its last F*; B and G wanted) */
        snp_plant_advance(v->plant, host_now());
        double values[8] = {v->plant->qpos[v->joint], v->plant->qvel[v->joint]};
        v->q = values[0], v->qd = values[1], v->fresh = 0;
        if (!v->local) {
            query(m, 2, m->ids, values, now, 20, v->b_ids, now);
            return;
        }
        int64_t ids[8] = {m->ids[0], m->ids[1]}, wanted[26];
        for (int k = 0; k < 6; k++) ids[2 + k] = v->f_ids[k], values[2 + k] = v->f_star[k];
        memcpy(wanted, v->b_ids, sizeof v->b_ids), memcpy(wanted + 20, v->g_ids, sizeof v->g_ids);
        m->deadline = scheduled + m->budget_ns; /* (its one exchange) */
        query(m, 8, ids, values, now, 26, wanted, now);
        return;
    }
    int64_t ids[2] = {m->ids[0], m->ids[1]};
    double values[2] = {m->pos, m->vel};
    query(m, 2, ids, values, now, 1, &m->ids[2], now + m->period_ns);
}

static int64_t cycle_no(const module_t *m) { return (m->scheduled / m->period_ns) & 0xFFFFFFFF; }

/* neighbour (VdcModule._pass_in): D from F*_r and G, and its force carried into its inboard
 * neighbour's frame, sent there (none from the base's) */
static void pass_in(module_t *m) {
    vdc_module_t *v = m->vdc;
    double f[6], r[9], out[6];
    for (int k = 0; k < 6; k++) f[k] = v->f_star[k] + v->g[k];
    v->tau_r = f[2];
    if (v->joint == 0 || !v->nb_port) return;
    turned(v->body_rot, v->q, r);
    force_xt(r, v->body_pos, f, out);
    uint8_t p[VDC_G_SIZE];
    head(p, 0, PID_MRT, m->source_process, 0, REPLY);
    put32(p + 15, (uint32_t)cycle_no(m)), put32(p + 19, 6);
    for (int k = 0; k < 6; k++) {
        uint8_t *at = p + 23 + 16 * k;
        put32(at, (uint32_t)v->g_in_ids[k]), putf(at + 4, out[k]), put64(at + 8, (uint64_t)(cycle_no(m) * m->period_ns));
    }
    seal(p, sizeof p);
    send_via(&m->route, (int)m->fd, p, sizeof p, v->nb_ip, v->nb_port, m->loss, &rng_state, &m->sent, &m->lost,
             &m->errors);
}

static void finish(module_t *m, int64_t now) {
    m->stage = STAGE_DONE;
    int64_t *r = m->records[m->n_records < RECORDS ? m->n_records++ : RECORDS - 1];
    r[0] = m->scheduled, r[1] = m->start, r[2] = now, r[3] = m->missed_now;
    vdc_module_t *v = m->vdc;
    if (v != NULL) { /* its motor: the chain's share and its own; on its brake after guesses in a row */
        plant_t *pl = v->plant;
        if (v->neighbour && v->have_b) pass_in(m);
        v->missed_run = m->missed_now ? v->missed_run + 1 : 0;
        if (v->missed_run >= v->safe_after) {
            if (pl->driven[v->joint]) {
                snp_plant_advance(pl, host_now());
                pl->driven[v->joint] = 0, pl->hold[v->joint] = pl->qpos[v->joint];
                v->braked++;
            }
        } else if (v->have_b) {
            snp_plant_advance(pl, host_now());
            pl->tau[v->joint] = motor_torque(v), pl->driven[v->joint] = 1;
        }
        return;
    }
    m->vel += (m->v_des - m->vel) * 0.5; /* the joint: a fast drive after the desired velocity */
    m->pos += m->vel * (double)m->period_ns / 1e9;
}

static void second(module_t *m, int64_t now) { /* [C, D] */
    m->deadline = m->scheduled + m->budget_ns;
    vdc_module_t *v = m->vdc;
    if (v == NULL) { /* the desired force from the velocity error */
        double force = 5.0 * (m->v_des - m->vel);
        m->stage = STAGE_CD;
        query(m, 1, &m->ids[3], &force, m->start, 1, &m->ids[4], m->start + m->period_ns);
        return;
    }
    if (!v->have_b) { /* none yet: its joint stays on the brake */
        finish(m, now);
        return;
    }
    if (!v->fresh) { /* this cycle's B did not come: its last, carried on */
        double dt = (double)m->period_ns / 1e9;
        v->b[0] += v->b[1] * dt;
        for (int k = 0; k < 6; k++) v->b[2 + k] += v->b[8 + k] * dt;
    }
    double f[6]; /* (the inertial parameters adapt on a B that came only: a guessed one's V_r runs on
                  * while its V stands, and a stall's error is no measure of them) */
    snp_vdc_net_force(v, v->fresh ? (double)m->period_ns / 1e9 : 0.0, f);
    if (v->neighbour && !v->tip) { /* G of this cycle from its outboard neighbour: wait for it */
        memcpy(v->f_star, f, sizeof f);
        m->stage = STAGE_CD, m->qid = cycle_no(m);
        if (v->g_early_at == m->qid + 1) { /* it came already */
            memcpy(v->g, v->g_early, sizeof v->g);
            v->g_early_at = 0;
            finish(m, now);
        }
        return;
    }
    if (v->local) { /* D here: F*_r and G on its axis; the cycle ends */
        memcpy(v->f_star, f, sizeof f);
        v->tau_r = f[2] + v->g[2];
        finish(m, now);
        return;
    }
    m->stage = STAGE_CD;
    query(m, 6, v->f_ids, f, m->start, 1, &m->ids[4], m->start);
}

static void miss(module_t *m) {
    if (m->stage == STAGE_AB)
        m->missed_ab++;
    else
        m->missed_cd++;
    m->missed_now++;
}

static void answered(module_t *m, int have, double value, int64_t now) { /* have 0: denied */
    if (!have)
        miss(m);
    if (m->stage == STAGE_AB) {
        if (have) m->v_des = value;
        second(m, now);
    } else {
        if (have) m->torque = value;
        if (have && m->vdc != NULL) m->vdc->tau_r = value;
        finish(m, now);
    }
}

static void expired(module_t *m, int64_t now) { /* no answer by the deadline: guess, go on */
    miss(m);
    if (m->stage == STAGE_AB)
        second(m, now);
    else
        finish(m, now);
}

static void schedule(module_t *m, int64_t after) { /* the first grid point at or after `after` */
    int64_t d = after - m->phase_ns;
    int64_t k = d >= 0 ? (d + m->period_ns - 1) / m->period_ns : -((-d) / m->period_ns);
    m->next_start = k * m->period_ns + m->phase_ns;
}

static void timers(module_t *m, int64_t host) { /* JointModule.poll */
    int64_t now = master_of(m, host);
    if (m->stage != STAGE_DONE && now >= m->deadline) expired(m, now);
    if (now >= m->next_start) {
        if (m->stage != STAGE_DONE) {
            m->overruns++;
            finish(m, now);
        }
        start(m, m->next_start, now);
        schedule(m, now + 1);
    }
}

/* B or D (a reply of one item) or a denial of the query in flight: 1 if it was, else 0. */
static int fast_path(module_t *m, const uint8_t *p, ssize_t n, int64_t host) {
    vdc_module_t *v = m->vdc;
    if (v != NULL && v->neighbour && n == VDC_G_SIZE) { /* its outboard neighbour's G */
        if (p[1] != PID_MRT || p[2] || p[12] || p[13] || p[14] != REPLY || !crcs_ok(p, (size_t)n)) return 0;
        if (get32(p + 19) != 6 || get32(p + 23) != (uint32_t)v->g_ids[0]) return 0;
        uint32_t cycle = get32(p + 15);
        if (m->stage == STAGE_AB && cycle == (uint32_t)cycle_no(m)) { /* before B: kept until it waits */
            for (int k = 0; k < 6; k++) v->g_early[k] = getf(p + 27 + 16 * k);
            v->g_early_at = (int64_t)cycle + 1;
            return 1;
        }
        if (m->stage != STAGE_CD || cycle != (uint32_t)m->qid) {
            m->late++;
            return 1;
        }
        for (int k = 0; k < 6; k++) v->g[k] = getf(p + 27 + 16 * k);
        finish(m, master_of(m, host));
        return 1;
    }
    int b = v != NULL && n == (v->local ? VDC_BL_SIZE : VDC_B_SIZE);
    if (n != ANSWER_SIZE && n != DENIAL_SIZE && !b) return 0;
    if (p[1] != PID_MRT || p[2] != 0 || p[12] != 0 || p[13] != 0) return 0;
    if (!crcs_ok(p, (size_t)n)) return 0;
    if (b) { /* VDC's B (and G, local): its 20 (26) values, if it answers the [A, B] in flight */
        uint32_t items = v->local ? 26 : 20;
        if (p[14] != REPLY || get32(p + 19) != items || get32(p + 23) != (uint32_t)v->b_ids[0]) return 0;
        if (v->local && get32(p + 23 + 16 * 20) != (uint32_t)v->g_ids[0]) return 0;
        if (m->stage != STAGE_AB || get32(p + 15) != (uint32_t)m->qid) {
            m->late++;
            return 1;
        }
        for (int k = 0; k < 20; k++) v->b[k] = getf(p + 27 + 16 * k);
        for (int k = 0; k < 6 && v->local; k++) v->g[k] = getf(p + 27 + 16 * (20 + k));
        v->have_b = v->fresh = 1;
        answered(m, 1, 0.0, master_of(m, host));
        return 1;
    }
    int answer = n == ANSWER_SIZE && p[14] == REPLY && get32(p + 19) == 1;
    if (!answer && !(n == DENIAL_SIZE && p[14] == DENIAL)) return 0;
    if (m->stage == STAGE_DONE || get32(p + 15) != (uint32_t)m->qid) {
        m->late++; /* an answer to a query already guessed */
        return 1;
    }
    answered(m, answer, answer ? (double)getf(p + 27) : 0.0, master_of(m, host));
    return 1;
}

/* --- the loop -------------------------------------------------------------------------------- */

int snp_cycle_init(uint64_t seed) {
    crc_init();
    rng_state = seed ? seed : rng_state;
    return (int)sizeof(module_t);
}

/* Run the modules' cycles until host time `until` (CLOCK_MONOTONIC ns); a datagram that is not
 * a cycle's answer is copied to buf and described in *h (RUN_HANDED), the others left queued.
 * Polls without sleeping while a cycle is in flight and spin_ns after the last datagram, wakes
 * lead_ns before what is due next.  mono_of_real: CLOCK_REALTIME - CLOCK_MONOTONIC, for the
 * kernel's receive stamps (SO_TIMESTAMPNS on the sockets). */
int snp_cycle_run(module_t **mods, int n, int64_t until, int64_t mono_of_real, int64_t spin_ns,
                  int64_t lead_ns, uint8_t *buf, int64_t cap, handed_t *h) {
    struct pollfd fds[MAX_MODULES];
    if (n > MAX_MODULES) return -E2BIG;
    for (int i = 0; i < n; i++) fds[i].fd = (int)mods[i]->fd, fds[i].events = POLLIN;
    int64_t spin_until = 0;
    uint8_t p[2048], q[2048];
    spin_t spin;
    spin_init(&spin);
    int ret = RUN_UNTIL;
    for (;;) {
        int64_t now = host_now(), wake = until;
        int busy = 0, full = 0;
        for (int i = 0; i < n; i++) {
            module_t *m = mods[i];
            if (!m->active) continue;
            timers(m, now);
            full |= m->n_records >= RECORDS - 4; /* (a pass finishes at most two cycles a module) */
            busy |= m->stage != STAGE_DONE;
            int64_t w = host_of(m, m->stage != STAGE_DONE && m->deadline < m->next_start ? m->deadline : m->next_start);
            if (w < wake) wake = w;
        }
        if (full) {
            ret = RUN_RECORDS_FULL;
            break;
        }
        if (now >= until) break;
        int64_t wait = 0; /* ns; 0: poll without sleeping */
        /* (spin_ns 0: never poll without sleeping, not even with a cycle in flight: a process that
         * shares its core with the master would keep it from answering) */
        if ((!busy || spin_ns == 0) && now >= spin_until && wake - lead_ns > now) wait = wake - lead_ns - now;
        if (wait) spin_sleep(&spin); else spin_poll(&spin);
        struct timespec ts = {wait / 1000000000, wait % 1000000000};
        int ready = ppoll(fds, (nfds_t)n, &ts, NULL);
        if (ready < 0 && errno != EINTR) {
            ret = -errno;
            break;
        }
        if (ready <= 0) continue;
        for (int i = 0; i < n; i++) {
            if (!(fds[i].revents & (POLLIN | POLLERR))) continue;
            module_t *m = mods[i];
            int64_t ip, port, at;
            ssize_t got;
            while ((got = receive((int)m->fd, p, sizeof p, mono_of_real, &ip, &port, &at)) >= 0) {
                spin_until = host_now() + spin_ns;
                const uint8_t *d = p;
                ssize_t len = got;
                if (m->route.on) { /* (its return address out; the datagram as it came to Python) */
                    int64_t from;
                    if ((len = route_in(&m->route, p, got, ip, port, q, &from)) < 0) continue;
                    d = q;
                }
                if (m->active && fast_path(m, d, len, at)) continue;
                spin_sleep(&spin);
                return hand(h, i, p, got, at, ip, port, buf, cap);
            }
        }
    }
    spin_sleep(&spin);
    return ret;
}
