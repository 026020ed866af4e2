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
    /* the cycle (Python seeds pos, vel, next_start, qid when it sets active) */
    double pos, vel, v_des, torque;
    int64_t next_start, scheduled, start, deadline, qid, stage, missed_now;
    /* counted since Python last took them */
    int64_t missed_ab, missed_cd, overruns, sent, lost, errors, late, n_records;
    int64_t records[RECORDS][4]; /* scheduled, T1, end (master ns), exchanges guessed */
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
    send_lossy((int)m->fd, p, n, m->master_ip, m->master_port, m->loss, &rng_state, &m->sent, &m->lost, &m->errors);
}

/* --- the cycle (JointModule._start, _second, _answered, _expired, _finish) -------------------- */

/* A (2 inputs, 1 wanted) or C (1 input, 1 wanted): QueryShape.pack with no return address. */
static void query(module_t *m, int n_in, const int64_t *ids_in, const double *values, int64_t stamp,
                  int64_t wanted, int64_t wanted_at) {
    uint8_t p[A_SIZE];
    size_t size = n_in == 2 ? A_SIZE : C_SIZE;
    m->qid = (m->qid + 1) & 0xFFFFFFFF;
    head(p, 0, PID_MRT, m->source_process, 0, QUERY);
    put32(p + 15, (uint32_t)m->qid), put64(p + 19, (uint64_t)m->deadline), put32(p + 27, (uint32_t)n_in);
    uint8_t *q = p + 31;
    for (int i = 0; i < n_in; i++, q += 16)
        put32(q, (uint32_t)ids_in[i]), putf(q + 4, values[i]), put64(q + 8, (uint64_t)stamp);
    put32(q, 1), put32(q + 4, (uint32_t)wanted), put64(q + 8, (uint64_t)wanted_at);
    seal(p, size);
    send_master(m, p, size);
}

static void start(module_t *m, int64_t scheduled, int64_t now) {
    m->scheduled = scheduled, m->start = now, m->stage = STAGE_AB, m->missed_now = 0;
    m->deadline = scheduled + m->budget_ns / 2;
    int64_t ids[2] = {m->ids[0], m->ids[1]};
    double values[2] = {m->pos, m->vel};
    query(m, 2, ids, values, now, m->ids[2], now + m->period_ns);
}

static void second(module_t *m) { /* [C, D]: the desired force from the velocity error */
    double force = 5.0 * (m->v_des - m->vel);
    m->deadline = m->scheduled + m->budget_ns;
    m->stage = STAGE_CD;
    query(m, 1, &m->ids[3], &force, m->start, m->ids[4], m->start + m->period_ns);
}

static void finish(module_t *m, int64_t now) {
    m->stage = STAGE_DONE;
    int64_t *r = m->records[m->n_records < RECORDS ? m->n_records++ : RECORDS - 1];
    r[0] = m->scheduled, r[1] = m->start, r[2] = now, r[3] = m->missed_now;
    m->vel += (m->v_des - m->vel) * 0.5; /* the joint: a fast drive after the desired velocity */
    m->pos += m->vel * (double)m->period_ns / 1e9;
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
        second(m);
    } else {
        if (have) m->torque = value;
        finish(m, now);
    }
}

static void expired(module_t *m, int64_t now) { /* no answer by the deadline: guess, go on */
    miss(m);
    if (m->stage == STAGE_AB)
        second(m);
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
    if (n != ANSWER_SIZE && n != DENIAL_SIZE) return 0;
    if (p[1] != PID_MRT || p[2] != 0 || p[12] != 0 || p[13] != 0) return 0;
    if (!crcs_ok(p, (size_t)n)) return 0;
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
    uint8_t p[2048];
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
        if (!busy && now >= spin_until && wake - lead_ns > now) wait = wake - lead_ns - now;
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
                if (m->active && fast_path(m, p, got, at)) continue;
                spin_sleep(&spin);
                return hand(h, i, p, got, at, ip, port, buf, cap);
            }
        }
    }
    spin_sleep(&spin);
    return ret;
}
