/* The loop model's run (cell/controller/loop.py, LoopModel.run) in C: n status periods of the data
 * plane's P loop and the drive, for `rows` candidates of `dof` joints at once.  The same arithmetic,
 * window by window, as the numpy version (which stays the reference and the fallback): the command
 * answering a window's last status is kept and acts from the next period; between two changes the
 * drive's velocity ramps towards its goal at most a_max per period, and the trapezoid of the
 * velocities moves the position.  The controller fits every TP with about six runs a section: in C
 * a motion's TPs take well under a millisecond instead of tens. */
#include <math.h>
#include <stdint.h>

static double clip(double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* One joint, n status periods on from (*q, *v, *held): the state there, in place. */
static void run_one(double *q, double *v, double *held, int64_t tick, int64_t n, int64_t w, double c1,
                    double c2, double v_max, double a_dt, double p_trg, double v_trg, double status_s) {
    double qk = *q, vk = *v, hk = *held;
    double pull = c1 * v_trg + c2 * p_trg;
    double goal = clip(hk, -v_max, v_max);
    int64_t i = 0;
    while (i < n) {
        int64_t phase = (tick + i) % w;
        int kept = phase == w - 1;
        int64_t m;
        if (kept) {
            hk = (1.0 - c1) * vk + pull - c2 * qk;
            m = 1;
        } else {
            m = w - 1 - phase;
            if (n - i < m) m = n - i;
        }
        double gap = goal - vk, sum = 0.0, last = 0.0;
        for (int64_t s = 1; s <= m; s++) {
            double bound = (double)s * a_dt;
            last = clip(gap, -bound, bound);
            sum += last;
        }
        qk = qk + ((double)m * vk + sum - 0.5 * last) * status_s;
        vk = vk + last;
        if (kept) goal = clip(hk, -v_max, v_max);
        i += m;
    }
    *q = qk;
    *v = vk;
    *held = hk;
}

/* q, v, held: (rows, dof), in: the state; out: the state n periods on.  p_trg, v_trg: (rows, dof).
 * c1, c2, v_max, a_dt (a_max * status_s): (dof). */
void loop_run(int64_t rows, int64_t dof, double *q, double *v, double *held, int64_t tick, int64_t n,
              int64_t w, const double *c1, const double *c2, const double *v_max, const double *a_dt,
              const double *p_trg, const double *v_trg, double status_s) {
    for (int64_t r = 0; r < rows; r++)
        for (int64_t j = 0; j < dof; j++) {
            int64_t k = r * dof + j;
            run_one(&q[k], &v[k], &held[k], tick, n, w, c1[j], c2[j], v_max[j], a_dt[j], p_trg[k],
                    v_trg[k], status_s);
        }
}

#define MAX_DOF 64
#define MAX_CANDIDATES 256

/* LoopModel.fit in C, step for step (the numpy version is the reference): per section, a grid of
 * `candidates` v_trg from -span to span brackets where the modelled robot crosses the plan's
 * position, then regula falsi (Illinois) closes in, all joints together until every one is within
 * tol (or cannot move).  q_end: (sections, dof), ns: each section's status periods; q, v, held: the
 * start state, in place the end state; out: (sections, dof) the fitted v_trg; tq, tv, theld:
 * (sections + 1, dof) the states on the way.  Returns 0, or -1 for sizes past the static bounds. */
int loop_fit(int64_t sections, int64_t dof, const double *q_end, const int64_t *ns, double *q,
             double *v, double *held, int64_t tick, int64_t w, const double *c1, const double *c2,
             const double *v_max, const double *a_dt, double status_s, int64_t candidates,
             int64_t steps, double tol, double *out, double *tq, double *tv, double *theld,
             int64_t lead) {
    if (dof > MAX_DOF || candidates > MAX_CANDIDATES || candidates < 2) return -1;
    double lo[MAX_DOF], hi[MAX_DOF], f_lo[MAX_DOF], f_hi[MAX_DOF], side[MAX_DOF], rise[MAX_DOF];
    double guess[MAX_DOF], sq[MAX_DOF], sv[MAX_DOF], sh[MAX_DOF], sf[MAX_DOF], qe[MAX_CANDIDATES];
    for (int64_t j = 0; j < dof; j++) {
        tq[j] = q[j];
        tv[j] = v[j];
        theld[j] = held[j];
    }
    for (int64_t k = 0; k < sections; k++) {
        /* (led TPs: the robot is on the target `lead` periods after the section's end, where the
         * command of its last window has acted; the state goes on from the section's end) */
        int64_t n = ns[k] + lead;
        const double *target = &q_end[k * dof];
        for (int64_t j = 0; j < dof; j++) {
            double span = 4.0 * v_max[j] + 1.0, start = -span;
            double step = (span - start) / (double)(candidates - 1);
            int64_t below = 0;
            for (int64_t c = 0; c < candidates; c++) {
                double cand = c == candidates - 1 ? span : (double)c * step + start;
                double a = q[j], b = v[j], h = held[j];
                run_one(&a, &b, &h, tick, n, w, c1[j], c2[j], v_max[j], a_dt[j], target[j], cand, status_s);
                qe[c] = a;
                below += a < target[j];
            }
            int64_t i = below < 1 ? 1 : (below > candidates - 1 ? candidates - 1 : below);
            lo[j] = i - 1 == candidates - 1 ? span : (double)(i - 1) * step + start;
            hi[j] = i == candidates - 1 ? span : (double)i * step + start;
            f_lo[j] = qe[i - 1] - target[j];
            f_hi[j] = qe[i] - target[j];
            side[j] = 0.0;
        }
        for (int64_t it = 0; it < steps; it++) {
            int done = 1;
            for (int64_t j = 0; j < dof; j++) {
                rise[j] = f_hi[j] - f_lo[j];
                double frac = rise[j] > 0 ? -f_lo[j] / rise[j] : 0.5;
                guess[j] = lo[j] + clip(frac, 0.0, 1.0) * (hi[j] - lo[j]);
                sq[j] = q[j];
                sv[j] = v[j];
                sh[j] = held[j];
                run_one(&sq[j], &sv[j], &sh[j], tick, n, w, c1[j], c2[j], v_max[j], a_dt[j], target[j],
                        guess[j], status_s);
                sf[j] = sq[j] - target[j];
                if (!(fabs(sf[j]) <= tol || rise[j] <= 0)) done = 0;
            }
            if (done) break;
            for (int64_t j = 0; j < dof; j++) {
                double f = sf[j];
                int low = f < 0;
                if (low) {
                    lo[j] = guess[j];
                    f_lo[j] = f;
                } else {
                    hi[j] = guess[j];
                    f_hi[j] = f;
                }
                if (low && side[j] < 0) f_hi[j] = 0.5 * f_hi[j];
                if (!low && side[j] > 0) f_lo[j] = 0.5 * f_lo[j];
                side[j] = low ? -1.0 : 1.0;
            }
        }
        for (int64_t j = 0; j < dof; j++) {
            out[k * dof + j] = guess[j];
            if (lead > 0) {
                sq[j] = q[j];
                sv[j] = v[j];
                sh[j] = held[j];
                run_one(&sq[j], &sv[j], &sh[j], tick, ns[k], w, c1[j], c2[j], v_max[j], a_dt[j],
                        target[j], guess[j], status_s);
            }
            q[j] = sq[j];
            v[j] = sv[j];
            held[j] = sh[j];
            tq[(k + 1) * dof + j] = q[j];
            tv[(k + 1) * dof + j] = v[j];
            theld[(k + 1) * dof + j] = held[j];
        }
        tick += ns[k];
    }
    return 0;
}

/* The modelled robot at every status period of a motion's TPs: q, v, held (dof), the start state,
 * in place the end state; ns, p_trg, v_trg: each section's periods and TP; out: (sum ns, dof), the
 * positions after each period. */
void loop_path(int64_t sections, int64_t dof, const int64_t *ns, const double *p_trg,
               const double *v_trg, double *q, double *v, double *held, int64_t tick, int64_t w,
               const double *c1, const double *c2, const double *v_max, const double *a_dt,
               double status_s, double *out) {
    int64_t row = 0;
    for (int64_t k = 0; k < sections; k++) {
        for (int64_t i = 0; i < ns[k]; i++, row++, tick++)
            for (int64_t j = 0; j < dof; j++) {
                run_one(&q[j], &v[j], &held[j], tick, 1, w, c1[j], c2[j], v_max[j], a_dt[j],
                        p_trg[k * dof + j], v_trg[k * dof + j], status_s);
                out[row * dof + j] = q[j];
            }
    }
}
