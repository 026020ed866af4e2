/* A real-time budget for a process's Python (cell/sched.py rest_at: a robots process that ticks a
 * UR daemon's group in Python, a data plane's control plane).  That Python runs at SCHED_FIFO, under
 * the native loops of its CPU; if it ever has more work than its CPU, the kernel's RT throttling
 * (950 ms of each second) stops every real-time thread of that CPU for the rest of the second: the
 * robots' C tick of every other arm, the data plane's loop.  A watcher thread, at the native loops'
 * priority, reads the CPU time of the process's other threads when they could have spent the
 * budget at the soonest and at each window's end; once they used BUDGET of a WINDOW it moves them
 * to the normal policy until the window ends (the kernel's limit is never reached; they still run,
 * at their nice value).  The idea of sched.Spin, for code that cannot check its own budget
 * (uvloop's callbacks, C extensions).
 */
#define _GNU_SOURCE
#include "rt_thread.h"
#include <dirent.h>
#include <stdint.h>
#include <stdlib.h>
#include <sys/resource.h>
#include <time.h>
#include <unistd.h>

#define MAX_LOOPS 32

typedef struct {
    int64_t priority;  /* SCHED_FIFO of the budgeted threads while they have budget left */
    int64_t nice;      /* theirs at the normal policy, once it is spent */
    int64_t window_ns, budget_ns, check_ns; /* check_ns: the least time between two looks */
    int64_t cpus;                           /* the CPUs the budgeted threads may run on */
    int64_t loops[MAX_LOOPS]; /* the native loops' thread ids: not budgeted, never moved */
    int64_t n_loops;          /* (written by Python after the id: read with acquire) */
    int64_t stop, tid;        /* tid: the watcher's own */
    int64_t spent;            /* windows whose budget was spent */
    int64_t normal_ns;        /* time the budgeted threads spent at the normal policy */
    int64_t used_max_ns;      /* the most they used of one window */
    int64_t looks;            /* the watcher's wake-ups */
    void *rt;                 /* (C's own: the thread) */
} budget_t;

static int64_t mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static int64_t cpu_ns(clockid_t clock) {
    struct timespec ts;
    if (clock_gettime(clock, &ts)) return 0; /* (a thread gone: it uses nothing more) */
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* the kernel's CPU clock of another thread of this process (MAKE_THREAD_CPUCLOCK(tid, SCHED)) */
static clockid_t thread_clock(int64_t tid) { return (clockid_t)((~(clockid_t)tid << 3) | 6); }

static int exempt(budget_t *b, int64_t tid) {
    if (tid == b->tid) return 1;
    int64_t n = __atomic_load_n(&b->n_loops, __ATOMIC_ACQUIRE);
    for (int64_t k = 0; k < n && k < MAX_LOOPS; k++)
        if (b->loops[k] == tid) return 1;
    return 0;
}

/* CPU time of every thread of the process but the exempt ones */
static int64_t budgeted_ns(budget_t *b) {
    int64_t total = cpu_ns(CLOCK_PROCESS_CPUTIME_ID) - cpu_ns(thread_clock(b->tid));
    int64_t n = __atomic_load_n(&b->n_loops, __ATOMIC_ACQUIRE);
    for (int64_t k = 0; k < n && k < MAX_LOOPS; k++) total -= cpu_ns(thread_clock(b->loops[k]));
    return total;
}

#define MAX_MOVED 256
static pid_t moved[MAX_MOVED]; /* the threads the last demote() moved (one watcher a process) */
static int n_moved;

/* every budgeted thread at real-time priority (SCHED_FIFO, at most b->priority: never a native loop
 * above it, never a thread its code put at the normal policy) to the normal policy at b->nice */
static void demote(budget_t *b) {
    n_moved = 0;
    DIR *d = opendir("/proc/self/task");
    if (!d) return;
    struct dirent *e;
    while ((e = readdir(d)) && n_moved < MAX_MOVED) {
        int64_t tid = atoll(e->d_name);
        struct sched_param sp;
        if (tid <= 0 || exempt(b, tid) || (sched_getscheduler((pid_t)tid) & 0xff) != SCHED_FIFO) continue;
        if (sched_getparam((pid_t)tid, &sp) || sp.sched_priority > b->priority) continue;
        sp.sched_priority = 0;
        if (sched_setscheduler((pid_t)tid, SCHED_OTHER, &sp)) continue;
        setpriority(PRIO_PROCESS, (id_t)tid, (int)b->nice);
        moved[n_moved++] = (pid_t)tid;
    }
    closedir(d);
}

/* the threads demote() moved back to SCHED_FIFO b->priority */
static void restore(budget_t *b) {
    struct sched_param sp = {.sched_priority = (int)b->priority};
    for (int k = 0; k < n_moved; k++) /* (one made a native loop meanwhile is its own) */
        if (!exempt(b, moved[k])) sched_setscheduler(moved[k], SCHED_FIFO, &sp);
    n_moved = 0;
}

static void *watch(void *arg) {
    budget_t *b = arg;
    __atomic_store_n(&b->tid, (int64_t)gettid(), __ATOMIC_RELEASE);
    int64_t start = mono_ns(), base = budgeted_ns(b), since = 0, used = 0;
    int normal = 0;
    while (!__atomic_load_n(&b->stop, __ATOMIC_ACQUIRE)) {
        /* the next look: the window's end, or the soonest the budget could be spent (the threads
         * use at most `cpus` CPU-seconds a second): an idle Python costs it 2-3 wakes a window */
        int64_t now = mono_ns(), wake = start + b->window_ns;
        if (!normal) {
            int64_t soonest = now + (b->budget_ns - used) / (b->cpus > 0 ? b->cpus : 1);
            if (soonest < wake) wake = soonest;
        }
        if (wake < now + b->check_ns) wake = now + b->check_ns;
        struct timespec at = {.tv_sec = wake / 1000000000, .tv_nsec = wake % 1000000000};
        if (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &at, NULL)) continue;
        now = mono_ns();
        used = budgeted_ns(b) - base;
        if (now - start >= b->window_ns) { /* a new window: its budget whole again */
            if (used > b->used_max_ns) b->used_max_ns = used;
            if (normal) {
                restore(b);
                b->normal_ns += now - since;
                normal = 0;
            }
            start = now;
            base = budgeted_ns(b);
            used = 0;
        } else if (!normal && used >= b->budget_ns) {
            demote(b);
            b->spent++;
            normal = 1;
            since = now;
        }
        b->looks++;
    }
    if (normal) restore(b);
    return NULL;
}

/* Start the watcher at SCHED_FIFO `priority` (over the budgeted threads); 0, or the errno */
int bg_start(budget_t *b, int64_t priority) {
    pthread_t *t = calloc(1, sizeof *t);
    if (!t) return ENOMEM;
    b->stop = 0;
    int rc = rt_thread_start(t, (int)priority, watch, b);
    if (rc) {
        free(t);
        return rc;
    }
    b->rt = t;
    while (!__atomic_load_n(&b->tid, __ATOMIC_ACQUIRE)) sched_yield();
    return 0;
}

void bg_stop(budget_t *b) {
    if (!b->rt) return;
    __atomic_store_n(&b->stop, 1, __ATOMIC_RELEASE);
    pthread_join(*(pthread_t *)b->rt, NULL);
    free(b->rt);
    b->rt = NULL;
}
