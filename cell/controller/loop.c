/* The loop model's run (cell/controller/loop.py, LoopModel.run) in C: n status periods of the data
 * plane's P loop and the drive, for `rows` candidates of `dof` joints at once.  The same arithmetic,
 * window by window, as the numpy version (which stays the reference and the fallback): the command
 * answering a window's last status is kept and acts from the next period; between two changes the
 * drive's velocity ramps towards its goal at most a_max per period, and the trapezoid of the
 * velocities moves the position.  The controller fits every TP with about six runs a section: in C
 * a motion's TPs take well under a millisecond instead of tens. */
#include <stdint.h>

static double clip(double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* q, v, held: (rows, dof), in: the state; out: the state n periods on.  p_trg, v_trg: (rows, dof).
 * c1, c2, v_max, a_dt (a_max * status_s): (dof). */
void loop_run(int64_t rows, int64_t dof, double *q, double *v, double *held, int64_t tick, int64_t n,
              int64_t w, const double *c1, const double *c2, const double *v_max, const double *a_dt,
              const double *p_trg, const double *v_trg, double status_s) {
    for (int64_t r = 0; r < rows; r++) {
        for (int64_t j = 0; j < dof; j++) {
            int64_t k = r * dof + j;
            double qk = q[k], vk = v[k], hk = held[k];
            double pull = c1[j] * v_trg[k] + c2[j] * p_trg[k];
            double goal = clip(hk, -v_max[j], v_max[j]);
            int64_t i = 0;
            while (i < n) {
                int64_t phase = (tick + i) % w;
                int kept = phase == w - 1;
                int64_t m;
                if (kept) {
                    hk = (1.0 - c1[j]) * vk + pull - c2[j] * qk;
                    m = 1;
                } else {
                    m = w - 1 - phase;
                    if (n - i < m) m = n - i;
                }
                double gap = goal - vk, sum = 0.0, last = 0.0;
                for (int64_t s = 1; s <= m; s++) {
                    double bound = (double)s * a_dt[j];
                    last = clip(gap, -bound, bound);
                    sum += last;
                }
                qk = qk + ((double)m * vk + sum - 0.5 * last) * status_s;
                vk = vk + last;
                if (kept) goal = clip(hk, -v_max[j], v_max[j]);
                i += m;
            }
            q[k] = qk;
            v[k] = vk;
            held[k] = hk;
        }
    }
}
